"""Environment throughput: the batched env against raw mujoco and TorchRL's DMControlWrapper.

Same world, same process, interleaved repeats, medians:
  (a) a raw ``mujoco.mj_step`` loop with the same substeps (the ceiling);
  (b) ``modnet.make_env(num_envs=64).rollout(T)`` with a random policy;
  (c) ``DMControlWrapper(modnet.make_world(...)).rollout(T)``;
and for pixels, frames/s of ``make_env(pixels=True)`` against a bare ``mujoco.Renderer``
drawing the same scene, with the env's default render processes (one on 2 cores: two
processes draw at once) and with none (this process draws every frame).
Targets: b/a >= 0.5, b/c >= 10, pixels >= 0.8 with no render process, and above 1 with
one on a machine with a core to spare.

    python benchmarks/env_throughput.py [--robot four_link --task reach_black --repeats 5 --pixel-envs 16]

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
from torchrl.envs import DMControlWrapper

import modnet
from modnet.envs import CAMERA, open_renderer
from modnet.specs import CONTROL_SUBSTEPS, PIXELS_SHAPE


def raw_steps_per_s(world, steps: int) -> float:
    data = mujoco.MjData(world.model)
    world.reset_data(data, world.conditions()[0])
    controls = np.random.default_rng(0).uniform(-2, 2, (steps, world.robot.action_dim))
    start = time.perf_counter()
    for u in controls:
        data.ctrl[:] = u
        mujoco.mj_step(world.model, data, CONTROL_SUBSTEPS)
    return steps / (time.perf_counter() - start)


def batched_steps_per_s(robot: str, task: str, num_envs: int, horizon: int) -> float:
    env = modnet.make_env(robot, task, num_envs=num_envs)
    start = time.perf_counter()
    env.rollout(horizon)
    return num_envs * horizon / (time.perf_counter() - start)


def dmcontrol_steps_per_s(robot: str, task: str, horizon: int) -> float:
    env = DMControlWrapper(modnet.make_world(robot, task))
    start = time.perf_counter()
    env.rollout(horizon)
    return horizon / (time.perf_counter() - start)


def pixel_env_frames_per_s(
    robot: str, task: str, num_envs: int, horizon: int, render_processes: int | None = None
) -> tuple[float, int]:
    """Frames/s of a pixel env's rollout, and how many render processes drew beside it."""
    env = modnet.make_env(robot, task, num_envs=num_envs, pixels=True, render_processes=render_processes)
    start = time.perf_counter()
    env.rollout(horizon)
    rate = num_envs * horizon / (time.perf_counter() - start)
    processes = env.num_render_processes
    env.close()
    return rate, processes


def renderer_frames_per_s(world, frames: int) -> float:
    data = mujoco.MjData(world.model)
    world.reset_data(data, world.conditions()[0])
    renderer = open_renderer(world.model, *PIXELS_SHAPE[:2])
    out = np.zeros(PIXELS_SHAPE, dtype=np.uint8)
    start = time.perf_counter()
    for _ in range(frames):
        renderer.update_scene(data, camera=CAMERA)
        renderer.render(out=out)
    rate = frames / (time.perf_counter() - start)
    renderer.close()
    return rate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--robot", default="four_link")
    parser.add_argument("--task", default="reach_black")
    parser.add_argument("--num-envs", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--pixel-envs", type=int, default=16, help="copies of the pixel env (GPS: M * N)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    world = modnet.get_world(args.robot, args.task)
    T = world.task.horizon

    cases = ("raw", "batched", "dmcontrol", "pixels", "pixels_1p", "renderer")
    runs: dict[str, list[float]] = {k: [] for k in cases}
    batched_steps_per_s(args.robot, args.task, args.num_envs, 5)  # warm up compilation and caches
    for _ in range(args.repeats):
        runs["raw"].append(raw_steps_per_s(world, args.num_envs * T))
        runs["batched"].append(batched_steps_per_s(args.robot, args.task, args.num_envs, T))
        runs["dmcontrol"].append(dmcontrol_steps_per_s(args.robot, args.task, T))
        rate, render_processes = pixel_env_frames_per_s(args.robot, args.task, args.pixel_envs, T)
        runs["pixels"].append(rate)
        runs["pixels_1p"].append(
            pixel_env_frames_per_s(args.robot, args.task, args.pixel_envs, T, render_processes=0)[0]
        )
        runs["renderer"].append(renderer_frames_per_s(world, args.pixel_envs * T))
    med = {k: statistics.median(v) for k, v in runs.items()}
    for k, v in runs.items():
        print(f"{k:>10}: median {med[k]:>10.0f}/s  runs {[round(x) for x in v]}")
    figures = {
        "world": world.name,
        "num_envs": args.num_envs,
        "horizon": T,
        "repeats": args.repeats,
        "raw_steps_per_s": round(med["raw"]),
        "batched_steps_per_s": round(med["batched"]),
        "dmcontrol_steps_per_s": round(med["dmcontrol"]),
        "pixel_envs": args.pixel_envs,
        "pixel_env_frames_per_s": round(med["pixels"]),
        "pixel_env_render_processes": render_processes,
        "pixel_env_one_process_frames_per_s": round(med["pixels_1p"]),
        "renderer_frames_per_s": round(med["renderer"]),
        "batched_vs_raw": round(med["batched"] / med["raw"], 3),
        "batched_vs_dmcontrol": round(med["batched"] / med["dmcontrol"], 2),
        "pixels_vs_renderer": round(med["pixels"] / med["renderer"], 3),
        "pixels_one_process_vs_renderer": round(med["pixels_1p"] / med["renderer"], 3),
        "render_process_speedup": round(med["pixels"] / med["pixels_1p"], 3),
    }
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
