"""Turn run.py outputs into the machine-readable results under ``docs/results/``.

    # one zero-shot job (python run.py ... eval.random_conditions=20)
    python benchmarks/publish_results.py zero-shot RUN_DIR --experiment color_reach_state
    # a leave-one-world-out sweep (python run.py -m holdout=all ...)
    python benchmarks/publish_results.py lowo SWEEP_DIR --experiment color_reach_state_lowo
    # the same held-out world trained by BADMM and by MDGPS
    python benchmarks/publish_results.py algorithms BADMM_DIR MDGPS_DIR --experiment badmm_vs_mdgps
    # published seeds of one zero-shot experiment, drawn beside the paper's table
    python benchmarks/publish_results.py figure docs/results/color_reach_32conditions_clip_targets*.json \
        --experiment color_reach_32conditions_clip_targets

Each writes ``docs/results/<experiment>.json`` (and, for a sweep, the heatmap
``docs/<experiment>.png``; for a fine-tuning run, its curves ``docs/<experiment>_finetune.png``)
from the jobs' own ``results.json`` files, with the command that produced them (read from
Hydra's ``.hydra/overrides.yaml``), the environment samples, the wall time and the code's commit, and
the paper's numbers where the paper has that experiment.  The last line is the written JSON.

``figure`` reads published JSON files instead of run directories (the seeds of one experiment:
the same command but for ``seed=``) and draws ``docs/<experiment>_vs_paper.png``: at the 4 test
positions the paper's bars beside ours (each seed a dot, the bar their mean), and on the random
positions each seed's mean with its 95% interval.  Its last line is a JSON summary of what it drew.

``finetune-figure`` reads published fine-tuning JSON files (the seeds of one or more experiments)
and draws ``docs/<experiment>.png``: per experiment, every start's samples on the training
conditions and its network at the test positions, iteration by iteration, at each seed:

    python benchmarks/publish_results.py finetune-figure docs/results/manipulation_*_4scenes_*.json \
        --experiment manipulation_finetune_4scenes

``finetune-table`` reads the same files, groups them the same way and writes nothing: it prints
RESULTS.md's fine-tuning cells, a markdown table per experiment (a row per seed, a column per
start: the network's best distance at the test positions (its iteration) / its mean over the
curve, and the first iteration below the success distance and how many were; then its samples'
first -> last iteration and first success), each start's count of seeds whose network reached
it and the mean of the seeds' means, and with several experiments (say, draws of one setting)
in how many of them each seed reached it; its last line is the same as JSON:

    python benchmarks/publish_results.py finetune-table docs/results/manipulation_*_elu_*_seed*_epyc.json

``per-scene-figure`` reads outputs of ``benchmarks/finetune_per_scene.py`` (its last lines,
saved as JSON files) and draws ``docs/<experiment>.png``: a panel per output, every scene's
samples iteration by iteration, coloured by when one of them first moved the object:

    python benchmarks/publish_results.py per-scene-figure docs/results/finetune_per_scene_*.json \
        --experiment finetune_per_scene

With ``--iterations N`` the two ``finetune-`` kinds read each run's first N iterations only, the
figures of a shorter budget from longer runs (:func:`first_iterations`). With
``--network-on training`` the table reads the network run on the conditions its samples were
drawn on instead of at the test positions: whether it follows its own samples.
"""

from __future__ import annotations

import argparse
import json
import shlex
import shutil
import textwrap
from pathlib import Path

import numpy as np
import yaml
from matplotlib.figure import Figure
from matplotlib.ticker import FormatStrFormatter, LogLocator, MaxNLocator, NullFormatter

from modnet.aggregate import collect, write_heatmap
from modnet.files import write_atomically
from modnet.report import COLORS, LABELS
from modnet.universes import get_universe

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

#: The paper's tables (distance over the last 5 steps at its 4 test positions).
PAPER = {
    "color_reach": {
        "ours": [0.12, 0.28, 0.21, 0.08],
        "random": [1.16, 1.29, 1.35, 1.29],
        "wrong_task": [2.34, 1.75, 1.65, 2.41],
    },
    "visual_manipulation": {
        "ours": [0.48, 0.19, 0.25, 0.23],
        "random": [0.95, 1.79, 1.54, 0.94],
        "wrong_task": [0.95, 1.14, 1.27, 1.32],
    },
}


#: Universes whose table the paper reports for a sibling universe (the same grid from images).
PAPER_COUNTERPART = {"color_reach_state": "color_reach"}

#: The paper's fine-tuning claim (section V-B figure), for which it gives curves, not numbers.
PAPER_FINETUNE = (
    "the composed start without shaping learns faster than scratch with shaping; "
    "scratch without shaping makes no progress"
)


def command(run_dir: Path, machine: dict | None = None) -> str:
    """The ``python run.py`` line that produced the job in ``run_dir`` (its Hydra overrides);
    ``resume=true`` is left out: a resumed run gives what the uninterrupted one gives.  Led by
    the variables that chose the run's kernels (see :func:`kernel_settings`)."""
    overrides = yaml.safe_load((run_dir / ".hydra" / "overrides.yaml").read_text()) or []
    kept = [o for o in overrides if not o.startswith(("hydra.run.dir", "resume="))]
    return " ".join([*kernel_settings(machine), "python run.py", *kept])


