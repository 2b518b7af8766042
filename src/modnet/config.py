"""Typed run configuration: what ``run.py`` hands the library, and the Hydra schema it is checked against.

:class:`RunConfig` is the whole job (universe, held-out world, GPS budget, bank architecture,
evaluation, logger).  Its ``gps`` and ``bank`` parts are not hand-written copies of the
library's :class:`~modnet.gps.trainer.GPSConfig` and :class:`~modnet.bank.BankConfig`: they
are derived from them field by field (:func:`schema_of`), so a field added to or retuned
in the library shows up in ``conf/`` with the library's default, and :func:`build` turns
the checked values back into the library's dataclasses.

Nothing here reads Hydra's config object: ``run.py`` turns it into a :class:`RunConfig`
(``OmegaConf.to_object``) and hands that in.

Examples:
    >>> run = RunConfig(universe="tiny")
    >>> run.gps.iterations, run.gps_config() == GPSConfig()  # the library's defaults
    (10, True)
    >>> run.gps.algo = "ilqr"
    >>> run.gps_config()
    Traceback (most recent call last):
    ...
    modnet.config.ConfigError: gps.algo must be one of 'mdgps', 'badmm', got 'ilqr'
"""

from __future__ import annotations

import dataclasses
import logging
import typing
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

from modnet.bank import BankConfig, ModuleBank
from modnet.envs import WorldEnv
from modnet.evaluate import FINETUNE_STARTS, evaluation_env
from modnet.gps.badmm import BADMMConfig
from modnet.gps.dynamics import DynamicsPriorConfig
from modnet.gps.trainer import GPSConfig, check_train_modules
from modnet.pretrain import PretrainConfig
from modnet.universes import Split, Universe, get_universe
from modnet.worlds import CONDITION_SETS, NUM_FIXED_CONDITIONS

log = logging.getLogger(__name__)

__all__ = [
    "BankSchema",
    "ConfigError",
    "EvalConfig",
    "GPSSchema",
    "LoggerConfig",
    "PretrainSchema",
    "RunConfig",
    "build",
    "register_configs",
    "schema_of",
    "validate",
]

LOGGERS = ("wandb", "csv", "tensorboard", "none")


class ConfigError(ValueError):
    """A configuration value the run cannot use, named by its dotted key."""


def _hydra_type(hint: Any) -> Any:
    """The annotation OmegaConf accepts for ``hint``: ``Literal`` choices become ``str``."""
    if typing.get_origin(hint) is typing.Literal:
        return str
    return hint


def schema_of(
    cls: type,
    name: str,
    *,
    nested: Mapping[type, type] | None = None,
    extra: tuple[tuple[str, type, Any], ...] = (),
    exclude: tuple[str, ...] = (),
) -> type:
    """An OmegaConf-compatible dataclass ``name`` with the fields and defaults of dataclass ``cls``.

    ``Literal`` fields become ``str`` (:func:`build` checks the choices); a nested dataclass
    field takes the schema ``nested`` maps its class to; ``extra`` adds ``(name, type,
    default)`` fields that only the run uses (e.g. the number of iterations) and ``exclude``
    hides library fields the run sets itself.  Assign the result to a module-level name
    equal to ``name`` in this module (configs pickle their schema by name).

    Examples:
        >>> from modnet.gps.badmm import BADMMConfig
        >>> schema = schema_of(BADMMConfig, "BADMMSchema")
        >>> schema().inner_iterations == BADMMConfig().inner_iterations
        True
    """
    hints = typing.get_type_hints(cls)
    specs: list[tuple[str, Any, Any]] = []
    for f in fields(cls):
        if f.name in exclude:
            continue
        default = f.default if f.default is not MISSING else f.default_factory()  # type: ignore[misc]
        if is_dataclass(default):
            schema = (nested or {})[type(default)]
            values = {k.name: getattr(default, k.name) for k in fields(default)}
            specs.append((f.name, schema, field(default_factory=lambda s=schema, v=values: s(**v))))
        else:
            specs.append((f.name, _hydra_type(hints[f.name]), field(default=default)))
    specs += [(n, t, field(default=d)) for n, t, d in extra]
    schema = dataclasses.make_dataclass(name, specs)
    schema.__module__ = __name__
    schema.__doc__ = (
        f"Hydra schema of :class:`{cls.__module__}.{cls.__qualname__}` (same fields and defaults)."
    )
    return schema


