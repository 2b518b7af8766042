"""Time GPS iterations on the 11-world state-based colour-reach grid and split them by phase.

3 robots (three_link, three_link_short, four_link) x 4 colours, four_link/reach_black held
out.  Prints the share of each phase (sampling, cost expansion, dynamics fit, LQR, S-step)
of the median iteration, and the batched env's share against a raw ``mj_step`` run of the
same number of control steps in the same process (the sampling reference).

    python benchmarks/gps_iteration.py [--iterations 3 --algo mdgps]

The last line is one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import mujoco
import numpy as np
import torch

from modnet.bank import ModuleBank
from modnet.gps.trainer import PHASES, GPSConfig, GPSTrainer
from modnet.specs import CONTROL_SUBSTEPS

ROBOTS = ["three_link", "three_link_short", "four_link"]
TASKS = ["reach_red", "reach_green", "reach_yellow", "reach_black"]
HOLDOUT = ("four_link", "reach_black")


def raw_seconds(trainer: GPSTrainer) -> float:
    """Seconds a bare mj_step loop takes for the control steps one iteration samples."""
    total = 0.0
    for state in trainer.states.values():
        world, env = state.sampler.world, state.sampler.env
        data = mujoco.MjData(world.model)
        world.reset_data(data, world.conditions()[0])
        steps = env.batch_size[0] * env.horizon
        start = time.perf_counter()
        for _ in range(steps):
            data.ctrl[:] = 0.1
            mujoco.mj_step(world.model, data, CONTROL_SUBSTEPS)
        total += time.perf_counter() - start
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--iterations", type=int, default=3)
    parser.add_argument("--algo", default=GPSConfig.algo, choices=["mdgps", "badmm"])
    args = parser.parse_args()
    torch.set_num_threads(1)
    worlds = [(r, t) for r in ROBOTS for t in TASKS if (r, t) != HOLDOUT]
    bank = ModuleBank.build(ROBOTS, TASKS, seed=0)
    trainer = GPSTrainer(bank, worlds, GPSConfig(algo=args.algo))
    per_iteration = []
    for i in range(args.iterations):
        before = dict(trainer.timings)
        start = time.perf_counter()
        trainer.step()
        wall = time.perf_counter() - start
        phases = {p: trainer.timings[p] - before.get(p, 0.0) for p in PHASES}
        per_iteration.append((wall, phases))
        print(f"iteration {i}: {wall:.2f}s " + " ".join(f"{p}={v:.2f}s" for p, v in phases.items()))
    # iteration 0 also fits the policy to the initial controllers; report the later ones
    steady = per_iteration[1:] or per_iteration
    wall = statistics.median(w for w, _ in steady)
    shares = {p: statistics.median(ph[p] / w for w, ph in steady) for p in PHASES}
    sampling = statistics.median(ph["sampling"] for _, ph in steady)
    reference = statistics.median(raw_seconds(trainer) for _ in range(3))
    figures = {
        "worlds": len(worlds),
        "algo": args.algo,
        "iterations": args.iterations,
        "median_iteration_s": round(wall, 3),
        "share": {p: round(v, 3) for p, v in shares.items()},
        "unaccounted_share": round(1 - sum(shares.values()), 3),
        "sampling_vs_raw_mj_step": round(reference / sampling, 3),
        "samples_per_iteration": int(sum(s.sampler.env.batch_size[0] for s in trainer.states.values())),
    }
    print(json.dumps(figures))


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
