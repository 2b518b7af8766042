"""The repository's commands as the tests call them.

``run_py`` runs ``python run.py`` in a fresh interpreter, as a user's job runs. ``run_script``
runs a quick script (a refusal, publishing, scoring a saved run) in this process instead: a
fresh interpreter would spend most of those seconds importing torch. ``load_script`` imports a
script to call its functions.
"""

import importlib.util
import io
import os
import runpy
import subprocess
import sys
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"
ITERATIONS = 4  # GPS iterations of the tiny runs
FINETUNE_SAMPLES = 3  # samples per condition of the shared tiny run's fine-tuning (it trains with 2)
ENV = {
    **os.environ,
    "PYTHONUNBUFFERED": "1",
    "WANDB_MODE": "offline",
    "WANDB_SILENT": "true",
    "HYDRA_FULL_ERROR": "0",
}


def run_py(*overrides: str, timeout: float = 300, **popen) -> subprocess.CompletedProcess:
    """``python run.py <overrides>`` from the repository root; output captured as text."""
    return subprocess.run(
        [sys.executable, str(ROOT / "run.py"), *overrides],
        cwd=ROOT,
        env=ENV,
        capture_output=True,
        text=True,
        timeout=timeout,
        **popen,
    )


def load_script(script: Path, name: str):
    """A script (run.py, a benchmark) imported as the module ``name``, to call its functions.

    Registered in ``sys.modules`` as an import would be: dataclasses look their module up there.
    """
    spec = importlib.util.spec_from_file_location(name, script)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def run_script(script: Path, *args: str) -> subprocess.CompletedProcess:
    """``python SCRIPT ARGS`` run in this process, as its ``__main__`` with its folder on
    ``sys.path``: what ``subprocess.run(..., capture_output=True, text=True)`` would return.

    ``sys.exit("message")`` gives exit status 1 and the message on stderr, as Python does; any
    other exception propagates, traceback and all. torch's thread count and random state are
    restored afterwards, so the script leaves the tests as it found them.
    """
    stdout, stderr = io.StringIO(), io.StringIO()
    argv, path, threads = sys.argv, sys.path[:], torch.get_num_threads()
    status: int | str | None = 0
    try:
        with torch.random.fork_rng(devices=[]), redirect_stdout(stdout), redirect_stderr(stderr):
            sys.argv = [str(script), *args]
            sys.path.insert(0, str(script.parent))
            runpy.run_path(str(script), run_name="__main__")
    except SystemExit as exit:
        status = exit.code
    finally:
        sys.argv, sys.path[:] = argv, path
        torch.set_num_threads(threads)
    if isinstance(status, str):
        stderr.write(status + "\n")
        status = 1
    out, err = stdout.getvalue(), stderr.getvalue()
    return subprocess.CompletedProcess([str(script), *args], status or 0, out, err)
