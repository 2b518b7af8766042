"""Many worlds in one pass: ``ModuleBank.forward_worlds`` against a Python loop over worlds.

The colour-reaching grid of the paper: 3 robots x 4 colours minus the held-out
four_link/reach_black = 11 worlds, each with a batch of conditions x samples x steps
observations.  One step = forward of every world's composed network, a regression loss
summed over worlds (the GPS S-step shape), backward.  The loop calls each world's composed
``TensorDictSequential`` in turn (22 module calls); ``forward_worlds`` runs each of the
7 modules once on the concatenation of its worlds' batches.

The headline case (top-level keys of the JSON) is the full batch with the default dropout,
timed in train mode as training runs; ``cases`` adds dropout off and the GPS S-step minibatch
(25 rows per world).  On CPU, dropout's Bernoulli masks cost as much as the matrix products
and are the same work both ways, so the gain is largest without dropout and for small
batches, where per-call overhead dominates.

Prints progress, then ONE JSON object on its last line with the medians and the ratios.

    python benchmarks/bank_forward.py --repeats 30
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
from modnet.worlds import robot_spec, task_spec

ROBOTS = ("three_link", "three_link_short", "four_link")
COLOURS = ("reach_red", "reach_green", "reach_yellow", "reach_black")
HELD_OUT = ("four_link", "reach_black")


def observations(world: World, batch: tuple[int, ...], generator: torch.Generator) -> TensorDict:
    """Random observations of the right sizes (from the specs) and a target action."""
    robot, task = robot_spec(world[0]), task_spec(world[1])
    rand = lambda *shape: torch.randn(*batch, *shape, generator=generator)
    return TensorDict(
        {
            ("robot", "state"): rand(robot.state_dim),
            ("task", "state"): rand(task.state_dim),
            "target": rand(robot.action_dim),
        },
        batch_size=batch,
    )


def paired_medians(
    first: Callable[[], None], second: Callable[[], None], repeats: int, warmup: int
) -> tuple[float, float]:
    """Median milliseconds of two steps timed in alternation (a shared machine's load hits both)."""
    for _ in range(warmup):
        first(), second()
    times: tuple[list[float], list[float]] = ([], [])
    for _ in range(repeats):
        for step, log in zip((first, second), times, strict=True):
            start = time.perf_counter()
            step()
            log.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times[0]), 1e3 * statistics.median(times[1])


def time_case(batch: tuple[int, ...], dropout: float, repeats: int, warmup: int) -> dict:
    """Median forward+backward time of the loop and of ``forward_worlds`` for one setting."""
    worlds = [(r, c) for r in ROBOTS for c in COLOURS if (r, c) != HELD_OUT]
    generator = torch.Generator().manual_seed(0)
    batches = {w: observations(w, batch, generator) for w in worlds}
    bank = ModuleBank.build(ROBOTS, COLOURS, seed=0, dropout=dropout)
    networks = {w: bank.compose(*w)[0] for w in worlds}  # each world's TensorDictSequential

    def loss(means: dict[World, torch.Tensor]) -> torch.Tensor:
        return sum(((means[w] - batches[w]["target"]) ** 2).sum(-1).mean() for w in worlds)

    def loop_means() -> dict[World, torch.Tensor]:
        return {w: networks[w](batches[w].copy())["loc"] for w in worlds}

    def grouped_means() -> dict[World, torch.Tensor]:
        return {w: out["loc"] for w, out in bank.forward_worlds(batches).items()}

    def step(means: Callable[[], dict[World, torch.Tensor]]) -> Callable[[], None]:
        def run() -> None:
            bank.zero_grad(set_to_none=True)
            loss(means()).backward()

        return run

    bank.eval()  # same numbers both ways (no dropout) before timing
    with torch.no_grad():
        loop, grouped = loop_means(), grouped_means()
    max_abs_diff = max(float((loop[w] - grouped[w]).abs().max()) for w in worlds)
    bank.train()  # time what training runs: dropout on
    loop_ms, grouped_ms = paired_medians(step(loop_means), step(grouped_means), repeats, warmup)
    case = {
        "batch_per_world": list(batch),
        "dropout": dropout,
        "loop_ms": round(loop_ms, 3),
        "forward_worlds_ms": round(grouped_ms, 3),
        "speedup": round(loop_ms / grouped_ms, 3),
        "max_abs_diff": max_abs_diff,
    }
    print(
        f"{len(worlds)} worlds, batch {batch} per world, dropout {dropout}: loop {loop_ms:.2f} ms, "
        f"forward_worlds {grouped_ms:.2f} ms, x{loop_ms / grouped_ms:.2f} (max |diff| {max_abs_diff:.1e})"
    )
    return case


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--conditions", type=int, default=4)
    parser.add_argument("--samples", type=int, default=5)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--minibatch", type=int, default=25, help="GPS S-step rows per world")
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    default_dropout = BankConfig().dropout
    full = (args.conditions, args.samples, args.steps)
    print(f"torch threads {torch.get_num_threads()}, {args.repeats} repeats (median)")
    headline = time_case(full, default_dropout, args.repeats, args.warmup)
    others = [
        time_case(full, 0.0, args.repeats, args.warmup),
        time_case((args.minibatch,), default_dropout, args.repeats, args.warmup),
        time_case((args.minibatch,), 0.0, args.repeats, args.warmup),
    ]
    result = {
        "benchmark": "bank_forward",
        "worlds": 11,
        "repeats": args.repeats,
        "threads": torch.get_num_threads(),
        **headline,
        "cases": others,
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
