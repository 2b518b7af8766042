"""The module bank: every task and robot module (or, generally, one module per factor value).

A bank is keyed by factor names in the order data flows, e.g. ``("task", "robot")``: the
task module ``g_k`` writes an interface that the robot module ``f_r`` reads, and the policy
of world ``(r, k)`` is ``f_r(g_k(o_task), o_robot)``.  Worlds are named root first (the
factor that writes the action first): ``compose("four_link", "reach_black")``.  More
degrees of variation are more factors, e.g. ``("object", "task", "robot")``; each module
reads whichever upstream interfaces its :class:`~modnet.modules.ModuleArch` names.

* :meth:`ModuleBank.build` makes a robot/task bank whose sizes all come from
  :func:`~modnet.worlds.robot_spec` and :func:`~modnet.worlds.task_spec`; the
  architecture options live in :class:`BankConfig`.
* :meth:`ModuleBank.compose` gives a TorchRL :class:`~torchrl.modules.ProbabilisticActor`
  whose ``TensorDictSequential`` holds the bank's own modules (shared, never copied).
* :meth:`ModuleBank.forward_worlds` evaluates many worlds in one pass, each module once
  on the concatenation of its worlds' batches (the multi-world GPS loss).
* :meth:`ModuleBank.save` / :meth:`ModuleBank.load` / :meth:`ModuleBank.load_module`:
  a ``manifest.json`` plus one ``torch.save``'d state dict per module, loaded with
  ``weights_only=True`` (no code from the files ever runs).

Examples:
    >>> import torch
    >>> from torchrl.envs.utils import ExplorationType, set_exploration_type
    >>> from modnet.envs import make_env
    >>> bank = ModuleBank.build(["three_link", "four_link"], ["reach_red", "reach_black"], seed=0)
    >>> policy = bank.compose("four_link", "reach_black")  # never trained together
    >>> policy[0]["robot"] is bank.get("robot", "four_link")
    True
    >>> with set_exploration_type(ExplorationType.DETERMINISTIC):
    ...     td = make_env("four_link", "reach_black", num_envs=8).rollout(5, policy)
    >>> td["action"].shape, td["interface", "task"].shape
    (torch.Size([8, 5, 4]), torch.Size([8, 5, 12]))
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import zlib
from collections import OrderedDict, defaultdict
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any, Literal

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictSequential
from tensordict.utils import NestedKey
from torch import nn
from torchrl.envs.utils import ExplorationType
from torchrl.modules import IndependentNormal, ProbabilisticActor

from modnet.files import write_atomically
from modnet.modules import Activation, BankModule, ModuleArch, check_positive_ints, key_to_str
from modnet.specs import EE_DIM
from modnet.worlds import robot_spec, task_spec

__all__ = ["BankConfig", "BankError", "ModuleBank", "World"]

World = tuple[str, ...]  # one module name per factor, root (action-writing) factor first
ROBOT_TASK = ("task", "robot")
MONOLITHIC = "world"  # the one factor of a monolithic bank: a network per world
MANIFEST = "manifest.json"
FORMAT = "modnet.bank/1"
_SPECS: dict[str, Callable[[str], object]] = {"robot": robot_spec, "task": task_spec}
_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_\-]*")
_RESERVED = frozenset(dir(nn.ModuleDict()))  # "train", "eval", "type", "keys", ...


def monolithic_name(world: Sequence[str]) -> str:
    """The name of a monolithic bank's network for ``world``: ``"ROBOT-TASK"``.

    Examples:
        >>> monolithic_name(("three_link", "reach_red"))
        'three_link-reach_red'
        >>> monolithic_world(monolithic_name(("three_link", "reach_red")))
        ('three_link', 'reach_red')
    """
    return "-".join(world)


def monolithic_world(name: str) -> tuple[str, str]:
    """``(robot, task)`` of a monolithic network's ``name``: the inverse of :func:`monolithic_name`."""
    robot, _, task = name.partition("-")
    return robot, task


class BankError(ValueError):
    """A bank, module or file that does not fit: names what and which sizes."""


