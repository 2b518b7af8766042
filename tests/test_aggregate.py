"""Sweep directory -> robot x task heatmap; a real 2-job joblib multirun of run.py feeds it."""

import json
import math

import pytest
from commands import BENCHMARKS, run_py, run_script

from modnet.aggregate import AggregateError, collect, main


def write_results(path, holdout, mean, universe="tiny"):
    path.mkdir(parents=True)
    results = {
        "universe": universe,
        "holdout": holdout,
        "robots": ["three_link", "four_link"],
        "tasks": ["reach_red", "reach_black"],
        "methods": {"composed": {"mean": mean}},
    }
    (path / "results.json").write_text(json.dumps(results))


def test_cells_hold_each_held_out_worlds_composed_distance_averaged_over_repeats(tmp_path):
    write_results(tmp_path / "0", "four_link/reach_black", 0.2)
    write_results(tmp_path / "1", "four_link/reach_black", 0.4)  # another seed of the same world
    write_results(tmp_path / "nested" / "2", "three_link/reach_red", 0.9)
    heatmap = collect(tmp_path)
    assert heatmap.robots == ["three_link", "four_link"] and heatmap.tasks == ["reach_red", "reach_black"]
    assert heatmap.distance[1, 1] == pytest.approx(0.3) and heatmap.distance[0, 0] == pytest.approx(0.9)
    assert math.isnan(heatmap.distance[0, 1]) and heatmap.runs.tolist() == [[1, 0], [0, 2]]


def test_cli_writes_png_and_csv_and_refuses_empty_or_mixed_sweeps(tmp_path, capsys):
    write_results(tmp_path / "0", "four_link/reach_black", 0.25)
    main([str(tmp_path)])
    assert "1 of 4 worlds held out" in capsys.readouterr().out
    assert (tmp_path / "heatmap.csv").read_text().splitlines() == [
        "robot,reach_red,reach_black",
        "three_link,,",
        "four_link,,0.250000",
    ]
    assert (tmp_path / "heatmap.png").stat().st_size > 1000
    with pytest.raises(AggregateError, match="no results.json"):
        collect(tmp_path / "0" / "missing")
    write_results(tmp_path / "1", "three_link/reach_red", 0.5, universe="manipulation")
    with pytest.raises(AggregateError, match="mixes universes"):
        collect(tmp_path)


def test_a_two_job_joblib_multirun_writes_two_results_and_aggregates(tmp_path):
    done = run_py(
        "-m",
        "universe=tiny",
        "logger=csv",
        "hydra/launcher=joblib",
        "hydra.launcher.n_jobs=2",
        "holdout=four_link/reach_black,three_link/reach_red",
        f"hydra.sweep.dir={tmp_path}",
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    results = sorted(tmp_path.rglob("results.json"))
    assert len(results) == 2
    assert {json.loads(r.read_text())["holdout"] for r in results} == {
        "four_link/reach_black",
        "three_link/reach_red",
    }
    for r in results:  # each job's progress in its own run.log, not only in the launcher's stdout
        held_out = json.loads(r.read_text())["holdout"]
        assert f"Zero-shot {held_out}" in (r.parent / "run.log").read_text()
    main([str(tmp_path)])  # python -m modnet.aggregate SWEEP_DIR
    assert (tmp_path / "heatmap.png").exists()
    rows = (tmp_path / "heatmap.csv").read_text().splitlines()
    assert rows[0] == "robot,reach_red,reach_black"
    assert rows[1].split(",")[1] and not rows[1].split(",")[2]  # three_link/reach_red held out
    assert rows[2].split(",")[2] and not rows[2].split(",")[1]  # four_link/reach_black held out

    # benchmarks/publish_results.py turns the same sweep into docs/results JSON
    docs = tmp_path / "docs"

    def publish(*args):
        done = run_script(BENCHMARKS / "publish_results.py", *args, "--docs", str(docs))
        assert done.returncode == 0, done.stderr
        return json.loads(done.stdout.splitlines()[-1])

    sweep = publish("lowo", str(tmp_path), "--experiment", "tiny_lowo")
    assert json.loads((docs / "results" / "tiny_lowo.json").read_text()) == sweep
    assert (docs / "tiny_lowo.png").exists() and len(sweep["jobs"]) == 2
    assert sweep["command"].startswith("python run.py -m universe=tiny") and "n_jobs=2" in sweep["command"]
    assert sweep["samples"]["trajectories"] == sum(j["samples"]["trajectories"] for j in sweep["jobs"]) > 0
    job = next(r.parent for r in results if json.loads(r.read_text())["holdout"] == "four_link/reach_black")
    one = publish("zero-shot", str(job), "--experiment", "tiny")
    assert one["holdout"] == "four_link/reach_black" and len(one["positions"]) == 4
    assert set(one["positions"][0]) == {"ours", "random", "wrong_task", "start"} and one["wall_s"] > 0
    starts = [position["start"] for position in one["positions"]]  # where each arm started
    assert one["means"]["start"] == pytest.approx(sum(starts) / len(starts), abs=1e-4) and min(starts) > 0
    both = publish("algorithms", str(job), str(job), "--experiment", "tiny_algorithms")
    assert [r["algo"] for r in both["runs"]] == ["badmm", "badmm"]
    recorded = json.loads((job / "results.json").read_text())
    code = recorded["code"]  # the commit that ran, in every form
    assert one["code"] == code and [r["code"] for r in both["runs"]] == [code, code]
    assert code in [j["code"] for j in sweep["jobs"]]
    machine = recorded["machine"]  # and the machine, likewise
    assert machine["cpu_capability"] and one["machine"] == machine
    assert [r["machine"] for r in both["runs"]] == [machine, machine]
    assert machine in [j["machine"] for j in sweep["jobs"]]