def build(cls: type, values: Any, prefix: str = "") -> Any:
    """The library dataclass ``cls`` from a schema instance or mapping with (a subset of) its fields.

    Lists become tuples, nested dataclasses are built recursively, and ``Literal`` fields
    are checked against their choices (:class:`ConfigError` naming the key and the choices).
    """
    if is_dataclass(values):
        values = {f.name: getattr(values, f.name) for f in fields(values)}
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in fields(cls):
        if f.name not in values:
            continue
        value, hint, key = values[f.name], hints[f.name], f"{prefix}{f.name}"
        if is_dataclass(hint):
            value = build(hint, value, f"{key}.")
        elif isinstance(value, list):
            value = tuple(value)
        elif typing.get_origin(hint) is typing.Literal and value not in typing.get_args(hint):
            choices = ", ".join(repr(c) for c in typing.get_args(hint))
            raise ConfigError(f"{key} must be one of {choices}, got {value!r}")
        kwargs[f.name] = value
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{prefix.rstrip('.') or cls.__name__}: {err}") from err


DynamicsPriorSchema = schema_of(DynamicsPriorConfig, "DynamicsPriorSchema")
BADMMSchema = schema_of(BADMMConfig, "BADMMSchema")
GPSSchema = schema_of(
    GPSConfig,
    "GPSSchema",
    nested={DynamicsPriorConfig: DynamicsPriorSchema, BADMMConfig: BADMMSchema},
    extra=(("iterations", int, 10),),  # GPS iterations of the main training run
    exclude=("init_from_policy",),  # set by the fine-tuning driver only
)
PretrainSchema = schema_of(PretrainConfig, "PretrainSchema")
BankSchema = schema_of(
    BankConfig,
    "BankSchema",
    extra=(("policy", str, "modular"),),  # "modular", or "monolithic": one network per world
)


