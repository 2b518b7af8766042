"""One S-step SGD step from images: the colour-reach vision bank against the same bank from states.

The S-step of the image experiments (``color_reach``, ``visual_manipulation``) regresses
every training world's composed policy onto its controllers' actions, from 64x80 images.
One SGD step = :class:`~modnet.gps.loss.PolicyRegressionLoss` over the 11 training worlds
of the colour-reach grid (``batch_per_world`` rows each), backward, Adam.  Timed, in
alternation so a shared machine's load hits all alike:

* ``state``: the bank of ``color_reach_state`` (the reference: what the state experiments pay);
* ``pixels_stride1``: the vision bank with both convolutions at stride 1 (the layout before stride 2);
* ``pixels``: the vision bank as built now (``BankConfig.conv_strides``, first conv stride 2);
* ``pixels_2_threads``: the same step on 2 torch threads (run.py's ``threads=2``) instead of 1.

Every case but the last runs on 1 thread, as run.py does by default.  Prints progress, then
ONE JSON object on its last line with the medians and the ratios.

    python benchmarks/pixel_sgd.py --repeats 5
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable

import torch
from tensordict import TensorDict

from modnet.bank import BankConfig, ModuleBank, World
from modnet.gps.loss import PolicyRegressionLoss
from modnet.specs import EE_DIM, PIXELS_SHAPE
from modnet.universes import get_universe, world_name
from modnet.worlds import robot_spec, task_spec


def batch_of(world: World, rows: int, pixels: bool, generator: torch.Generator) -> TensorDict:
    """Random S-step rows of the right sizes: observations, target action, precision, weight."""
    robot, task = robot_spec(world[0]), task_spec(world[1])
    rand = lambda *shape: torch.randn(rows, *shape, generator=generator)
    td = TensorDict(
        {
            ("robot", "state"): rand(robot.state_dim),
            ("task", "state"): rand(task.state_dim),
            "target_action": rand(robot.action_dim),
            "precision": torch.eye(robot.action_dim).expand(rows, -1, -1),
            "weight": torch.ones(rows),
        },
        batch_size=[rows],
    )
    if pixels:
        td["task", "ee"] = rand(EE_DIM)
        shape = (rows, *PIXELS_SHAPE)
        td["task", "pixels"] = torch.randint(0, 256, shape, generator=generator, dtype=torch.uint8)
    return td


def sgd_step(config: BankConfig, pixels: bool, rows: int) -> Callable[[], None]:
    universe = get_universe("color_reach")
    training = universe.split().training
    bank = ModuleBank.build(universe.robots, universe.tasks, config=config, pixels=pixels, seed=0)
    loss = PolicyRegressionLoss(bank)
    optimizer = torch.optim.Adam(bank.parameters(), lr=1e-3)
    generator = torch.Generator().manual_seed(0)
    batch = TensorDict({world_name(w): batch_of(w, rows, pixels, generator) for w in training}, batch_size=[])
    bank.train()

    def step() -> None:
        optimizer.zero_grad(set_to_none=True)
        loss(batch)["loss_regression"].backward()
        optimizer.step()

    return step


def on_threads(step: Callable[[], None], threads: int) -> Callable[[], None]:
    """``step`` run on ``threads`` torch threads, the count restored after it."""

    def run() -> None:
        before = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            step()
        finally:
            torch.set_num_threads(before)

    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch-per-world", type=int, default=128, help="GPSConfig.batch_per_world")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(1)  # as run.py

    now = BankConfig()
    cases = {
        "state": sgd_step(now, False, args.batch_per_world),
        "pixels_stride1": sgd_step(BankConfig(conv_strides=(1, 1)), True, args.batch_per_world),
        "pixels": sgd_step(now, True, args.batch_per_world),
        "pixels_2_threads": on_threads(sgd_step(now, True, args.batch_per_world), 2),
    }
    times: dict[str, list[float]] = {name: [] for name in cases}
    for step in cases.values():  # warm-up
        step()
    for _ in range(args.repeats):
        for name, step in cases.items():
            start = time.perf_counter()
            step()
            times[name].append(1e3 * (time.perf_counter() - start))
    ms = {name: statistics.median(t) for name, t in times.items()}
    for name, value in ms.items():
        print(f"{name:15s} {value:9.1f} ms per SGD step (11 worlds x {args.batch_per_world} rows)")
    result = {
        "benchmark": "pixel_sgd",
        "worlds": 11,
        "batch_per_world": args.batch_per_world,
        "repeats": args.repeats,
        "threads": torch.get_num_threads(),
        "conv_strides": list(now.conv_strides),
        "median_ms": {name: round(value, 1) for name, value in ms.items()},
        "pixels_vs_state": round(ms["pixels"] / ms["state"], 2),
        "stride1_vs_strided": round(ms["pixels_stride1"] / ms["pixels"], 2),
        "one_vs_two_threads": round(ms["pixels"] / ms["pixels_2_threads"], 2),
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
