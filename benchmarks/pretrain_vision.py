"""The vision pretraining of a universe on its own: how well each module learns to find the objects.

Builds the bank ``python run.py universe=U [overrides]`` would build, runs the same
pose-regression pretraining as that run does before GPS (``modnet.pretrain``; seeded, so
the figures equal the run's ``pretrain.json``), and reports, per module, the localisation
error on held-out scenes per object, beside the error of always guessing the mean position.
Also measures what a scene costs to render against a raw ``mujoco.mj_step`` of the same
world, in the same process.

Prints a line per module, then ONE JSON object on its last line.

    python benchmarks/pretrain_vision.py                      # color_reach, its conf's settings
    python benchmarks/pretrain_vision.py universe=color_reach pretrain.images=1000 pretrain.epochs=20
"""

from __future__ import annotations

import json
import statistics
import sys
import time
from pathlib import Path

import mujoco
import numpy as np
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from modnet.config import RunConfig, register_configs, validate
from modnet.pretrain import pretrain_vision, render_scenes
from modnet.worlds import get_world

CONF = Path(__file__).resolve().parents[1] / "conf"


def render_vs_step(robot: str, task: str, repeats: int = 5, n: int = 200) -> float:
    """Median over ``repeats`` of (seconds per rendered scene) / (seconds per raw ``mj_step``)."""
    world = get_world(robot, task)
    data = mujoco.MjData(world.model)
    ratios = []
    for r in range(repeats):
        start = time.perf_counter()
        render_scenes(world, n, np.random.default_rng(r))
        scene = (time.perf_counter() - start) / n
        start = time.perf_counter()
        for _ in range(n):
            mujoco.mj_step(world.model, data)
        step = (time.perf_counter() - start) / n
        ratios.append(scene / step)
    return statistics.median(ratios)


def main() -> None:
    torch.set_num_threads(1)  # as run.py
    overrides = sys.argv[1:] or ["universe=color_reach"]
    register_configs()
    with initialize_config_dir(config_dir=str(CONF), version_base=None):
        run: RunConfig = OmegaConf.to_object(compose("config", overrides=overrides))
    universe, split = validate(run)
    if not run.pretrain.images:
        sys.exit(f"pretrain_vision.py: pretraining is off for {overrides}: set pretrain.images")
    bank = run.new_bank(universe)
    start = time.perf_counter()
    report = pretrain_vision(bank, split.training, run.pretrain_config())
    seconds = time.perf_counter() - start
    for module, figures in report.items():
        errors = ", ".join(f"{k} {v:.3f}" for k, v in figures["object_errors"].items())
        off, guess = figures["val_error"], figures["baseline_error"]
        print(f"{module}: {off:.3f} m off (mean guess {guess:.3f}); {errors}")
    rounded = {
        module: {
            "val_error": round(f["val_error"], 4),
            "baseline_error": round(f["baseline_error"], 4),
            "object_errors": {k: round(v, 4) for k, v in f["object_errors"].items()},
        }
        for module, f in report.items()
    }
    print(
        json.dumps(
            {
                "overrides": overrides,
                "images_per_module": run.pretrain.images,
                "epochs": run.pretrain.epochs,
                "modules": rounded,
                "seconds": round(seconds, 1),
                "render_scene_vs_mj_step": round(render_vs_step(*split.training[0]), 1),
            }
        )
    )


if __name__ == "__main__":
    main()
