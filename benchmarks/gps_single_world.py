"""Train one world with GPS and report the neural-network policy's final distances.

    python benchmarks/gps_single_world.py --robot three_link --task reach [--algo mdgps --iterations 10]

The distance is the task's (end-effector or object to goal) averaged over the last 5 steps
of a deterministic rollout of the composed policy (not the local controllers) from each
test condition.  The last line is one JSON object:
``{"final_distance": [...], "success_distance": ..., "iterations": ..., "samples": ..., "wall_s": ...}``.
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from modnet.bank import ModuleBank
from modnet.evaluate import evaluation_env, score
from modnet.gps.trainer import GPSConfig, GPSTrainer
from modnet.worlds import task_spec


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--robot", default="three_link")
    parser.add_argument("--task", default="reach")
    parser.add_argument("--algo", default=GPSConfig.algo, choices=["mdgps", "badmm"])
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--samples", type=int, default=5, help="samples per condition")
    parser.add_argument("--conditions", type=int, default=16, help="training conditions")
    parser.add_argument("--dropout", type=float, default=0.0)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    start = time.perf_counter()
    bank = ModuleBank.build([args.robot], [args.task], seed=args.seed, dropout=args.dropout)
    config = GPSConfig(
        algo=args.algo, samples_per_condition=args.samples, num_conditions=args.conditions, seed=args.seed
    )
    trainer = GPSTrainer(bank, [(args.robot, args.task)], config)
    for i in range(args.iterations):
        diag = trainer.step()[f"{args.robot}/{args.task}"]
        print(f"iteration {i}: " + " ".join(f"{k}={v:.3g}" for k, v in diag.items()), flush=True)
    distance = score(bank, args.robot, args.task, evaluation_env(args.robot, args.task)).distance
    wall = time.perf_counter() - start
    print(
        json.dumps(
            {
                "world": f"{args.robot}/{args.task}",
                "algo": args.algo,
                "final_distance": [round(float(d), 4) for d in distance],
                "success_distance": task_spec(args.task).success_distance,
                "iterations": args.iterations,
                "samples": trainer.samples["trajectories"],
                "env_steps": trainer.samples["env_steps"],
                "wall_s": round(wall, 1),
            }
        )
    )


if __name__ == "__main__":
    main()