def sweep_command(sweep_dir: Path, num_worlds: int, machine: dict | None = None) -> str:
    """The ``python run.py -m`` line of a sweep, ``holdout=all`` when it held out every world."""
    overrides = yaml.safe_load((sweep_dir / "multirun.yaml").read_text())["hydra"]["overrides"]
    hydra = [o for o in overrides["hydra"] if not o.startswith(("hydra.mode", "hydra.sweep.dir"))]
    task = [
        "holdout=all" if o.startswith("holdout=") and o.count(",") + 1 == num_worlds else o
        for o in overrides["task"]
    ]
    return " ".join([*kernel_settings(machine), "python run.py -m", *task, *hydra])


def kernel_settings(machine: dict | None) -> list[str]:
    """``NAME=value`` for each variable that chose a run's kernels, as ``results.json``'s
    ``machine`` records them (``modnet.report.KERNEL_VARIABLES``): they change its figures, so
    a published command sets them as the run did."""
    variables = (machine or {}).get("kernel_variables") or {}
    return [f"{name}={shlex.quote(value)}" for name, value in variables.items()]


def _round(x: float) -> float:
    return round(float(x), 4)


def _rounded(value):
    """Floats rounded as in every published figure, through nested dicts; ints kept."""
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    return _round(value) if isinstance(value, float) else value


def _wall_s(results: dict) -> float:
    """The seconds a job measured (training, evaluation, fine-tuning), summed."""
    return round(sum(results["seconds"].values()), 1)


def zero_shot(run_dir: Path, experiment: str, docs: Path = DOCS) -> dict:
    results = json.loads((run_dir / "results.json").read_text())
    methods = results["methods"]
    wrong = methods["wrong_task"]  # None where no other task module reads this world's task state
    n = len(methods["composed"]["distance"])
    wrong_distance = wrong["distance"] if wrong else [None] * n
    # where each position starts (an untouched object's distance); None: run before results recorded it
    start = methods["start"]["distance"] if methods.get("start") else [None] * n
    ours, random = methods["composed"]["distance"], methods["random"]["distance"]
    rows = zip(ours, random, wrong_distance, start, strict=True)
    names = ["composed", "random"] + (["wrong_task"] if wrong else [])
    means = names + (["start"] if methods.get("start") else [])
    out = {
        "experiment": experiment,
        "universe": results["universe"],
        "holdout": results["holdout"],
        "algo": results["algo"],
        "seed": results["seed"],
        "command": command(run_dir, results.get("machine")),
        "success_distance": results["success_distance"],
        "wrong_task_module": wrong["task"] if wrong else None,
        "positions": [
            {
                "ours": _round(o),
                "random": _round(r),
                "wrong_task": None if w is None else _round(w),
                "start": None if s is None else _round(s),
            }
            for o, r, w, s in rows
        ],
        "means": {name: _round(methods[name]["mean"]) for name in means},
        "success_rate": {name: methods[name]["success_rate"] for name in names},
        "samples": results["samples"],
        "wall_s": _wall_s(results),
        "code": results.get("code"),  # None: run before results.json recorded it
        "machine": results.get("machine"),  # None: run before results.json recorded it
    }
    paper = PAPER_COUNTERPART.get(results["universe"], results["universe"])
    if paper in PAPER and paper_holdout(results):
        out["paper"] = {"universe": paper, **PAPER[paper]}
    if results.get("random_conditions"):
        out["extended"] = _extended(results)
    if "pretrain" in results:  # the vision modules' pose pretraining: rendered scenes, not env steps
        out["pretrain"] = {
            module: {k: _rounded(v) for k, v in figures.items() if k != "seconds"}
            for module, figures in results["pretrain"].items()
        }
    if "finetune_failed" in results:  # {start: the numerical error that stopped it}; its curve ends there
        out["finetune_failed"] = results["finetune_failed"]
    if "finetune" in results:
        out["finetune"] = finetuning(results)
        docs.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(run_dir / "finetune.png", docs / f"{experiment}_finetune.png")
    return out


def finetuning(results: dict) -> dict:
    """Fine-tuning curves (iteration -> mean test distance; 0: before), iterations to success and,
    where the run recorded them, the mean distance of each iteration's samples (entry i:
    iteration i + 1), the network's on the training conditions (entry i: after i iterations)
    and each iteration's GPS diagnostics (entry i: iteration i + 1)."""
    success = results["success_distance"]
    curves = {start: [_round(d) for d in curve] for start, curve in results["finetune"].items()}
    return {
        "curves": curves,
        "iterations_to_success": _iterations_to_success(curves, success),
        "sampled": {
            start: [_round(d) for d in curve] for start, curve in results.get("finetune_sampled", {}).items()
        }
        or None,
        # the network's mean distance on the training conditions after 0, 1, ... iterations
        "training_conditions": {
            start: [_round(d) for d in curve] for start, curve in results.get("finetune_training", {}).items()
        }
        or None,
        "samples": results.get("finetune_samples"),
        # each iteration's GPS diagnostics (entry i: iteration i + 1), to 4 significant digits,
        # since some (eta, the KL) are far below the distances' 4 decimals
        "diagnostics": {
            start: [{k: float(f"{v:.4g}") for k, v in d.items()} for d in iterations]
            for start, iterations in results.get("finetune_diagnostics", {}).items()
        }
        or None,
        "paper": PAPER_FINETUNE if paper_holdout(results) else None,
    }


def paper_holdout(results: dict) -> bool:
    """Whether the run held out the world the paper held out (its universe's default): only
    then do the paper's figures stand beside it."""
    return results["holdout"] == get_universe(results["universe"]).holdout


