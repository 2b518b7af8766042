"""run.py end to end on the tiny universe: outputs, resuming a killed run, and configs refused up front."""

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from commands import BENCHMARKS, ENV, FINETUNE_SAMPLES, ITERATIONS, ROOT, load_script, run_py, run_script
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from modnet.bank import ModuleBank
from modnet.checkpoint import CheckpointError, load_checkpoint
from modnet.config import ConfigError, LoggerConfig, RunConfig, register_configs, validate
from modnet.loggers import RunLogger
from modnet.report import code_version, machine


def load_run_module():
    """run.py (the Hydra entry point at the repository root) imported as a module."""
    return load_script(ROOT / "run.py", "modnet_run")


def composed_run(*overrides: str) -> RunConfig:
    """The typed config ``python run.py <overrides>`` would run with."""
    register_configs()
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
        return OmegaConf.to_object(compose("config", overrides=list(overrides)))


def test_tiny_pipeline_end_to_end_in_under_two_minutes(tiny_run):
    run_dir, done, seconds = tiny_run
    assert done.returncode == 0, done.stderr[-3000:]
    assert seconds < 120
    results = json.loads((run_dir / "results.json").read_text())
    assert results["universe"] == "tiny" and results["holdout"] == "four_link/reach_black"
    assert results["success_distance"] == 0.1 and results["iterations"] == ITERATIONS
    assert results["threads"] == 1  # torch's, by default: what the figures repeat at
    samples = results["samples"]
    assert samples["trajectories"] > 0
    assert samples["env_steps"] == samples["trajectories"] * results["horizon"]
    methods = results["methods"]
    assert set(methods) >= {"composed", "random", "wrong_task", "wrong_task_each"}
    for scores in (
        methods["composed"],
        methods["random"],
        methods["wrong_task"],
        methods["wrong_task_each"]["reach_red"],
    ):
        assert len(scores["distance"]) == 4 and 0 <= scores["success_rate"] <= 1
    assert methods["wrong_task"]["task"] == "reach_red"
    assert len(results["random_conditions"]["methods"]["composed"]["distance"]) == 3
    assert set(results["finetune"]) == {"composed", "wrong_task", "scratch_shaping", "scratch_no_shaping"}
    assert all(len(curve) == 2 for curve in results["finetune"].values())  # before + 1 iteration
    assert set(results["finetune_samples"]) == set(results["finetune"])
    # eval.finetune_samples_per_condition: every fine-tuning iteration samples each training
    # condition FINETUNE_SAMPLES times, whatever the training drew (2)
    iterations = len(results["finetune"]["composed"]) - 1
    conditions = composed_run("universe=tiny").gps.num_conditions
    finetune_trajectories = {s["trajectories"] for s in results["finetune_samples"].values()}
    assert finetune_trajectories == {iterations * conditions * FINETUNE_SAMPLES}
    # each iteration's samples: one mean distance per iteration, no entry for "before"
    assert {s: len(c) for s, c in results["finetune_sampled"].items()} == {s: 1 for s in results["finetune"]}
    diagnostics = results["finetune_diagnostics"]  # and each iteration's GPS diagnostics
    assert {s: [d["distance"] for d in its] for s, its in diagnostics.items()} == results["finetune_sampled"]
    assert results["code"] == code_version()  # the commit that ran; None/None for an installed copy
    assert results["machine"] == machine()  # where its figures repeat to the digit
    for name in [
        "learning_curves.png",
        "zero_shot.png",
        "final_positions.png",
        "final_positions.gif",
        "finetune.png",
        "zero_shot.csv",
        "history.json",
        "checkpoint.pt",
        "bank/manifest.json",
    ]:
        assert (run_dir / name).stat().st_size > 0, name
    assert "composed" in done.stdout and "Zero-shot four_link/reach_black" in done.stdout
    # run.log keeps what it printed: every GPS iteration, the table, every fine-tuning iteration
    logged = (run_dir / "run.log").read_text()
    for line in [f"iteration {i}: " for i in range(1, ITERATIONS + 1)] + [
        "Zero-shot four_link/reach_black",
        "fine-tuning from composed, iteration 1: test distance",
        f"results in {run_dir}",
    ]:
        assert line in logged and line in done.stdout, line
    scalars = run_dir / "tiny-four_link-reach_black" / "scalars"
    assert list((scalars / "train").rglob("distance.csv"))
    assert (scalars / "finetune" / "composed" / "sampled_distance.csv").stat().st_size > 0
    assert (scalars / "finetune" / "composed" / "gps" / "kl.csv").stat().st_size > 0


