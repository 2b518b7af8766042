"""Pretraining a vision task module's convolutions to find the objects of its scene.

Levine, Finn et al.'s visuomotor policies, whose architecture the modular networks paper
follows, start the convolutions from a pose-regression pretraining rather than from random
weights: the feature points of the spatial softmax are trained to predict where the
objects are.  GPS then fine-tunes them end to end.  Without it the S-step has to discover
the objects from a few training scenes alone (in the colour-reaching experiment every
training world shows the same 16 block layouts); with it, the composed colour-reaching
policy from images ends 0.276 from the block instead of 0.755 (``docs/RESULTS.md``).

:func:`pretrain_vision` does that pretraining for every module of a bank that reads images
(the vision task modules; in a monolithic bank, each world's network, so the baseline gets
the same start):

* it renders ``images`` random scenes of the task (objects placed by the task's own
  ``sample_params``, the arm at uniformly random joint angles so that it is seen
  anywhere), spread evenly over the *training* worlds that use the module, so the held-out
  world's arm-task pair is never shown;
* labels each with the positions of the task's objects (every ``pos`` observable but the
  end-effector's), read from the simulator's sensors;
* trains the module's :class:`~modnet.modules.PixelEncoder` and a throw-away linear head
  on the feature points to regress those positions (z-scored), holding out a tenth of
  the scenes to report the localisation error in metres.

The scenes come from their own random stream, apart from the train, test and random
condition sets, so no evaluation scene is ever rendered for pretraining.

Examples:
    >>> from modnet.bank import ModuleBank
    >>> bank = ModuleBank.build(["three_link"], ["reach"], pixels=True, seed=0)
    >>> report = pretrain_vision(bank, [("three_link", "reach")], PretrainConfig(images=40, epochs=1))
    >>> sorted(report["task/reach"])
    ['baseline_error', 'images', 'object_errors', 'seconds', 'val_error']
    >>> list(report["task/reach"]["object_errors"])
    ['target']
"""

from __future__ import annotations

import math
import time
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
import torch
from torch import nn

from modnet.bank import ModuleBank
from modnet.envs import CAMERA, open_renderer
from modnet.modules import BankModule, check_positive_ints
from modnet.specs import PIXELS_SHAPE
from modnet.worlds import SCENE_STREAM, World, get_world

__all__ = ["PretrainConfig", "object_slots", "objects", "pretrain_vision", "probe_vision", "render_scenes"]

VALIDATION_FRACTION = 0.1
#: appended to a module's pretraining stream: the probe's scenes (:func:`probe_vision`) are
#: neither pretraining scenes nor any condition set's
PROBE_STREAM = 1


@dataclass(frozen=True)
class PretrainConfig:
    """Pose-regression pretraining of the modules that read images (off when ``images`` is 0).

    Args:
        images: random scenes rendered per module (0: no pretraining).
        epochs: passes over them.
        batch_size: images per Adam step.
        lr: Adam's learning rate.
        seed: the scenes' and the head's seed (``run.py``: the run's ``seed``).

    Examples:
        >>> PretrainConfig(images=-1)
        Traceback (most recent call last):
        ...
        ValueError: images must be a non-negative integer, got -1
    """

    images: int = 0
    epochs: int = 30
    batch_size: int = 64
    lr: float = 1e-3
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("images", "seed"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"{name} must be a non-negative integer, got {value!r}")
        if self.images and self.images < 20:
            raise ValueError(f"images must be 0 (off) or at least 20, got {self.images}")
        check_positive_ints("epochs", (self.epochs,))
        check_positive_ints("batch_size", (self.batch_size,))
        lr = self.lr
        if isinstance(lr, bool) or not isinstance(lr, (int, float)) or not (math.isfinite(lr) and lr > 0):
            raise ValueError(f"lr must be a positive finite number, got {lr!r}")


def objects(world: World) -> list[str]:
    """The objects whose positions the image shows and pretraining regresses, in state order.

    Examples:
        >>> objects(get_world("three_link", "reach_red"))
        ['red', 'green', 'yellow', 'black']
    """
    return [name for name, kind in world.task.observables if kind == "pos" and name != "ee"]


def object_slots(world: World) -> list[int]:
    """Where the objects' positions sit in the task state: every ``pos`` observable but the
    end-effector's (what the image shows and the task module must find).

    Examples:
        >>> object_slots(get_world("three_link", "reach_red"))  # red, green, yellow, black
        [4, 5, 6, 7, 8, 9, 10, 11]
    """
    slots = [world.task.slot(name, "pos") for name in objects(world)]
    return [i for s in slots for i in range(s.start, s.stop)]


