"""Modular policy networks, the main job: validate -> train -> save -> evaluate -> report.

Hold out one world of a universe, train the robot and task modules on all the others with
guided policy search, then compose the held-out world's modules zero-shot and compare them
with a random network and the wrong task module, as in the paper's tables.

    python run.py                                        # color_reach_state, four_link/reach_black held out
    python run.py universe=tiny logger=csv               # about 15 seconds
    python run.py holdout=three_link/reach_green finetune=true
    python run.py -m holdout=all hydra/launcher=joblib   # leave-one-world-out sweep, in parallel
    python -m modnet.aggregate multirun/<universe>/<date>   # the sweep's robot x task heatmap
    python run.py resume=true hydra.run.dir=outputs/<universe>/<date>   # continue a killed run

Everything a run writes goes to its directory: checkpoint.pt, bank/, history.json,
results.json, zero_shot.csv, the figures, run.log (what it printed, timestamped) and the
logger's files (wandb offline by default).
"""

from __future__ import annotations

import os

os.environ.setdefault("WANDB_MODE", "offline")  # nothing leaves the machine unless asked
os.environ.setdefault("WANDB_SILENT", "true")

import dataclasses  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import hydra  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402
from tqdm import tqdm  # noqa: E402
from tqdm.contrib.logging import logging_redirect_tqdm  # noqa: E402

from modnet import report  # noqa: E402
from modnet.bank import ModuleBank  # noqa: E402
from modnet.checkpoint import CHECKPOINT, Checkpoint, CheckpointError, load_checkpoint, save_checkpoint  # noqa: E402
from modnet.config import ConfigError, RunConfig, flatten, held_out_env, register_configs, validate  # noqa: E402
from modnet.evaluate import FineTuning, FineTuningFailed, ZeroShot, finetune, zero_shot  # noqa: E402
from modnet.gps.trainer import GPSConfig, GPSTrainer  # noqa: E402
from modnet.loggers import RunLogger  # noqa: E402
from modnet.pretrain import pretrain_vision  # noqa: E402
from modnet.universes import Split, Universe, UniverseError, get_universe, world_name  # noqa: E402
from modnet.worlds import get_world  # noqa: E402

CONF = Path(__file__).resolve().parent / "conf"
PRETRAIN_REPORT = "pretrain.json"  # the vision pretraining's figures, kept for a resumed run
register_configs()
#: The job's progress: to the console and, through Hydra's logging, to the run's own ``run.log``.
job_log = logging.getLogger("run")


#: Options added after some checkpoints were written, with the value that changes nothing.
NEWER_OPTIONS = {
    "bank.softmax_temperature": 1.0,
    "gps.dynamics_ridge": GPSConfig.dynamics_ridge,
    "gps.noise_smoothing": 0.0,
    "gps.dynamics_prior_per_condition": False,
    "gps.train_convolutions": True,
    "gps.clip_targets": False,
    "gps.sample_on_policy": False,
    "gps.policy_linearization": "regression",
    "gps.scenes_per_world": False,
    "gps.c_step": "lqr",
    "gps.pi2_kl": GPSConfig.pi2_kl,
    "gps.pi2_covariance_damping": GPSConfig.pi2_covariance_damping,
    "gps.train_modules": "all",
    "gps.relabel_policy_states": "off",
    "gps.relabel_tracking_weight": None,
    "gps.pi2_policy_weight": 0.0,
    "gps.pi2_step_smoothing": 0.0,
    "gps.pi2_policy_feedback": False,
    "gps.feedback_weight": 0.0,
    "gps.s_step_precision": "controllers",
}
#: Limits on failure, not shapes of training: a run they stopped resumes with a looser one.
NOT_IDENTITY = ("gps.max_held_iterations",)