def publish_zero_shot(run_dir: Path, experiment: str, docs: Path) -> dict:
    """``benchmarks/publish_results.py zero-shot`` on a run directory: the JSON it prints."""
    args = ["zero-shot", str(run_dir), "--experiment", experiment, "--docs", str(docs)]
    published = run_script(BENCHMARKS / "publish_results.py", *args)
    assert published.returncode == 0, published.stderr
    return json.loads(published.stdout.splitlines()[-1])


def publish_edited(run_dir: Path, edit, experiment: str, docs: Path) -> dict:
    """Publish a copy of a finished run (without its bank and logs) whose results.json ``edit``
    changed in place, as if the run had produced it."""
    copy = docs / f"{experiment}_run"
    shutil.copytree(run_dir, copy, ignore=shutil.ignore_patterns("bank", "*.pt", "wandb", "tiny-*"))
    results = json.loads((copy / "results.json").read_text())
    edit(results)
    (copy / "results.json").write_text(json.dumps(results))
    return publish_zero_shot(copy, experiment, docs)


def test_published_fine_tuning_has_curves_iterations_to_success_samples_and_commit(tiny_run, tmp_path):
    run_dir, done, _ = tiny_run
    assert done.returncode == 0, done.stderr[-3000:]
    published = publish_zero_shot(run_dir, "tiny_finetune", tmp_path)
    tuning = published["finetune"]
    results = json.loads((run_dir / "results.json").read_text())
    assert tuning["curves"] == {s: pytest.approx(c, abs=1e-4) for s, c in results["finetune"].items()}
    for start, curve in tuning["curves"].items():
        reached = tuning["iterations_to_success"][start]
        below = [i for i, d in enumerate(curve) if d < results["success_distance"]]
        assert reached == (below[0] if below else None)
    assert tuning["samples"] == results["finetune_samples"]
    sampled = results["finetune_sampled"]
    assert tuning["sampled"] == {s: pytest.approx(c, abs=1e-4) for s, c in sampled.items()}
    on_scenes = results["finetune_training"]  # the network on the training conditions, entry 0 before
    assert tuning["training_conditions"] == {s: pytest.approx(c, abs=1e-4) for s, c in on_scenes.items()}
    assert all(len(on_scenes[s]) == len(c) for s, c in results["finetune"].items())
    diagnostics = results["finetune_diagnostics"]  # to 4 significant digits
    assert tuning["diagnostics"] == {
        s: [{k: pytest.approx(v, rel=1e-3) for k, v in d.items()} for d in its]
        for s, its in diagnostics.items()
    }
    assert published["code"] == results["code"]
    assert (tmp_path / "tiny_finetune_finetune.png").read_bytes() == (run_dir / "finetune.png").read_bytes()
    assert tuning["paper"].startswith("the composed start without shaping")  # the paper's held-out world


