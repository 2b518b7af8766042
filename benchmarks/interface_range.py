"""Is the held-out composition's interface one its robot module has seen?

The robot module ``f_r`` of the held-out world ``(r, k)`` was trained on the interfaces of
other task modules; zero-shot it reads ``g_k``'s, which it never met.  This script rolls
each policy out (mean actions, no dropout) at ``--num-conditions`` random positions and
compares, in the units of what ``f_r`` read in training (each interface entry standardised
by its mean and spread over ``f_r``'s training worlds, every step of every episode):

* ``rms_heldout``: the root mean square of ``g_k``'s standardised interface as the composed
  policy acts in the held-out world (1 or less: where ``f_r`` trained; 3: three spreads off);
* ``rms_robot_training``: the same for ``f_r``'s own training interfaces (about 1, the
  reference);
* ``outside_heldout``: the fraction of the held-out interface's entries beyond the range
  ``f_r`` read in training (per entry), and ``outside_task_training`` the same for what
  ``g_k`` wrote on its own training worlds, with their robots;
* ``zero_shot``: the composed policy's mean final distance at those positions.

Prints a line per run, then ONE JSON object on its last line.

    python benchmarks/interface_range.py outputs/manipulation/<date> [more run directories]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from _run_dir import finished_run

from modnet.bank import ModuleBank
from modnet.evaluate import evaluation_env, rollout
from modnet.modules import interface_key
from modnet.universes import get_universe, parse_world


def interface_figures(
    heldout: torch.Tensor, robot_training: torch.Tensor, task_training: torch.Tensor
) -> dict:
    """The figures above from three ``[..., D]`` interface samples (any leading shape).

    Examples:
        >>> seen = torch.randn(1000, 16, generator=torch.Generator().manual_seed(0))
        >>> f = interface_figures(seen[:500], seen, 5 + seen)  # five spreads off: mostly outside
        >>> f["outside_heldout"], round(f["rms_robot_training"], 1), f["outside_task_training"] > 0.8
        (0.0, 1.0, True)
    """
    seen = robot_training.reshape(-1, robot_training.shape[-1])
    mean, spread = seen.mean(0), seen.std(0).clamp_min(1e-6)
    low, high = seen.min(0).values, seen.max(0).values

    def rms(z: torch.Tensor) -> float:
        return ((z - mean) / spread).pow(2).mean(-1).sqrt().mean().item()

    def outside(z: torch.Tensor) -> float:
        return ((z < low) | (z > high)).float().mean().item()

    return {
        "rms_heldout": rms(heldout),
        "rms_robot_training": rms(robot_training),
        "outside_heldout": outside(heldout),
        "outside_task_training": outside(task_training),
    }


def run_figures(run_dir: Path, results: dict, num_conditions: int) -> dict:
    """Roll the run's bank out on its held-out world and the worlds its two modules trained on."""
    bank = ModuleBank.load(run_dir / "bank")
    universe = get_universe(results["universe"])
    robot, task = parse_world(results["holdout"])
    key = interface_key("task")

    def interface(world: tuple[str, str]) -> tuple[torch.Tensor, torch.Tensor]:
        env = evaluation_env(
            *world,
            conditions="random",
            num_conditions=num_conditions,
            horizon=results["horizon"],  # the run's episode length, as its zero-shot table
            pixels=universe.pixels,
        )
        td, _ = rollout(bank, *world, env)
        return td[key], env.final_distance(td)

    heldout, distance = interface((robot, task))  # rollout: mean actions, no dropout, no autograd
    robot_training = torch.cat([interface(w)[0] for w in sorted(bank.trained_on("robot", robot))])
    task_training = torch.cat([interface(w)[0] for w in sorted(bank.trained_on("task", task))])
    figures = interface_figures(heldout, robot_training, task_training)
    return {
        "holdout": results["holdout"],
        "activation": bank.config.activation,
        "zero_shot": round(distance.mean().item(), 4),
        **{name: round(value, 4) for name, value in figures.items()},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", type=Path, nargs="+", help="run.py run directories (with bank/)")
    parser.add_argument("--num-conditions", type=int, default=20, help="random positions per world")
    args = parser.parse_args()
    if args.num_conditions < 1:
        parser.error(f"--num-conditions must be at least 1, got {args.num_conditions}")
    results = {run_dir: finished_run(parser, run_dir) for run_dir in args.run_dirs}
    for run_dir, result in results.items():
        if result.get("policy", "modular") != "modular":
            parser.error(f"{run_dir} trained a {result['policy']} bank: only modular banks have an interface")
    torch.set_num_threads(1)
    runs = {}
    for run_dir, result in results.items():
        runs[str(run_dir)] = figures = run_figures(run_dir, result, args.num_conditions)
        print(
            f"{run_dir}: {figures['activation']}, zero-shot {figures['zero_shot']:.3f}, held-out interface "
            f"{figures['rms_heldout']:.2f} spreads ({figures['outside_heldout']:.1%} outside the range), "
            f"training {figures['rms_robot_training']:.2f}"
        )
    print(json.dumps({"benchmark": "interface_range", "num_conditions": args.num_conditions, "runs": runs}))


if __name__ == "__main__":
    main()
