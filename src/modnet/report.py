"""What a run shows: the zero-shot table (text and CSV), results JSON, learning curves,
the zero-shot bar chart, the fine-tuning curves and the final positions (PNG strip and GIF).

Everything here works from the JSON-able results of :mod:`modnet.evaluate` and the trainer's
history, so figures can be redrawn from a run directory alone.  Figures are drawn with
matplotlib's object API (no pyplot state, no backend to choose) and returned, so a notebook
can show them.

Examples:
    >>> results = {"holdout": "four_link/reach_black", "success_distance": 0.1, "methods": {
    ...     "start": {"distance": [0.8, 0.6], "mean": 0.7, "success_rate": 0.0},
    ...     "composed": {"distance": [0.05, 0.12], "mean": 0.085, "success_rate": 0.5},
    ...     "random": {"distance": [1.2, 1.3], "mean": 1.25, "success_rate": 0.0},
    ...     "wrong_task": {"task": "reach_red", "distance": [0.9, 1.1], "mean": 1.0, "success_rate": 0.0}}}
    >>> print(zero_shot_table(results))
    Zero-shot four_link/reach_black: distance averaged over the last 5 steps (success below 0.1)
    condition  at start  random network  wrong task (reach_red)  composed
            1     0.800           1.200                   0.900     0.050
            2     0.600           1.300                   1.100     0.120
         mean     0.700           1.250                   1.000     0.085
      success      0.00            0.00                    0.00      0.50
"""

from __future__ import annotations

import csv
import io
import json
import os
import platform
import subprocess
from collections.abc import Collection, Mapping, Sequence
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import mujoco
import numpy as np
import torch
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from modnet.files import write_atomically

__all__ = [
    "code_version",
    "final_positions_strip",
    "machine",
    "plot_finetune",
    "plot_learning_curves",
    "plot_zero_shot",
    "save_final_positions",
    "write_json",
    "write_zero_shot_csv",
    "zero_shot_table",
]

LABELS = {"start": "at start", "random": "random network", "wrong_task": "wrong task", "composed": "composed"}
COLORS = {"start": "silver", "random": "tab:gray", "wrong_task": "tab:orange", "composed": "tab:blue"}


def write_json(path: str | os.PathLike, data: Any) -> Path:
    """``data`` as indented JSON, written atomically."""
    path = Path(path)
    text = json.dumps(data, indent=2)
    write_atomically(path, lambda tmp: tmp.write_text(text))
    return path


#: Environment variables that choose which kernels torch, MKL, oneDNN and OpenBLAS run, and so
#: a run's last digits: on an AVX-512 machine, ``MKL_ENABLE_INSTRUCTIONS=AVX2`` alone ends the
#: default job somewhere else (docs/RESULTS.md, "What did not match").
KERNEL_VARIABLES = (
    "ATEN_CPU_CAPABILITY",
    "MKL_ENABLE_INSTRUCTIONS",
    "MKL_CBWR",
    "ONEDNN_MAX_CPU_ISA",
    "OPENBLAS_CORETYPE",
)


def machine() -> dict[str, Any]:
    """What decides a run's last digits besides its code and torch's threads, for ``results.json``:
    the CPU, the kernels torch chose for it (and the variables set to choose them), and the
    numerical libraries' versions.

    GPS feeds each iteration's rounding into the next, so the same command at the same commit
    can end somewhere else on another CPU (docs/RESULTS.md, "What did not match"). With this
    beside ``code``, a figure says where it repeats to the digit.

    Examples:
        >>> sorted(machine())
        ['cpu', 'cpu_capability', 'kernel_variables', 'mujoco', 'numpy', 'torch']
        >>> machine()["torch"] == torch.__version__
        True
        >>> set(machine()["kernel_variables"]) <= set(KERNEL_VARIABLES)  # those set, by name
        True
    """
    return {
        "cpu": _cpu_model(),
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "kernel_variables": {name: os.environ[name] for name in KERNEL_VARIABLES if name in os.environ},
        "torch": torch.__version__,
        "numpy": np.__version__,
        "mujoco": mujoco.__version__,
    }


def _cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (Linux), else what ``platform`` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


RUN_PATHS = ("src/modnet", "domains", "conf", "run.py")
"""The checkout's paths whose tracked files a run executes, relative to its root: what
:func:`code_version` calls dirty when changed."""