def test_a_numerical_failure_in_one_fine_tuning_start_stops_only_that_start_and_names_itself(tmp_path):
    """The wrong-task start fails in its second iteration: its curve keeps the first, the starts
    after it still run, everything is written (results.json with the failure, the figure, the
    published JSON), and then the error ends the run, naming the start, world and condition."""
    run_dir = tmp_path / "failing"
    overrides = ["universe=tiny", "logger=csv", "gps.iterations=1", "finetune=true"]
    overrides += ["eval.finetune_iterations=2", f"hydra.run.dir={run_dir}"]
    script = f"""
import runpy, sys
import modnet.evaluate as evaluate
from modnet.gps.errors import NumericalError
starts, real_start_bank, RealTrainer = [], evaluate._start_bank, evaluate.GPSTrainer
def start_bank(bank_dir, start, *args):
    starts.append(start)
    return real_start_bank(bank_dir, start, *args)
class FailingTrainer(RealTrainer):
    def step(self):
        if starts[-1] == "wrong_task" and self.iteration == 1:
            raise NumericalError(
                "injected Q_uu failure", world="four_link/reach_black", condition=2, iteration=1
            )
        return super().step()
evaluate._start_bank, evaluate.GPSTrainer = start_bank, FailingTrainer  # finetune looks them up when it runs
sys.argv = ["run.py", *{overrides!r}]
runpy.run_path({str(ROOT / "run.py")!r}, run_name="__main__")
"""
    done = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=300
    )
    assert done.returncode != 0
    message = "injected Q_uu failure [world=four_link/reach_black, condition=2, iteration=1]"
    assert f"fine-tuning failed from wrong_task: {message}" in done.stderr
    assert "Zero-shot four_link/reach_black" in done.stdout
    assert f"[run][WARNING] - fine-tuning from wrong_task stopped: {message}" in done.stdout  # not INFO
    results = json.loads((run_dir / "results.json").read_text())
    assert results["finetune_failed"] == {"wrong_task": message}
    lengths = {start: len(curve) for start, curve in results["finetune"].items()}
    assert lengths == {"composed": 3, "wrong_task": 2, "scratch_shaping": 3, "scratch_no_shaping": 3}
    sampled = {start: len(curve) for start, curve in results["finetune_sampled"].items()}
    assert sampled == {start: n - 1 for start, n in lengths.items()}
    assert results["methods"]["composed"]["mean"] > 0 and results["iterations"] == 1
    assert (run_dir / "zero_shot.csv").read_text().count("\n") >= 5
    assert (run_dir / "finetune.png").stat().st_size > 0 and (run_dir / "bank" / "manifest.json").exists()
    published = publish_zero_shot(run_dir, "failing", tmp_path / "docs")
    assert published["finetune_failed"] == results["finetune_failed"]
    assert {s: len(c) for s, c in published["finetune"]["curves"].items()} == lengths


def test_the_papers_claims_stand_only_beside_the_world_the_paper_held_out(tiny_run, tmp_path):
    run_dir, done, _ = tiny_run
    assert done.returncode == 0, done.stderr[-3000:]
    published = publish_edited(  # as a run with holdout=three_link/reach_red
        run_dir, lambda results: results.update(holdout="three_link/reach_red"), "tiny_other", tmp_path
    )
    assert published["finetune"]["paper"] is None


def test_a_published_command_sets_the_variables_that_chose_the_runs_kernels(tiny_run, tmp_path):
    run_dir, done, _ = tiny_run
    assert done.returncode == 0, done.stderr[-3000:]

    def published_with(kernels: dict, experiment: str) -> dict:  # as if the run had been started so
        return publish_edited(
            run_dir, lambda results: results["machine"].update(kernel_variables=kernels), experiment, tmp_path
        )

    plain = published_with({}, "tiny_plain")
    assert plain["command"].startswith("python run.py universe=tiny")
    kernels = {"MKL_ENABLE_INSTRUCTIONS": "AVX2"}  # on an AVX-512 machine: other figures (RESULTS)
    published = published_with(kernels, "tiny_avx2")
    assert published["command"] == "MKL_ENABLE_INSTRUCTIONS=AVX2 " + plain["command"]
    assert published["machine"]["kernel_variables"] == kernels