def run_identity(run: RunConfig, universe: Universe, split: Split) -> dict:
    """What a checkpoint must match to be resumed: everything that shapes training but its length.

    Flat (``"gps.badmm.dual_rate": 0.2``), so a mismatch names the very keys that differ."""
    parts = {
        "universe": universe.name,
        "holdout": world_name(split.holdout),
        "training_worlds": [world_name(w) for w in split.training],
        "pixels": universe.pixels,
        "policy": run.bank.policy,
        "seed": run.seed,
        "gps": dataclasses.asdict(run.gps_config()),
        "bank": run.bank_config().to_json(),
    }
    # Options newer than some checkpoints stay out while they are at their do-nothing
    # defaults, so a run saved before they existed still resumes.
    if run.pretrain.images:
        parts["pretrain"] = dataclasses.asdict(run.pretrain_config())
    identity = flatten(parts)
    for key in NOT_IDENTITY:
        del identity[key]
    for key, default in NEWER_OPTIONS.items():
        if identity[key] == default:
            del identity[key]
    return identity


def resume_point(run: RunConfig, checkpoint: Path, identity: dict) -> Checkpoint | None:
    """The checkpoint to continue (``resume=true``), or None to start afresh; never overwrite a run."""
    if run.resume:
        if checkpoint.exists():
            return load_checkpoint(checkpoint, identity)
        job_log.info(f"resume=true but no checkpoint at {checkpoint}: starting from iteration 0")
        return None
    if checkpoint.exists():
        raise CheckpointError(
            f"{checkpoint} already holds a run: pass resume=true to continue it, "
            "or choose another hydra.run.dir"
        )
    return None


def train(trainer: GPSTrainer, iterations: int, checkpoint: Path, identity: dict, log: RunLogger) -> None:
    """GPS iterations up to ``iterations``; a checkpoint after each, so a killed run loses at most one."""
    bar = tqdm(range(trainer.iteration, iterations), desc="GPS", initial=trainer.iteration, total=iterations)
    with logging_redirect_tqdm():  # log lines above the bar, not through it
        for _ in bar:
            diagnostics = trainer.step()
            save_checkpoint(checkpoint, trainer.state_dict(), identity)
            log.iteration(trainer.iteration, diagnostics)
            bar.set_postfix(mean_distance=f"{np.mean([d['distance'] for d in diagnostics.values()]):.3f}")
            job_log.info(
                f"iteration {trainer.iteration}: "
                + ", ".join(
                    f"{w} d={d['distance']:.3f} c={d['sampled_cost']:.1f}" for w, d in diagnostics.items()
                )
            )


def pretrain(run: RunConfig, split: Split, bank: ModuleBank, report_file: Path) -> None:
    """Teach the bank's vision modules where the objects are, on the training worlds' scenes."""
    pretrained = pretrain_vision(bank, split.training, run.pretrain_config())
    report.write_json(report_file, pretrained)
    for module, figures in pretrained.items():
        job_log.info(
            f"pretrained {module}'s convolutions on {figures['images']} scenes: objects found "
            f"{figures['val_error']:.3f} m off (the mean position: {figures['baseline_error']:.3f} m)"
        )


def evaluate(run: RunConfig, universe: Universe, split: Split, bank: ModuleBank) -> tuple[dict, ZeroShot]:
    """Zero-shot on the held-out world's test conditions (and random ones when asked): ``results.json``."""
    ev, (robot, task) = run.eval, split.holdout
    env = held_out_env(run, universe, split)
    frames = (ev.frame_height, ev.frame_width, ev.gif_frames)
    result = zero_shot(bank, robot, task, env, baseline_seed=ev.baseline_seed, frames=frames)
    results = {
        "universe": universe.name,
        "holdout": world_name(split.holdout),
        "robots": list(universe.robots),
        "tasks": list(universe.tasks),
        "training_worlds": [world_name(w) for w in split.training],
        "policy": run.bank.policy,
        "algo": run.gps.algo,
        "seed": run.seed,
        "horizon": env.horizon,
        "success_distance": env.world.task.success_distance,
        "conditions": ev.conditions,
        "methods": result.to_json(),
    }
    if ev.random_conditions > 0:
        random_env = held_out_env(run, universe, split, random=True)
        results["random_conditions"] = {
            "num_conditions": ev.random_conditions,
            "seed": ev.random_seed,
            "methods": zero_shot(bank, robot, task, random_env, baseline_seed=ev.baseline_seed).to_json(),
        }
    return results, result


