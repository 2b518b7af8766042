"""Time GPS iterations of a run's training grid and split them by phase.

Builds the trainer ``python run.py [overrides]`` would train (by default the 11-world
state-based colour-reach grid: 3 robots x 4 colours, four_link/reach_black held out, with
that universe's budget), without pretraining or logging.  Prints the share of each phase
(sampling, cost expansion, dynamics fit, LQR, the policy's forward passes over the samples,
S-step) of the median iteration after the first, and the sampling's time against a raw
``mj_step`` run of the same number of control steps in the same process (the reference;
from images the sampling also renders every frame).

    python benchmarks/gps_iteration.py [--iterations 3] [algo=mdgps]
    python benchmarks/gps_iteration.py --iterations 2 universe=color_reach     # from 64x80 images
    python benchmarks/gps_iteration.py --iterations 2 universe=color_reach threads=2

The last line is one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import mujoco
import numpy as np
import torch
from hydra import compose, initialize_config_dir
from hydra.errors import HydraException
from omegaconf import OmegaConf

from modnet.config import ConfigError, RunConfig, register_configs, validate
from modnet.gps.trainer import PHASES, GPSTrainer
from modnet.specs import CONTROL_SUBSTEPS
from modnet.universes import UniverseError

CONF = Path(__file__).resolve().parents[1] / "conf"


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
    parser.add_argument("--iterations", type=int, default=3, help="2 or more (the first is not reported)")
    parser.add_argument("overrides", nargs="*", help="run.py overrides, e.g. universe=color_reach algo=mdgps")
    args = parser.parse_args()
    if args.iterations < 2:
        parser.error("--iterations must be at least 2: the first iteration is not reported")
    register_configs()
    try:  # a bad override ends in one line, before any work
        with initialize_config_dir(config_dir=str(CONF), version_base=None):
            run: RunConfig = OmegaConf.to_object(compose("config", overrides=args.overrides))
        universe, split = validate(run)
    except (HydraException, ConfigError, UniverseError) as err:
        parser.error(" ".join(str(err).split()))
    torch.set_num_threads(run.threads)  # as run.py: 1 unless overridden (threads=2)
    config = run.gps_config()
    trainer = GPSTrainer(run.new_bank(universe), split.training, config, pixels=universe.pixels)
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
    steady = per_iteration[1:]
    wall = statistics.median(w for w, _ in steady)
    shares = {p: statistics.median(ph[p] / w for w, ph in steady) for p in PHASES}
    sampling = statistics.median(ph["sampling"] for _, ph in steady)
    reference = statistics.median(raw_seconds(trainer) for _ in range(3))
    figures = {
        "benchmark": "gps_iteration",
        "overrides": args.overrides,
        "universe": universe.name,
        "pixels": universe.pixels,
        "worlds": len(split.training),
        "algo": config.algo,
        "conditions": config.num_conditions,
        "samples_per_condition": config.samples_per_condition,
        "sgd_steps": config.sgd_steps,
        "iterations": args.iterations,
        "threads": run.threads,
        "median_iteration_s": round(wall, 3),
        "share": {p: round(v, 3) for p, v in shares.items()},
        "unaccounted_share": round(1 - sum(shares.values()), 3),
        "sampling_vs_raw_mj_step": round(reference / sampling, 3),  # the fraction raw stepping would take
        "samples_per_iteration": int(sum(s.sampler.env.batch_size[0] for s in trainer.states.values())),
    }
    print(json.dumps(figures))


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