def test_the_saved_bank_knows_what_each_module_was_trained_on(tiny_run):
    run_dir, done, _ = tiny_run
    assert done.returncode == 0
    bank = ModuleBank.load(run_dir / "bank")
    assert ("four_link", "reach_black") not in bank.trained_on("robot", "four_link")
    assert bank.trained_on("task", "reach_black") == {("three_link", "reach_black")}
    history = json.loads((run_dir / "history.json").read_text())
    assert [h["iteration"] for h in history] == [1, 2, 3, 4]
    assert set(history[0]["worlds"]) == {
        "three_link/reach_red",
        "three_link/reach_black",
        "four_link/reach_red",
    }


def test_a_killed_run_resumes_from_its_last_checkpoint_and_loses_nothing(tmp_path, tiny_run):
    overrides = ["universe=tiny", "logger=none", f"gps.iterations={ITERATIONS}", f"hydra.run.dir={tmp_path}"]
    checkpoint = tmp_path / "checkpoint.pt"
    job = subprocess.Popen(
        [sys.executable, str(ROOT / "run.py"), *overrides],
        cwd=ROOT,
        env=ENV,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 120
        while not checkpoint.exists() and job.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        job.kill()
        job.wait()
    assert checkpoint.exists() and not (tmp_path / "results.json").exists(), "killed too late"
    before = load_checkpoint(checkpoint)
    assert 1 <= before.iteration < ITERATIONS

    resumed = run_py(*overrides, "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"after iteration {before.iteration}" in resumed.stdout
    history = json.loads((tmp_path / "history.json").read_text())
    assert [h["iteration"] for h in history] == [1, 2, 3, 4]  # every iteration exactly once
    assert [h["worlds"] for h in history[: before.iteration]] == before.trainer["history"]
    assert load_checkpoint(checkpoint).iteration == ITERATIONS
    # the same numbers as the run that was never killed, to the last bit
    assert history == json.loads((tiny_run[0] / "history.json").read_text())
    resumed_results = json.loads((tmp_path / "results.json").read_text())
    assert resumed_results["methods"] == json.loads((tiny_run[0] / "results.json").read_text())["methods"]
    # the training time counts the killed part's iterations too
    assert resumed_results["seconds"]["train"] >= float(before.trainer["seconds"]) > 0


def test_an_existing_run_is_never_overwritten_nor_resumed_under_another_config(tmp_path, tiny_run):
    run_dir, done, _ = tiny_run
    assert done.returncode == 0
    run = load_run_module()
    config = composed_run("universe=tiny")
    universe, split = validate(config)
    identity = run.run_identity(config, universe, split)
    checkpoint = tmp_path / "checkpoint.pt"
    checkpoint.write_bytes((run_dir / "checkpoint.pt").read_bytes())
    with pytest.raises(CheckpointError, match="already holds a run: pass resume=true to continue it"):
        run.resume_point(config, checkpoint, identity)
    config.resume = True
    assert run.resume_point(config, checkpoint, identity).iteration == ITERATIONS
    changed = composed_run("universe=tiny", "gps.sgd_steps=7", "resume=true")
    with pytest.raises(
        CheckpointError,
        match="belongs to a different run; gps.sgd_steps: 50 in the checkpoint, 7 in this run$",
    ):
        run.resume_point(changed, checkpoint, run.run_identity(changed, universe, split))
    longer = composed_run("universe=tiny", "gps.iterations=5", "resume=true")  # training may go on
    assert run.resume_point(longer, checkpoint, run.run_identity(longer, universe, split)).iteration == 4
    # a run stopped on conditions held too long resumes with a looser limit
    looser = composed_run("universe=tiny", "gps.max_held_iterations=10", "resume=true")
    assert run.resume_point(looser, checkpoint, run.run_identity(looser, universe, split)).iteration == 4
    # a finished bank may be fine-tuned again with another budget
    budget = composed_run("universe=tiny", "eval.finetune_samples_per_condition=20", "resume=true")
    assert run.resume_point(budget, checkpoint, run.run_identity(budget, universe, split)).iteration == 4


def test_a_corrupt_checkpoint_stops_the_run_with_one_message_and_stays(tmp_path):
    checkpoint = tmp_path / "checkpoint.pt"
    checkpoint.write_bytes(b"half a checkpoint")
    start = time.perf_counter()
    corrupt = run_py("universe=tiny", "logger=none", "resume=true", f"hydra.run.dir={tmp_path}")
    assert corrupt.returncode != 0
    assert f"corrupt checkpoint {checkpoint}" in corrupt.stderr and "Traceback" not in corrupt.stderr
    assert checkpoint.read_bytes() == b"half a checkpoint"
    assert time.perf_counter() - start < 30


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["universe=colour"], "Could not find 'universe/colour'"),  # Hydra's, as it composes
        (["universe=color_reach", "pretrain.epochs=0"], "pretrain: epochs must hold positive integers"),
    ],
)
def test_bad_configs_fail_in_seconds_with_one_clear_message(tmp_path, overrides, message):
    """From the command line: one of Hydra's refusals and one of modnet's, each a line without a
    traceback. (The rest of modnet's messages: test_config.py, through ``validate``.)"""
    start = time.perf_counter()
    done = run_py(*overrides, "logger=none", f"hydra.run.dir={tmp_path}")
    assert done.returncode != 0
    assert message in done.stderr and "Traceback" not in done.stderr
    assert time.perf_counter() - start < 30
    assert not (tmp_path / "checkpoint.pt").exists()