def code_version(package_dir: str | os.PathLike | None = None) -> dict[str, Any]:
    """The git commit of the modnet code that ran, for a run's ``results.json``.

    ``{"commit": sha, "dirty": bool}`` where ``package_dir`` (default: this package) is the
    ``src/modnet`` of a git checkout, ``dirty`` meaning that a tracked file of what a run
    executes (:data:`RUN_PATHS`: the package, ``domains/``, ``conf/`` and ``run.py``) differs
    from the commit; edits to the docs, tests or benchmarks leave it ``False``.
    ``{"commit": None, "dirty": None}`` for an installed copy, which has no commit (a
    site-packages inside some other repository does not count as a checkout).

    Examples:
        >>> code_version("/")  # not a modnet checkout
        {'commit': None, 'dirty': None}
    """
    package = Path(package_dir or Path(__file__).parent).resolve()
    unknown = {"commit": None, "dirty": None}

    def git(*args: str) -> str:
        done = subprocess.run(
            ["git", *args], cwd=package, capture_output=True, text=True, check=True, timeout=30
        )
        return done.stdout.strip()

    try:
        top = Path(git("rev-parse", "--show-toplevel")).resolve()
        if package != top / "src" / "modnet":
            return unknown
        paths = [str(top / path) for path in RUN_PATHS]
        return {
            "commit": git("rev-parse", "HEAD"),
            "dirty": bool(git("status", "--porcelain", "--untracked-files=no", "--", *paths)),
        }
    except (OSError, subprocess.SubprocessError):  # no git, or not inside a repository
        return unknown