@dataclass
class EvalConfig:
    """The zero-shot evaluation, its pictures and the optional fine-tuning comparison.

    Args:
        conditions: the condition set of the zero-shot table ("test": the paper's 4 test positions).
        num_conditions: how many of them (None: the set's 4).
        random_conditions: when > 0, also evaluate on this many random conditions (mean, 95% CI).
        random_seed: the random conditions' seed.
        baseline_seed: initialisation seed of the random-network baseline.
        frame_height, frame_width: size of the final-position pictures (at most 512 x 640).
        gif_frames: at most this many frames in the rollout GIF.
        finetune_iterations: GPS iterations per fine-tuning start (with ``finetune=true``).
        finetune_starts: which starts to compare (composed, wrong_task, scratch_shaping,
            scratch_no_shaping).
        finetune_samples_per_condition: samples per condition and iteration of every
            fine-tuning start (None: the training's ``gps.samples_per_condition``). Not part
            of a checkpoint's identity, so ``resume=true`` on a copy of a finished run
            fine-tunes its bank with another budget.
        finetune_sample_on_policy: every fine-tuning start samples the composed policy itself
            from its second iteration on, instead of the controllers (``gps.sample_on_policy``
            for fine-tuning only; not part of a checkpoint's identity either).
        finetune_kl_step: the LQR's KL budget per time step in every fine-tuning start
            (None: ``gps.kl_step``); not part of a checkpoint's identity. PI2 does not read it
            (its step is ``finetune_pi2_kl``); PILQR's LQR pass does.
        finetune_sgd_steps: the S-step's SGD steps per iteration in every fine-tuning start
            (None: ``gps.sgd_steps``); not part of a checkpoint's identity.
        finetune_dynamics_prior_per_condition: every fine-tuning start keeps one dynamics
            prior per condition (True) or one over all conditions (False); None:
            ``gps.dynamics_prior_per_condition``. Not part of a checkpoint's identity.
        finetune_policy_linearization: how every fine-tuning start linearises the composed
            policy ("regression" or "jacobian", :class:`~modnet.gps.GPSConfig`'s
            ``policy_linearization``); None: ``gps.policy_linearization``. Not part of a
            checkpoint's identity.
        finetune_algo: the GPS algorithm of every fine-tuning start ("mdgps" or "badmm");
            None: the training's. Not part of a checkpoint's identity.
        finetune_c_step: the C-step of every fine-tuning start ("lqr", or "pi2" or "pilqr" with MDGPS);
            None: ``gps.c_step``. Not part of a checkpoint's identity.
        finetune_num_conditions: the scenes every fine-tuning start samples on the held-out
            world; None: ``gps.num_conditions``. Not part of a checkpoint's identity.
        finetune_train_modules: which modules every fine-tuning start's S-step trains ("all",
            "task" or "robot"; :class:`~modnet.gps.GPSConfig`'s ``train_modules``); None:
            ``gps.train_modules``. Not part of a checkpoint's identity.
        finetune_relabel_policy_states: every fine-tuning start's S-step also imitates the
            controllers at the states the network visits acting alone ("sampled": with its
            noise, or "mean": its mean actions; DAgger's relabelling, MDGPS only; "off": not;
            :class:`~modnet.gps.GPSConfig`'s ``relabel_policy_states``); None:
            ``gps.relabel_policy_states``. Not part of a checkpoint's identity.
        finetune_init_variance: the variance of the first controllers of the scratch starts
            (the transferred starts begin from the composed policy's linearisation and its
            spread); None: ``gps.init_variance``. Not part of a checkpoint's identity.
        finetune_pi2_kl: the KL from uniform of the sample weights of every fine-tuning start's
            PI2 (or PILQR) step, per time step (:class:`~modnet.gps.GPSConfig`'s ``pi2_kl``;
            smaller: a smaller step); None: ``gps.pi2_kl``. Not part of a checkpoint's identity.
        finetune_pi2_covariance_damping: how slowly every fine-tuning start's PI2 (or PILQR)
            shrinks its exploration (larger: slower; :class:`~modnet.gps.GPSConfig`'s
            ``pi2_covariance_damping``); None: ``gps.pi2_covariance_damping``. Not part of a
            checkpoint's identity.
        finetune_relabel_tracking_weight: with ``finetune_relabel_policy_states``, label the
            network's states with the controllers' feedback fitted anew by a tracking LQR of
            this torque weight (:class:`~modnet.gps.GPSConfig`'s ``relabel_tracking_weight``);
            None: ``gps.relabel_tracking_weight``. Not part of a checkpoint's identity.
        finetune_pi2_policy_weight: every fine-tuning start's PI2 also weighs how far each sample
            strayed from the composed policy (MDGPS's trust region; :class:`~modnet.gps.GPSConfig`'s
            ``pi2_policy_weight``, with ``finetune_c_step=pi2``); None: ``gps.pi2_policy_weight``.
            Not part of a checkpoint's identity.
        finetune_pi2_step_smoothing: every fine-tuning start's PI2 filters its step of the
            feed-forward along time with a Gaussian of this many steps (:class:`~modnet.gps.GPSConfig`'s
            ``pi2_step_smoothing``, with ``finetune_c_step=pi2``); None: ``gps.pi2_step_smoothing``.
            Not part of a checkpoint's identity.
        finetune_pi2_policy_feedback: every fine-tuning start's PI2 gives its controllers the
            network's feedback after each step (:class:`~modnet.gps.GPSConfig`'s
            ``pi2_policy_feedback``, with ``finetune_c_step=pi2``); None: ``gps.pi2_policy_feedback``.
            Not part of a checkpoint's identity.
        finetune_feedback_weight: every fine-tuning start's S-step also regresses the network's
            Jacobian onto the controllers' gains with this weight (:class:`~modnet.gps.GPSConfig`'s
            ``feedback_weight``, MDGPS only); None: ``gps.feedback_weight``. Not part of a
            checkpoint's identity.
        finetune_s_step_precision: how every fine-tuning start's S-step weighs each condition
            and step (:class:`~modnet.gps.GPSConfig`'s ``s_step_precision``: "controllers" or
            "normalized"); None: ``gps.s_step_precision``. Not part of a checkpoint's identity.
        finetune_seed: the seed of every fine-tuning start's noise, batches and dropout, and of
            the scratch starts' weights (:class:`~modnet.gps.GPSConfig`'s ``seed``); None:
            ``gps.seed``. The bank, the held-out world's scenes and the zero-shot table stay
            as they are, so several values on copies of one run (``resume=true``; not part of
            a checkpoint's identity) measure how far fine-tuning alone moves a result. A
            scratch start reads nothing of the bank, so with this set it is the same run at
            every ``seed``: one scratch run per value, not one per bank.
    """

    conditions: str = "test"
    num_conditions: int | None = None
    random_conditions: int = 0
    random_seed: int = 0
    baseline_seed: int = 12345
    frame_height: int = 256
    frame_width: int = 320
    gif_frames: int = 25
    finetune_iterations: int = 10
    finetune_starts: list[str] = field(default_factory=lambda: list(FINETUNE_STARTS))
    finetune_samples_per_condition: int | None = None
    finetune_sample_on_policy: bool = False
    finetune_kl_step: float | None = None
    finetune_sgd_steps: int | None = None
    finetune_dynamics_prior_per_condition: bool | None = None
    finetune_policy_linearization: str | None = None
    finetune_algo: str | None = None
    finetune_c_step: str | None = None
    finetune_num_conditions: int | None = None
    finetune_train_modules: str | None = None
    finetune_relabel_policy_states: str | None = None
    finetune_init_variance: float | None = None
    finetune_pi2_kl: float | None = None
    finetune_pi2_covariance_damping: float | None = None
    finetune_relabel_tracking_weight: float | None = None
    finetune_pi2_policy_weight: float | None = None
    finetune_pi2_step_smoothing: float | None = None
    finetune_pi2_policy_feedback: bool | None = None
    finetune_feedback_weight: float | None = None
    finetune_s_step_precision: str | None = None
    finetune_seed: int | None = None