def test_tensorboard_logger_starts_or_says_what_is_missing(tmp_path):
    try:
        import tensorboard  # noqa: F401
    except ImportError:  # not a modnet dependency: the run must refuse before training
        with pytest.raises(ConfigError, match="logger=tensorboard cannot start: .*pip install tensorboard"):
            RunLogger.open(LoggerConfig(backend="tensorboard"), tmp_path, "tiny")
    else:
        with RunLogger.open(LoggerConfig(backend="tensorboard"), tmp_path, "tiny") as log:
            log.iteration(1, {"three_link/reach_red": {"distance": 0.5}})


def test_wandb_runs_offline_inside_the_run_directory_and_closes_for_the_next_job(tmp_path, monkeypatch):
    """Hydra's basic launcher runs a sweep's jobs in one process: each job's wandb run must end."""
    wandb = pytest.importorskip("wandb")
    monkeypatch.delenv("WANDB_MODE", raising=False)  # offline must come from the config itself
    for job in ("0", "1"):
        with RunLogger.open(LoggerConfig(), tmp_path / job, f"tiny-job{job}", "tiny") as log:
            assert wandb.run is not None and wandb.run.settings.mode == "offline"
            log.iteration(1, {"three_link/reach_red": {"distance": 0.5, "sampled_cost": 3.0}})
        assert wandb.run is None
        assert len(list((tmp_path / job / "wandb").glob("offline-run-*/run-*.wandb"))) == 1


@pytest.mark.slow
def test_holdout_all_sweeps_every_world_in_one_process_with_wandb(tmp_path):
    done = run_py("-m", "universe=tiny", "holdout=all", "gps.iterations=1", f"hydra.sweep.dir={tmp_path}")
    assert done.returncode == 0, done.stderr[-3000:]
    holdouts = {json.loads(r.read_text())["holdout"] for r in tmp_path.rglob("results.json")}
    assert holdouts == {
        "three_link/reach_red",
        "three_link/reach_black",
        "four_link/reach_red",
        "four_link/reach_black",
    }
    assert len(list(tmp_path.glob("*/wandb/offline-run-*"))) == 4


def test_checkpoints_hold_plain_data_only(tiny_run):
    run_dir, done, _ = tiny_run
    assert done.returncode == 0
    payload = torch.load(run_dir / "checkpoint.pt", weights_only=True)  # would raise on any object
    assert payload["format"] == "modnet.checkpoint/1" and payload["trainer"]["iteration"] == ITERATIONS