def _columns(methods: Mapping[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """(header, scores) of the table's columns: the distance at the start (where the run recorded
    it), then the paper's order: random, wrong task, composed."""
    columns = [(LABELS["start"], methods["start"])] if methods.get("start") else []
    columns.append((LABELS["random"], methods["random"]))
    if methods.get("wrong_task"):
        columns.append((f"{LABELS['wrong_task']} ({methods['wrong_task']['task']})", methods["wrong_task"]))
    columns.append((LABELS["composed"], methods["composed"]))
    return columns


def zero_shot_table(results: Mapping[str, Any]) -> str:
    """The paper's table: one row per test condition, random network | wrong task module | composed,
    after the distance each condition starts from."""
    columns = _columns(results["methods"])
    headers = ["condition"] + [h for h, _ in columns]
    rows = [
        [str(i + 1)] + [f"{scores['distance'][i]:.3f}" for _, scores in columns]
        for i in range(len(columns[0][1]["distance"]))
    ]
    rows.append(["mean"] + [f"{scores['mean']:.3f}" for _, scores in columns])
    rows.append(["success"] + [f"{scores['success_rate']:.2f}" for _, scores in columns])
    widths = [max(len(r[i]) for r in [headers, *rows]) for i in range(len(headers))]
    lines = [
        f"Zero-shot {results['holdout']}: distance averaged over the last 5 steps "
        f"(success below {results['success_distance']:g})",
        "  ".join(
            h.ljust(w) if i else h.rjust(w) for i, (h, w) in enumerate(zip(headers, widths, strict=True))
        ),
    ]
    lines += ["  ".join(c.rjust(w) for c, w in zip(row, widths, strict=True)) for row in rows]
    return "\n".join(lines)


def write_zero_shot_csv(results: Mapping[str, Any], path: str | os.PathLike) -> Path:
    """One row per test condition: start, random, best wrong task, each wrong task, composed distances."""
    methods = results["methods"]
    columns = {"start": methods["start"]} if methods.get("start") else {}
    columns["random"] = methods["random"]
    if methods.get("wrong_task"):
        columns["wrong_task"] = methods["wrong_task"]
    columns |= {f"wrong_task:{task}": scores for task, scores in methods["wrong_task_each"].items()}
    columns["composed"] = methods["composed"]
    out = io.StringIO()
    writer = csv.writer(out)
    writer.writerow(["condition", *columns])
    for i in range(len(methods["composed"]["distance"])):
        writer.writerow([i + 1, *(f"{scores['distance'][i]:.6f}" for scores in columns.values())])
    writer.writerow(["mean", *(f"{scores['mean']:.6f}" for scores in columns.values())])
    writer.writerow(["success_rate", *(scores["success_rate"] for scores in columns.values())])
    path = Path(path)
    write_atomically(path, lambda tmp: tmp.write_text(out.getvalue()))
    return path


def _save(fig: Figure, path: str | os.PathLike | None) -> Figure:
    if path is not None:
        fig.savefig(path, dpi=120, bbox_inches="tight")
    return fig


def plot_learning_curves(
    history: Sequence[Mapping[str, Mapping[str, float]]],
    path: str | os.PathLike | None = None,
    metrics: Sequence[str] = ("distance", "sampled_cost"),
) -> Figure:
    """One panel per metric, one line per training world, over GPS iterations."""
    fig = Figure(figsize=(5 * len(metrics), 3.6), layout="constrained")
    axes = fig.subplots(1, len(metrics), squeeze=False)[0]
    worlds = list(history[0]) if history else []
    iterations = np.arange(1, len(history) + 1)
    for ax, metric in zip(axes, metrics, strict=True):
        for world in worlds:
            ax.plot(
                iterations, [step[world].get(metric, np.nan) for step in history], marker=".", label=world
            )
        ax.set_xlabel("GPS iteration")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_ylabel(metric.replace("_", " "))
        if metric == "sampled_cost" and history and min(s[w][metric] for s in history for w in worlds) > 0:
            ax.set_yscale("log")
    if worlds:
        axes[-1].legend(fontsize="x-small", loc="upper left", bbox_to_anchor=(1.02, 1))
    fig.suptitle("training worlds: the controllers' samples per iteration")
    return _save(fig, path)


def plot_zero_shot(results: Mapping[str, Any], path: str | os.PathLike | None = None) -> Figure:
    """Bars per test condition (and their mean): the distance at the start, random network, wrong
    task module, composed."""
    methods = results["methods"]
    keys = [k for k in ("start", "random", "wrong_task", "composed") if methods.get(k)]
    n = len(methods["composed"]["distance"])
    fig = Figure(figsize=(1.2 * (n + 1) + 2, 3.6), layout="constrained")
    ax = fig.subplots()
    width = 0.8 / len(keys)
    x = np.arange(n + 1)
    for i, key in enumerate(keys):
        values = [*methods[key]["distance"], methods[key]["mean"]]
        label = LABELS[key] + (f" ({methods[key]['task']})" if key == "wrong_task" else "")
        ax.bar(x + (i - (len(keys) - 1) / 2) * width, values, width, label=label, color=COLORS[key])
    ax.axhline(results["success_distance"], color="k", lw=0.8, ls="--", label="success distance")
    ax.set_xticks(x, [str(i + 1) for i in range(n)] + ["mean"])
    ax.set_xlabel("test condition")
    ax.set_ylabel("final distance")
    ax.set_title(f"zero-shot {results['holdout']}")
    ax.legend(fontsize="small")
    return _save(fig, path)


def plot_finetune(
    curves: Mapping[str, Sequence[float]],
    success_distance: float,
    path: str | os.PathLike | None = None,
    title: str = "",
    failed: Collection[str] = (),
    training: Mapping[str, Sequence[float]] | None = None,
) -> Figure:
    """The neural network policy's mean test distance per fine-tuning iteration, one line per start;
    the ``failed`` starts (stopped by a numerical failure) end in a cross and say so.
    ``training`` (per start, the same on the world's training conditions) adds each start's
    dotted line in its colour: a few test positions, each solved or not, can belie it.

    Examples:
        >>> fig = plot_finetune({"composed": [0.15, 0.1]}, 0.05, training={"composed": [0.17, 0.12]})
        >>> [line.get_linestyle() for line in fig.axes[0].get_lines()]  # the last one: its legend key
        ['-', ':', '--', ':']
    """
    fig = Figure(figsize=(5.5, 3.6), layout="constrained")
    ax = fig.subplots()
    for start, curve in curves.items():
        label = start.replace("_", " ") + (" (numerical failure)" if start in failed else "")
        (line,) = ax.plot(range(len(curve)), curve, marker=".", label=label)
        if start in failed:
            ax.plot(len(curve) - 1, curve[-1], marker="x", ms=9, color=line.get_color())
        if training and start in training:
            ax.plot(range(len(training[start])), training[start], ls=":", color=line.get_color())
    ax.axhline(success_distance, color="k", lw=0.8, ls="--", label="success distance")
    if training:
        ax.plot([], [], ls=":", color="grey", label="dotted: training conditions")
    ax.set_xlabel("GPS iteration on the held-out world")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel("mean distance (solid: test positions)" if training else "mean test distance")
    ax.set_title(title or "fine-tuning")
    ax.legend(fontsize="small")
    return _save(fig, path)


def _tile(frames: np.ndarray, gap: int = 4) -> np.ndarray:
    """``[B, H, W, 3]`` -> one ``[H, B * (W + gap) - gap, 3]`` image, white gaps between copies."""
    batch, height, _, _ = frames.shape
    spacer = np.full((height, gap, 3), 255, dtype=np.uint8)
    parts = [p for frame in frames for p in (frame, spacer)][:-1]
    return np.concatenate(parts, axis=1) if batch else np.zeros((height, 0, 3), np.uint8)


def final_positions_strip(frames: np.ndarray) -> np.ndarray:
    """The last frame of every condition side by side (``frames``: ``[F, B, H, W, 3]``)."""
    return _tile(frames[-1])


def save_final_positions(
    frames: np.ndarray, png: str | os.PathLike, gif: str | os.PathLike, fps: float = 10.0
) -> None:
    """The final-position strip as a PNG and the whole rollout (conditions side by side) as a GIF."""
    iio.imwrite(png, final_positions_strip(frames))
    movie = np.stack([_tile(step) for step in frames])
    movie = np.concatenate([movie, np.repeat(movie[-1:], int(fps), axis=0)])  # hold the end a second
    iio.imwrite(gif, movie, duration=1000 / fps, loop=0)
