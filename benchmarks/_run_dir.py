"""What the benchmark scripts that read a finished ``run.py`` run directory share."""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path

#: what every finished run directory holds: the figures and the saved bank
FINISHED = ("results.json", "bank/manifest.json")


def finished_run(parser: argparse.ArgumentParser, run_dir: Path, needed: Sequence[str] = FINISHED) -> dict:
    """``run_dir``'s ``results.json``; when it lacks one of ``needed``, the parser's one-line
    error naming what is missing (before any long work starts)."""
    missing = [name for name in needed if not (run_dir / name).exists()]
    if missing:
        parser.error(f"{run_dir} is not a finished run.py run directory: no {', '.join(missing)}")
    return json.loads((run_dir / "results.json").read_text())