#: the GPSConfig fields an ``eval.finetune_<field>`` sets for the fine-tuning starts alone
#: (``None``: training's value)
FINETUNE_GPS_OVERRIDES = (
    "samples_per_condition",
    "kl_step",
    "sgd_steps",
    "dynamics_prior_per_condition",
    "policy_linearization",
    "algo",
    "c_step",
    "num_conditions",
    "train_modules",
    "relabel_policy_states",
    "init_variance",
    "pi2_kl",
    "pi2_covariance_damping",
    "relabel_tracking_weight",
    "pi2_policy_weight",
    "pi2_step_smoothing",
    "pi2_policy_feedback",
    "feedback_weight",
    "s_step_precision",
    "seed",
)


@dataclass
class LoggerConfig:
    """Where metrics, the resolved config and figures go (``torchrl.record.loggers``).

    Args:
        backend: "wandb" (offline, inside the run directory), "csv", "tensorboard" or "none".
        project: the wandb project / the experiment's family name.
        mode: wandb's mode; "offline" keeps everything on this machine.
    """

    backend: str = "wandb"
    project: str = "modnet"
    mode: str = "offline"


@dataclass
class RunConfig:
    """One job of ``run.py``: hold out a world of a universe, train the rest, evaluate zero-shot.

    Args:
        universe: a name from :data:`modnet.universes.UNIVERSES` (the ``universe`` config group).
        holdout: ``ROBOT/TASK``; None holds out the universe's own; ``all`` (with ``-m``)
            sweeps every world.
        seed: initialisation seed of the bank (``gps.seed`` follows it in ``conf/config.yaml``).
        resume: continue from the run directory's checkpoint.
        finetune: after the zero-shot evaluation, compare GPS fine-tuning from four starts.
        threads: torch's threads for the networks (1: the small state networks gain nothing
            from more on 2 cores). From images 2 make an S-step 1.8 times as fast on 2 cores
            (``benchmarks/pixel_sgd.py``, ``one_vs_two_threads``), but sums then run in another
            order: a run's figures repeat to the digit only at the same count (``results.json``
            records it; a resumed run, its last part's).
        pretrain: pose-regression pretraining of the vision task modules before GPS
            (:class:`modnet.pretrain.PretrainConfig`; ``pretrain.images=0`` is off).
    """

    universe: str = dataclasses.MISSING  # type: ignore[assignment]
    holdout: str | None = None
    seed: int = 0
    resume: bool = False
    finetune: bool = False
    threads: int = 1
    gps: GPSSchema = field(default_factory=GPSSchema)  # type: ignore[valid-type]
    bank: BankSchema = field(default_factory=BankSchema)  # type: ignore[valid-type]
    pretrain: PretrainSchema = field(default_factory=PretrainSchema)  # type: ignore[valid-type]
    eval: EvalConfig = field(default_factory=EvalConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)

    def gps_config(self, **changes: Any) -> GPSConfig:
        """The library's :class:`GPSConfig` of this run (``changes`` override fields)."""
        return dataclasses.replace(build(GPSConfig, self.gps, "gps."), **changes)

    def finetune_gps_config(self) -> GPSConfig:
        """The :class:`GPSConfig` of the fine-tuning starts: the training's, with each field
        of :data:`FINETUNE_GPS_OVERRIDES` replaced by its ``eval.finetune_<field>`` when set
        (not None), and sampling the policy with ``eval.finetune_sample_on_policy``.

        Examples:
            >>> run = RunConfig(universe="tiny", eval=EvalConfig(finetune_samples_per_condition=20))
            >>> run.gps_config().samples_per_condition, run.finetune_gps_config().samples_per_condition
            (5, 20)
        """
        changes: dict[str, Any] = {
            name: value
            for name in FINETUNE_GPS_OVERRIDES
            if (value := getattr(self.eval, f"finetune_{name}")) is not None
        }
        if self.eval.finetune_sample_on_policy:
            changes["sample_on_policy"] = True
        config = self.gps_config()
        try:  # GPSConfig checks each value, and what it allows beside the training's options
            return dataclasses.replace(config, **changes)
        except ValueError as err:
            keys = ", ".join(f"eval.finetune_{name}={value}" for name, value in changes.items())
            raise ConfigError(f"{keys}: {err}") from err

    def bank_config(self) -> BankConfig:
        return build(BankConfig, self.bank, "bank.")

    def pretrain_config(self) -> PretrainConfig:
        return build(PretrainConfig, self.pretrain, "pretrain.")

    def new_bank(self, universe: Universe) -> ModuleBank:
        """The untrained bank this run starts from: every robot and task module of ``universe``
        (or one network per world with ``bank.policy=monolithic``), seeded by ``seed``."""
        return ModuleBank.build(
            universe.robots,
            universe.tasks,
            pixels=universe.pixels,
            policy=self.bank.policy,
            config=self.bank_config(),
            seed=self.seed,
        )

    def check(self) -> None:
        """Values no schema type can rule out; :class:`ConfigError` naming the key."""
        training = self.gps_config()
        finetune = self.finetune_gps_config()  # the training's GPS options, then fine-tuning's overrides
        lqr_steps = (  # (key, its GPS config, the value set, None where left alone, PI2's key)
            ("gps.kl_step", training, None if training.kl_step == GPSConfig.kl_step else training.kl_step,
             "gps.pi2_kl"),
            ("eval.finetune_kl_step", finetune, self.eval.finetune_kl_step, "eval.finetune_pi2_kl"),
        )
        for key, config, value, pi2_key in lqr_steps:
            if config.c_step == "pi2" and value is not None:
                # a warning: published PI2 commands carry it, and they must still run as they did
                log.warning(
                    f"{key}={value} is the LQR's step, and the C-step is pi2, which does not read it: "
                    f"its step is {pi2_key} (now {config.pi2_kl})"
                )
        self.bank_config()
        self.pretrain_config()
        if self.bank.policy not in ("modular", "monolithic"):
            raise ConfigError(f"bank.policy must be 'modular' or 'monolithic', got {self.bank.policy!r}")
        choices = (("gps.train_modules", self.gps_config()), ("eval.finetune_train_modules", finetune))
        for key, config in choices:  # the trainer refuses it too, but only after the training
            try:
                check_train_modules(config.train_modules, self.bank.policy, key)
            except ValueError as err:
                raise ConfigError(str(err)) from err
        if self.threads < 1:
            raise ConfigError(f"threads must be at least 1, got {self.threads}")
        if self.gps.iterations < 1:
            raise ConfigError(f"gps.iterations must be at least 1, got {self.gps.iterations}")
        if self.logger.backend not in LOGGERS:
            raise ConfigError(
                f"logger.backend must be one of {', '.join(LOGGERS)}, got {self.logger.backend!r}"
            )
        unknown = sorted(set(self.eval.finetune_starts) - set(FINETUNE_STARTS))
        if unknown:
            raise ConfigError(f"eval.finetune_starts: unknown {unknown}; valid: {', '.join(FINETUNE_STARTS)}")
        if self.eval.conditions not in CONDITION_SETS:
            raise ConfigError(
                f"eval.conditions must be one of {', '.join(CONDITION_SETS)}, got {self.eval.conditions!r}"
            )
        least = 1 if self.eval.conditions == "random" else NUM_FIXED_CONDITIONS
        if self.eval.num_conditions is not None and self.eval.num_conditions < least:
            raise ConfigError(f"eval.num_conditions must be at least {least}, got {self.eval.num_conditions}")
        if not (1 <= self.eval.frame_height <= 512 and 1 <= self.eval.frame_width <= 640):
            raise ConfigError("eval.frame_height/frame_width must be at most 512 x 640 (the scene's buffer)")