def _extended(results: dict) -> dict | None:
    """The zero-shot scores on the extra random positions (``eval.random_conditions``), if any."""
    extra = results.get("random_conditions")
    if not extra:
        return None
    m = extra["methods"]
    return {
        "n": extra["num_conditions"],
        "seed": extra["seed"],
        "ours_mean": _round(m["composed"]["mean"]),
        "ours_ci95": [_round(c) for c in m["composed"]["ci95"]],
        "ours_success_rate": m["composed"]["success_rate"],
        "random_mean": _round(m["random"]["mean"]),
        "wrong_task_mean": _round(m["wrong_task"]["mean"]) if m["wrong_task"] else None,
        "start_mean": _round(m["start"]["mean"]) if m.get("start") else None,
    }


def lowo(sweep_dir: Path, experiment: str, docs: Path = DOCS) -> dict:
    files = sorted(sweep_dir.rglob("results.json"))
    jobs = []
    for f in files:
        r = json.loads(f.read_text())
        m = r["methods"]
        jobs.append(
            {
                "holdout": r["holdout"],
                "composed": _round(m["composed"]["mean"]),
                "random": _round(m["random"]["mean"]),
                "wrong_task": _round(m["wrong_task"]["mean"]) if m["wrong_task"] else None,
                "composed_success_rate": m["composed"]["success_rate"],
                "beats_both": bool(
                    m["composed"]["mean"] < m["random"]["mean"]
                    and (not m["wrong_task"] or m["composed"]["mean"] < m["wrong_task"]["mean"])
                ),
                "samples": r["samples"],
                "wall_s": _wall_s(r),
                "code": r.get("code"),
                "machine": r.get("machine"),
            }
        )
    heatmap = collect(sweep_dir)
    order = [f"{robot}/{task}" for robot in heatmap.robots for task in heatmap.tasks]
    jobs.sort(key=lambda job: order.index(job["holdout"]))  # the heatmap's order, robot-major
    _, png = write_heatmap(heatmap, sweep_dir)
    figure = docs / f"{experiment}.png"
    figure.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(png, figure)
    composed = np.array([j["composed"] for j in jobs])
    return {
        "experiment": experiment,
        "universe": heatmap.universe,
        "command": sweep_command(sweep_dir, heatmap.distance.size, jobs[0]["machine"] if jobs else None),
        "robots": heatmap.robots,
        "tasks": heatmap.tasks,
        "composed_distance": [[None if np.isnan(v) else _round(v) for v in row] for row in heatmap.distance],
        "jobs": jobs,
        "worlds_beating_both_baselines": sum(j["beats_both"] for j in jobs),
        "composed_mean_over_worlds": _round(composed.mean()),
        "figure": figure.name,
        "samples": {k: sum(j["samples"][k] for j in jobs) for k in ("trajectories", "env_steps")},
        "wall_s": round(sum(j["wall_s"] for j in jobs), 1),
    }


def last_iteration(run_dir: Path) -> list[dict]:
    return list(json.loads((run_dir / "history.json").read_text())[-1]["worlds"].values())


def algorithms(run_dirs: list[Path], experiment: str) -> dict:
    runs = []
    for run_dir in run_dirs:
        r = json.loads((run_dir / "results.json").read_text())
        composed = r["methods"]["composed"]
        runs.append(
            {
                "algo": r["algo"],
                "holdout": r["holdout"],
                "command": command(run_dir, r.get("machine")),
                "composed_distance": [_round(d) for d in composed["distance"]],
                "composed_mean": _round(composed["mean"]),
                "composed_success_rate": composed["success_rate"],
                "extended": _extended(r),
                # the training worlds' controller samples in the last iteration
                "final_sample_distance": _round(np.mean([w["distance"] for w in last_iteration(run_dir)])),
                "samples": r["samples"],
                "wall_s": _wall_s(r),
                "code": r.get("code"),
                "machine": r.get("machine"),
            }
        )
    return {"experiment": experiment, "runs": runs}


#: command-line options that change how a job runs, not what it computes (seed aside, see figure);
#: :func:`command` has already left out ``resume=`` and ``hydra.run.dir``
_SAME_EXPERIMENT_IGNORES = ("seed=", "threads=", "logger=", "hydra.")


#: options as older commits spelt them, and their spelling now (the same code path): before
#: d0efcfb the relabelling was a flag, ``true`` what ``sampled`` is now
_RENAMED_OPTIONS = {"eval.finetune_relabel_policy_states=true": "eval.finetune_relabel_policy_states=sampled"}


def _experiment_of(command: str) -> str:
    """A published command without its seed and without options that do not change the numbers,
    each option spelt as it is now.

    Examples:
        >>> _experiment_of("python run.py seed=3 logger=csv eval.finetune_relabel_policy_states=true")
        'python run.py eval.finetune_relabel_policy_states=sampled'
    """
    options = (_RENAMED_OPTIONS.get(o, o) for o in command.split())
    return " ".join(o for o in options if not o.startswith(_SAME_EXPERIMENT_IGNORES))


def _log_scale(ax) -> None:
    """A log y axis labelled in plain numbers (0.1, 0.2, 0.5, 1), not powers of ten."""
    ax.set_yscale("log")
    ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
    ax.yaxis.set_minor_formatter(NullFormatter())


