"""Which of the held-out world's scenes a fine-tuning start pulls home, and which it never moves.

A run's fine-tuning diagnostics give each iteration's mean over the scenes GPS samples
(``distance``), how many scenes' samples end within the success distance
(``conditions_within``) and how far the farthest scene's end (``distance_worst_condition``),
but not which scenes those are.  This reruns one start's fine-tuning on a finished run's bank,
exactly as ``run.py finetune=true`` does (the same trainer, seeds and calls, so its
diagnostics repeat the run's: ``matches_run`` says whether every iteration's ``distance``
does), and records per scene:

- ``params``: the scene (the task's parameters: for a drawer the cabinet front's x and y, the
  initial and the target opening) and ``arm_qpos``, the arm's initial joint angles;
- ``untouched``: the distance when nothing moves the object;
- ``network``: the start's network rolled out with mean actions before fine-tuning: its final
  distance, how near the end-effector comes to the object (``closest_approach``), where it is
  then (``offset_at_closest``: end-effector minus object, x and y) and the most the object
  moves from where it started (``object_moved``), as :func:`object_contact.contact` gives them;
- ``sampled``: each iteration's mean distance of the scene's samples (the per-scene figures the
  run's ``distance`` averages), and ``closest_approach``, ``offset_at_closest`` and
  ``object_moved`` of the last iteration's samples (means over them), and ``first_touched``, the
  first iteration one of its samples moved the object by ``--moved`` (None: none ever did);
- ``outcome``: ``within`` (the last iteration's samples end within the success distance),
  ``never_moved`` (no iteration's samples move the object by ``--moved`` on average) or
  ``partly``.

Beside them, ``counts`` of each outcome and ``touched_by_iteration``: how many scenes had a
sample move the object by ``--moved`` at each iteration.

Prints a line per scene, then ONE JSON object on its last line.

    python benchmarks/finetune_per_scene.py outputs/manipulation
    python benchmarks/finetune_per_scene.py outputs/manipulation --start wrong_task --iterations 10
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from _run_dir import FINISHED, finished_run
from first_finetune_iteration import start_trainer
from object_contact import contact, rounded
from publish_results import command
from tensordict import TensorDict

from modnet.config import held_out_env, saved_run, validate
from modnet.evaluate import rollout, score, training_env
from modnet.worlds import get_world

STARTS = ("composed", "wrong_task", "scratch_shaping", "scratch_no_shaping")
OUTCOMES = ("within", "partly", "never_moved")
CONTACT = ("closest_approach", "offset_at_closest", "object_moved")  # of object_contact.contact


def _as_rollout(task_states: torch.Tensor) -> TensorDict:
    """Samples' task states ``[M, N, T, task_dim]`` (the states each action was taken in) as
    the ``[M * N, T - 1]`` rollout :func:`object_contact.contact` reads."""
    before, after = task_states[..., :-1, :].flatten(0, 1), task_states[..., 1:, :].flatten(0, 1)
    return TensorDict({"task": {"state": before}, "next": {"task": {"state": after}}}, before.shape[:2])


def _rounded(value: torch.Tensor) -> float | list:
    return rounded(value.tolist())


def per_scene(run_dir: Path, start: str, iterations: int, moved: float) -> dict:
    """Rerun ``start``'s fine-tuning of the finished run in ``run_dir`` for ``iterations``
    iterations; the per-scene figures (the module's docstring), ``moved`` what counts as
    moving the object."""
    run = saved_run(run_dir)
    results = json.loads((run_dir / "results.json").read_text())
    universe, split = validate(run)
    robot, task = results["holdout"].split("/")
    trainer = start_trainer(run_dir, run, universe, results, start)
    bank, (state,) = trainer.bank, trainer.states.values()
    definition = state.sampler.world.task
    test_positions = held_out_env(run, universe, split)
    scenes = training_env(robot, task, trainer.config, horizon=results["horizon"], pixels=trainer.pixels)

    td, _ = rollout(bank, robot, task, scenes)  # the network before fine-tuning, mean actions
    network = contact(definition, td)
    network_final, untouched = scenes.final_distance(td), scenes.start_distance(td)

    # finetune()'s calls in its order, the scores between iterations included
    score(bank, robot, task, test_positions), score(bank, robot, task, scenes)
    sampled, moved_by, touched, run_distance = [], [], [], []
    for _ in range(iterations):
        (diagnostics,) = trainer.step().values()
        samples = state.samples
        M, N = samples.distance.shape
        found = contact(definition, _as_rollout(samples.X[..., state.sampler.world.robot.state_dim :]))
        found = {key: value.reshape(M, N, *value.shape[1:]) for key, value in found.items()}
        sampled.append(samples.distance.mean(-1))  # [M]
        moved_by.append(found["object_moved"].mean(-1))
        touched.append(found["object_moved"].amax(-1) >= moved)  # one of the scene's samples moved it
        run_distance.append(diagnostics["distance"])
        score(bank, robot, task, test_positions), score(bank, robot, task, scenes)
    sampled, moved_by, touched = torch.stack(sampled), torch.stack(moved_by), torch.stack(touched)  # [I, M]
    last = found  # the last iteration's samples, [M, N, ...]

    # the rerun is the run's fine-tuning: every iteration's mean sampled distance, to 10 digits
    recorded = [d["distance"] for d in results.get("finetune_diagnostics", {}).get(start, [])][:iterations]
    matches = bool(recorded) and [round(d, 10) for d in run_distance[: len(recorded)]] == [
        round(d, 10) for d in recorded
    ]
    params = scenes.condition_params
    n_joints = len(params[0]) - definition.param_dim
    rows = []
    for m in range(sampled.shape[1]):
        if sampled[-1, m] < definition.success_distance:
            outcome = "within"
        elif moved_by[:, m].max() < moved:
            outcome = "never_moved"
        else:
            outcome = "partly"
        ever = touched[:, m].nonzero()
        rows.append(
            {
                "scene": m,
                "params": np.round(params[m, n_joints:], 4).tolist(),
                "arm_qpos": np.round(params[m, :n_joints], 4).tolist(),
                "untouched": _rounded(untouched[m]),
                "network": {
                    "final": _rounded(network_final[m]),
                    **{key: _rounded(network[key][m]) for key in CONTACT},
                },
                "sampled": {
                    "by_iteration": _rounded(sampled[:, m]),
                    "best": _rounded(sampled[:, m].min()),
                    **{key: _rounded(last[key][m].mean(0)) for key in CONTACT},
                    "most_moved": _rounded(moved_by[:, m].max()),
                    "first_touched": int(ever[0]) + 1 if len(ever) else None,
                },
                "outcome": outcome,
            }
        )
    return {
        "benchmark": "finetune_per_scene",
        "command": "python benchmarks/finetune_per_scene.py RUN_DIR "
        f"--start {start} --iterations {iterations} --moved {moved:g}",
        "run_command": command(run_dir, results.get("machine")),  # what made RUN_DIR
        "run_dir": str(run_dir),
        "holdout": results["holdout"],
        "start": start,
        "iterations": iterations,
        "success_distance": definition.success_distance,
        "moved_threshold": moved,
        "matches_run": matches,
        "compared_iterations": len(recorded),
        "counts": {o: sum(r["outcome"] == o for r in rows) for o in OUTCOMES},
        "touched_by_iteration": touched.sum(-1).tolist(),
        "scenes": rows,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a finished run.py run directory with finetune=true")
    parser.add_argument("--start", choices=STARTS, default="composed")
    parser.add_argument("--iterations", type=int, default=None, help="default: the run's")
    parser.add_argument(
        "--moved", type=float, default=0.01, help="how far the object must move to count as moved"
    )
    args = parser.parse_args()
    results = finished_run(parser, args.run_dir, (*FINISHED, ".hydra/config.yaml"))
    if get_world(*results["holdout"].split("/")).task.moved == "ee":
        parser.error(f"{results['holdout']} moves nothing but the end effector: no object to touch")
    if args.start == "wrong_task" and "wrong_task" not in results["methods"]:
        valid = ", ".join(s for s in STARTS if s != "wrong_task")
        parser.error(f"{args.run_dir}'s bank has no wrong task module; valid starts: {valid}")
    run = saved_run(args.run_dir)
    torch.set_num_threads(run.threads)
    iterations = args.iterations if args.iterations is not None else run.eval.finetune_iterations
    if iterations < 1:
        parser.error(f"--iterations must be at least 1, got {iterations}")
    out = per_scene(args.run_dir, args.start, iterations, args.moved)
    print(f"{out['start']} on {out['holdout']}, {iterations} iterations; the run's own: {out['matches_run']}")
    for row in out["scenes"]:
        print(
            f"scene {row['scene']:2d} {row['outcome']:11s} params {row['params']} "
            f"untouched {row['untouched']:.3f} network {row['network']['final']:.3f} "
            f"(approach {row['network']['closest_approach']:.3f}) best sampled {row['sampled']['best']:.3f} "
            f"moved {row['sampled']['most_moved']:.3f}",
            flush=True,
        )
    print(json.dumps(out))


if __name__ == "__main__":
    main()