def check_name(what: str, name: object) -> str:
    """``name`` if it can key an ``nn.ModuleDict`` and a file, else :class:`BankError`.

    Examples:
        >>> check_name("task", "reach_red")
        'reach_red'
        >>> check_name("robot", "train")
        Traceback (most recent call last):
        ...
        modnet.bank.BankError: robot name 'train' cannot key a module: ...
    """
    if not isinstance(name, str) or not _NAME.fullmatch(name) or name in _RESERVED:
        raise BankError(
            f"{what} name {name!r} cannot key a module: use letters, digits, '_' and '-' "
            "(no '.'), and no nn.Module attribute such as 'train', 'eval' or 'type'"
        )
    return name


@dataclass(frozen=True)
class BankConfig:
    """Architecture options of a robot/task bank (paper and GPS-code defaults).

    Args:
        task_hidden: hidden layers of a state task module before its bottleneck (3x80).
        vision_hidden: fully connected layers of a vision task module after the spatial
            softmax, fed with the feature points and the task state (one of 80).
        robot_hidden: hidden layers of a robot module before the action mean (80, 80).
        monolithic_hidden: layers of a monolithic per-world network; ``None`` uses
            ``task_hidden + robot_hidden`` (a network of the modular pair's size).
        interface_dim: width of the task -> robot bottleneck (12).
        dropout: dropout after every hidden layer (0.2: the authors' keep-probability 0.8).
        interface_dropout: dropout on the interface; ``None`` reuses ``dropout``.
        conv_channels: filters of the vision task module's convolutions (10, 20).
        kernel_size: their square kernel (3).
        conv_strides: their strides (2, 1): the first convolution halves the 64x80 image, which
            makes an S-step SGD step 7 times cheaper on a CPU (``benchmarks/pixel_sgd.py``).
        softmax_temperature: temperature of the spatial softmax of every module that reads
            images (1; ``color_reach`` uses 0.05, under which pose-regression pretraining
            finds all four blocks: :mod:`modnet.pretrain`).
        init_log_std: initial log-std of every action dimension (``log sqrt(0.1)``: GPS's
            initial policy variance 0.1).
        activation: the nonlinearity of every fully connected layer and interface bottleneck
            (``"relu"``, the paper's; or a smooth one: ``"tanh"``, ``"elu"``, ``"softplus"``,
            ``"silu"``; :data:`modnet.modules.ACTIVATIONS`). Convolutions stay ReLU.

    Examples:
        >>> BankConfig(interface_dim=8, dropout=0.0).interface_dim
        8
        >>> BankConfig(dropout=1.5)
        Traceback (most recent call last):
        ...
        ValueError: dropout must be a probability in [0, 1), got 1.5
    """

    task_hidden: tuple[int, ...] = (80, 80, 80)
    vision_hidden: tuple[int, ...] = (80,)
    robot_hidden: tuple[int, ...] = (80, 80)
    monolithic_hidden: tuple[int, ...] | None = None
    interface_dim: int = 12
    dropout: float = 0.2
    interface_dropout: float | None = None
    conv_channels: tuple[int, ...] = (10, 20)
    kernel_size: int = 3
    conv_strides: tuple[int, ...] = (2, 1)
    softmax_temperature: float = 1.0
    init_log_std: float = -1.1512925464970228
    activation: Activation = "relu"

    def __post_init__(self) -> None:
        for f in fields(self):  # a list (from JSON, YAML or a notebook) is the tuple it stands for
            if isinstance(value := getattr(self, f.name), list):
                object.__setattr__(self, f.name, tuple(value))
        check_positive_ints("interface_dim", (self.interface_dim,))
        # Every other field is checked by the ModuleArch it ends up in: build one of each.
        self.task_arch(1, pixels=True)
        self.task_arch(1, pixels=False)
        self.robot_arch(1, 1)
        self.monolithic_arch(1, 1, 1, pixels=False)

    def _common(self) -> dict[str, Any]:
        return {
            "dropout": self.dropout,
            "conv_channels": self.conv_channels,
            "kernel_size": self.kernel_size,
            "conv_strides": self.conv_strides,
            "softmax_temperature": self.softmax_temperature,
            "activation": self.activation,
        }

    def task_arch(self, task_state_dim: int, pixels: bool) -> ModuleArch:
        """A task module: ``("task", "state")`` -> ``("interface", "task")``; a vision one reads
        ``("task", "pixels")`` and, of the state, only the end-effector ``("task", "ee")``."""
        return ModuleArch(
            factor="task",
            head="interface",
            out_dim=self.interface_dim,
            observations=(_task_observation(task_state_dim, pixels),),
            pixels=("task", "pixels") if pixels else None,
            hidden=self.vision_hidden if pixels else self.task_hidden,
            interface_dropout=self.dropout if self.interface_dropout is None else self.interface_dropout,
            **self._common(),
        )

    def robot_arch(self, robot_state_dim: int, action_dim: int) -> ModuleArch:
        """A robot module: ``("interface", "task")`` and ``("robot", "state")`` -> ``loc``, ``scale``."""
        return ModuleArch(
            factor="robot",
            head="gaussian",
            out_dim=action_dim,
            observations=((("robot", "state"), robot_state_dim),),
            reads=(("task", self.interface_dim),),
            hidden=self.robot_hidden,
            init_log_std=self.init_log_std,
            **self._common(),
        )

    def monolithic_arch(
        self, robot_state_dim: int, task_state_dim: int, action_dim: int, pixels: bool
    ) -> ModuleArch:
        """One network per world reading both states (and pixels) -> ``loc``, ``scale``."""
        hidden = self.monolithic_hidden
        return ModuleArch(
            factor=MONOLITHIC,
            head="gaussian",
            out_dim=action_dim,
            observations=((("robot", "state"), robot_state_dim), _task_observation(task_state_dim, pixels)),
            pixels=("task", "pixels") if pixels else None,
            hidden=self.task_hidden + self.robot_hidden if hidden is None else hidden,
            init_log_std=self.init_log_std,
            **self._common(),
        )

    def to_json(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> BankConfig:
        names = {f.name for f in fields(cls)}
        if not isinstance(data, Mapping) or set(data) - names:
            raise ValueError(f"a bank config is a JSON object with fields among {sorted(names)}")
        return cls(**data)


def _task_observation(task_state_dim: int, pixels: bool) -> tuple[NestedKey, int]:
    """What a policy reads of the task state: all of it, or with pixels only the end-effector."""
    return (("task", "ee"), EE_DIM) if pixels else (("task", "state"), task_state_dim)


@contextlib.contextmanager
def _seeded(seed: int | None, *labels: str) -> Iterator[None]:
    """Initialise under a seed derived from ``seed`` and ``labels`` (global RNG untouched).

    One module's initial weights then depend on its own name only, not on what else the
    bank holds.  ``seed=None`` draws from the global RNG.
    """
    if seed is None:
        yield
        return
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(zlib.crc32("/".join((str(seed), *labels)).encode()))
        yield


def _sizes(arch: ModuleArch) -> dict[str, Any]:
    """A module's input and output sizes keyed ``"in task/state"``, ``"out loc"``, ..."""
    inputs = {f"in {key_to_str(k)}": v for k, v in arch.inputs.items()}
    return inputs | {f"out {key_to_str(k)}": v for k, v in arch.outputs.items()}


class ModuleBank(nn.Module):
    """Modules keyed by factor and name; composes them into per-world TorchRL actors.

    Args:
        factors: factor names in the order data flows; the last one writes the action.
        config: the architecture options :meth:`build` used (kept in the manifest).
        pixels: whether task modules read ``("task", "pixels")``.
        policy: ``"modular"``, or ``"monolithic"`` for one network per world (the
            baseline); a monolithic bank stores its networks under the factor ``"world"``.

    Examples:
        >>> bank = ModuleBank(("object", "task", "robot"))
        >>> bank.world_factors  # how worlds are named: root first
        ('robot', 'task', 'object')
        >>> ModuleBank(("task", "eval"))
        Traceback (most recent call last):
        ...
        modnet.bank.BankError: factor name 'eval' cannot key a module: ...
    """

    def __init__(
        self,
        factors: Sequence[str] = ROBOT_TASK,
        *,
        config: BankConfig | None = None,
        pixels: bool = False,
        policy: Literal["modular", "monolithic"] = "modular",
    ) -> None:
        super().__init__()
        factors = tuple(check_name("factor", f) for f in factors)
        if not factors or len(set(factors)) != len(factors):
            raise BankError(f"a bank needs distinct factor names, got {factors}")
        if policy not in ("modular", "monolithic"):
            raise BankError(f"policy must be 'modular' or 'monolithic', got {policy!r}")
        self.factors = factors
        self.config = config or BankConfig()
        self.pixels = bool(pixels)
        self.policy = policy
        slots = (MONOLITHIC,) if policy == "monolithic" else factors
        self.factor_modules = nn.ModuleDict({f: nn.ModuleDict() for f in slots})
        self._trained_on: dict[tuple[str, str], set[World]] = defaultdict(set)

    # --- building -----------------------------------------------------------------------------
    @classmethod
    def build(
        cls,
        robots: Sequence[str],
        tasks: Sequence[str],
        *,
        pixels: bool = False,
        policy: Literal["modular", "monolithic"] = "modular",
        config: BankConfig | None = None,
        seed: int | None = 0,
        **options: Any,
    ) -> ModuleBank:
        """A robot/task bank: one task module per task and one robot module per robot.

        Every size comes from the robot and task specs.  ``options`` override fields of
        ``config`` (``interface_dim=8, dropout=0.0``...).  ``seed`` makes initialisation
        reproducible (each module seeded from ``seed`` and its name); ``None`` uses the
        global RNG.  ``policy="monolithic"`` builds one network per (robot, task) pair.

        Examples:
            >>> bank = ModuleBank.build(["three_link"], ["reach", "push"], interface_dim=8)
            >>> bank.names("task"), bank.get("robot", "three_link").in_keys
            (('reach', 'push'), [('interface', 'task'), ('robot', 'state')])
            >>> ModuleBank.build(["six_link"], ["reach"])
            Traceback (most recent call last):
            ...
            ValueError: unknown robot 'six_link'; valid robots: three_link, ...
        """
        valid = {f.name for f in fields(BankConfig)}
        if set(options) - valid:
            raise TypeError(f"unknown bank options {sorted(set(options) - valid)}; valid: {sorted(valid)}")
        config = replace(config or BankConfig(), **options)
        if isinstance(robots, str) or isinstance(tasks, str) or not robots or not tasks:
            raise ValueError("build needs a non-empty list of robots and of tasks")
        robots, tasks = list(dict.fromkeys(robots)), list(dict.fromkeys(tasks))
        for robot in robots:
            robot_spec(robot)
        for task in tasks:
            task_spec(task)
        bank = cls(ROBOT_TASK, config=config, pixels=pixels, policy=policy)
        if policy == "monolithic":
            slots = [(MONOLITHIC, monolithic_name((r, k))) for r in robots for k in tasks]
        else:
            slots = [("task", k) for k in tasks] + [("robot", r) for r in robots]
        for factor, name in slots:
            with _seeded(seed, factor, name):
                bank.add(factor, name, BankModule(bank._recipe(factor, name)))
        return bank

    def _recipe(self, factor: str, name: str) -> ModuleArch | None:
        """The architecture :meth:`build` gives ``(factor, name)``; ``None`` off robot/task banks."""
        if self.factors != ROBOT_TASK:
            return None
        if factor == "task":
            return self.config.task_arch(task_spec(name).state_dim, self.pixels)
        if factor == "robot":
            robot = robot_spec(name)
            return self.config.robot_arch(robot.state_dim, robot.action_dim)
        robot_name, task_name = monolithic_world(name)
        robot, task = robot_spec(robot_name), task_spec(task_name)
        return self.config.monolithic_arch(robot.state_dim, task.state_dim, robot.action_dim, self.pixels)

    def add(self, factor: str, name: str, module: BankModule) -> BankModule:
        """Put ``module`` in the bank as ``factor``'s ``name`` (replacing any module there).

        The module takes the bank's train/eval mode.
        """
        slot = self._slot(factor)
        check_name(factor, name)
        if not isinstance(module, BankModule):
            raise BankError(f"a bank holds BankModule objects, got {type(module).__name__}")
        if module.factor != factor:
            raise BankError(f"{name!r} is a {module.factor} module; it cannot be a {factor} module")
        slot[name] = module.train(self.training)
        return module

    def _slot(self, factor: str) -> nn.ModuleDict:
        if factor not in self.factor_modules:
            raise BankError(f"unknown factor {factor!r}; this bank's: {', '.join(self.factor_modules)}")
        return self.factor_modules[factor]

    def get(self, factor: str, name: str) -> BankModule:
        """The module ``name`` of ``factor``; ``ValueError`` naming the valid choices."""
        slot = self._slot(factor)
        if name not in slot:
            if factor in _SPECS and self.factors == ROBOT_TASK:
                _SPECS[factor](name)  # an unknown robot/task: names every valid one
            raise BankError(
                f"this bank has no {factor} module {name!r}; its {factor} modules: "
                f"{', '.join(slot) or 'none'}"
            )
        return slot[name]

    def names(self, factor: str) -> tuple[str, ...]:
        """The names of ``factor``'s modules, in insertion order."""
        return tuple(self._slot(factor))

    @property
    def world_factors(self) -> tuple[str, ...]:
        """The factor of each name in a world tuple: root (action) first."""
        return tuple(reversed(self.factors))

    # --- composing ----------------------------------------------------------------------------
    def world(self, *names: str, **by_factor: str) -> World:
        """The world tuple from names given root first or by factor (``robot=..., task=...``).

        Examples:
            >>> bank = ModuleBank.build(["three_link"], ["reach"])
            >>> bank.world(task="reach", robot="three_link"), bank.world("three_link/reach")
            (('three_link', 'reach'), ('three_link', 'reach'))
        """
        if by_factor:
            if names or set(by_factor) != set(self.factors):
                raise BankError(
                    f"name one module per factor {self.world_factors}, positionally (root first) "
                    f"or by factor, not both; got {names} and {by_factor}"
                )
            return tuple(by_factor[f] for f in self.world_factors)
        if len(names) == 1 and "/" in names[0]:
            names = tuple(names[0].split("/"))
        if len(names) != len(self.factors) or not all(isinstance(n, str) for n in names):
            raise BankError(f"a world names one module per factor {self.world_factors}; got {names}")
        return tuple(names)

    def _as_world(self, key: World | str) -> World:
        return self.world(*key) if isinstance(key, tuple) else self.world(key)

    def parts(self, world: World) -> OrderedDict[str, BankModule]:
        """The modules of ``world`` in evaluation order, keyed by factor; checks their wiring."""
        world = self.world(*world)
        if self.policy == "monolithic":
            for factor, name in zip(self.world_factors, world, strict=True):
                if factor in _SPECS:
                    _SPECS[factor](name)
            return OrderedDict([(MONOLITHIC, self.get(MONOLITHIC, monolithic_name(world)))])
        parts = OrderedDict((f, self.get(f, n)) for f, n in zip(self.world_factors, world, strict=True))
        parts = OrderedDict(reversed(parts.items()))
        written: dict[NestedKey, int] = {}
        for factor, module in parts.items():
            for upstream, width in module.arch.reads:
                have = written.get(("interface", upstream))
                if have != width:
                    name = world[self.world_factors.index(factor)]
                    raise BankError(
                        f"world {'/'.join(world)}: the {factor} module {name!r} "
                        f"reads the {upstream} interface at width {width}, but "
                        + ("no earlier module writes it" if have is None else f"it is {have} wide")
                    )
            written.update(module.arch.outputs)
        if module.arch.head != "gaussian":
            raise BankError(f"world {'/'.join(world)}: the last factor {factor!r} must write the action")
        return parts

    def compose(self, *names: str, **by_factor: str) -> ProbabilisticActor:
        """The Gaussian TorchRL actor of a world, e.g. ``compose("four_link", "reach_black")``.

        Its ``TensorDictSequential`` (``policy[0]``) holds the bank's own modules under
        their factor names (``policy[0]["task"]``), so training either trains the bank.
        It writes the interface(s), ``"loc"``, ``"scale"`` and ``"action"``: a sample from
        ``IndependentNormal(loc, scale)`` by default, the mean under
        ``set_exploration_type(ExplorationType.DETERMINISTIC)``.  Any pair of modules
        composes, trained together or not (zero-shot, or a wrong-task baseline).
        """
        return ProbabilisticActor(
            TensorDictSequential(self.parts(self.world(*names, **by_factor))),
            in_keys=["loc", "scale"],
            distribution_class=IndependentNormal,
            default_interaction_type=ExplorationType.RANDOM,
            return_log_prob=False,
        )

    # --- many worlds at once ------------------------------------------------------------------------
    def forward_worlds(
        self, batches: Mapping[World | str, TensorDictBase], rows_per_pass: int | None = None
    ) -> dict[World, TensorDictBase]:
        """Evaluate the composed networks of many worlds, each module once.

        ``batches`` maps worlds to TensorDicts of their observations (any batch shape).
        Stage by stage, the worlds sharing a module are concatenated (flattened over
        their batch dims) and that module runs once on them.  Returns, per world, a
        TensorDict of the batch's shape holding every module output (interfaces,
        ``"loc"``, ``"scale"``), with autograd intact: the same numbers as running each
        world's :meth:`compose`\\ d network in turn.

        With ``rows_per_pass`` the rows (every world's batch flattened) go through in passes
        of at most that many rows per world, the outputs put back in each batch's shape.
        From images this bounds the memory of evaluating many samples, and passes small
        enough for the convolutions' activations to stay in cache are faster per image.

        Examples:
            >>> import torch
            >>> from tensordict import TensorDict
            >>> bank = ModuleBank.build(["three_link", "four_link"], ["reach_red"], dropout=0.0)
            >>> obs = lambda n_joints: TensorDict(
            ...     {("robot", "state"): torch.randn(5, 2 * n_joints),
            ...      ("task", "state"): torch.randn(5, 12)},
            ...     batch_size=[5])
            >>> three, four = ("three_link", "reach_red"), ("four_link", "reach_red")
            >>> out = bank.forward_worlds({three: obs(3), four: obs(4)})
            >>> out[four]["loc"].shape
            torch.Size([5, 4])
        """
        worlds = {self._as_world(w): td for w, td in batches.items()}
        if rows_per_pass is not None:
            return self._forward_in_passes(worlds, rows_per_pass)
        chains = {w: list(self.parts(w).values()) for w in worlds}
        rows = {w: td.batch_size.numel() for w, td in worlds.items()}
        made: dict[World, dict[NestedKey, torch.Tensor]] = {w: {} for w in worlds}

        def flat_input(world: World, key: NestedKey) -> torch.Tensor:
            if key in made[world]:
                return made[world][key]
            td = worlds[world]
            value = td.get(key)
            return value.reshape(rows[world], *value.shape[td.batch_dims :])

        for stage in range(max(len(c) for c in chains.values())):
            groups: dict[BankModule, list[World]] = defaultdict(list)  # modules hash by identity
            for world, chain in chains.items():
                groups[chain[stage]].append(world)
            for module, members in groups.items():
                inputs = [_cat([flat_input(w, key) for w in members]) for key in module.in_keys]
                result = module.module(*inputs)
                result = result if isinstance(result, tuple) else (result,)
                for key, value in zip(module.out_keys, result, strict=True):
                    for world, part in zip(members, value.split([rows[w] for w in members]), strict=True):
                        made[world][key] = part
        out = {}
        for world, td in worlds.items():
            result = TensorDict(batch_size=td.batch_size)
            for key, value in made[world].items():
                result.set(key, value.reshape(*td.batch_size, *value.shape[1:]))
            out[world] = result
        return out

    def _forward_in_passes(
        self, worlds: dict[World, TensorDictBase], rows: int
    ) -> dict[World, TensorDictBase]:
        if rows < 1:
            raise ValueError(f"rows_per_pass must be at least 1, got {rows}")
        flat = {w: td.reshape(td.batch_size.numel()) for w, td in worlds.items()}  # -1 fails when empty
        longest = max(td.shape[0] for td in flat.values())  # batches may differ (task horizons)
        parts: dict[World, list[TensorDictBase]] = {w: [] for w in flat}
        for i in range(0, max(longest, 1), rows):  # every world in the first pass, empty ones too
            batch = {w: td[i : i + rows] for w, td in flat.items() if i < td.shape[0] or i == 0}
            out = self.forward_worlds(batch)
            for world, td in out.items():
                parts[world].append(td)
        return {w: torch.cat(parts[w]).reshape(worlds[w].batch_size) for w in worlds}

    forward = forward_worlds

    def fit_normalization(
        self, batches: Mapping[World | str, TensorDictBase], keep_function: bool = False
    ) -> None:
        """Set every used module's observation normalisation from the worlds' samples.

        A module shared by several worlds is fitted on all of their samples pooled.  With
        ``keep_function`` each module's first layer absorbs the change, so the policies act
        exactly as before (GPS refits this way every iteration).
        """
        pooled: dict[BankModule, list[TensorDictBase]] = defaultdict(list)
        for world, td in batches.items():
            for module in self.parts(self._as_world(world)).values():
                keys = [k for k, _ in module.arch.observations]
                if keys:
                    pooled[module].append(td.select(*keys).reshape(-1))
        for module, samples in pooled.items():
            module.fit_normalization(torch.cat(samples), keep_function)

    # --- bookkeeping and baselines ----------------------------------------------------------------
    def _module_names(self) -> Iterator[tuple[str, str, BankModule]]:
        for factor, slot in self.factor_modules.items():
            for name, module in slot.items():
                yield factor, name, module

    def slot_names(self, world: World) -> list[tuple[str, str]]:
        """``(factor, name)`` of each module of ``world`` (one ``("world", "ROBOT-TASK")`` when monolithic).

        Examples:
            >>> ModuleBank.build(["three_link"], ["reach"]).slot_names(("three_link", "reach"))
            [('robot', 'three_link'), ('task', 'reach')]
        """
        if self.policy == "monolithic":
            return [(MONOLITHIC, monolithic_name(world))]
        return list(zip(self.world_factors, world, strict=True))

    def mark_trained(self, *names: str, **by_factor: str) -> None:
        """Record that a world's modules were trained on it (kept in the manifest)."""
        world = self.world(*names, **by_factor)
        self.parts(world)
        for slot in self.slot_names(world):
            self._trained_on[slot].add(world)

    def trained_on(self, factor: str, name: str) -> frozenset[World]:
        """The worlds module ``name`` of ``factor`` was marked trained on."""
        self.get(factor, name)
        return frozenset(self._trained_on.get((factor, name), ()))

    def fresh_copy(self, seed: int | None = None, keep_normalization: bool = True) -> ModuleBank:
        """The same architecture, freshly initialised: the "random network" baseline.

        Normalisation buffers are copied unless ``keep_normalization=False``; trained-on
        records are not.
        """
        copy = type(self)(self.factors, config=self.config, pixels=self.pixels, policy=self.policy)
        for factor, name, module in self._module_names():
            with _seeded(seed, factor, name):
                fresh = copy.add(factor, name, BankModule(module.arch))
            if keep_normalization:
                fresh.module.normalizers.load_state_dict(module.module.normalizers.state_dict())
        return copy.train(self.training)

    # --- files ------------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> Path:
        """Write ``manifest.json`` and ``<factor>/<name>.pt`` (a state dict) per module.

        Every file is written to a temporary name then ``os.replace``\\ d; the manifest
        goes last, so a directory with a manifest is complete.
        """
        path = Path(path)
        entries = []
        for factor, name, module in self._module_names():
            state = {k: v.detach().clone() for k, v in module.state_dict().items()}
            write_atomically(path / factor / f"{name}.pt", lambda p, s=state: torch.save(s, p))
            entries.append(
                {
                    "factor": factor,
                    "name": name,
                    "kind": module.arch.head,
                    "file": f"{factor}/{name}.pt",
                    "sizes": _sizes(module.arch),
                    "arch": module.arch.to_json(),
                    "trained_on": sorted(list(w) for w in self._trained_on.get((factor, name), ())),
                }
            )
        import modnet

        manifest = {
            "format": FORMAT,
            "modnet_version": getattr(modnet, "__version__", "0.1.0"),
            "factors": list(self.factors),
            "policy": self.policy,
            "pixels": self.pixels,
            "interface_dim": self.config.interface_dim,
            "config": self.config.to_json(),
            "modules": entries,
        }
        text = json.dumps(manifest, indent=2)
        write_atomically(path / MANIFEST, lambda p: p.write_text(text))
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> ModuleBank:
        """Rebuild a saved bank from its manifest and weights (no training config needed).

        Like any new ``nn.Module`` it starts in train mode (dropout on): call ``.eval()``
        to evaluate.  Raises :class:`BankError` for a missing or corrupt manifest or weights file.
        """
        path = Path(path)
        manifest = _read_manifest(path)
        try:
            bank = cls(
                manifest["factors"],
                config=BankConfig.from_json(manifest["config"]),
                pixels=manifest["pixels"],
                policy=manifest["policy"],
            )
        except (KeyError, TypeError, ValueError) as err:
            raise BankError(f"corrupt manifest {path / MANIFEST}: {err}") from err
        for entry in manifest["modules"]:
            factor, name, module, trained = _load_entry(path, entry)
            bank.add(factor, name, module)
            bank._trained_on[factor, name] = trained
        return bank

    def load_module(
        self, path: str | os.PathLike, factor: str, name: str, *, into: str | None = None
    ) -> BankModule:
        """Load module ``name`` of ``factor`` from the bank saved at ``path`` into this bank.

        It lands as ``into`` (default ``name``), replacing any module there.  Its input and
        output sizes must match what this bank expects at that slot (the module it
        replaces, or what :meth:`build` would make there); otherwise :class:`BankError`
        lists every mismatched size.
        """
        path = Path(path)
        target = check_name(factor, into or name)
        self._slot(factor)
        entries = _read_manifest(path)["modules"]
        entry = next((e for e in entries if (e.get("factor"), e.get("name")) == (factor, name)), None)
        if entry is None:
            saved = ", ".join(f"{e.get('factor')}/{e.get('name')}" for e in entries)
            raise BankError(f"no {factor} module {name!r} in the bank at {path}; it holds: {saved}")
        _, _, module, trained = _load_entry(path, entry)
        expected = self.get(factor, target).arch if target in self.names(factor) else None
        expected = expected or self._recipe(factor, target)
        if expected is None:  # a bank without recipes: at least the interfaces must match
            peers = [m.arch for m in self.factor_modules[factor].values()]
            expected = peers[0] if peers else None
            only = lambda k: k.split(" ")[1].startswith("interface/")
        else:
            only = lambda k: True
        if expected is not None:
            want, got = _sizes(expected), _sizes(module.arch)
            wrong = [
                f"{k} is {got.get(k, 'absent')} there but {want.get(k, 'absent')} here"
                for k in sorted(set(want) | set(got))
                if only(k) and want.get(k) != got.get(k)
            ]
            if wrong:
                raise BankError(
                    f"cannot load {factor} module {name!r} from {path} as {factor} {target!r}: "
                    + "; ".join(wrong)
                )
        self.add(factor, target, module)
        self._trained_on[factor, target] = trained
        return module


def _cat(tensors: list[torch.Tensor]) -> torch.Tensor:
    return tensors[0] if len(tensors) == 1 else torch.cat(tensors)


def _read_manifest(path: Path) -> dict[str, Any]:
    file = path / MANIFEST
    try:
        manifest = json.loads(file.read_text())
    except FileNotFoundError as err:
        raise BankError(f"no saved bank at {path}: {MANIFEST} is missing") from err
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise BankError(f"corrupt manifest {file}: {err}") from err
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise BankError(f"corrupt manifest {file}: not a {FORMAT} manifest")
    if not isinstance(manifest.get("modules"), list):
        raise BankError(f"corrupt manifest {file}: no list of modules")
    return manifest


def _load_entry(path: Path, entry: Any) -> tuple[str, str, BankModule, set[World]]:
    """Rebuild one manifest entry's module and load its weights (``weights_only``)."""
    try:
        factor, name = check_name("factor", entry["factor"]), check_name("module", entry["name"])
        module = BankModule(ModuleArch.from_json(entry["arch"]))
        trained = {tuple(w) for w in entry.get("trained_on", [])}
    except (KeyError, TypeError, ValueError) as err:
        raise BankError(f"corrupt manifest {path / MANIFEST}: bad module entry {entry!r}: {err}") from err
    file = path / factor / f"{name}.pt"  # never a path taken from the manifest
    try:
        state = torch.load(file, map_location="cpu", weights_only=True)
    except FileNotFoundError as err:
        raise BankError(f"weights of {factor} module {name!r} are missing: {file}") from err
    except Exception as err:  # unpickling refused or failed: the file is not plain tensors
        raise BankError(f"corrupt weights for {factor} module {name!r} in {file}: {err}") from err
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise BankError(f"corrupt weights for {factor} module {name!r} in {file}: not a state dict")
    try:
        module.load_state_dict(state)
    except RuntimeError as err:
        raise BankError(
            f"weights of {factor} module {name!r} in {file} do not fit its manifest architecture "
            f"{_sizes(module.arch)}: {err}"
        ) from err
    return factor, name, module, trained
