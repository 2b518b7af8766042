"""Zero-shot evaluation of a held-out world, its baselines, and fine-tuning from four starts.

The paper's protocol (Tables I and II): compose the held-out robot's module with the
held-out task's module, never trained together, and roll it out with deterministic
actions from each test condition.  The metric is the task's distance averaged over the
last 5 steps (:meth:`~modnet.envs.WorldEnv.final_distance`); success is a distance below
the task's ``success_distance``.  Two baselines must fail where the composition works:

* ``random``: the same architecture freshly initialised (:meth:`ModuleBank.fresh_copy`);
* ``wrong_task``: the right robot module with each other task module (reported one by one,
  and the best of them, i.e. the lowest mean distance).

Beside them, ``start`` is each condition's distance before any action: where an object stays
when no policy touches it (for reaching, where the arm starts).  A policy that ends above it
left things worse than it found them.

:func:`finetune` runs GPS on the held-out world from the composed modules and the wrong task
module (both without the cost's shaping term, as in the paper), and from scratch with and
without it, and records the neural network policy's test distance after every iteration.
A start that fails numerically stops there; the others still run, and
:class:`FineTuningFailed` then carries everything measured.

Examples:
    >>> from modnet.bank import ModuleBank
    >>> bank = ModuleBank.build(["three_link", "four_link"], ["reach_red", "reach_black"], seed=0)
    >>> env = evaluation_env("four_link", "reach_black", horizon=10)
    >>> result = zero_shot(bank, "four_link", "reach_black", env)
    >>> sorted(result.to_json())
    ['composed', 'random', 'start', 'wrong_task', 'wrong_task_each']
    >>> len(result.composed.distance)  # one per test condition
    4
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from modnet.bank import MONOLITHIC, ModuleBank, monolithic_name, monolithic_world
from modnet.envs import WorldEnv, make_env
from modnet.gps.errors import NumericalError
from modnet.gps.trainer import GPSConfig, GPSTrainer
from modnet.worlds import get_world

__all__ = [
    "FINETUNE_STARTS",
    "FineTuning",
    "FineTuningFailed",
    "Scores",
    "ZeroShot",
    "evaluation_env",
    "finetune",
    "misfit",
    "rollout",
    "score",
    "start_config",
    "training_env",
    "zero_shot",
]

FINETUNE_STARTS = ("composed", "wrong_task", "scratch_shaping", "scratch_no_shaping")


@dataclass
class Scores:
    """One policy's final distances on a condition set, and what follows from them.

    Examples:
        >>> s = Scores([0.05, 0.2, 0.07, 0.4], success_distance=0.1)
        >>> s.mean, s.success_rate
        (0.18, 0.5)
    """

    distance: list[float]  # one per condition
    success_distance: float

    @property
    def mean(self) -> float:
        return float(np.mean(self.distance))

    @property
    def success_rate(self) -> float:
        return float(np.mean([d < self.success_distance for d in self.distance]))

    @property
    def ci95(self) -> tuple[float, float] | None:
        """Student-t 95% confidence interval of the mean distance (None for a single condition)."""
        n = len(self.distance)
        if n < 2:
            return None
        from scipy.stats import t

        half = float(t.ppf(0.975, n - 1) * np.std(self.distance, ddof=1) / math.sqrt(n))
        return self.mean - half, self.mean + half

    def to_json(self) -> dict[str, Any]:
        ci = self.ci95
        return {
            "distance": [round(d, 6) for d in self.distance],
            "mean": round(self.mean, 6),
            "ci95": None if ci is None else [round(c, 6) for c in ci],
            "success_rate": self.success_rate,
        }


@dataclass
class ZeroShot:
    """The held-out world's zero-shot scores: composed modules and the two baselines.

    ``start`` holds each condition's distance before any action (an untouched object's).
    ``frames`` (``[F, B, H, W, 3]`` uint8) is the composed rollout, when it was recorded.
    ``skipped`` names the wrong task modules that cannot read the held-out world's task
    state, and why.
    """

    composed: Scores
    random: Scores
    wrong_task_each: dict[str, Scores]
    start: Scores
    skipped: dict[str, str] = field(default_factory=dict)
    frames: np.ndarray | None = None

    @property
    def wrong_task(self) -> tuple[str, Scores] | None:
        """The best wrong task module (lowest mean distance) and its scores."""
        if not self.wrong_task_each:
            return None
        return min(self.wrong_task_each.items(), key=lambda item: item[1].mean)

    def to_json(self) -> dict[str, Any]:
        best = self.wrong_task
        methods: dict[str, Any] = {
            "composed": self.composed.to_json(),
            "random": self.random.to_json(),
            "wrong_task": None if best is None else {"task": best[0], **best[1].to_json()},
            "wrong_task_each": {task: s.to_json() for task, s in self.wrong_task_each.items()},
            "start": self.start.to_json(),
        }
        if self.skipped:
            methods["wrong_task_skipped"] = dict(self.skipped)
        return methods


def evaluation_env(
    robot: str,
    task: str,
    *,
    conditions: str = "test",
    num_conditions: int | None = None,
    seed: int = 0,
    horizon: int | None = None,
    pixels: bool = False,
) -> WorldEnv:
    """One env copy per condition of the set (the paper's 4 test positions by default)."""
    return make_env(
        robot,
        task,
        num_envs=len(get_world(robot, task).conditions(conditions, seed, num_conditions)),
        pixels=pixels,
        conditions=conditions,
        seed=seed,
        num_conditions=num_conditions,
        horizon=horizon,
    )


def training_env(
    robot: str, task: str, config: GPSConfig, *, horizon: int | None = None, pixels: bool = False
) -> WorldEnv:
    """One env copy per training condition of ``config`` (the scenes its GPS samples), to score
    a network where it trains; ``horizon`` defaults to ``config.horizon``."""
    return evaluation_env(
        robot,
        task,
        conditions=config.conditions,
        num_conditions=config.num_conditions,
        seed=config.scene_seed(robot, task),
        horizon=config.horizon if horizon is None else horizon,
        pixels=pixels,
    )


@contextlib.contextmanager
def evaluating(bank: ModuleBank) -> Iterator[None]:
    """Dropout off, deterministic (mean) actions, no autograd; the bank's mode is restored after."""
    was_training = bank.training
    bank.eval()
    try:
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            yield
    finally:
        bank.train(was_training)


def rollout(
    bank: ModuleBank,
    robot: str,
    policy_task: str,
    env: WorldEnv,
    frames: tuple[int, int, int] | None = None,
) -> tuple[TensorDictBase, np.ndarray | None]:
    """Roll ``bank.compose(robot, policy_task)`` out in ``env`` for its horizon, deterministically.

    ``frames=(height, width, max_frames)`` also renders every copy at (at most ``max_frames``)
    evenly spaced steps, the first and last included: ``[F, B, height, width, 3]`` uint8.
    """
    policy = bank.compose(robot, policy_task)
    pictures: list[np.ndarray] = []
    callback = None
    if frames is not None:
        height, width, most = frames
        every = max(1, math.ceil(env.horizon / max(1, most - 1)))
        steps = iter(range(1, env.horizon))

        def callback(env: WorldEnv, td: TensorDictBase) -> None:  # after every step but the last
            if next(steps) % every == 0:
                pictures.append(env.render_frames(height, width))

    with evaluating(bank):
        start = env.reset()
        if frames is not None:
            pictures.append(env.render_frames(height, width))
        td = env.rollout(
            env.horizon, policy, callback, auto_reset=False, tensordict=start, break_when_any_done=False
        )
        if frames is not None:
            pictures.append(env.render_frames(height, width))  # the final positions
    return td, (np.stack(pictures) if frames is not None else None)


def score(bank: ModuleBank, robot: str, policy_task: str, env: WorldEnv) -> Scores:
    """Final distances of ``compose(robot, policy_task)`` acting in ``env`` (the held-out world)."""
    td, _ = rollout(bank, robot, policy_task, env)
    return Scores(env.final_distance(td).tolist(), env.world.task.success_distance)


def misfit(bank: ModuleBank, robot: str, task: str, env: WorldEnv) -> str | None:
    """Why ``compose(robot, task)`` cannot read ``env``'s observations (None when it can)."""
    for module in bank.parts(bank.world(robot, task)).values():
        for key, width in module.arch.observations:
            have = env.observation_spec[key].shape[-1]
            if have != width:
                return f"it reads a {'/'.join(key)} of size {width}, the held-out world has {have}"
    return None


def zero_shot(
    bank: ModuleBank,
    robot: str,
    task: str,
    env: WorldEnv,
    *,
    baseline_seed: int = 12345,
    frames: tuple[int, int, int] | None = None,
) -> ZeroShot:
    """Score the composed modules, a random network and every wrong task module on ``env``'s
    conditions, beside the distance each condition starts from.

    ``env`` is the held-out world (:func:`evaluation_env`); ``frames`` records the composed
    rollout (see :func:`rollout`).
    """
    td, pictures = rollout(bank, robot, task, env, frames)
    success = env.world.task.success_distance
    composed = Scores(env.final_distance(td).tolist(), success)
    start = Scores(env.start_distance(td).tolist(), success)
    random = score(bank.fresh_copy(seed=baseline_seed), robot, task, env)
    wrong, skipped = {}, {}
    for other in bank_tasks(bank):
        if other == task:
            continue
        reason = misfit(bank, robot, other, env)
        if reason is None:
            wrong[other] = score(bank, robot, other, env)
        else:
            skipped[other] = reason
    return ZeroShot(composed, random, wrong, start, skipped, pictures)


def bank_tasks(bank: ModuleBank) -> tuple[str, ...]:
    """The tasks a robot/task bank holds modules (or, monolithic, networks) for."""
    if bank.policy == "monolithic":
        return tuple(dict.fromkeys(monolithic_world(name)[1] for name in bank.names(MONOLITHIC)))
    return bank.names("task")


def _start_bank(bank_dir: Path, start: str, robot: str, task: str, wrong_task: str | None, seed: int):
    """A private copy of the saved bank set up for one fine-tuning start."""
    bank = ModuleBank.load(bank_dir)
    if start == "wrong_task":
        if bank.policy == "monolithic":
            wrong, own = monolithic_name((robot, wrong_task)), monolithic_name((robot, task))
            bank.load_module(bank_dir, MONOLITHIC, wrong, into=own)
        else:
            bank.load_module(bank_dir, "task", wrong_task, into=task)
    elif start.startswith("scratch"):
        bank = bank.fresh_copy(seed=seed, keep_normalization=False)
    return bank


@dataclass
class FineTuning:
    """What :func:`finetune` measured, per start: the network's mean test distance after 0, 1,
    ... GPS iterations (``curves``; entry 0: before fine-tuning), the mean distance of the
    trajectories each iteration sampled (``sampled``; entry i: iteration i + 1's samples, drawn
    from the local controllers, or from the network at a transferred start's first iteration)
    and the environment samples it drew.  ``sampled`` falling while ``curves`` stays flat means
    the controllers learn what the network does not take up; ``training`` (the network on the
    training conditions) falling with it means the network learns them but not the test
    positions."""

    curves: dict[str, list[float]]
    sampled: dict[str, list[float]]
    samples: dict[str, dict[str, int]]
    #: like ``curves``, on the world's training conditions (mean actions, as at the test positions)
    training: dict[str, list[float]] = field(default_factory=dict)
    #: the starts a :class:`~modnet.gps.errors.NumericalError` stopped, with its message; their
    #: curves end at the last iteration that finished
    failed: dict[str, str] = field(default_factory=dict)
    #: each iteration's GPS diagnostics on the held-out world (:meth:`GPSTrainer.step`'s:
    #: ``distance`` is ``sampled``'s entry, with the C-step's KL, step size, action gap, ...)
    diagnostics: dict[str, list[dict[str, float]]] = field(default_factory=dict)


class FineTuningFailed(RuntimeError):
    """Some fine-tuning starts failed numerically; ``result`` holds what every start measured
    (the failed ones up to their last finished iteration), ``errors`` each failure."""

    def __init__(self, result: FineTuning, errors: dict[str, NumericalError]) -> None:
        self.result = result
        self.errors = errors
        lines = "; ".join(f"from {start}: {err}" for start, err in errors.items())
        super().__init__(f"fine-tuning failed {lines}")


def start_config(config: GPSConfig, start: str) -> GPSConfig:
    """The GPS options of one fine-tuning start (the paper's section V-B protocol).

    Only ``scratch_shaping`` keeps the cost's shaping term (when ``config.shaping``): the
    transferred starts must learn from the task's cost alone, which is the paper's point.
    ``composed`` and ``wrong_task`` sample their first iteration from the network and start
    the controllers from its linearisation, on its actions as applied (``init_from_policy``).
    """
    if start not in FINETUNE_STARTS:
        raise ValueError(f"unknown fine-tuning start {start!r}; valid starts: {', '.join(FINETUNE_STARTS)}")
    return replace(
        config,
        init_from_policy=start in ("composed", "wrong_task"),
        shaping=config.shaping and start == "scratch_shaping",
    )


def finetune(
    bank_dir: str | Path,
    robot: str,
    task: str,
    env: WorldEnv,
    config: GPSConfig,
    *,
    iterations: int,
    wrong_task: str | None,
    starts: Sequence[str] = FINETUNE_STARTS,
    pixels: bool = False,
    progress: Callable[[str, int, float, float], None] | None = None,
) -> FineTuning:
    """GPS on the held-out world alone from each start; the test distance after every iteration.

    Starts: ``composed`` (the saved bank as is), ``wrong_task`` (``wrong_task``'s module in
    the held-out task's place), ``scratch_shaping`` and ``scratch_no_shaping`` (a freshly
    initialised bank); see :func:`start_config` for each one's cost and first samples.  All
    use ``config``'s seeds.  Returns the :class:`FineTuning` curves ``{start: [mean test
    distance after 0, 1, ..., iterations iterations]}``, the same on the world's training
    conditions (the scenes GPS samples, without noise: with four test positions the test curve
    moves in steps of a whole position), the mean distance of each iteration's samples, each
    iteration's GPS diagnostics and each start's sample counts; ``wrong_task`` is left out
    when there is no wrong task module (None).  ``progress(start, iteration, test_distance,
    sampled_distance)`` is called after each iteration.

    A :class:`~modnet.gps.errors.NumericalError` stops only its own start: the other starts
    still run (each is a fresh trainer with the same seeds), and then :class:`FineTuningFailed`
    is raised with the complete :class:`FineTuning`, whose ``failed`` names the stopped starts.
    """
    bank_dir = Path(bank_dir)
    result = FineTuning(curves={}, sampled={}, samples={})
    errors: dict[str, NumericalError] = {}
    scenes = training_env(robot, task, config, horizon=env.horizon, pixels=pixels)
    for start in starts:
        if start == "wrong_task" and wrong_task is None:
            continue
        bank = _start_bank(bank_dir, start, robot, task, wrong_task, config.seed)
        trainer = GPSTrainer(bank, [(robot, task)], start_config(config, start), pixels=pixels)
        curve, sampled, diagnosed = [score(bank, robot, task, env).mean], [], []
        on_scenes = [score(bank, robot, task, scenes).mean]
        result.curves[start], result.training[start], result.sampled[start] = curve, on_scenes, sampled
        result.diagnostics[start] = diagnosed
        try:
            for iteration in range(iterations):
                (diagnostics,) = trainer.step().values()  # the held-out world is the only one
                diagnosed.append({name: float(value) for name, value in diagnostics.items()})
                sampled.append(diagnosed[-1]["distance"])
                curve.append(score(bank, robot, task, env).mean)
                on_scenes.append(score(bank, robot, task, scenes).mean)
                if progress is not None:
                    progress(start, iteration + 1, curve[-1], sampled[-1])
        except NumericalError as err:
            errors[start] = err
            result.failed[start] = str(err)
        result.samples[start] = trainer.samples
    if errors:
        raise FineTuningFailed(result, errors)
    return result