def render_scenes(world: World, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` random scenes of ``world`` from the top camera and their objects' positions.

    Returns uint8 images ``[n, 64, 80, 3]`` and float32 positions ``[n, len(object_slots)]``.
    Objects are placed by the task's ``sample_params``; every joint of the arm is uniform
    in ``[-pi, pi)``.  Only the forward kinematics run (no stepping), so an arm drawn over
    an object does not push it.
    """
    model, data = world.model, mujoco.MjData(world.model)
    renderer = open_renderer(model, *PIXELS_SHAPE[:2])
    slots = object_slots(world)
    images = np.zeros((n, *PIXELS_SHAPE), dtype=np.uint8)
    positions = np.zeros((n, len(slots)), dtype=np.float32)
    try:
        for i in range(n):
            arm = rng.uniform(-np.pi, np.pi, world.robot.n_joints)
            world.reset_data(data, np.concatenate([arm, world.task.sample_params(rng)]))
            renderer.update_scene(data, camera=CAMERA)
            renderer.render(out=images[i])
            positions[i] = world.observe(data.sensordata)[1][slots]
    finally:
        renderer.close()
    return images, positions


def pretrain_vision(
    bank: ModuleBank, worlds: Sequence[tuple[str, str]], config: PretrainConfig
) -> dict[str, dict[str, Any]]:
    """Pretrain the convolutions of every module that reads images in the policies of ``worlds``.

    For each such module, ``config.images`` scenes spread over the worlds in ``worlds`` that
    use it.  Returns, keyed ``"factor/name"`` (``"task/reach_red"``), the validation error
    (mean distance in metres between predicted and true object positions; per object in
    ``object_errors``) next to the error of always predicting the mean position
    (``baseline_error``), the number of scenes and the seconds taken.  Only the module's
    :class:`~modnet.modules.PixelEncoder` keeps what it learnt.
    """
    if config.images == 0:
        return {}
    report = {}
    for (factor, name), (module, module_worlds) in _vision_modules(bank, worlds).items():
        start = time.perf_counter()
        label = f"{factor}/{name}"
        rng = np.random.default_rng([config.seed, SCENE_STREAM, zlib.crc32(name.encode())])
        counts = np.diff(np.linspace(0, config.images, len(module_worlds) + 1).round().astype(int))
        scenes = [render_scenes(w, int(k), rng) for w, k in zip(module_worlds, counts, strict=True) if k]
        images = torch.from_numpy(np.concatenate([s[0] for s in scenes]))
        targets = torch.from_numpy(np.concatenate([s[1] for s in scenes]))
        figures = _regress(module.module.pixels, images, targets, objects(module_worlds[0]), config)
        report[label] = {**figures, "seconds": time.perf_counter() - start}
    return report


def _vision_modules(
    bank: ModuleBank, worlds: Sequence[tuple[str, str]]
) -> dict[tuple[str, str], tuple[BankModule, list[World]]]:
    """The modules that read images in the policies of ``worlds`` (and whose task shows objects),
    keyed ``(factor, name)``, each with the worlds of ``worlds`` that use it."""
    users: dict[tuple[str, str], tuple[BankModule, list[World]]] = {}
    for robot, task in worlds:
        world = get_world(robot, task)
        for factor, name in bank.slot_names((robot, task)):
            module = bank.get(factor, name)
            if module.module.pixels is not None and object_slots(world):
                users.setdefault((factor, name), (module, []))[1].append(world)
    return users


@torch.no_grad()
def probe_vision(
    bank: ModuleBank, worlds: Sequence[tuple[str, str]], scenes: int, seed: int = 0, ridge: float = 1e-6
) -> dict[str, dict[str, Any]]:
    """How well each vision module's feature points still show where the objects are: a linear probe.

    Pretraining teaches the convolutions to find the objects; GPS then trains them end to
    end on a few scenes, and nothing keeps them finding the objects elsewhere.  The probe
    measures what a bank's convolutions show *now*, without training them: for every module
    that reads images in the policies of ``worlds``, ``scenes`` random scenes per world
    (rendered as for pretraining, from a random stream of their own, apart from the
    pretraining's and every condition set's) go through its frozen
    :class:`~modnet.modules.PixelEncoder`, and a ridge least-squares map from the feature
    points (and a constant) to the objects' positions is fitted on the first
    ``1 - VALIDATION_FRACTION`` of each world's scenes, pooled over the worlds.

    Returns, keyed ``"factor/name"``: ``worlds``, the held-out scenes' error per world and
    object (mean planar distance in metres), and ``baseline_error``, the error of guessing
    the training scenes' mean position, pooled.

    Examples:
        >>> bank = ModuleBank.build(["three_link"], ["reach"], pixels=True, seed=0)
        >>> report = probe_vision(bank, [("three_link", "reach")], scenes=20)
        >>> list(report["task/reach"]["worlds"])
        ['three_link/reach']
        >>> list(report["task/reach"]["worlds"]["three_link/reach"])
        ['target']
    """
    if scenes < 2:
        raise ValueError(f"scenes must be at least 2 per world (some to fit, some to test), got {scenes}")
    report = {}
    for (factor, name), (module, module_worlds) in _vision_modules(bank, worlds).items():
        encoder, was_training = module.module.pixels, module.training
        module.eval()
        rng = np.random.default_rng([seed, SCENE_STREAM, zlib.crc32(name.encode()), PROBE_STREAM])
        n_val = max(1, int(scenes * VALIDATION_FRACTION))
        fit, held_out = [], {}
        for world in module_worlds:
            images, positions = render_scenes(world, scenes, rng)
            points = torch.cat([encoder(b) for b in torch.from_numpy(images).split(256)]).to(torch.float64)
            targets = torch.from_numpy(positions).to(torch.float64)
            fit.append((points[:-n_val], targets[:-n_val]))
            held_out[world.name] = (points[-n_val:], targets[-n_val:])
        module.train(was_training)
        points, targets = (torch.cat(parts) for parts in zip(*fit, strict=True))
        design = _with_constant(points)
        gram = design.T @ design + ridge * len(design) * torch.eye(design.shape[1], dtype=design.dtype)
        weights = torch.linalg.solve(gram, design.T @ targets)
        names = objects(module_worlds[0])
        errors = {}
        for world_name, (p, y) in held_out.items():
            predicted = _with_constant(p) @ weights
            errors[world_name] = dict(zip(names, _point_errors(predicted, y).tolist(), strict=True))
        y = torch.cat([y for _, y in held_out.values()])
        baseline = float(_point_errors(targets.mean(0).expand_as(y), y).mean())
        report[f"{factor}/{name}"] = {
            "scenes": scenes * len(module_worlds),
            "worlds": errors,
            "baseline_error": baseline,
        }
    return report


def _with_constant(x: torch.Tensor) -> torch.Tensor:
    """``[n, k]`` -> ``[n, k + 1]``: a column of ones for a linear map's offset."""
    return torch.cat([x, x.new_ones(len(x), 1)], 1)


def _regress(
    encoder: nn.Module, images: torch.Tensor, targets: torch.Tensor, names: list[str], config: PretrainConfig
) -> dict[str, Any]:
    """Train ``encoder`` plus a linear head to regress ``targets`` (the positions of the objects
    ``names``) from ``images``; the held-out tenth's errors."""
    generator = torch.Generator().manual_seed(config.seed)
    order = torch.randperm(len(images), generator=generator)
    n_val = max(1, int(len(images) * VALIDATION_FRACTION))
    val, train = order[:n_val], order[n_val:]
    mean, std = targets[train].mean(0), targets[train].std(0).clamp_min(1e-3)
    head = nn.Linear(encoder.out_dim, targets.shape[-1])
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        head.reset_parameters()
    params = list(encoder.parameters()) + list(head.parameters())
    optimizer = torch.optim.Adam(params, lr=config.lr)
    was_training = encoder.training
    encoder.train()
    for _ in range(config.epochs):
        for batch in train[torch.randperm(len(train), generator=generator)].split(config.batch_size):
            loss = (head(encoder(images[batch])) - (targets[batch] - mean) / std).square().mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    encoder.eval()
    with torch.no_grad():
        predicted = torch.cat([head(encoder(images[b])) for b in val.split(256)]) * std + mean
    encoder.train(was_training)
    errors = _point_errors(predicted, targets[val])
    return {
        "images": len(images),
        "val_error": float(errors.mean()),
        "baseline_error": float(_point_errors(mean.expand_as(targets[val]), targets[val]).mean()),
        "object_errors": dict(zip(names, errors.tolist(), strict=True)),
    }


def _point_errors(predicted: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """Mean planar distance between predicted and true points (``[n, 2 k]`` each), per point: ``[k]``."""
    return (predicted - true).unflatten(-1, (-1, 2)).norm(dim=-1).mean(0)
