"""The policy over an iteration's samples from images, in passes of a few rows per world.

Between S-steps, GPS evaluates the composed networks of every training world at all of
that iteration's samples (BADMM: once per round, four times an iteration), without
gradients.  From 64x80 images it took about as long as the S-step's SGD
(`benchmarks/gps_iteration.py universe=color_reach`).  ``GPSTrainer`` runs it in passes of
``PIXEL_ROWS_PER_PASS`` rows per world (``ModuleBank.forward_worlds(..., rows_per_pass=)``).
This times passes of several sizes on the 11 worlds of ``color_reach`` (random images
through the untrained vision bank), in alternation so a shared machine's load hits all
alike, and checks that every size gives the same outputs as the trainer's.  Ratios are
against 512 rows per pass, the trainer's size before.

    python benchmarks/policy_passes.py [--rows 16 64 128] [--images 1024] [--repeats 5]

Prints a line per size, then ONE JSON object on its last line.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch
from pixel_sgd import batch_of

from modnet.bank import ModuleBank
from modnet.gps.trainer import PIXEL_ROWS_PER_PASS
from modnet.universes import get_universe, world_name

REFERENCE_ROWS = 512


def passes(bank: ModuleBank, obs: dict, rows: int) -> torch.Tensor:
    """Every world's mean action at every row, ``rows`` rows per world in each pass."""
    with torch.no_grad():
        out = bank.forward_worlds(obs, rows_per_pass=rows)
    return torch.cat([td["loc"] for td in out.values()], dim=-1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--rows",
        type=int,
        nargs="+",
        default=[16, 64, 128],
        help=f"besides the trainer's {PIXEL_ROWS_PER_PASS} and {REFERENCE_ROWS}",
    )
    parser.add_argument("--images", type=int, default=1024, help="rows per world")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(1)  # as run.py
    sizes = sorted(set(args.rows) | {PIXEL_ROWS_PER_PASS, REFERENCE_ROWS})
    universe = get_universe("color_reach")
    bank = ModuleBank.build(universe.robots, universe.tasks, pixels=True, seed=0).eval()
    generator = torch.Generator().manual_seed(0)
    targets = ("target_action", "precision", "weight")  # batch_of makes S-step rows; keep the inputs
    obs = {
        world_name(w): batch_of(w, args.images, True, generator).exclude(*targets)
        for w in universe.split().training
    }
    trainers = passes(bank, obs, PIXEL_ROWS_PER_PASS)
    same = {rows: torch.equal(passes(bank, obs, rows), trainers) for rows in sizes}
    times: dict[int, list[float]] = {rows: [] for rows in sizes}
    for _ in range(args.repeats):
        for rows in sizes:
            start = time.perf_counter()
            passes(bank, obs, rows)
            times[rows].append(1e3 * (time.perf_counter() - start) / (args.images * len(obs)))
    ms = {rows: statistics.median(t) for rows, t in times.items()}
    for rows, value in ms.items():
        print(f"{rows:5d} rows per world and pass: {value:.3f} ms per image, same outputs: {same[rows]}")
    print(
        json.dumps(
            {
                "benchmark": "policy_passes",
                "worlds": len(obs),
                "images_per_world": args.images,
                "repeats": args.repeats,
                "trainer_rows_per_pass": PIXEL_ROWS_PER_PASS,
                "median_ms_per_image": {str(rows): round(v, 4) for rows, v in ms.items()},
                "same_outputs": {str(rows): v for rows, v in same.items()},
                "reference_vs_trainer": round(ms[REFERENCE_ROWS] / ms[PIXEL_ROWS_PER_PASS], 2),
            }
        )
    )


if __name__ == "__main__":
    main()
