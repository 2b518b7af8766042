"""Score a trained bank on every world of its universe, training worlds and held-out alike.

A zero-shot result means most beside what the same bank does on the worlds it was trained
on, at positions it never saw: if those are as far off, what limits the held-out world is
the network's generalisation to new positions, not the composition.  For each world of
the run's universe, the composed policy (mean actions, no dropout) runs from the 4 test
positions (or ``--conditions random --num-conditions N``) and the task's distance over the
last 5 steps is averaged, as in the zero-shot table.

Prints a line per world, then ONE JSON object on its last line.

    python benchmarks/score_bank.py outputs/color_reach_state/<date>
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from _run_dir import finished_run

from modnet.bank import ModuleBank
from modnet.evaluate import evaluating, evaluation_env, score
from modnet.universes import get_universe, world_name


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a run.py run directory (with bank/ and results.json)")
    parser.add_argument("--conditions", default="test", help="condition set: test (default) or random")
    parser.add_argument("--num-conditions", type=int, default=None)
    args = parser.parse_args()

    results = finished_run(parser, args.run_dir)
    universe = get_universe(results["universe"])
    holdout = results["holdout"]
    bank = ModuleBank.load(args.run_dir / "bank")
    means = {}
    with evaluating(bank):
        for robot, task in universe.worlds:
            env = evaluation_env(
                robot,
                task,
                conditions=args.conditions,
                num_conditions=args.num_conditions,
                horizon=results["horizon"],  # the run's episode length (as its zero-shot table)
                pixels=universe.pixels,
            )
            name = world_name((robot, task))
            means[name] = round(score(bank, robot, task, env).mean, 4)
            print(f"{name:32s} {means[name]:.3f}{'  (held out)' if name == holdout else ''}")
    training = [v for name, v in means.items() if name != holdout]
    out = {
        "benchmark": "score_bank",
        "run_dir": str(args.run_dir),
        "universe": universe.name,
        "holdout": holdout,
        "conditions": args.conditions,
        "mean_distance": means,
        "training_worlds": {
            "min": min(training),
            "max": max(training),
            "mean": round(sum(training) / len(training), 4),
        },
        "held_out": means[holdout],
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
