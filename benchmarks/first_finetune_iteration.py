"""What fine-tuning's first GPS iteration does to a transferred start, free of sampling noise.

A transferred start (the composed modules, or a wrong task module) begins fine-tuning by
sampling its network, starting the controllers from the network's linearisation (clipped to
the torque limits), and then running BADMM's rounds: a C-step, then S-steps, dual steps and
C-steps.  Sampled distances are too noisy to say which of these loses what the network did
zero-shot (one draw of 160 trajectories moves by about 0.01), so this reruns that iteration
on a finished run's bank, as ``run.py finetune=true`` does, and rolls out with mean actions
(no noise: every difference is exact) on the held-out world's training conditions:

- ``network_before``: the network as the bank holds it;
- ``linearisation``: its linearisation, the controllers' start and the first C-step's centre;
- ``first_c_step``: the controllers after the first C-step, before any S-step;
- ``first_lqr_part`` (PILQR only): the same before PI2's correction, the LQR's step alone;
- ``last_c_step``: the controllers the iteration ends with;
- ``network_after``: the network after the iteration's S-steps;
- ``untouched``: the distance each condition starts from.

Where the C-step fits a model (the LQR and PILQR), ``linearisation_predicted`` and
``first_c_step_predicted`` are where that model (the dynamics fitted to the iteration's samples)
says the same controllers end: the mean path of the linear dynamics, scored like the rollouts
(over a window one step earlier: the model ends at the last state it has a successor for).
Beside the real figures they show what the C-step expected of its step and what it got.

``network_after_test`` is the network after the iteration at the test positions, the second
point of the run's fine-tuning curve (``run_curve_1``): the two agree when this reran the
run's iteration.  ``--kl-step`` repeats everything at each KL budget (the run's
``eval.finetune_kl_step``, else ``gps.kl_step``, when not given). ``--policy-linearization``
linearises the network by regression or by its Jacobian (``gps.policy_linearization``; the
run's fine-tuning choice when not given). ``--algo`` and ``--c-step`` set fine-tuning's
algorithm and C-step (``lqr``, ``pi2`` or ``pilqr``; the last two with ``--algo mdgps``), by
default the run's. ``--s-step-onto linearisation`` is a control for the S-step: after each C-step
(recorded as usual) the controllers are put back to the network's linearisation, so the S-step
regresses onto what the network already did, and ``network_after`` says whether the S-step
alone keeps it.

Prints a line per KL budget, then ONE JSON object on its last line.

    python benchmarks/first_finetune_iteration.py outputs/manipulation --kl-step 1.0 0.2
    python benchmarks/first_finetune_iteration.py outputs/manipulation --policy-linearization jacobian
    python benchmarks/first_finetune_iteration.py outputs/manipulation --algo mdgps --c-step pilqr
    python benchmarks/first_finetune_iteration.py outputs/manipulation --s-step-onto linearisation
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import torch
from _run_dir import FINISHED, finished_run
from tensordict import TensorDictBase

from modnet.config import RunConfig, held_out_env, saved_run, validate
from modnet.envs import FINAL_STEPS, WorldEnv
from modnet.evaluate import _start_bank, rollout, score, start_config, training_env
from modnet.gps.controller import LinearGaussianGains
from modnet.gps.lqr import lqr_forward
from modnet.gps.trainer import C_STEPS, POLICY_LINEARIZATIONS, GPSTrainer
from modnet.universes import Universe

TRANSFERRED = ("composed", "wrong_task")


def controller_rollout(scenes: WorldEnv, trainer: GPSTrainer, gains: LinearGaussianGains) -> TensorDictBase:
    """The held-out world's controllers with ``gains`` acting on ``scenes`` (its training
    conditions), mean actions only; the controllers keep their own gains afterwards."""
    (state,) = trainer.states.values()
    controller, kept = state.controller, state.controller.gains
    controller.set_gains(gains)
    controller.deterministic = True
    try:
        with torch.no_grad():
            return scenes.rollout(scenes.horizon, controller, break_when_any_done=False)
    finally:
        controller.deterministic = None
        controller.set_gains(kept)


def controller_distance(scenes: WorldEnv, trainer: GPSTrainer, gains: LinearGaussianGains) -> float:
    """Mean final distance of :func:`controller_rollout`."""
    return float(scenes.final_distance(controller_rollout(scenes, trainer, gains)).mean())


def predicted_distance(trainer: GPSTrainer, gains: LinearGaussianGains) -> float:
    """Mean final distance the iteration's fitted dynamics predict for ``gains``: their mean
    path from each condition's fitted initial state, the task's distance averaged over its
    last ``FINAL_STEPS`` states. The model has no successor of the last state, so its window
    ends one step before a rollout's (:func:`controller_distance`)."""
    (state,) = trainer.states.values()
    world = state.sampler.world
    mean = lqr_forward(gains, state.current.dynamics).mu  # [M, T, dX + dU]
    task_state = mean[..., world.robot.state_dim : gains.state_dim]
    return float(world.task.distance(task_state)[:, -FINAL_STEPS:].mean(-1).mean())


def start_trainer(
    run_dir: Path, run: RunConfig, universe: Universe, results: dict, start: str, **options
) -> GPSTrainer:
    """The trainer ``run.py finetune=true`` fine-tunes ``start`` with (on the held-out world of the
    finished run in ``run_dir``, whose ``universe`` :func:`~modnet.config.validate` returned), with
    ``options`` replacing the run's fine-tuning GPS options."""
    robot, task = results["holdout"].split("/")
    wrong_task = results["methods"]["wrong_task"]["task"] if "wrong_task" in results["methods"] else None
    config = start_config(dataclasses.replace(run.finetune_gps_config(), **options), start)
    bank = _start_bank(run_dir / "bank", start, robot, task, wrong_task, config.seed)
    return GPSTrainer(bank, [(robot, task)], config, pixels=universe.pixels)