def compare_finetuning(
    run: RunConfig, universe: Universe, split: Split, run_dir: Path, wrong_task: str | None, log: RunLogger
) -> tuple[FineTuning, FineTuningFailed | None]:
    """GPS on the held-out world from the composed modules, the wrong task module and from scratch
    (with and without shaping): the network's mean test distance per iteration, plotted and logged,
    and the mean distance of each iteration's samples, logged. A start that fails numerically keeps
    its curve up to the failure; the failure comes back beside the curves, for the caller to raise
    once everything is written."""
    failure = None
    try:
        tuning = finetune(
            run_dir / "bank",
            *split.holdout,
            held_out_env(run, universe, split),
            run.finetune_gps_config(),
            iterations=run.eval.finetune_iterations,
            wrong_task=wrong_task,
            starts=run.eval.finetune_starts,
            pixels=universe.pixels,
            progress=lambda s, i, d, sampled: job_log.info(
                f"fine-tuning from {s}, iteration {i}: test distance {d:.3f} (its samples {sampled:.3f})"
            ),
        )
    except FineTuningFailed as err:
        tuning, failure = err.result, err
        for start, message in tuning.failed.items():
            job_log.warning(f"fine-tuning from {start} stopped: {message}")
    title = f"fine-tuning {world_name(split.holdout)}"
    success = get_world(*split.holdout).task.success_distance
    report.plot_finetune(
        tuning.curves,
        success,
        run_dir / "finetune.png",
        title=title,
        failed=tuning.failed,
        training=tuning.training,
    )
    for name, curve in tuning.curves.items():
        for i, distance in enumerate(curve):
            log.scalars({f"finetune/{name}/distance": distance}, step=i)
        for i, distance in enumerate(tuning.sampled[name], start=1):
            log.scalars({f"finetune/{name}/sampled_distance": distance}, step=i)
        for i, distance in enumerate(tuning.training[name]):
            log.scalars({f"finetune/{name}/training_distance": distance}, step=i)
        for i, diagnostics in enumerate(tuning.diagnostics[name], start=1):
            log.scalars({f"finetune/{name}/gps/{key}": value for key, value in diagnostics.items()}, step=i)
    return tuning, failure


def write_results(run_dir: Path, results: dict, seconds: dict[str, float], code: dict, threads: int) -> None:
    """``results.json``: the figures, with the seconds each stage took, the code, torch's threads
    and the machine (together, what a figure needs to repeat to the digit)."""
    results["seconds"] = {k: round(v, 1) for k, v in seconds.items()}
    results["code"] = code
    results["threads"] = threads
    results["machine"] = report.machine()
    report.write_json(run_dir / "results.json", results)