def test_score_bank_scores_every_world_and_agrees_with_the_zero_shot_table(tiny_run):
    run_dir, done, _ = tiny_run
    assert done.returncode == 0, done.stderr[-3000:]
    scored = run_script(BENCHMARKS / "score_bank.py", str(run_dir))
    assert scored.returncode == 0, scored.stderr
    figures = json.loads(scored.stdout.splitlines()[-1])
    results = json.loads((run_dir / "results.json").read_text())
    assert set(figures["mean_distance"]) == {f"{r}/{t}" for r in results["robots"] for t in results["tasks"]}
    assert figures["held_out"] == pytest.approx(results["methods"]["composed"]["mean"], abs=1e-4)
    training = [figures["mean_distance"][w] for w in results["training_worlds"]]
    assert figures["training_worlds"]["mean"] == pytest.approx(sum(training) / len(training), abs=1e-4)


def test_action_gap_compares_every_training_worlds_controllers_with_the_network(tiny_run):
    run_dir, done, _ = tiny_run
    assert done.returncode == 0, done.stderr[-3000:]
    script = BENCHMARKS / "action_gap.py"
    gap = run_script(script, str(run_dir))
    assert gap.returncode == 0, gap.stderr[-3000:]
    figures = json.loads(gap.stdout.splitlines()[-1])
    results = json.loads((run_dir / "results.json").read_text())
    assert list(figures["worlds"]) == results["training_worlds"] and figures["iteration"] == ITERATIONS
    for world in figures["worlds"].values():
        assert 0 < world["gap_clipped"] <= world["gap"] and 0 <= world["saturated"] <= 1
        assert world["controller_distance"] > 0
    empty = run_script(script, str(run_dir / "bank"))
    assert empty.returncode == 2 and "not a run.py run directory: no .hydra/config.yaml" in empty.stderr


def test_object_contact_names_the_valid_worlds_and_refuses_a_task_without_an_object(tiny_run):
    run_dir, done, _ = tiny_run
    assert done.returncode == 0, done.stderr[-3000:]
    script = BENCHMARKS / "object_contact.py"
    unknown = run_script(script, str(run_dir), "--world", "four_link/push")
    assert unknown.returncode == 2 and "valid: three_link/reach_red" in unknown.stderr, unknown.stderr
    reach = run_script(script, str(run_dir))
    assert reach.returncode == 2 and "moves nothing but the end effector" in reach.stderr, reach.stderr


def test_options_at_their_do_nothing_defaults_stay_out_of_the_checkpoint_identity():
    """A run saved before pretraining, the softmax temperature, the dynamics ridge, noise
    smoothing and frozen convolutions existed still resumes; changing any of them makes a
    different run."""
    run_py = load_run_module()
    base = composed_run("universe=color_reach", "seed=3")
    universe, split = validate(base)
    plain = run_py.run_identity(
        composed_run("universe=color_reach", "bank.softmax_temperature=1.0", "pretrain.images=0"),
        universe,
        split,
    )
    assert not any(k.startswith("pretrain.") or k == "bank.softmax_temperature" for k in plain)
    assert "gps.dynamics_ridge" not in plain and "gps.noise_smoothing" not in plain
    assert "gps.train_convolutions" not in plain and "gps.clip_targets" not in plain
    assert "gps.policy_linearization" not in plain and "gps.scenes_per_world" not in plain
    options = [
        "gps.dynamics_ridge=1e-3",
        "gps.noise_smoothing=2",
        "gps.train_convolutions=false",
        "gps.clip_targets=true",
        "gps.scenes_per_world=true",
    ]
    ridged = composed_run("universe=color_reach", *options)
    ridged = run_py.run_identity(ridged, universe, split)
    assert ridged["gps.dynamics_ridge"] == 1e-3 and ridged["gps.noise_smoothing"] == 2.0
    assert ridged["gps.train_convolutions"] is False and ridged["gps.clip_targets"] is True
    assert ridged["gps.scenes_per_world"] is True
    pretrained = run_py.run_identity(base, universe, split)
    assert pretrained["pretrain.images"] == 4000 and pretrained["bank.softmax_temperature"] == 0.05
    assert pretrained["pretrain.seed"] == 3  # follows the run seed