def validate(run: RunConfig) -> tuple[Universe, Split]:
    """Check everything that can be checked before any work; the universe and its train/held-out split.

    Raises :class:`ConfigError` or :class:`~modnet.universes.UniverseError` with one message
    naming what is wrong and the valid choices.
    """
    universe = get_universe(run.universe)
    if run.holdout == "all":
        raise ConfigError(
            "holdout=all is a leave-one-world-out sweep: run it as a multirun, `python run.py -m holdout=all`"
        )
    split = universe.split(run.holdout)
    run.check()
    if run.pretrain.images and not universe.pixels:
        raise ConfigError(
            f"pretrain.images={run.pretrain.images} pretrains vision task modules, and universe "
            f"{universe.name!r} has none: use an image universe or pretrain.images=0"
        )
    for name, config in (
        ("gps.policy_linearization", run.gps_config()),
        ("eval.finetune_policy_linearization", run.finetune_gps_config()),
    ):
        if universe.pixels and config.policy_linearization == "jacobian":
            raise ConfigError(
                f"{name}=jacobian differentiates a policy that reads the state, and universe "
                f"{universe.name!r} reads images: use regression"
            )
        for option in ("pi2_policy_feedback", "feedback_weight"):
            value = getattr(config, option)
            if universe.pixels and value:
                raise ConfigError(
                    f"{name.replace('policy_linearization', option)}={str(value).lower()} differentiates "
                    f"a policy that reads the state, and universe {universe.name!r} reads images: "
                    "leave it off"
                )
    return universe, split


