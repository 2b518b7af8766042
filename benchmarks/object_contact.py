"""Does a policy reach, touch and move the object of a held-out manipulation world?

Fine-tuning without the cost's shaping term (the paper's composed and wrong-task starts)
learns only from samples that move the object: until one does, every sample costs the same.
This measures how far each start is from that, on a run's held-out world (or, for
comparison, on one of its training worlds with ``--world robot/task``):

1. Each policy (the composed modules, the random network and each wrong task module) acts
   with mean actions from the 4 test positions.  Per position: the task's distance (as in
   the zero-shot table), the closest the end effector comes to the object, the most the
   object moves from where it started, and how far from the arm's base the object starts and
   the end effector ends.  Beside them, how far from the base the objects of the robot's
   training worlds start (the run's training conditions): a robot module asked to reach
   beyond them must extrapolate.
2. The composed policy then samples as fine-tuning's first iteration does, from its own
   Gaussian (``--std-scale`` widens it), ``--samples`` times from each of ``--conditions``
   random positions; it counts the samples that move the object more than ``--moved``, and
   those that bring it that much closer to its goal (the only ones whose cost differs).

Prints a line per policy, then ONE JSON object on its last line.

    python benchmarks/object_contact.py outputs/manipulation
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from _run_dir import FINISHED, finished_run
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from modnet.bank import ModuleBank
from modnet.config import saved_run
from modnet.evaluate import bank_tasks, evaluating, evaluation_env, misfit, rollout, training_env
from modnet.gps.sampling import WorldSampler
from modnet.gps.trainer import GPSConfig
from modnet.specs import TaskDefinition
from modnet.universes import get_universe
from modnet.worlds import get_world


def contact(task: TaskDefinition, td: TensorDictBase) -> dict[str, torch.Tensor]:
    """Per trajectory of a ``[B, T]`` rollout: the closest the end effector comes to the object,
    where it is then (``offset_at_closest``: end effector minus object, x and y, ``[B, 2]``),
    the most the object moves, the most it comes closer to its goal than where it started, and
    the distances from the arm's base (the origin) of the object at the start and of the end
    effector at the end."""
    first = td["task", "state"][:, 0].double()
    states = td["next", "task", "state"].double()
    moved = (task.part(states, task.moved) - task.part(first, task.moved)[:, None]).norm(dim=-1)
    offset = task.shaping_offset(states)  # [B, T, 3]
    closest, when = offset.norm(dim=-1).min(-1)
    return {
        "closest_approach": closest,
        "offset_at_closest": offset[torch.arange(len(when)), when, :2],
        "object_moved": moved.max(-1).values,
        "progress": task.distance(first) - task.distance(states).min(-1).values,
        "object_from_base": task.part(first, task.moved).norm(dim=-1),
        "end_effector_from_base": task.part(states[:, -1], "ee").norm(dim=-1),
    }


def rounded(values):
    """``values`` (a float or nested lists of them, as ``Tensor.tolist`` gives) to 4 decimals."""
    return [rounded(v) for v in values] if isinstance(values, list) else round(values, 4)


def objects_seen(config: GPSConfig, results: dict, robot: str) -> dict[str, list[float]]:
    """How far from the base the objects of ``robot``'s training worlds start, in the training
    conditions of the run's GPS options ``config``: ``{world: [min, max]}``."""
    seen = {}
    for world in results["training_worlds"]:
        other_robot, task = world.split("/")
        if other_robot != robot:
            continue
        definition = get_world(robot, task).task
        if definition.moved == "ee":
            continue
        state = training_env(robot, task, config).reset()["task", "state"].double()
        start = definition.part(state, definition.moved).norm(dim=-1)
        seen[world] = [round(float(start.min()), 4), round(float(start.max()), 4)]
    return seen


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a run.py run directory (with bank/ and results.json)")
    parser.add_argument("--conditions", type=int, default=16, help="random positions for the sampling")
    parser.add_argument("--samples", type=int, default=5, help="samples per position (GPS's default)")
    parser.add_argument("--std-scale", type=float, default=1.0, help="multiplies the policy's action std")
    parser.add_argument("--moved", type=float, default=0.005, help="what counts as moving the object")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--world", default=None, help="robot/task instead of the held-out world")
    args = parser.parse_args()

    results = finished_run(parser, args.run_dir, (*FINISHED, ".hydra/config.yaml"))
    world = args.world or results["holdout"]
    worlds = [f"{r}/{t}" for r in results["robots"] for t in results["tasks"]]
    if world not in worlds:
        parser.error(f"--world {world!r} is not in this run's universe; valid: {', '.join(worlds)}")
    robot, task = world.split("/")
    bank = ModuleBank.load(args.run_dir / "bank")
    pixels = get_universe(results["universe"]).pixels
    env = evaluation_env(robot, task, horizon=results["horizon"], pixels=pixels)
    definition = env.world.task
    if definition.moved == "ee":
        parser.error(f"{task} moves nothing but the end effector: no object to touch")

    run = saved_run(args.run_dir)
    random_network = bank.fresh_copy(seed=run.eval.baseline_seed)  # the zero-shot table's
    policies = {"composed": (bank, task), "random": (random_network, task)}
    for other in bank_tasks(bank):
        if other != task and misfit(bank, robot, other, env) is None:  # as in the zero-shot table
            policies[f"wrong_task:{other}"] = (bank, other)
    deterministic = {}
    for name, (policy_bank, policy_task) in policies.items():
        td, _ = rollout(policy_bank, robot, policy_task, env)
        row = {key: rounded(value.tolist()) for key, value in contact(definition, td).items()}
        row["distance"] = [round(v, 4) for v in env.final_distance(td).tolist()]
        deterministic[name] = row
        print(
            f"{name:28s} distance {row['distance']}  closest approach {row['closest_approach']}"
            f"  object moved {row['object_moved']}  progress {row['progress']}"
            f"  end effector ends {row['end_effector_from_base']} from the base"
        )
    print(f"the {definition.moved} starts {deterministic['composed']['object_from_base']} from the base")
    seen = objects_seen(run.gps_config(), results, robot)
    for name, (lo, hi) in seen.items():
        print(f"  {name} (training): objects start {lo} to {hi} from the base")

    acting = list(bank.parts(bank.world(robot, task)).values())[-1]  # owns the action distribution
    acting.set_std(acting.log_std.exp() * args.std_scale)
    sampler = WorldSampler(  # GPS's own sampler, as fine-tuning's first iteration uses it
        robot,
        task,
        conditions="random",
        num_conditions=args.conditions,
        samples_per_condition=args.samples,
        horizon=results["horizon"],
        pixels=pixels,
    )
    torch.manual_seed(args.seed)
    with evaluating(bank), set_exploration_type(ExplorationType.RANDOM):
        found = contact(definition, sampler.rollout(bank.compose(robot, task)))
    moved, closest, progress = found["object_moved"], found["closest_approach"], found["progress"]
    sampled = {
        "trajectories": moved.numel(),
        "std": [round(s, 4) for s in acting.log_std.exp().tolist()],
        "moved_the_object": int((moved > args.moved).sum()),
        "object_moved_max": round(float(moved.max()), 4),
        "brought_it_closer": int((progress > args.moved).sum()),
        "progress_max": round(float(progress.max()), 4),
        "closest_approach_median": round(float(closest.median()), 4),
        "closest_approach_min": round(float(closest.min()), 4),
    }
    print(
        f"composed, sampled: {sampled['moved_the_object']} of {sampled['trajectories']} trajectories move "
        f"the {definition.moved} more than {args.moved} (at most {sampled['object_moved_max']}), "
        f"{sampled['brought_it_closer']} bring it that much closer to its goal (at most "
        f"{sampled['progress_max']}); closest "
        f"approach median {sampled['closest_approach_median']}, min {sampled['closest_approach_min']}"
    )
    out = {
        "benchmark": "object_contact",
        "run_dir": str(args.run_dir),
        "holdout": results["holdout"],
        "world": world,
        "object": definition.moved,
        "test_positions": deterministic,
        "objects_seen_in_training": seen,
        "sampled": {**sampled, "std_scale": args.std_scale, "moved_threshold": args.moved},
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
