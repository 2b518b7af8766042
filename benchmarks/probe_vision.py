"""Do a trained bank's vision modules still find the objects? A linear probe, after GPS and before it.

Pretraining (``modnet.pretrain``) teaches each vision task module's convolutions to find the
objects in 4,000 random scenes; GPS then trains them end to end on the few scenes of its
training conditions.  :func:`modnet.pretrain.probe_vision` fits a linear map from a module's
frozen feature points to the objects' positions on fresh random scenes of every world that
uses it, the held-out world included, and reports the error on scenes it did not fit.  Run on
the bank a ``run.py`` job saved, it says whether the convolutions still find the objects at
new positions; with ``--before-gps`` the same probe also runs on the modules as pretraining
left them (rebuilt from the run's own config and seed: the pretraining is deterministic per
seed, and the script checks that it repeats the run's ``pretrain.json``).

Prints a line per module and world, then ONE JSON object on its last line.

    python benchmarks/probe_vision.py RUN_DIR                    # the bank GPS left
    python benchmarks/probe_vision.py RUN_DIR --before-gps       # and as pretraining left it
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
from _run_dir import FINISHED, finished_run

from modnet.bank import ModuleBank
from modnet.config import saved_run, validate
from modnet.pretrain import pretrain_vision, probe_vision
from modnet.universes import get_universe


def pretrained_bank(run_dir: Path) -> tuple[ModuleBank, bool]:
    """The bank the run in ``run_dir`` started GPS from (its config and seed, pretrained again),
    and whether the pretraining repeated the run's figures."""
    run = saved_run(run_dir)
    universe, split = validate(run)
    before = torch.get_num_threads()
    torch.set_num_threads(run.threads)  # the run's count: another sums in another order
    try:
        bank = run.new_bank(universe)
        report = pretrain_vision(bank, split.training, run.pretrain_config())
    finally:
        torch.set_num_threads(before)  # the probe itself runs as the rest of this script
    recorded = json.loads((run_dir / "pretrain.json").read_text())
    return bank, validation_errors(report) == validation_errors(recorded)


def validation_errors(report: dict) -> dict[str, float]:
    """Each module's pretraining error, as ``pretrain_vision`` reports it (JSON keeps floats exact)."""
    return {module: figures["val_error"] for module, figures in report.items()}


def show(label: str, report: dict, holdout: str) -> dict:
    """Print a line per module and world; the figures rounded for the JSON."""
    out = {}
    for module, figures in report.items():
        out[module] = {"baseline_error": round(figures["baseline_error"], 4), "worlds": {}}
        for world, errors in figures["worlds"].items():
            out[module]["worlds"][world] = {k: round(v, 4) for k, v in errors.items()}
            text = ", ".join(f"{k} {v:.3f}" for k, v in errors.items())
            held = "  (held out)" if world == holdout else ""
            print(f"{label:10s} {module:18s} {world:32s} {text}{held}")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a finished run.py run directory of an image universe")
    parser.add_argument("--scenes", type=int, default=500, help="random scenes per world (default 500)")
    parser.add_argument(
        "--before-gps", action="store_true", help="also probe the modules as pretraining left them"
    )
    args = parser.parse_args()
    if args.scenes < 2:
        parser.error(f"--scenes must be at least 2 per world (some to fit, some to test), got {args.scenes}")
    config = (".hydra/config.yaml",) if args.before_gps else ()
    results = finished_run(parser, args.run_dir, (*FINISHED, *config))
    universe = get_universe(results["universe"])
    if not universe.pixels:
        parser.error(f"universe {universe.name!r} reads no images: nothing to probe")
    if args.before_gps and not (args.run_dir / "pretrain.json").exists():
        parser.error(f"{args.run_dir} ran without pretraining (no pretrain.json): nothing for --before-gps")
    torch.set_num_threads(1)  # as run.py by default
    holdout = results["holdout"]
    start = time.perf_counter()
    out = {"benchmark": "probe_vision", "run_dir": str(args.run_dir), "holdout": holdout}
    out["scenes_per_world"] = args.scenes
    bank = ModuleBank.load(args.run_dir / "bank")
    after = probe_vision(bank, universe.worlds, args.scenes, results["seed"])
    out["after_gps"] = show("after GPS", after, holdout)
    if args.before_gps:
        bank, out["pretraining_repeated"] = pretrained_bank(args.run_dir)
        before = probe_vision(bank, universe.worlds, args.scenes, results["seed"])
        out["before_gps"] = show("before GPS", before, holdout)
    out["seconds"] = round(time.perf_counter() - start, 1)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