@hydra.main(version_base=None, config_path="conf", config_name="config")
def main(cfg: DictConfig) -> None:
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    run: RunConfig = OmegaConf.to_object(cfg)
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    checkpoint = run_dir / CHECKPOINT

    # 1. validate everything checkable before any work; one message, non-zero exit
    try:
        universe, split = validate(run)
        identity = run_identity(run, universe, split)
        resume_from = resume_point(run, checkpoint, identity)
        log = RunLogger.open(run.logger, run_dir, f"{universe.name}-{'-'.join(split.holdout)}", universe.name)
    except (ConfigError, UniverseError, CheckpointError) as err:
        sys.exit(f"run.py: {err}")
    torch.set_num_threads(run.threads)
    seconds: dict[str, float] = {}
    code = report.code_version()  # as it started (a resumed run: its last part)

    with log:
        log.config(flatten(OmegaConf.to_container(cfg, resolve=True)))

        # 2. train the bank on every training world
        bank = run.new_bank(universe)
        if resume_from is None:  # a resumed bank has its pretraining in its weights
            (run_dir / PRETRAIN_REPORT).unlink(missing_ok=True)  # a crashed attempt's figures
            if run.pretrain.images:
                pretrain(run, split, bank, run_dir / PRETRAIN_REPORT)
        trainer = GPSTrainer(bank, split.training, run.gps_config(), pixels=universe.pixels)
        if resume_from is not None:
            trainer.load_state_dict(resume_from.trainer)
            job_log.info(f"resumed {checkpoint} after iteration {trainer.iteration}")
        train(trainer, run.gps.iterations, checkpoint, identity, log)
        seconds["train"] = trainer.seconds  # GPS iterations only, summed over a resumed run's parts

        # 3. save the bank (manifest included) and the training curves
        for world in split.training:
            bank.mark_trained(*world)
        bank.save(run_dir / "bank")
        history = [{"iteration": i + 1, "worlds": worlds} for i, worlds in enumerate(trainer.history)]
        report.write_json(run_dir / "history.json", history)
        report.plot_learning_curves(trainer.history, run_dir / "learning_curves.png")
        figures = ["learning_curves", "zero_shot", "final_positions"]

        # 4. zero-shot: composed modules vs a random network vs the wrong task module
        start = time.perf_counter()
        results, result = evaluate(run, universe, split, bank)
        results["iterations"] = trainer.iteration
        results["samples"] = trainer.samples
        if (run_dir / PRETRAIN_REPORT).exists():
            results["pretrain"] = json.loads((run_dir / PRETRAIN_REPORT).read_text())
            # as measured per module when it ran, so a resumed run reports it too
            seconds["pretrain"] = sum(f["seconds"] for f in results["pretrain"].values())
        seconds["evaluate"] = time.perf_counter() - start
        job_log.info(report.zero_shot_table(results))
        report.write_zero_shot_csv(results, run_dir / "zero_shot.csv")

        # 5. optionally: GPS on the held-out world from four starts
        failure = None  # a start that failed numerically: raised once everything is written
        if run.finetune:
            start = time.perf_counter()
            wrong_task = result.wrong_task[0] if result.wrong_task else None
            tuning, failure = compare_finetuning(run, universe, split, run_dir, wrong_task, log)
            if tuning.failed:
                results["finetune_failed"] = tuning.failed
            results["finetune"] = tuning.curves
            results["finetune_sampled"] = tuning.sampled
            results["finetune_training"] = tuning.training
            results["finetune_diagnostics"] = tuning.diagnostics
            results["finetune_samples"] = tuning.samples
            figures.append("finetune")
            seconds["finetune"] = time.perf_counter() - start

        # 6. report: results.json, figures, logger
        write_results(run_dir, results, seconds, code, run.threads)
        report.plot_zero_shot(results, run_dir / "zero_shot.png")
        report.save_final_positions(
            result.frames, run_dir / "final_positions.png", run_dir / "final_positions.gif"
        )
        log.scalars(
            {
                f"zero_shot/{method}/{stat}": results["methods"][method][stat]
                for method in ("composed", "random", "wrong_task", "start")
                if results["methods"][method]
                for stat in ("mean", "success_rate")
            },
            step=trainer.iteration,
        )
        log.figures({name: run_dir / f"{name}.png" for name in figures})
        job_log.info(f"results in {run_dir}")
    if failure is not None:  # after the logger has closed, so that it keeps everything
        raise failure


def expand_holdout_all(argv: list[str]) -> list[str]:
    """In a multirun, ``holdout=all`` -> ``holdout=<every world of the universe>`` (leave one world out)."""
    if "holdout=all" not in argv or not ({"-m", "--multirun"} & set(argv)):
        return argv  # outside a multirun, validation explains that `all` is a sweep
    names = [a.split("=", 1)[1] for a in argv if a.startswith("universe=")]
    if not names:
        from hydra import compose, initialize_config_dir

        with initialize_config_dir(config_dir=str(CONF), version_base=None):
            names = [compose("config").universe]
    if len(names) != 1 or "," in names[0]:
        sys.exit("run.py: holdout=all sweeps the worlds of one universe; give a single universe=NAME")
    try:
        worlds = get_universe(names[0]).worlds
    except UniverseError as err:
        sys.exit(f"run.py: {err}")
    return [f"holdout={','.join(map(world_name, worlds))}" if a == "holdout=all" else a for a in argv]


if __name__ == "__main__":
    sys.argv = expand_holdout_all(sys.argv)
    main()
