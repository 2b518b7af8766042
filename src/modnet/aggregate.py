"""A leave-one-world-out sweep -> a robot x task heatmap of the zero-shot composed distance.

Every job of ``python run.py -m holdout=all`` writes a ``results.json``; this gathers them
(any depth below the sweep directory), places each held-out world's composed mean test
distance in its (robot, task) cell (the mean over jobs when seeds repeat a world) and
writes ``heatmap.png`` and ``heatmap.csv`` into the sweep directory.

    python -m modnet.aggregate multirun/color_reach_state/2024-05-01_12-00-00

Examples:
    >>> import json, tempfile
    >>> from pathlib import Path
    >>> sweep = Path(tempfile.mkdtemp())
    >>> for i, world in enumerate(["four_link/reach_black", "three_link/reach_red"]):
    ...     (sweep / str(i)).mkdir()
    ...     results = {"universe": "tiny", "holdout": world, "robots": ["three_link", "four_link"],
    ...                "tasks": ["reach_red", "reach_black"],
    ...                "methods": {"composed": {"mean": 0.1 * (i + 1)}}}
    ...     _ = (sweep / str(i) / "results.json").write_text(json.dumps(results))
    >>> heatmap = collect(sweep)
    >>> heatmap.distance.round(2).tolist()
    [[0.2, nan], [nan, 0.1]]
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import os
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from modnet.files import write_atomically

__all__ = ["Heatmap", "collect", "main", "plot_heatmap", "write_heatmap"]


class AggregateError(ValueError):
    """A sweep directory that holds no results, or results of several universes."""


@dataclass
class Heatmap:
    """Composed zero-shot mean distance per held-out (robot, task); NaN where no job held it out."""

    universe: str
    robots: list[str]
    tasks: list[str]
    distance: np.ndarray  # [robots, tasks]
    runs: np.ndarray  # [robots, tasks] how many jobs each cell averages


def collect(sweep_dir: str | os.PathLike) -> Heatmap:
    """Read every ``results.json`` below ``sweep_dir`` into a :class:`Heatmap`."""
    sweep_dir = Path(sweep_dir)
    files = sorted(sweep_dir.rglob("results.json"))
    if not files:
        raise AggregateError(f"no results.json below {sweep_dir}: is it a run.py -m sweep directory?")
    results = [json.loads(f.read_text()) for f in files]
    universes = sorted({r["universe"] for r in results})
    if len(universes) != 1:
        raise AggregateError(f"{sweep_dir} mixes universes {universes}: aggregate one sweep at a time")
    robots, tasks = results[0]["robots"], results[0]["tasks"]
    cells: dict[tuple[int, int], list[float]] = defaultdict(list)
    for r in results:
        robot, task = r["holdout"].split("/")
        cells[robots.index(robot), tasks.index(task)].append(r["methods"]["composed"]["mean"])
    distance = np.full((len(robots), len(tasks)), np.nan)
    runs = np.zeros((len(robots), len(tasks)), dtype=int)
    for (i, j), values in cells.items():
        distance[i, j], runs[i, j] = float(np.mean(values)), len(values)
    return Heatmap(universes[0], robots, tasks, distance, runs)


def plot_heatmap(heatmap: Heatmap, path: str | os.PathLike | None = None) -> Figure:
    """Cells coloured and labelled by the composed distance; blank where no job held the world out."""
    fig = Figure(
        figsize=(1.3 * len(heatmap.tasks) + 2.5, 0.8 * len(heatmap.robots) + 1.8), layout="constrained"
    )
    ax = fig.subplots()
    image = ax.imshow(np.ma.masked_invalid(heatmap.distance), cmap="viridis_r")
    fig.colorbar(image, ax=ax, label="composed zero-shot distance")
    ax.set_xticks(range(len(heatmap.tasks)), heatmap.tasks, rotation=30, ha="right")
    ax.set_yticks(range(len(heatmap.robots)), heatmap.robots)
    ax.set_xlabel("held-out task")
    ax.set_ylabel("held-out robot")
    for (i, j), value in np.ndenumerate(heatmap.distance):
        if not np.isnan(value):
            ax.text(j, i, f"{value:.2f}", ha="center", va="center", color="w", fontsize="small")
    ax.set_title(f"{heatmap.universe}: leave one world out")
    if path is not None:
        fig.savefig(path, dpi=120, bbox_inches="tight")
    return fig


def write_heatmap(heatmap: Heatmap, out_dir: str | os.PathLike) -> tuple[Path, Path]:
    """``heatmap.csv`` (robots x tasks, empty where missing) and ``heatmap.png`` in ``out_dir``."""
    out_dir = Path(out_dir)
    text = io.StringIO()
    writer = csv.writer(text)
    writer.writerow(["robot", *heatmap.tasks])
    for robot, row in zip(heatmap.robots, heatmap.distance, strict=True):
        writer.writerow([robot, *("" if np.isnan(v) else f"{v:.6f}" for v in row)])
    csv_path, png_path = out_dir / "heatmap.csv", out_dir / "heatmap.png"
    write_atomically(csv_path, lambda tmp: tmp.write_text(text.getvalue()))
    plot_heatmap(heatmap, png_path)
    return csv_path, png_path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m modnet.aggregate", description=__doc__.split("\n")[0])
    parser.add_argument("sweep_dir", type=Path, help="a `python run.py -m ...` sweep directory")
    parser.add_argument(
        "--out", type=Path, default=None, help="where to write (default: the sweep directory)"
    )
    args = parser.parse_args(argv)
    try:
        heatmap = collect(args.sweep_dir)
    except AggregateError as err:
        parser.exit(1, f"{parser.prog}: error: {err}\n")
    paths = write_heatmap(heatmap, args.out or args.sweep_dir)
    held_out = f"{int((heatmap.runs > 0).sum())} of {heatmap.distance.size} worlds held out"
    print(f"{heatmap.universe}: {held_out}; wrote {paths[0]} and {paths[1]}")


if __name__ == "__main__":
    main()