def paper_figure(published: list[dict]) -> tuple[Figure, dict]:
    """The seeds of one zero-shot experiment (published JSON, see :func:`zero_shot`) beside the
    paper's table: a figure and a summary of what it shows.

    Left, the paper's 4 test positions and their mean: the paper's bars (hatched) beside ours for
    the composed modules, the random network and the wrong task module; ours are the mean over
    the seeds, each seed a dot.  Right, where the runs scored random positions: each seed's mean
    with its 95% confidence interval, the random network's and the wrong task module's means,
    and the paper's mean over its test positions as a line.  Raises ``ValueError`` for runs of
    different experiments, a repeated seed, or an experiment the paper has no table for.
    """
    if not published:
        raise ValueError("no published results to draw")
    first = published[0]
    experiments = {_experiment_of(p["command"]) for p in published}
    if len(experiments) > 1:
        raise ValueError(f"the runs are not one experiment at several seeds: {sorted(experiments)}")
    seeds = [p["seed"] for p in published]
    if len(set(seeds)) < len(seeds):
        raise ValueError(f"a seed is given twice: {seeds}")
    if "paper" not in first:
        raise ValueError(
            f"the paper has no table for {first['universe']} holding out {first['holdout']}; "
            f"it has: {', '.join(f'{u} ({get_universe(u).holdout} held out)' for u in PAPER)}"
        )
    published = sorted(published, key=lambda p: p["seed"])
    paper = first["paper"]
    methods = {"ours": "composed", "random": "random", "wrong_task": "wrong_task"}  # published -> run's name
    keys = {key: LABELS[method] for key, method in methods.items()}
    colours = {key: COLORS[method] for key, method in methods.items()}  # as in each run's zero_shot.png
    n = len(paper["ours"])
    here = {  # [seeds, positions + the run's own mean]; NaN where a run had no wrong task module
        key: np.array(
            [[*(pos[key] for pos in p["positions"]), p["means"].get(method)] for p in published], dtype=float
        )
        for key, method in methods.items()
    }
    theirs = {key: np.array([*paper[key], np.mean(paper[key])]) for key in keys}

    extended = [p for p in published if p.get("extended")]
    fig = Figure(figsize=(11 if extended else 7.5, 4.4), layout="constrained")
    axes = fig.subplots(1, 2 if extended else 1, squeeze=False, width_ratios=[2, 1] if extended else None)[0]
    ax = axes[0]
    x = np.arange(n + 1)
    width = 0.8 / (2 * len(keys))
    for i, key in enumerate(keys):
        left = x + (2 * i - len(keys) + 0.5) * width
        ax.bar(
            left,
            theirs[key],
            width,
            color="white",
            edgecolor=colours[key],
            hatch="///",
            label=f"{keys[key]}, paper",
        )
        ax.bar(left + width, np.nanmean(here[key], 0), width, color=colours[key], label=f"{keys[key]}, here")
        if len(published) > 1:
            for row in here[key]:
                ax.plot(left + width, row, ls="none", marker=".", ms=4, color="k")
    if all(pos.get("start") is not None for p in published for pos in p["positions"]):  # the scene's own
        start = np.array([pos["start"] for pos in first["positions"]])
        ax.hlines([*start, start.mean()], x - 0.42, x + 0.42, colors="k", lw=1.2, label="at start")
    ax.axhline(first["success_distance"], color="k", lw=0.8, ls="--", label="success distance")
    ax.set_xticks(x, [str(i + 1) for i in range(n)] + ["mean"])
    ax.set_xlabel("the paper's test position")
    ax.set_ylabel("distance over the last 5 steps")
    _log_scale(ax)  # the composed bars are a tenth of the baselines': a ratio reads as a height
    drawn = f"{len(published)} seeds (dots)" if len(published) > 1 else f"seed {first['seed']}"
    ax.set_title(f"{first['holdout']} held out, {drawn}")
    ax.legend(fontsize="x-small", ncol=4, loc="upper center", bbox_to_anchor=(0.5, -0.17))

    if extended:
        ax = axes[1]
        xs = np.arange(len(extended))
        means = np.array([p["extended"]["ours_mean"] for p in extended])
        ci = np.array([p["extended"]["ours_ci95"] for p in extended])
        ax.errorbar(
            xs,
            means,
            yerr=[means - ci[:, 0], ci[:, 1] - means],
            fmt="o",
            color=colours["ours"],
            capsize=3,
            label="composed (95% interval)",
        )
        for key, name in (("random", "random_mean"), ("wrong_task", "wrong_task_mean")):
            ax.plot(
                xs,
                [p["extended"][name] or np.nan for p in extended],
                ls="none",
                marker="s",
                color=colours[key],
                label=f"{keys[key]} (mean)",
            )
        ax.axhline(
            theirs["ours"][-1], color=colours["ours"], lw=0.8, ls=":", label="composed, paper (mean of its 4)"
        )
        ax.axhline(first["success_distance"], color="k", lw=0.8, ls="--")
        ax.set_xticks(xs, [str(p["seed"]) for p in extended])
        ax.set_xlim(-0.5, len(extended) - 0.5)
        _log_scale(ax)
        ax.set_xlabel("seed")
        ax.set_title(f"{extended[0]['extended']['n']} random positions")
        ax.legend(fontsize="x-small", ncol=2, loc="upper center", bbox_to_anchor=(0.5, -0.17))
    fig.suptitle(first["command"].replace(f"seed={first['seed']}", "seed=S"), fontsize="small")

    summary = {
        "universe": first["universe"],
        "holdout": first["holdout"],
        "seeds": [p["seed"] for p in published],
        "positions_mean_over_seeds": {key: [_round(v) for v in np.nanmean(here[key], 0)] for key in keys},
        "at_or_below_paper": [int((p_ours <= paper["ours"]).sum()) for p_ours in here["ours"][:, :n]],
        "ratio_to_random": [_round(r) for r in here["ours"][:, n] / here["random"][:, n]],
        "random_positions_mean": [p["extended"]["ours_mean"] for p in extended],
        "paper": {key: [_round(v) for v in theirs[key]] for key in keys},
    }
    return fig, summary