def held_out_env(run: RunConfig, universe: Universe, split: Split, random: bool = False) -> WorldEnv:
    """The held-out world as ``run.py`` evaluates it, one env copy per test condition of ``run``
    (``random``: per extra random condition)."""
    ev = run.eval
    conditions, number, seed = (
        ("random", ev.random_conditions, ev.random_seed)
        if random
        else (ev.conditions, ev.num_conditions, run.gps.condition_seed)
    )
    return evaluation_env(
        *split.holdout,
        conditions=conditions,
        num_conditions=number,
        seed=seed,
        horizon=run.gps.horizon,
        pixels=universe.pixels,
    )


def saved_run(run_dir: str | Path) -> RunConfig:
    """The :class:`RunConfig` of the ``run.py`` job in ``run_dir``, from the config Hydra saved
    there (``.hydra/config.yaml``), to rebuild what that job built; pass it to :func:`validate`."""
    from omegaconf import OmegaConf

    values = OmegaConf.load(Path(run_dir) / ".hydra" / "config.yaml")
    return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(RunConfig), values))


def register_configs() -> None:
    """Register :class:`RunConfig` as the schema ``run_schema`` that ``conf/config.yaml`` extends."""
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(name="run_schema", node=RunConfig)


def flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"gps": {"lr": 1e-3}}`` -> ``{"gps.lr": 1e-3}`` (lists and None kept as they are)."""
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, Mapping):
            flat.update(flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat
