"""How far a trained network's actions are from the controllers it imitates, and where.

GPS's S-step regresses the composed policies onto their controllers' actions at the
controllers' samples.  Where the network ends far from the blocks while its controllers end
close, the gap between the two actions says why.  This script restores a finished (or
checkpointed) ``run.py`` run's trainer from its ``checkpoint.pt``, samples every training
world once with the controllers it holds (``samples_per_condition`` rollouts from each
training condition, as an iteration samples them), and compares, at those states:

- ``gap``: the norm of controller minus network mean action (the trainer's ``action_gap``);
- ``gap_clipped``: the same with both clipped to the torque limits the arms apply;
- ``gap_by_part``: ``gap_clipped`` over the first fifth of the episode, the rest of its first
  half, and its second half (approach, then reaching and holding at the target);
- ``saturated``: the share of the controllers' mean torques beyond the limits;
- ``controller_distance``: where those samples end (the task's distance, last 5 steps).

Prints a line per world, then ONE JSON object on its last line.

    python benchmarks/action_gap.py RUN_DIR
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from tensordict import TensorDictBase

from modnet.bank import ModuleBank
from modnet.checkpoint import load_checkpoint
from modnet.config import saved_run, validate
from modnet.evaluate import evaluating
from modnet.gps.trainer import PIXEL_ROWS_PER_PASS, GPSTrainer
from modnet.specs import TORQUE_LIMIT

#: where the parts of ``gap_by_part`` end, as fractions of the horizon
PARTS = {"first_fifth": 0.2, "to_half": 0.5, "second_half": 1.0}


def restored_trainer(run_dir: Path) -> GPSTrainer:
    """The trainer of the run in ``run_dir`` (its config), in the state its checkpoint holds."""
    run = saved_run(run_dir)
    universe, split = validate(run)
    trainer = GPSTrainer(run.new_bank(universe), split.training, run.gps_config(), pixels=universe.pixels)
    trainer.load_state_dict(load_checkpoint(run_dir / "checkpoint.pt").trainer)
    return trainer


def clipped_gaps(asked: torch.Tensor, network: torch.Tensor) -> torch.Tensor:
    """The norms ``[...]`` of ``asked - network`` (actions ``[..., dU]``), both clipped to the
    torque limits the arms apply."""
    clip = TORQUE_LIMIT
    return (asked.clamp(-clip, clip) - network.clamp(-clip, clip)).norm(dim=-1)


def network_mean_actions(bank: ModuleBank, name: str, obs: TensorDictBase, pixels: bool) -> torch.Tensor:
    """The mean actions (float64) of world ``name``'s network at ``obs``, in passes bounded
    for images when ``pixels``."""
    with evaluating(bank):
        out = bank.forward_worlds({name: obs}, rows_per_pass=PIXEL_ROWS_PER_PASS if pixels else None)
    return out[bank.world(name)]["loc"].to(torch.float64)


def gap_figures(asked: torch.Tensor, network: torch.Tensor, distance: torch.Tensor) -> dict:
    """The figures of one world from the controllers' and network's mean actions ``[M, N, T, dU]``."""
    clipped = clipped_gaps(asked, network)  # [M, N, T]
    horizon, start, parts = asked.shape[2], 0, {}
    for part, end in PARTS.items():
        stop = max(start + 1, round(end * horizon))
        parts[part] = round(float(clipped[:, :, start:stop].mean()), 4)
        start = stop
    return {
        "gap": round(float((asked - network).norm(dim=-1).mean()), 4),
        "gap_clipped": round(float(clipped.mean()), 4),
        "gap_by_part": parts,
        "saturated": round(float((asked.abs() > TORQUE_LIMIT).double().mean()), 4),
        "controller_distance": round(float(distance.mean()), 4),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a run.py run directory (with checkpoint.pt)")
    args = parser.parse_args()
    missing = [n for n in (".hydra/config.yaml", "checkpoint.pt") if not (args.run_dir / n).exists()]
    if missing:
        parser.error(f"{args.run_dir} is not a run.py run directory: no {', '.join(missing)}")

    torch.set_num_threads(1)
    trainer = restored_trainer(args.run_dir)
    worlds = {}
    for name, state in trainer.states.items():
        samples = state.sampler.sample(state.controller)
        network = network_mean_actions(trainer.bank, name, samples.obs, trainer.pixels)
        asked = state.controller.gains.mean_actions(samples.X)
        worlds[name] = gap_figures(asked, network, samples.distance)
        f = worlds[name]
        parts = " / ".join(f"{v:.3f}" for v in f["gap_by_part"].values())
        print(
            f"{name:32s} gap {f['gap']:.3f}  clipped {f['gap_clipped']:.3f} ({parts})  "
            f"saturated {f['saturated']:.2f}  controllers end {f['controller_distance']:.3f}"
        )

    def mean(key: str) -> float:
        return round(sum(f[key] for f in worlds.values()) / len(worlds), 4)

    out = {
        "benchmark": "action_gap",
        "run_dir": str(args.run_dir),
        "iteration": trainer.iteration,
        "worlds": worlds,
        "mean": {k: mean(k) for k in ("gap", "gap_clipped", "saturated", "controller_distance")},
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