#: each fine-tuning start's colour, as in every run's ``finetune.png`` (matplotlib's cycle, in
#: ``modnet.evaluate.FINETUNE_STARTS`` order)
START_COLORS = {"composed": "C0", "wrong_task": "C1", "scratch_shaping": "C2", "scratch_no_shaping": "C3"}


def _first_below(curve: list[float], bound: float, offset: int) -> int | None:
    """The iteration (entry i is iteration i + ``offset``) of the first entry below ``bound``."""
    return next((i + offset for i, d in enumerate(curve) if d < bound), None)


def _iterations_to_success(curves: dict[str, list[float]], success: float) -> dict[str, int | None]:
    """Per start, the first iteration whose mean test distance (``curves``, entry 0: before any)
    is below ``success``; None: never. The published ``iterations_to_success``."""
    return {start: _first_below(curve, success, 0) for start, curve in curves.items()}


def first_iterations(published: list[dict], iterations: int) -> list[dict]:
    """Published fine-tuning runs cut to their first ``iterations`` iterations, as a run of that
    many would have published them: each start's network curve (and its curve on the training
    conditions) to its first ``iterations + 1`` points, its samples' curve and diagnostics to
    their first ``iterations``, its iterations to success recomputed from the cut curves, and
    its samples drawn scaled to them. Fine-tuning does not look ahead, so a run of 100 iterations
    repeats the first 50 of a run of 50 with the same command otherwise: the figures of a
    shorter budget, read from longer runs. Raises ``ValueError`` where a run has fewer
    iterations, naming its seed.

    Examples:
        >>> run = {"seed": 0, "success_distance": 0.05,
        ...        "finetune": {"curves": {"composed": [0.15, 0.1, 0.04]},
        ...                     "sampled": {"composed": [0.12, 0.03]},
        ...                     "iterations_to_success": {"composed": 2},
        ...                     "samples": {"composed": {"trajectories": 20, "env_steps": 400}}}}
        >>> cut = first_iterations([run], 1)[0]["finetune"]
        >>> cut["curves"], cut["sampled"], cut["iterations_to_success"]
        ({'composed': [0.15, 0.1]}, {'composed': [0.12]}, {'composed': None})
        >>> cut["samples"]
        {'composed': {'trajectories': 10, 'env_steps': 200}}
    """
    if iterations < 1:
        raise ValueError(f"--iterations must be at least 1, got {iterations}")
    cut = []
    for p in published:
        finetune = dict(p["finetune"])
        ran = {start: len(curve) - 1 for start, curve in finetune["curves"].items()}
        for start, n in ran.items():
            if n < iterations:
                raise ValueError(f"seed {p['seed']}'s {start} ran {n} iterations, fewer than {iterations}")
        lengths = {"curves": 1, "training_conditions": 1, "sampled": 0, "diagnostics": 0}
        for key, extra in lengths.items():
            if finetune.get(key):
                finetune[key] = {start: curve[: iterations + extra] for start, curve in finetune[key].items()}
        if "iterations_to_success" in finetune:
            curves, success = finetune["curves"], p["success_distance"]
            finetune["iterations_to_success"] = _iterations_to_success(curves, success)
        if "samples" in finetune:
            finetune["samples"] = {
                start: {kind: count * iterations // ran[start] for kind, count in drawn.items()}
                for start, drawn in finetune["samples"].items()
            }
        cut.append({**p, "finetune": finetune})
    return cut


def _experiments(published: list[dict]) -> tuple[dict[str, list[dict]], list[str]]:
    """Published runs grouped into experiments by their command less the seed, each sorted by
    seed and named by the options that set it apart from the others ("(no further options)"
    where none do), and the options common to all. Raises ``ValueError`` for no runs or a
    repeated seed within an experiment."""
    if not published:
        raise ValueError("no published results to read")
    groups: dict[str, list[dict]] = {}
    for p in published:
        groups.setdefault(_experiment_of(p["command"]), []).append(p)
    for experiment, runs in groups.items():
        seeds = [p["seed"] for p in runs]
        if len(set(seeds)) < len(seeds):
            raise ValueError(f"a seed is given twice for {experiment!r}: {seeds}")
        runs.sort(key=lambda p: p["seed"])
    options = {experiment: experiment.split() for experiment in groups}
    common = [o for o in next(iter(options.values())) if all(o in opts for opts in options.values())]
    named = {
        " ".join(o for o in options[experiment] if o not in common) or "(no further options)": runs
        for experiment, runs in groups.items()
    }
    return named, common


def finetune_figure(published: list[dict]) -> tuple[Figure, dict]:
    """Fine-tuning runs (published JSON, see :func:`finetuning`), grouped into experiments by
    their command less the seed: one column per experiment, each start's curve at every seed
    (thin) and their median (thick, with several seeds). Top, the distance of each iteration's
    samples on the world's training conditions (the controllers, as they explore); bottom, the
    network's mean distance at the test positions (0: before fine-tuning). The summary gives,
    per experiment and start, the first iteration below the success distance at each seed that
    ran the start (seed -> iteration; None: never), for the samples and for the network.
    Raises ``ValueError`` for a repeated seed within an experiment, or runs that recorded no
    samples' distances.
    """
    for p in published:
        if not p["finetune"].get("sampled"):
            raise ValueError(f"seed {p['seed']} of {p['command']!r} recorded no samples' distances")
    groups, common = _experiments(published)

    fig = Figure(figsize=(5 * len(groups) + 0.5, 7), layout="constrained")
    axes = fig.subplots(2, len(groups), squeeze=False, sharey="row")
    summary = {}
    for column, (name, runs) in enumerate(groups.items()):
        success = runs[0]["success_distance"]
        found: dict[str, dict[str, dict[int, int | None]]] = {}
        for row, (key, offset) in enumerate((("sampled", 1), ("curves", 0))):
            ax = axes[row, column]
            for start, colour in START_COLORS.items():
                drawn = [p for p in runs if start in p["finetune"][key]]
                curves = [p["finetune"][key][start] for p in drawn]
                if not curves:
                    continue
                for curve in curves:
                    ax.plot(range(offset, offset + len(curve)), curve, color=colour, lw=0.7, alpha=0.4)
                if len(curves) > 1 and len({len(c) for c in curves}) == 1:
                    median = np.median(np.array(curves), 0)
                    ax.plot(range(offset, offset + len(median)), median, color=colour, lw=2.2)
                ax.plot([], [], color=colour, lw=2.2, label=start.replace("_", " "))
                where = "samples" if key == "sampled" else "network"
                found.setdefault(start, {})[where] = {
                    p["seed"]: _first_below(c, success, offset) for p, c in zip(drawn, curves, strict=True)
                }
            ax.axhline(success, color="k", lw=0.8, ls="--", label="success distance")
            ax.set_xlabel("GPS iteration on the held-out world")
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        axes[0, column].legend(fontsize="x-small")  # the starts this experiment drew
        seeds = [p["seed"] for p in runs]
        title = f"{textwrap.fill(name, 60)}\nseeds {', '.join(map(str, seeds))}"
        axes[0, column].set_title(title, fontsize="small")
        summary[name] = {"seeds": seeds, "first_success": found}
    axes[0, 0].set_ylabel("samples, training conditions")
    axes[1, 0].set_ylabel("network, test positions")
    fig.suptitle(textwrap.fill(" ".join(common), 160), fontsize="x-small")
    return fig, {"success_distance": published[0]["success_distance"], "experiments": summary}


def network_figures(curve: list[float], success: float) -> dict:
    """One start's network at the test positions over fine-tuning (a published curve: entry i is
    the mean distance after i iterations, 0 the start): its best distance and the first
    iteration that reached it, the mean over the whole curve (the start and every iteration),
    the first iteration below the success distance (None: never), how many iterations were
    below it, and whether the curve is flat (it never moved by 1 mm).

    Examples:
        >>> figures = network_figures([0.15, 0.04, 0.06, 0.04], success=0.05)
        >>> figures["best"], figures["best_iteration"], figures["mean"]
        (0.04, 1, 0.0725)
        >>> figures["first_success"], figures["iterations_within"], figures["flat"]
        (1, 2, False)
    """
    best = min(range(len(curve)), key=curve.__getitem__)
    return {
        "best": curve[best],
        "best_iteration": best,
        "mean": _round(float(np.mean(curve))),
        "first_success": _first_below(curve, success, 0),
        "iterations_within": sum(d < success for d in curve),
        "flat": max(curve) - min(curve) < 1e-3,
    }


def _cell(figures: dict) -> str:
    """A markdown cell, as RESULTS.md's fine-tuning tables have them: the network's best (its
    iteration) / mean, bold where it is below the success distance, then the first iteration
    that is and how many are; "at the start" where fine-tuning never came nearer than zero-shot,
    "flat" where it never moved; then, where ``figures`` has them, the samples' (see
    :func:`_samples_cell`) after a semicolon.

    Examples:
        >>> _cell(network_figures([0.15, 0.04, 0.06, 0.03], success=0.05))
        '**0.030 (3)** / 0.070, first 1, 2 its'
        >>> _cell(network_figures([0.12, 0.13, 0.14], success=0.05))
        '0.120 at the start / 0.130'
        >>> _cell(network_figures([0.148, 0.1482, 0.1479], success=0.05))
        '0.148 flat'
        >>> figures = network_figures([0.15, 0.04, 0.06, 0.03], success=0.05)
        >>> _cell({**figures, "samples": samples_figures([0.16, 0.04, 0.03], success=0.05)})
        '**0.030 (3)** / 0.070, first 1, 2 its; 0.160 -> 0.030, first 2'
    """
    where = "at the start" if figures["best_iteration"] == 0 else f"({figures['best_iteration']})"
    best = f"{figures['best']:.3f} {where}"
    if figures["flat"]:
        cell = f"{figures['best']:.3f} flat"
    elif figures["first_success"] is None:
        cell = f"{best} / {figures['mean']:.3f}"
    else:
        cell = (
            f"**{best}** / {figures['mean']:.3f}, first {figures['first_success']}, "
            f"{figures['iterations_within']} its"
        )
    return f"{cell}; {_samples_cell(figures['samples'])}" if "samples" in figures else cell


def samples_figures(sampled: list[float], success: float) -> dict:
    """One start's samples over fine-tuning (a published ``sampled`` curve: entry i is the mean
    distance of iteration i + 1's samples on the training conditions): the first and the last
    iteration's, and the first iteration below the success distance (None: never).

    Examples:
        >>> samples_figures([0.16, 0.07, 0.04, 0.03], success=0.05)
        {'first': 0.16, 'last': 0.03, 'first_success': 3}
    """
    return {"first": sampled[0], "last": sampled[-1], "first_success": _first_below(sampled, success, 1)}


def _samples_cell(figures: dict) -> str:
    """The samples' markdown cell, as RESULTS.md has it: first -> last iteration, first success.

    Examples:
        >>> _samples_cell(samples_figures([0.16, 0.07, 0.04, 0.03], success=0.05))
        '0.160 -> 0.030, first 3'
    """
    cell = f"{figures['first']:.3f} -> {figures['last']:.3f}"
    return cell if figures["first_success"] is None else f"{cell}, first {figures['first_success']}"


#: where ``finetune-table`` reads the network: the published curve of each place it was run
NETWORK_CURVES = {"test": "curves", "training": "training_conditions"}


def finetune_table(published: list[dict], network_on: str = "test") -> tuple[str, dict]:
    """The network's figures of published fine-tuning runs (see :func:`network_figures`), and
    where a run recorded them its samples' (:func:`samples_figures`, under ``"samples"``), per
    experiment (grouped as in :func:`finetune_figure`), start and seed, as markdown tables (a
    row per seed, a column per start: the network's cell, then the samples') and a summary: per
    experiment and start, each seed's figures, the seeds whose network reached the success
    distance, and the mean of the seeds' means; with several experiments, also per start and
    seed how many of them reached it (``"across"``). ``network_on`` picks the network's curve:
    at the test positions (``"test"``, the published ``curves``) or run on the conditions its
    samples were drawn on (``"training"``, ``training_conditions``). Raises ``ValueError`` for a
    repeated seed within an experiment, or a run that did not record the curve asked for.
    """
    if network_on not in NETWORK_CURVES:
        raise ValueError(f"the network is read on one of {', '.join(NETWORK_CURVES)}, got {network_on!r}")
    key = NETWORK_CURVES[network_on]
    groups, common = _experiments(published)
    tables, summary = [], {}
    for name, runs in groups.items():
        for p in runs:
            if not p["finetune"].get(key):
                raise ValueError(f"seed {p['seed']} of {name!r} recorded no network curve {key!r}")
        starts = [s for s in START_COLORS if any(s in p["finetune"][key] for p in runs)]
        figures: dict[str, dict[int, dict]] = {start: {} for start in starts}
        for p in runs:
            sampled, success = p["finetune"].get("sampled") or {}, p["success_distance"]
            for start, curve in p["finetune"][key].items():
                figures[start][p["seed"]] = network_figures(curve, success)
                if start in sampled:
                    figures[start][p["seed"]]["samples"] = samples_figures(sampled[start], success)
        summary[name] = {
            start: {
                "seeds": by_seed,
                "reached": [seed for seed, f in by_seed.items() if f["first_success"] is not None],
                "mean_of_means": _round(float(np.mean([f["mean"] for f in by_seed.values()]))),
            }
            for start, by_seed in figures.items()
        }
        heading = name if network_on == "test" else f"{name}, the network on its training conditions"
        rows = [f"### {heading}", "", "| seed | " + " | ".join(starts) + " |"]
        rows.append("|---" * (len(starts) + 1) + "|")
        for p in runs:
            cells = [_cell(figures[s][p["seed"]]) if p["seed"] in figures[s] else "" for s in starts]
            rows.append(f"| {p['seed']} | " + " | ".join(cells) + " |")
        reached = [f"{len(summary[name][s]['reached'])} of {len(figures[s])}" for s in starts]
        rows.append("| reached | " + " | ".join(reached) + " |")
        means = [f"{summary[name][s]['mean_of_means']:.3f}" for s in starts]
        rows.append("| mean of means | " + " | ".join(means) + " |")
        tables.append("\n".join(rows))
    out = {"success_distance": published[0]["success_distance"], "experiments": summary}
    if len(summary) > 1:
        across, table = _across_experiments(summary)
        out["across"] = across
        tables.append(table)
    return "\n\n".join([f"common options: {' '.join(common)}", *tables]), out


def _across_experiments(summary: dict) -> tuple[dict, str]:
    """Per start and seed, in how many of the experiments that ran it the network reached the
    success distance (say, several draws of one setting), and over all of them: a summary and
    its markdown table."""
    across: dict[str, dict] = {}
    for experiment in summary.values():
        for start, figures in experiment.items():
            seeds = across.setdefault(start, {"seeds": {}})["seeds"]
            for seed in figures["seeds"]:
                reached, ran = seeds.get(seed, (0, 0))
                seeds[seed] = (reached + (seed in figures["reached"]), ran + 1)
    for counts in across.values():
        counts["seeds"] = dict(sorted(counts["seeds"].items()))
        counts["reached"] = sum(r for r, _ in counts["seeds"].values())
        counts["runs"] = sum(n for _, n in counts["seeds"].values())
    starts = list(across)
    seeds = sorted({seed for counts in across.values() for seed in counts["seeds"]})
    rows = ["### across the experiments: runs that reached it", "", "| seed | " + " | ".join(starts) + " |"]
    rows.append("|---" * (len(starts) + 1) + "|")
    for seed in seeds:
        counts = [across[s]["seeds"].get(seed) for s in starts]
        rows.append(f"| {seed} | " + " | ".join("{} of {}".format(*c) if c else "" for c in counts) + " |")
    totals = [f"{across[s]['reached']} of {across[s]['runs']}" for s in starts]
    rows.append("| all | " + " | ".join(totals) + " |")
    return across, "\n".join(rows)


#: finetune_per_scene.py's outcome of a scene: first touched at iteration 1, later, never
TOUCH_COLORS = {"at the first iteration": "C2", "later": "C1", "never": "C3"}


def _touched(scene: dict) -> str:
    first = scene["sampled"]["first_touched"]
    return "never" if first is None else "at the first iteration" if first == 1 else "later"


def per_scene_figure(published: list[dict]) -> tuple[Figure, dict]:
    """``benchmarks/finetune_per_scene.py``'s outputs (its last lines), a panel each: every
    scene's samples, iteration by iteration, coloured by when one of them first moved the
    object (at the first iteration, later, never). The summary gives, per output, the run's
    command, how many scenes each kind holds, and how many of each end within the success
    distance. Raises ``ValueError`` for no outputs."""
    if not published:
        raise ValueError("no published results to read")
    columns = min(3, len(published))
    rows = -(-len(published) // columns)
    fig = Figure(figsize=(4.6 * columns + 0.5, 3.6 * rows), layout="constrained")
    axes = fig.subplots(rows, columns, squeeze=False, sharey=True).ravel()
    for unused in axes[len(published) :]:
        unused.set_visible(False)
    summary = []
    for ax, out in zip(axes, published, strict=False):
        kinds = {kind: {"scenes": 0, "within": 0} for kind in TOUCH_COLORS}
        for scene in out["scenes"]:
            kind = _touched(scene)
            kinds[kind]["scenes"] += 1
            kinds[kind]["within"] += scene["outcome"] == "within"
            curve = scene["sampled"]["by_iteration"]
            ax.plot(range(1, len(curve) + 1), curve, color=TOUCH_COLORS[kind], lw=0.8, alpha=0.8)
        for kind, colour in TOUCH_COLORS.items():
            ax.plot([], [], color=colour, label=f"first moved {kind} ({kinds[kind]['scenes']})")
        ax.axhline(out["success_distance"], color="k", lw=0.8, ls="--", label="success distance")
        options = [o for o in out["run_command"].split() if o.startswith(("seed=", "eval.finetune_seed="))]
        ax.set_title(f"{out['holdout']}, {out['start']}\n{' '.join(options)}", fontsize="small")
        ax.set_xlabel("GPS iteration on the held-out world")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.legend(fontsize="x-small")
        summary.append({"run_command": out["run_command"], "start": out["start"], "touched": kinds})
    for ax in axes[::columns]:
        ax.set_ylabel("each scene's samples (mean distance)")
    return fig, {"runs": summary}


#: the kinds that read published JSON files: what reads them, what each file must be, and the
#: PNG's name for those that draw (the others print a markdown table)
PUBLISHED = {
    "figure": (paper_figure, "a published zero-shot result", "{}_vs_paper.png"),
    "finetune-figure": (finetune_figure, "a published fine-tuning result", "{}.png"),
    "finetune-table": (finetune_table, "a published fine-tuning result", None),
    "per-scene-figure": (per_scene_figure, "an output of finetune_per_scene.py", "{}.png"),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("kind", choices=["zero-shot", "lowo", "algorithms", *PUBLISHED])
    parser.add_argument(
        "paths",
        type=Path,
        nargs="+",
        help="run directories (a sweep directory for lowo, JSON files for the figures and the table)",
    )
    parser.add_argument("--experiment", help="the name under docs/ (all kinds but finetune-table)")
    parser.add_argument("--docs", type=Path, default=DOCS, help="the docs directory to write into")
    parser.add_argument(
        "--iterations", type=int, help="fine-tuning kinds: each run's first N iterations (a shorter budget)"
    )
    parser.add_argument(
        "--network-on",
        choices=list(NETWORK_CURVES),
        default="test",
        help="finetune-table: the network at the test positions (default) or on its training conditions",
    )
    args = parser.parse_args()
    if args.experiment is None and args.kind != "finetune-table":
        parser.error(f"{args.kind} writes under {args.docs}: give its name with --experiment")
    if args.iterations is not None and not args.kind.startswith("finetune"):
        parser.error(f"--iterations cuts fine-tuning runs; {args.kind} reads none")
    if args.network_on != "test" and args.kind != "finetune-table":
        parser.error(f"--network-on picks finetune-table's curve; {args.kind} reads no other")
    if args.kind in PUBLISHED:
        read, what, name = PUBLISHED[args.kind]
        try:
            published = [json.loads(path.read_text()) for path in args.paths]
            if args.iterations is not None:
                published = first_iterations(published, args.iterations)
            if args.kind == "finetune-table":
                drawn, summary = read(published, args.network_on)
            else:
                drawn, summary = read(published)
        except KeyError as error:
            parser.error(f"{args.kind}: a file is not {what} (it has no {error})")
        except (OSError, ValueError) as error:
            parser.error(f"{args.kind}: {error}")
        if name is None:
            print(drawn)
            print(json.dumps(summary))
            return
        path = args.docs / name.format(args.experiment)
        write_atomically(path, lambda tmp: drawn.savefig(tmp, format="png", dpi=120))
        print(json.dumps({"figure": str(path), **summary}))
        return
    if args.kind == "zero-shot":
        data = zero_shot(args.paths[0], args.experiment, args.docs)
    elif args.kind == "lowo":
        data = lowo(args.paths[0], args.experiment, args.docs)
    else:
        data = algorithms(args.paths, args.experiment)
    path = args.docs / "results" / f"{args.experiment}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(path, lambda tmp: tmp.write_text(json.dumps(data, indent=2) + "\n"))
    print(json.dumps(data))


if __name__ == "__main__":
    main()
