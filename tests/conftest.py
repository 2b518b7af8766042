"""Shared test set-up."""

import time

import pytest
import torch
from commands import FINETUNE_SAMPLES, ITERATIONS, run_py


@pytest.fixture(autouse=True, scope="session")
def one_thread():
    """Tiny CPU tensors: one torch thread, so a busy shared core cannot stall OpenMP barriers."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """One whole tiny job, shared by every test that reads a finished run: train, save, zero-shot
    (+ 3 random conditions), fine-tune, report. (run_dir, the finished process, its seconds)."""
    run_dir = tmp_path_factory.mktemp("tiny_run")
    start = time.perf_counter()
    done = run_py(
        "universe=tiny",
        "logger=csv",
        f"gps.iterations={ITERATIONS}",
        "finetune=true",
        f"eval.finetune_samples_per_condition={FINETUNE_SAMPLES}",
        "eval.random_conditions=3",
        f"hydra.run.dir={run_dir}",
    )
    return run_dir, done, time.perf_counter() - start
