"""The benchmark scripts: each ends with one JSON line; the single-world GPS run succeeds (slow)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from modnet.worlds import get_world

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"


def last_json(*args: str, timeout: float = 600) -> dict:
    out = subprocess.run(
        [sys.executable, *args], capture_output=True, text=True, timeout=timeout, check=True, cwd=BENCHMARKS
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_gps_on_one_world_brings_the_policy_within_the_success_distance():
    figures = last_json("gps_single_world.py", "--robot", "three_link", "--task", "reach", timeout=1200)
    assert len(figures["final_distance"]) == 4
    assert max(figures["final_distance"]) < figures["success_distance"], figures


def test_lqr_benchmark_reports_a_ratio_against_numpy():
    figures = last_json("lqr.py", "--repeats", "3")
    assert figures["max_abs_diff_K_k_chol"] < 1e-9 and figures["speedup_numpy_over_batched"] > 0


def test_pretrain_benchmark_reports_every_vision_module_and_a_ratio_against_mj_step():
    figures = last_json(
        "pretrain_vision.py", "universe=color_reach", "pretrain.images=40", "pretrain.epochs=1", timeout=300
    )
    assert set(figures["modules"]) == {f"task/reach_{c}" for c in ("red", "green", "yellow", "black")}
    for module in figures["modules"].values():
        assert list(module["object_errors"]) == ["red", "green", "yellow", "black"]
    assert figures["render_scene_vs_mj_step"] > 1  # a frame costs more than a physics step


def test_gps_single_world_traces_where_the_object_goes():
    """``--trace`` reads the right state slots: at step 0 every block is where its condition put it."""
    options = "--task push --conditions 4 --samples 2 --iterations 1 --trace".split()
    figures = last_json("gps_single_world.py", *options, timeout=600)
    trace = figures["trace"]
    assert trace["steps"] == [0, 20, 40, 60, 99]
    params = get_world("three_link", "push").conditions("train", 0, 4)[:, 3:]  # block (x, y), goal (x, y)
    start = np.hypot(*(params[:, :2] - params[:, 2:]).T)
    np.testing.assert_allclose([row[0] for row in trace["object_to_goal"]], start, atol=2e-3)
    assert all(len(row) == 5 and row[0] > 0.9 for row in trace["ee_to_object"])  # the arm starts far away