def first_iteration(
    run_dir: Path, run: RunConfig, results: dict, start: str, s_step_onto: str = "c_step", **options
) -> dict:
    """The start's first fine-tuning iteration, with ``options`` replacing the run's
    fine-tuning GPS options (``kl_step``, ``policy_linearization``, ``algo``, ``c_step``), and
    the S-step regressing onto the C-step's controllers or (``s_step_onto="linearisation"``)
    onto the network's linearisation."""
    universe, split = validate(run)
    trainer = start_trainer(run_dir, run, universe, results, start, **options)
    bank, config, (robot, task) = trainer.bank, trainer.config, results["holdout"].split("/")
    scenes = training_env(robot, task, config, horizon=results["horizon"], pixels=trainer.pixels)
    before = score(bank, robot, task, scenes)

    c_steps: list[LinearGaussianGains] = []  # each C-step's controllers
    lqr_parts: list[LinearGaussianGains] = []  # PILQR: each LQR step before PI2's correction

    def recording(step, corrects_lqr: bool):
        def recorded(state, *args, **kwargs):
            step(state, *args, **kwargs)
            if corrects_lqr:
                lqr_parts.append(c_steps.pop())
            c_steps.append(state.controller.gains)  # a snapshot
            if s_step_onto == "linearisation":
                state.controller.set_gains(state.current.gains)

        return recorded

    trainer._c_step = recording(trainer._c_step, corrects_lqr=False)
    trainer._pi2_step = recording(trainer._pi2_step, corrects_lqr=config.c_step == "pilqr")
    (diagnostics,) = trainer.step().values()
    (state,) = trainer.states.values()
    after, _ = rollout(bank, robot, task, scenes)
    test_positions = held_out_env(run, universe, split)
    distances = {
        "network_before": before.mean,
        "linearisation": controller_distance(scenes, trainer, state.current.gains),
        "first_c_step": controller_distance(scenes, trainer, c_steps[0]),
        **({"first_lqr_part": controller_distance(scenes, trainer, lqr_parts[0])} if lqr_parts else {}),
        "last_c_step": controller_distance(scenes, trainer, c_steps[-1]),
        "network_after": float(scenes.final_distance(after).mean()),
        "untouched": float(scenes.start_distance(after).mean()),
        "network_after_test": score(bank, robot, task, test_positions).mean,
    }
    if config.fits_model:
        distances["linearisation_predicted"] = predicted_distance(trainer, state.current.gains)
        distances["first_c_step_predicted"] = predicted_distance(trainer, c_steps[0])
    out = {name: round(d, 4) for name, d in distances.items()}
    out["sampled"] = round(float(diagnostics["distance"]), 4)
    out["kl"] = round(float(diagnostics["kl"]), 2)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a finished run.py run directory with finetune=true")
    parser.add_argument("--start", choices=TRANSFERRED, default="composed")
    parser.add_argument("--kl-step", type=float, nargs="+", default=None, help="KL budgets per time step")
    parser.add_argument(
        "--policy-linearization",
        choices=POLICY_LINEARIZATIONS,
        default=None,
        help="how the network is linearised (default: the run's fine-tuning choice)",
    )
    parser.add_argument("--algo", choices=["badmm", "mdgps"], default=None, help="default: the run's")
    parser.add_argument("--c-step", choices=C_STEPS, default=None, help="default: the run's")
    parser.add_argument(
        "--s-step-onto",
        choices=["c_step", "linearisation"],
        default="c_step",
        help="what the S-step regresses onto: the C-step's controllers, or (a control) the network's "
        "linearisation",
    )
    args = parser.parse_args()

    results = finished_run(parser, args.run_dir, (*FINISHED, ".hydra/config.yaml"))
    if args.start == "wrong_task" and "wrong_task" not in results["methods"]:
        parser.error(f"{args.run_dir}'s bank has no wrong task module; valid starts: composed")
    run = saved_run(args.run_dir)
    torch.set_num_threads(run.threads)
    tuned = run.finetune_gps_config()
    kl_steps = args.kl_step or [tuned.kl_step]
    options = dict(
        policy_linearization=args.policy_linearization or tuned.policy_linearization,
        algo=args.algo or tuned.algo,
        c_step=args.c_step or tuned.c_step,
    )
    if any(not k > 0 for k in kl_steps):
        parser.error(f"--kl-step must be positive, got {kl_steps}")
    try:
        dataclasses.replace(tuned, **options)
    except ValueError as err:  # e.g. PI2 under BADMM, refused before any work
        parser.error(str(err))

    curve = results.get("finetune", {}).get(args.start)
    out = {
        "run_dir": str(args.run_dir),
        "holdout": results["holdout"],
        "start": args.start,
        "run_curve_1": curve[1] if curve and len(curve) > 1 else None,
        "run_kl_step": tuned.kl_step,
        **options,
        "s_step_onto": args.s_step_onto,
        "by_kl_step": {},
    }
    for kl_step in kl_steps:
        figures = first_iteration(
            args.run_dir, run, results, args.start, s_step_onto=args.s_step_onto, kl_step=kl_step, **options
        )
        out["by_kl_step"][str(kl_step)] = figures
        print(f"kl_step {kl_step:g}: " + ", ".join(f"{k} {v:g}" for k, v in figures.items()), flush=True)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