def test_published_results_carry_the_vision_pretraining_figures(tiny_run, tmp_path):
    run_dir, done, _ = tiny_run
    assert done.returncode == 0, done.stderr[-3000:]
    figures = {"images": 4000, "val_error": 0.01234567, "baseline_error": 0.4, "seconds": 9.0}
    pretrained = {"reach_red": {**figures, "object_errors": {"red": 0.01234567}}}
    out = publish_edited(
        run_dir, lambda results: results.update(pretrain=pretrained), "tiny_pretrained", tmp_path
    )
    assert out["pretrain"] == {
        "reach_red": {
            "images": 4000,
            "val_error": 0.0123,
            "baseline_error": 0.4,
            "object_errors": {"red": 0.0123},
        }
    }


def test_an_image_run_pretrains_once_reports_it_and_a_resumed_run_does_not_pretrain_again(tmp_path):
    """color_reach at toy sizes: pretraining happens before GPS on a fresh run only."""
    small = [
        "universe=color_reach",
        "logger=none",
        "gps.num_conditions=4",
        "gps.samples_per_condition=1",
        "gps.sgd_steps=5",
        "gps.initial_sgd_steps=5",
        "gps.horizon=10",
        "pretrain.images=20",
        "pretrain.epochs=1",
        "threads=2",  # the probe must repeat the pretraining at the run's thread count
        f"hydra.run.dir={tmp_path}",
    ]
    first = run_py(*small, "gps.iterations=1")
    assert first.returncode == 0, first.stderr[-3000:]
    assert first.stdout.count("pretrained task/") == 4  # the four colour modules
    figures = (tmp_path / "pretrain.json").read_text()
    results = json.loads((tmp_path / "results.json").read_text())
    assert set(results["pretrain"]) == {f"task/reach_{c}" for c in ("red", "green", "yellow", "black")}
    assert results["seconds"]["pretrain"] > 0

    resumed = run_py(*small, "gps.iterations=2", "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "pretrained" not in resumed.stdout and "resumed" in resumed.stdout
    assert (tmp_path / "pretrain.json").read_text() == figures
    resumed_results = json.loads((tmp_path / "results.json").read_text())
    assert resumed_results["pretrain"] == results["pretrain"]
    # its wall time still counts the pretraining, as the first attempt measured it per module
    spent = round(sum(f["seconds"] for f in results["pretrain"].values()), 1)
    assert resumed_results["seconds"]["pretrain"] == results["seconds"]["pretrain"] == spent

    # the linear probe of its vision modules, after GPS and as its own pretraining left them
    script = BENCHMARKS / "probe_vision.py"
    few = run_script(script, str(tmp_path), "--scenes", "1")
    assert few.returncode == 2 and "--scenes must be at least 2" in few.stderr, few.stderr
    probe = run_script(script, str(tmp_path), "--scenes", "10", "--before-gps")
    assert probe.returncode == 0, probe.stderr[-3000:]
    figures = json.loads(probe.stdout.strip().splitlines()[-1])
    assert figures["pretraining_repeated"] is True  # the rebuilt bank starts where the run did
    for stage in ("after_gps", "before_gps"):
        assert set(figures[stage]) == set(results["pretrain"])
        worlds = figures[stage]["task/reach_black"]["worlds"]
        assert "four_link/reach_black" in worlds  # the held-out world is probed too
        assert list(worlds["four_link/reach_black"]) == ["red", "green", "yellow", "black"]
