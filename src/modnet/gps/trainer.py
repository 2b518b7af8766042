"""Guided policy search over every training world of a universe, training one module bank.

One :meth:`GPSTrainer.step` is one GPS iteration:

1. **sample**: N rollouts per condition of every world from its linear-Gaussian controllers
   (:class:`~modnet.gps.sampling.WorldSampler`, TorchRL env + replay-buffer storage), or
   from the composed policy itself (``init_from_policy``, ``sample_on_policy``);
2. **cost**: quadratic expansion of each world's torch cost by autograd;
3. **dynamics**: per-step linear-Gaussian fits with a GMM prior;
4. **C-step**: KL-constrained LQR per world and condition, against the linearised policy
   (MDGPS) or the previous controller plus BADMM's dual terms; or, with ``c_step="pi2"``
   (MDGPS), PI2's model-free reweighting of the samples (:mod:`modnet.gps.pi2`); with
   ``c_step="pilqr"`` (MDGPS), the LQR's step then PI2 on the cost its model misses;
5. **S-step**: SGD on the sum over worlds of the precision-weighted regression of each
   world's composed policy onto its controllers (:class:`~modnet.gps.loss.PolicyRegressionLoss`),
   then the policy's diagonal covariance is fitted. With ``relabel_policy_states`` (MDGPS)
   the composed policy is also rolled out alone, and the states it visits, labelled with the
   controllers' actions, join the regression (DAgger).

Examples:
    >>> from modnet.bank import ModuleBank
    >>> from modnet.gps.trainer import GPSConfig, GPSTrainer
    >>> worlds = [("three_link", "reach_red"), ("four_link", "reach_black")]
    >>> bank = ModuleBank.build(["three_link", "four_link"], ["reach_red", "reach_black"])
    >>> trainer = GPSTrainer(bank, worlds, GPSConfig(samples_per_condition=2, horizon=10, sgd_steps=5))
    >>> diagnostics = trainer.step()
    >>> sorted(diagnostics["three_link/reach_red"])[:4]
    ['action_gap', 'action_gap_applied', 'conditions_within', 'distance']
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
import zlib
from collections import defaultdict
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, fields
from typing import Literal, get_args

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs.utils import ExplorationType, set_exploration_type

from modnet.bank import ModuleBank
from modnet.gps.badmm import BADMMConfig, Multipliers, badmm_cost, badmm_targets, dual_step
from modnet.gps.controller import LinearGaussianController, LinearGaussianGains
from modnet.gps.cost import QuadraticCost, Ramp, expand_cost, state_spread, time_weights
from modnet.gps.dynamics import (
    DynamicsPriorConfig,
    DynamicsPriorGMM,
    LinearGaussianDynamics,
    PolicyPriorGMM,
    fit_dynamics,
    fit_policy_linearization,
    policy_linearization_from_jacobian,
)
from modnet.gps.errors import NumericalError, check_finite, location_suffix
from modnet.gps.loss import PolicyRegressionLoss, state_jacobian
from modnet.gps.lqr import (
    LQRConfig,
    LQRResult,
    adapt_step_mult,
    held_at_centre,
    kl_divergence,
    laplace_cost,
    lqr_forward,
    tracking_feedback,
)
from modnet.gps.lqr import solve_kl_constrained_lqr as c_step
from modnet.gps.pi2 import PI2Result, pi2_update, pilqr_update, policy_log_ratio
from modnet.gps.sampling import POLICY_KEYS, STATE_KEYS, Samples, WorldSampler, state_of
from modnet.modules import PixelEncoder
from modnet.specs import TORQUE_LIMIT
from modnet.worlds import CONDITION_SETS, NUM_FIXED_CONDITIONS

log = logging.getLogger(__name__)

#: where an iteration's time goes (``GPSTrainer.timings``): sampling the worlds, expanding the
#: cost, fitting dynamics and policy linearisations, the C-step ("lqr", or PI2 with
#: ``c_step="pi2"``, or both with ``"pilqr"``), the policy's forward passes over the samples
#: and the S-step's SGD
PHASES = ("sampling", "cost", "dynamics", "lqr", "policy", "s_step")


#: images per world in one no-grad pass of a vision bank over an iteration's samples: few
#: enough for the convolutions' activations to stay in cache, which makes a pass 2 to 3 times
#: faster per image than at 512 rows, with the same outputs (``benchmarks/policy_passes.py``)
PIXEL_ROWS_PER_PASS = 32


POLICY_LINEARIZATIONS = ("regression", "jacobian")
C_STEPS = ("lqr", "pi2", "pilqr")
#: ``GPSConfig.relabel_policy_states``: none, the policy with its noise, or its mean actions
RELABELLINGS = ("off", "sampled", "mean")
#: what ``GPSConfig.train_modules`` may name: every module, or those of one factor of a modular bank
TRAIN_MODULES = ("all", "task", "robot")
#: ``GPSConfig.s_step_precision``: the controllers' precision as it is, or scaled to one per step
S_STEP_PRECISIONS = ("controllers", "normalized")


def check_train_modules(train_modules: str, policy: str, key: str = "gps.train_modules") -> None:
    """Refuse to train one factor's modules of a monolithic bank (``policy``), which has one
    network per world; ``key`` names the option in the message.

    Examples:
        >>> check_train_modules("robot", "modular")
        >>> check_train_modules("robot", "monolithic")
        Traceback (most recent call last):
        ...
        ValueError: gps.train_modules=robot trains one factor's modules, and bank.policy=monolithic ...
    """
    if policy == "monolithic" and train_modules != "all":
        raise ValueError(
            f"{key}={train_modules} trains one factor's modules, and bank.policy=monolithic has one "
            "network per world: use all, or bank.policy=modular"
        )


@dataclass
class GPSConfig:
    """Options of a GPS run (defaults: GPS code and the paper, sized for a 2-core laptop)."""

    algo: Literal["mdgps", "badmm"] = "badmm"
    samples_per_condition: int = 5
    horizon: int | None = None  # the task's horizon when None
    conditions: str = "train"
    num_conditions: int | None = 16  # training conditions per world (None: the task's 4)
    condition_seed: int = 0
    shaping: bool = True
    cost_ramp: Ramp = "constant"
    final_cost_multiplier: float = 5.0
    init_variance: float = 1.0  # of the first controllers: their spread also sets the first input scaling
    init_kp: float = 0.5
    init_kd: float = 0.3
    #: exploration noise of the controllers' samples: a Gaussian filter of this many steps (sigma)
    #: along each episode, renormalised to the controllers' covariance (the GPS code's
    #: ``smooth_noise``, whose default is 2.0); 0 draws white noise at every step
    noise_smoothing: float = 0.0
    #: the LQR's KL budget per time step (with PILQR, its LQR pass's); PI2 does not read it, its
    #: step is ``pi2_kl``
    kl_step: float = 1.0
    #: bounds of the C-step's step multiplier (the GPS code's are 0.01 and 10; RESULTS,
    #: "What did not match", measures its floor on three_link/reach)
    min_step_mult: float = 0.5
    max_step_mult: float = 3.0
    #: the C-step's cap on eta; a condition whose KL bound no eta below it meets keeps the
    #: controllers its KL is measured from for the iteration, with a warning that names it
    #: (``held_conditions`` in the diagnostics; :func:`~modnet.gps.lqr.held_at_centre`)
    max_eta: float = 1e16
    #: a condition held so for this many iterations in a row is not being repaired: the run
    #: stops with a ``NumericalError`` that names it
    max_held_iterations: int = 3
    sgd_steps: int = 1000
    initial_sgd_steps: int = 1000
    batch_per_world: int = 128
    lr: float = 1e-3
    weight_decay: float = 1e-5
    ent_reg: float = 0.0
    #: ridge on the input block of the dynamics fit's covariance (the GPS code's ``sig_reg``).
    #: The state holds collinear parts (joint and end-effector velocities) and parts the samples
    #: may not move (an untouched object); along such directions the fit is unconstrained, and
    #: a tiny ridge can invent unstable modes that make the C-step fail (RESULTS, section 2).
    dynamics_ridge: float = 1e-6
    dynamics_prior: DynamicsPriorConfig = field(
        default_factory=lambda: DynamicsPriorConfig(max_clusters=20, min_samples_per_cluster=40)
    )
    #: one dynamics prior per condition, each buffering that condition's latest trajectories
    #: (as the GPS code keeps them), instead of one per world over all its conditions
    dynamics_prior_per_condition: bool = False
    badmm: BADMMConfig = field(default_factory=BADMMConfig)
    #: fine-tuning: sample the first iteration from the bank's composed policies and start the
    #: controllers from their linearisation (instead of fitting the policy to hold-position ones),
    #: taken in that iteration on their actions as applied, clipped to the torque limits
    init_from_policy: bool = False
    #: from the second iteration on, sample the composed policy itself instead of the
    #: controllers, and centre the C-step's trust region on its linearisation as it acts (the
    #: GPS code's ``sample_on_policy``); the S-step still imitates the controllers
    sample_on_policy: bool = False
    #: False: the convolutions of a vision bank keep the weights they start with (what pose
    #: pretraining taught them), and the S-step trains the layers after the feature points only
    #: (the trainer sets ``requires_grad=False`` on the bank's encoders, which stays so after it).
    #: True (the paper's visuomotor training) trains them end to end, and on a few training
    #: scenes they can unlearn an object elsewhere (RESULTS, section 1; ``benchmarks/probe_vision.py``)
    train_convolutions: bool = True
    #: which of the bank's modules the S-step trains: "all", or the modules of one factor only
    #: ("task" or "robot"; the others keep their weights, and the trainer sets
    #: ``requires_grad=False`` on them, which stays so after it). Fine-tuning sets it with
    #: ``eval.finetune_train_modules``: does the held-out world's robot module, or its task
    #: module, carry what the composition lacks? (RESULTS, "fine-tuning one module")
    train_modules: str = "all"
    #: regress the network onto the controllers' actions clipped to the torque limits the arms
    #: apply, instead of onto their unclipped means (the GPS code's): about a quarter of the
    #: reaching controllers' mean torques ask for more than the limit, where any action beyond
    #: it acts alike. Off by default; on reaching it brings the networks closer to the blocks
    #: (RESULTS, "regressing onto the torques the arms apply")
    clip_targets: bool = False
    #: how the composed policy is linearised around the samples, for the C-step's trust region
    #: and (fine-tuning) the first controllers: "regression" fits ``u ~ K x + k`` to its mean
    #: actions at the N samples of each step under a GMM prior (the GPS code's); "jacobian"
    #: takes ``K`` from the network's own derivative there (autograd; policies that read the
    #: state only, not images). Off by default (RESULTS, "linearising the policy by its Jacobian")
    policy_linearization: Literal["regression", "jacobian"] = "regression"
    #: each training world draws its own scenes (seeded by ``condition_seed`` and the world's
    #: name) instead of every world of a task sharing the task's: at the same samples a task
    #: module then trains on one set of layouts per robot, and a robot module on one per task.
    #: Evaluation's test and random sets are unchanged. Off by default (RESULTS, "scenes per world")
    scenes_per_world: bool = False
    #: the C-step: "lqr", the KL-constrained LQR on the dynamics fitted to the samples (the
    #: paper's), or "pi2", which reweights each condition's samples by their cost to go within
    #: a KL bound of the distribution that drew them, and needs no model (the GPS code's
    #: PIGPS; :mod:`modnet.gps.pi2`), or "pilqr", the LQR's step followed by PI2 on the
    #: cost its model does not explain (the GPS code's MDGPS-PILQR). Both are MDGPS C-steps
    #: (``algo="mdgps"``); PI2 stays near the controllers that sampled, or, with
    #: ``sample_on_policy``, near the policy itself. Off by default (RESULTS, "a model-free
    #: C-step", "PILQR")
    c_step: Literal["lqr", "pi2", "pilqr"] = "lqr"
    #: MDGPS: after each C-step, also roll the composed policy out alone and add the states it
    #: visits, labelled with the new controllers' mean actions there, to the S-step's training
    #: set (DAgger's relabelling, Ross et al. 2011): "sampled" rolls it out N times per
    #: condition with its own Gaussian noise (twice the samples), "mean" once per condition
    #: with its mean actions, as it acts when evaluated. The controllers' samples alone show the
    #: network a narrow tube of states, and acting alone it leaves it (RESULTS, "the authors'
    #: fine-tuning protocol"). Off by default (RESULTS, "relabelling the network's own states")
    relabel_policy_states: Literal["off", "sampled", "mean"] = "off"
    #: With ``relabel_policy_states``: None labels the network's states with the controllers as
    #: they are; a weight labels them with the controllers' feedback gains fitted anew, an LQR
    #: tracking their noise-free path on this iteration's dynamics (:func:`tracking_feedback`:
    #: the states scaled by their spread over the iteration's samples, the torques weighted this
    #: much over the controllers' action variance; smaller: stiffer), the same mean actions on
    #: that path. PI2 keeps the feedback of the network's first linearisation,
    #: which does not bring the arm back from where the network leads it (RESULTS, "a better
    #: expert for DAgger?")
    relabel_tracking_weight: float | None = None
    #: PI2 and PILQR: the KL from uniform of each step's sample weights (the GPS code's ``kl_threshold``;
    #: at most log N, all weight on the best sample; a config asking for log N or more is refused)
    pi2_kl: float = 1.0
    #: PI2 and PILQR: the covariance is damped towards the old one by this power (the GPS code's
    #: ``covariance_damping``; larger keeps exploring longer)
    pi2_covariance_damping: float = 2.0
    #: PI2: add this times each sample's log-likelihood ratio of the controllers over the policy
    #: (:func:`~modnet.gps.pi2.policy_log_ratio`, unit variances, the torques clipped to the
    #: limit; its mean is about half their squared gap) to its cost: MDGPS's trust region around
    #: the policy, which PI2 alone lacks (it stays near the controllers that sampled). Only its
    #: size against the task cost's matters (the temperature meets the KL bound). 0 is off, the
    #: GPS code's PIGPS (RESULTS, "PI2 held near the network")
    pi2_policy_weight: float = 0.0
    #: PI2: filter each step of the feed-forward along time with a Gaussian of this many steps
    #: (standard deviation): what neighbouring steps agree on stays, the chance mean of a few
    #: samples' noise at one step goes (:func:`~modnet.gps.pi2.pi2_update`). 0 is off, the GPS
    #: code's (RESULTS, "PI2's step smoothed along time")
    pi2_step_smoothing: float = 0.0
    #: PI2: after each step, give the controllers the policy's own feedback, the network's
    #: Jacobian along their noise-free path (policies that read the state only), and move the
    #: feed-forward so that the path stays (:meth:`LinearGaussianGains.with_feedback`). The
    #: controllers then differ from the network on their path only, and off it respond as it
    #: does; PI2 alone keeps the feedback of the network's first linearisation, from which the
    #: network drifts. Off by default, the GPS code's (RESULTS, "the network's feedback")
    pi2_policy_feedback: bool = False
    #: MDGPS: the S-step also regresses the network's Jacobian in the state onto the
    #: controllers' feedback gains at each sample, each state entry scaled by its spread over
    #: the iteration's samples, with this weight against the actions' regression
    #: (:class:`~modnet.gps.loss.PolicyRegressionLoss`; policies that read the state only).
    #: The samples show the network a narrow tube of states, and how it responds off the tube
    #: is left to chance; the controllers' gains say how they do. 0 is off, the GPS code's
    #: (RESULTS, "the network's feedback")
    feedback_weight: float = 0.0
    #: how the S-step weighs each (condition, step)'s regression: "controllers" by the
    #: controllers' action precision there (the GPS code's, the MDGPS objective's); "normalized"
    #: by that precision divided by its mean diagonal, so that every condition and step weighs
    #: alike and only the precision's shape across the action's dimensions is kept. PI2 shrinks
    #: each step's covariance on its own, and late in fine-tuning the controllers' precision can
    #: span orders of magnitude across steps (``precision_top_share`` in the diagnostics). The
    #: policy's covariance is fitted to the controllers' precision either way (RESULTS, "the
    #: S-step's weights")
    s_step_precision: Literal["controllers", "normalized"] = "controllers"
    #: the torch stream of the controllers' noise, the S-step's batches and dropout, and a
    #: scratch fine-tuning start's weights; not the scenes (``condition_seed``)
    seed: int = 0

    def __post_init__(self) -> None:
        for name in (
            "samples_per_condition",
            "sgd_steps",
            "initial_sgd_steps",
            "batch_per_world",
            "max_held_iterations",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"gps.{name} must be at least 1, got {getattr(self, name)}")
        if not self.init_variance > 0:
            raise ValueError(f"gps.init_variance must be positive, got {self.init_variance}")
        if not self.kl_step > 0:
            raise ValueError(f"gps.kl_step must be positive, got {self.kl_step}")
        if self.cost_ramp not in get_args(Ramp):
            ramps = ", ".join(get_args(Ramp))
            raise ValueError(f"gps.cost_ramp must be one of {ramps}, got {self.cost_ramp!r}")
        if not self.final_cost_multiplier > 0:
            raise ValueError(f"gps.final_cost_multiplier must be positive, got {self.final_cost_multiplier}")
        if not 0 < self.min_step_mult <= self.max_step_mult:
            raise ValueError(
                "gps.min_step_mult must be positive and at most gps.max_step_mult, "
                f"got {self.min_step_mult} and {self.max_step_mult}"
            )
        if not self.dynamics_ridge > 0:
            raise ValueError(f"gps.dynamics_ridge must be positive, got {self.dynamics_ridge}")
        if self.noise_smoothing < 0:
            raise ValueError(
                f"gps.noise_smoothing must be non-negative (0: white noise), got {self.noise_smoothing}"
            )
        if self.horizon is not None and self.horizon < 1:
            raise ValueError(f"gps.horizon must be at least 1 (or null for the task's), got {self.horizon}")
        if self.policy_linearization not in POLICY_LINEARIZATIONS:
            raise ValueError(
                f"gps.policy_linearization must be one of {', '.join(POLICY_LINEARIZATIONS)}, "
                f"got {self.policy_linearization!r}"
            )
        if self.train_modules not in TRAIN_MODULES:
            raise ValueError(
                f"gps.train_modules must be one of {', '.join(TRAIN_MODULES)}, got {self.train_modules!r}"
            )
        if self.c_step not in C_STEPS:
            raise ValueError(f"gps.c_step must be one of {', '.join(C_STEPS)}, got {self.c_step!r}")
        if self.c_step != "lqr" and self.algo != "mdgps":
            raise ValueError(
                f"gps.c_step={self.c_step} is an MDGPS C-step (BADMM's adds dual terms PI2 cannot "
                "weigh): use algo=mdgps, or gps.c_step=lqr"
            )
        if self.relabel_policy_states not in RELABELLINGS:
            raise ValueError(
                f"gps.relabel_policy_states must be one of {', '.join(RELABELLINGS)}, "
                f"got {self.relabel_policy_states!r}"
            )
        if self.relabel_tracking_weight is not None and not (
            self.relabel_tracking_weight > 0 and self.relabel_policy_states != "off"
        ):
            raise ValueError(
                "gps.relabel_tracking_weight weighs the torques of the relabelling's tracking LQR: it "
                "must be positive, with gps.relabel_policy_states sampled or mean (got "
                f"{self.relabel_tracking_weight} with {self.relabel_policy_states!r}), or null"
            )
        if self.relabel_policy_states != "off" and self.algo != "mdgps":
            raise ValueError(
                "gps.relabel_policy_states labels the network's states with the controllers' actions, "
                "an MDGPS S-step (BADMM's targets carry dual terms fitted at the controllers' samples): "
                "use algo=mdgps"
            )
        if not (self.pi2_kl > 0 and self.pi2_covariance_damping > 0):
            raise ValueError(
                "gps.pi2_kl and gps.pi2_covariance_damping must be positive, "
                f"got {self.pi2_kl} and {self.pi2_covariance_damping}"
            )
        if self.c_step != "lqr" and not self.pi2_kl < math.log(self.samples_per_condition):
            # PI2 would put all the weight on one sample, and its covariance would collapse to 0
            enough = math.ceil(math.exp(self.pi2_kl))
            enough += math.log(enough) <= self.pi2_kl
            raise ValueError(
                f"gps.pi2_kl={self.pi2_kl} needs more than {self.samples_per_condition} samples per "
                f"condition: PI2's weights of N samples are at most log N from uniform (here "
                f"{math.log(self.samples_per_condition):.3g}); use gps.samples_per_condition of at "
                f"least {enough}, or a gps.pi2_kl below {math.log(self.samples_per_condition):.3g}"
            )
        if not self.pi2_policy_weight >= 0 or (
            self.pi2_policy_weight and (self.c_step != "pi2" or self.sample_on_policy)
        ):
            raise ValueError(
                "gps.pi2_policy_weight weighs the policy's term in PI2's cost: it must be non-negative, "
                "and positive only with gps.c_step=pi2 and the controllers sampling (not "
                "sample_on_policy, where PI2 already reweights around the policy) (got "
                f"{self.pi2_policy_weight} with c_step={self.c_step!r}, "
                f"sample_on_policy={self.sample_on_policy})"
            )
        smoothing = self.pi2_step_smoothing
        if not 0 <= smoothing < float("inf") or (smoothing and self.c_step != "pi2"):
            raise ValueError(
                "gps.pi2_step_smoothing filters PI2's step along time (in time steps): it must be "
                f"finite and non-negative, and positive only with gps.c_step=pi2 (got {smoothing} "
                f"with c_step={self.c_step!r})"
            )
        if self.pi2_policy_feedback and (self.c_step != "pi2" or self.sample_on_policy):
            raise ValueError(
                "gps.pi2_policy_feedback gives PI2's controllers the policy's feedback: it needs "
                f"gps.c_step=pi2 and the controllers sampling (got c_step={self.c_step!r}, "
                f"sample_on_policy={self.sample_on_policy})"
            )
        if not 0 <= self.feedback_weight < float("inf") or (
            self.feedback_weight and (self.algo != "mdgps" or self.relabel_policy_states != "off")
        ):
            raise ValueError(
                "gps.feedback_weight weighs the network's Jacobian against the controllers' gains in "
                "the S-step: it must be finite and non-negative, and positive only with algo=mdgps "
                f"and gps.relabel_policy_states=off (got {self.feedback_weight} with "
                f"algo={self.algo!r}, relabel_policy_states={self.relabel_policy_states!r})"
            )
        if self.s_step_precision not in S_STEP_PRECISIONS:
            raise ValueError(
                f"gps.s_step_precision must be one of {', '.join(S_STEP_PRECISIONS)}, "
                f"got {self.s_step_precision!r}"
            )
        if self.conditions not in CONDITION_SETS:
            raise ValueError(
                f"gps.conditions must be one of {', '.join(CONDITION_SETS)}, got {self.conditions!r}"
            )
        if self.num_conditions is not None and self.num_conditions < NUM_FIXED_CONDITIONS:
            raise ValueError(
                f"gps.num_conditions must be at least {NUM_FIXED_CONDITIONS} (or null), "
                f"got {self.num_conditions}"
            )

    def scene_seed(self, robot: str, task: str) -> int:
        """The seed of ``robot``/``task``'s training scenes: ``condition_seed``, or with
        ``scenes_per_world`` one that also depends on the world's name.

        Examples:
            >>> GPSConfig().scene_seed("three_link", "push") == GPSConfig().scene_seed("four_link", "push")
            True
            >>> config = GPSConfig(scenes_per_world=True)
            >>> config.scene_seed("three_link", "push") == config.scene_seed("four_link", "push")
            False
        """
        if not self.scenes_per_world:
            return self.condition_seed
        return self.condition_seed << 32 | zlib.crc32(f"{robot}/{task}".encode())

    @property
    def fits_model(self) -> bool:
        """Whether the C-step plans on fitted dynamics and a quadratic cost (all but PI2)."""
        return self.c_step != "pi2"

    def lqr(self) -> LQRConfig:
        return LQRConfig(
            kl_step=self.kl_step,
            min_mult=self.min_step_mult,
            max_mult=self.max_step_mult,
            max_eta=self.max_eta,
        )


@dataclass
class Linearised:
    """What a C-step needs of one iteration: its controller, fitted dynamics and cost (the
    last two None under PI2, which needs no model)."""

    gains: LinearGaussianGains
    dynamics: LinearGaussianDynamics | None
    cost: QuadraticCost | None


@dataclass
class WorldState:
    """Everything GPS keeps about one world between iterations."""

    name: str
    sampler: WorldSampler
    controller: LinearGaussianController
    dynamics_prior: DynamicsPriorGMM | list[DynamicsPriorGMM]  # per world, or per condition
    policy_prior: PolicyPriorGMM
    eta: torch.Tensor  # [M]
    step_mult: torch.Tensor  # [M]
    held_streak: torch.Tensor  # [M] iterations in a row each condition was held at its centre
    held: torch.Tensor  # [M] held at any of this iteration's C-steps
    duals: Multipliers | None = None
    samples: Samples | None = None
    current: Linearised | None = None  # this iteration's sampling controller, dynamics, cost
    previous: Linearised | None = None
    policy: LinearGaussianGains | None = None  # the policy linearised around the samples
    policy_mean: torch.Tensor | None = None  # [M, N, T, dU]
    sampled_costs: torch.Tensor | None = None  # [M, N, T] the samples' time-weighted costs
    regression_data: ReplayBuffer | None = None  # the S-step's (observation, target) pairs
    mean_sampler: WorldSampler | None = None  # one mean rollout per condition (relabelling)
    diagnostics: dict[str, float] = field(default_factory=dict)


class GPSTrainer:
    """Trains ``bank`` on ``worlds`` (``(robot, task)`` pairs) by guided policy search.

    Args:
        bank: the module bank; every world's modules must be in it.
        worlds: the training worlds.
        config: the run's options.
        pixels: whether the policy reads ``("task", "pixels")`` (then the samples render).
    """

    def __init__(
        self,
        bank: ModuleBank,
        worlds: Sequence[tuple[str, str]],
        config: GPSConfig | None = None,
        *,
        pixels: bool = False,
    ) -> None:
        self.config = config = config or GPSConfig()
        if config.algo not in ("mdgps", "badmm"):
            raise ValueError(f"unknown GPS algorithm {config.algo!r}; valid: mdgps, badmm")
        if not worlds:
            raise ValueError("GPS needs at least one training world")
        if pixels and config.policy_linearization == "jacobian":
            raise ValueError(
                "gps.policy_linearization=jacobian needs a policy that reads the state; this one "
                "reads images: use regression"
            )
        for name in ("pi2_policy_feedback", "feedback_weight"):
            if pixels and getattr(config, name):
                raise ValueError(
                    f"gps.{name} differentiates a policy that reads the state; this one "
                    "reads images: leave it off"
                )
        check_train_modules(config.train_modules, bank.policy)
        if config.train_modules not in ("all", *bank.world_factors):  # before any world is built
            valid = ", ".join(("all", *bank.world_factors))
            raise ValueError(f"gps.train_modules={config.train_modules!r}: valid for this bank: {valid}")
        for world in worlds:
            bank.parts(bank.world(*world))  # fails early, naming what is missing
        torch.manual_seed(config.seed)
        self.bank = bank
        self.pixels = pixels
        self.iteration = 0
        self.seconds = 0.0  # wall time of every iteration so far, across resumes
        #: environment samples drawn so far (saved in checkpoints), including those of an iteration
        #: that stopped on a numerical error; a killed iteration's are drawn again after a resume
        self.drawn = {"trajectories": 0, "env_steps": 0}
        self.timings: dict[str, float] = defaultdict(float)
        self.states = {state.name: state for state in map(lambda w: self._init_world(*w), worlds)}
        self.loss = PolicyRegressionLoss(bank, config.feedback_weight)
        if not config.train_convolutions:
            for encoder in (m for m in bank.modules() if isinstance(m, PixelEncoder)):
                encoder.requires_grad_(False)
        if config.train_modules != "all":
            for factor in bank.world_factors:
                if factor != config.train_modules:
                    for name in bank.names(factor):
                        bank.get(factor, name).requires_grad_(False)
        trained = [p for p in bank.parameters() if p.requires_grad]
        self.optimizer = torch.optim.Adam(trained, lr=config.lr, weight_decay=config.weight_decay)
        self.history: list[dict[str, dict[str, float]]] = []

    # --- set-up -------------------------------------------------------------------------
    def _new_sampler(self, robot: str, task: str, samples_per_condition: int) -> WorldSampler:
        c = self.config
        return WorldSampler(
            robot,
            task,
            conditions=c.conditions,
            samples_per_condition=samples_per_condition,
            horizon=c.horizon,
            pixels=self.pixels,
            shaping=c.shaping,
            seed=c.scene_seed(robot, task),
            num_conditions=c.num_conditions,
        )

    def _init_world(self, robot: str, task: str) -> WorldState:
        c = self.config
        sampler = self._new_sampler(robot, task, c.samples_per_condition)
        M, T = sampler.num_conditions, sampler.horizon
        initial = sampler.env.reset()[:M]  # copies 0..M-1 start from conditions 0..M-1
        n = sampler.world.robot.n_joints
        controller = LinearGaussianController.initial(
            list(STATE_KEYS),
            num_conditions=M,
            horizon=T,
            state_dim=sampler.world.state_dim,
            joint_position_idx=range(n),
            joint_velocity_idx=range(n, 2 * n),
            hold_state=state_of(initial),
            kp=c.init_kp,
            kd=c.init_kd,
            variance=c.init_variance,
            action_dtype=torch.float32,
            noise_smoothing=c.noise_smoothing,
        )
        duals = None
        if c.algo == "badmm":
            duals = Multipliers.zeros(M, T, sampler.world.state_dim, n, c.badmm.initial_policy_weight)
        generator = torch.Generator().manual_seed(c.seed)
        prior = c.dynamics_prior
        return WorldState(
            name=sampler.name,
            sampler=sampler,
            controller=controller,
            dynamics_prior=(
                [DynamicsPriorGMM(prior, generator) for _ in range(M)]
                if c.dynamics_prior_per_condition
                else DynamicsPriorGMM(prior, generator)
            ),
            policy_prior=PolicyPriorGMM(prior, generator),
            eta=torch.ones(M, dtype=torch.float64),
            step_mult=torch.ones(M, dtype=torch.float64),
            held_streak=torch.zeros(M, dtype=torch.long),
            held=torch.zeros(M, dtype=torch.bool),
            duals=duals,
        )

    @contextlib.contextmanager
    def _timed(self, phase: str) -> Iterator[None]:
        start = time.perf_counter()
        yield
        self.timings[phase] += time.perf_counter() - start

    @contextlib.contextmanager
    def _acting(self) -> Iterator[None]:
        """The bank without dropout, as the composed policy acts (sampling, linearising,
        relabelling); back in training mode afterwards, also when that raises."""
        self.bank.eval()
        try:
            yield
        finally:
            self.bank.train()

    # --- one iteration ------------------------------------------------------------------------
    def step(self) -> dict[str, dict[str, float]]:
        """One GPS iteration over all worlds; returns per-world diagnostics (means over conditions).

        - ``distance``, ``sampled_cost``: the task's distance and the (time-weighted) cost of
          this iteration's samples;
        - ``predicted_cost``: the new controllers' task cost predicted under this iteration's
          fitted dynamics; compare it with the next iteration's ``sampled_cost`` to see how
          far the fitted dynamics can be trusted (not under PI2, which fits none);
        - ``expected_cost``: the C-step's own objective at its solution (under BADMM it adds
          the dual and policy terms, so it is not comparable with ``sampled_cost``);
        - ``kl``, ``eta``, ``step_mult``: the C-step's KL to its reference, its Lagrange
          multiplier and the step-size multiplier (PI2: the sample weights' KL from uniform and
          their temperature, means over steps; the step size stays 1); ``action_gap``:
          controller vs policy mean action at the samples, ``action_gap_applied`` the same
          clipped to the torque limits; ``nu`` (BADMM): the policy-KL weight;
          ``regression_loss``; ``precision_top_share``: the share of the S-step's weight (the
          controllers' precision) on the tenth of its samples that carry most, 0.1 when
          even; ``exploration``: the new controllers' spread, the root
          of their mean action variance (PI2 shrinks it by ``pi2_covariance_damping``);
          ``policy_kl`` (PI2): the mean of the term ``pi2_policy_weight`` adds to PI2's cost,
          in expectation half the squared gap of the sampling controllers' actions from the
          policy's (clipped to the torque limit), summed over steps.
        """
        start = time.perf_counter()
        states = list(self.states.values())
        from_policy = self._samples_policy()
        for state in states:
            self._sample_and_fit(state, self._composed(state) if from_policy else None)
        # Inputs z-scored over this iteration's states; after the first fit the networks'
        # first layers absorb the change, so no training is undone.
        fresh = self.iteration == 0 and not from_policy
        self.bank.fit_normalization({s.name: s.samples.obs for s in states}, keep_function=not fresh)
        if from_policy:  # the C-step is centred where the composed policy is, as it acts
            self._policy_outputs(states)
            for state in states:
                if self.iteration == 0:  # and the controllers start there
                    state.controller.set_gains(state.policy)
                state.current.gains = state.policy
                self._record_action_gap(state)  # against the linearisation it sampled with
        elif fresh:
            self._s_step(self.config.initial_sgd_steps, {s.name: self._controller_targets(s) for s in states})
        if self.config.algo == "mdgps":
            self._mdgps_update(states, outputs_ready=from_policy)
        else:
            self._badmm_update(states, outputs_ready=from_policy)
        for state in states:
            self._count_holds(state)
        diagnostics = {s.name: self._diagnose(s) for s in states}
        self.history.append(diagnostics)
        self.iteration += 1
        self.seconds += time.perf_counter() - start
        return diagnostics

    def _samples_policy(self) -> bool:
        """Whether this iteration samples the composed policy instead of the controllers: the
        first one with ``init_from_policy`` (fine-tuning), every later one with ``sample_on_policy``."""
        return self.config.init_from_policy if self.iteration == 0 else self.config.sample_on_policy

    def _composed(self, state: WorldState):
        return self.bank.compose(*self.bank.world(state.name))

    def _sample_and_fit(self, state: WorldState, policy=None) -> None:
        """Sample the world (with its controllers unless ``policy`` is given), and for the LQR and
        PILQR expand the cost and fit the dynamics (PI2 needs neither: a fifth of its iteration)."""
        c, world = self.config, state.sampler.world
        with self._timed("sampling"):
            samples = self._draw(state, policy or state.controller)
        with self._timed("cost"):
            weights = time_weights(state.sampler.horizon, c.cost_ramp, c.final_cost_multiplier)
            with torch.no_grad():
                state.sampled_costs = world.state_cost(samples.X, samples.U, c.shaping) * weights
                sampled = state.sampled_costs.sum(-1)
        cost = dynamics = None
        if c.fits_model:
            cost, dynamics = self._expanded(state, samples), self._fitted(state, samples)
        state.previous = state.current
        state.current = Linearised(state.controller.gains, dynamics, cost)  # a snapshot
        state.samples = samples
        state.held.fill_(False)
        per_condition = samples.distance.mean(-1)  # [M]: each condition's mean over its samples
        state.diagnostics = {
            "sampled_cost": float(sampled.mean()),
            "distance": float(samples.distance.mean()),
            # a mean can fall while some conditions never move: these tell the two apart
            "distance_worst_condition": float(per_condition.max()),
            "conditions_within": int((per_condition < world.task.success_distance).sum()),
        }

    def iteration_cost(self, state: WorldState) -> QuadraticCost:
        """The quadratic cost this iteration's C-step plans on; under PI2, which plans on none,
        the task's cost expanded around the iteration's samples now."""
        if state.current.cost is not None:
            return state.current.cost
        return self._expanded(state, state.samples)

    def iteration_dynamics(self, state: WorldState) -> LinearGaussianDynamics:
        """The dynamics this iteration's C-step plans on; under PI2, which plans on none,
        dynamics fitted to the iteration's samples now, as the LQR's C-step fits them (the
        samples join the dynamics prior: once an iteration)."""
        if state.current.dynamics is not None:
            return state.current.dynamics
        return self._fitted(state, state.samples)

    def _expanded(self, state: WorldState, samples: Samples) -> QuadraticCost:
        """The task's cost (shaped as configured, weighted along time) expanded around ``samples``."""
        c, world = self.config, state.sampler.world
        with self._timed("cost"):
            weights = time_weights(state.sampler.horizon, c.cost_ramp, c.final_cost_multiplier)
            task_cost = lambda x, u: world.state_cost(x, u, c.shaping)  # noqa: E731
            cost = expand_cost(task_cost, samples.X, samples.U, weights)
            check_finite("cost expansion", cost.C, world=state.name, iteration=self.iteration)
        return cost

    def _fitted(self, state: WorldState, samples: Samples) -> LinearGaussianDynamics:
        """Dynamics fitted to ``samples``, after they join the dynamics prior."""
        with self._timed("dynamics"):
            self._update_dynamics_prior(state, samples)
            return fit_dynamics(
                samples.X,
                samples.U,
                state.dynamics_prior,
                ridge=self.config.dynamics_ridge,
                world=state.name,
                iteration=self.iteration,
            )

    def _draw(self, state: WorldState, actor, sampler: WorldSampler | None = None) -> Samples:
        """One batch of trajectories from ``actor`` (N per condition, by the world's sampler
        unless ``sampler`` is given), counted in :attr:`samples`."""
        sampler = sampler or state.sampler
        with self._acting():
            samples = sampler.sample(actor)
        trajectories = sampler.env.batch_size[0]
        self.drawn["trajectories"] += trajectories
        self.drawn["env_steps"] += trajectories * sampler.horizon
        for name, value in (("sampled states", samples.X), ("sampled actions", samples.U)):
            # condition-major [M, ...], so the error names the condition
            check_finite(name, value, world=state.name, iteration=self.iteration)
        return samples

    def _update_dynamics_prior(self, state: WorldState, samples: Samples) -> None:
        where = dict(world=state.name, iteration=self.iteration)
        if isinstance(state.dynamics_prior, list):  # condition m's prior buffers condition m's samples
            for prior, X, U in zip(state.dynamics_prior, samples.X, samples.U, strict=True):
                prior.update(X, U, **where)
        else:  # sample-major order: the buffer of the latest trajectories spans every condition
            state.dynamics_prior.update(samples.X.transpose(0, 1), samples.U.transpose(0, 1), **where)

    # --- the policy around the samples ----------------------------------------------------------
    @torch.no_grad()
    def _policy_outputs(self, states: Sequence[WorldState]) -> None:
        """The composed policies' mean actions at every world's samples, and their linearisation
        (``gps.policy_linearization``; by regression the samples also feed the policy prior,
        which the Jacobian does not need).

        In an iteration that samples the policy (the first of fine-tuning, ``init_from_policy``;
        every later one with ``sample_on_policy``) the means are clipped to the torque limits
        first: a network untrained on its world can ask for far more torque than the arm has,
        and the controllers must start from, and the C-step stay near, what it does in the
        world.  Otherwise the network imitates the controllers, as in training.

        The LQR, alone or in PILQR, plans within a trust region around the linearisation, so it is
        fitted wherever a model is (``GPSConfig.fits_model``). PI2 (``c_step="pi2"``) needs it
        only where the policy sampled: it reweights around what drew the samples. Elsewhere
        only the means are computed, and ``state.policy`` is None.
        """
        as_applied = self._samples_policy()
        linearise = as_applied or self.config.fits_model
        with self._timed("policy"), self._acting():
            if self.config.policy_linearization == "jacobian" and linearise:
                out, jacobians = self._outputs_and_jacobians(states)
            else:
                out, jacobians = self._forward_samples(states), [None] * len(states)
        for state, result, jacobian in zip(states, out, jacobians, strict=True):
            mean = result["loc"].to(torch.float64)
            check_finite("policy action", mean, world=state.name, iteration=self.iteration)
            if as_applied:
                if jacobian is not None:
                    jacobian = _as_applied(jacobian, mean)
                mean = mean.clamp(-TORQUE_LIMIT, TORQUE_LIMIT)
            state.policy_mean = mean
            self._record_action_gap(state)
            if not linearise:
                state.policy = None
                continue
            covariance = torch.diag_embed(result["scale"].to(torch.float64).pow(2))
            where = dict(world=state.name, iteration=self.iteration)
            with self._timed("dynamics"):
                if jacobian is None:  # the regression's prior: refitted on the latest samples
                    state.policy_prior.update(state.samples.X.transpose(0, 1), mean.transpose(0, 1), **where)
                    state.policy = fit_policy_linearization(
                        state.samples.X, mean, covariance, state.policy_prior, **where
                    )
                else:
                    state.policy = policy_linearization_from_jacobian(
                        state.samples.X, mean, jacobian, covariance, **where
                    )

    def _outputs_and_jacobians(
        self, states: Sequence[WorldState], obs: Sequence[TensorDictBase] | None = None
    ) -> tuple[list[TensorDictBase], list[torch.Tensor]]:
        """The bank's outputs at every world's samples (or at ``obs``, one per world; as
        :meth:`_forward_samples`) and ``d loc / d x [M, N, T, dU, dX]``, by autograd through the
        same pass (a state policy reads ``x = [robot_state, task_state]`` itself), one backward
        pass per action dimension."""
        inputs = {}
        obs = [s.samples.obs for s in states] if obs is None else obs
        for state, world_obs in zip(states, obs, strict=True):
            leaves = world_obs.select(*STATE_KEYS).clone()
            for key in STATE_KEYS:
                leaves.set(key, leaves.get(key).detach().requires_grad_(True))
            inputs[state.name] = leaves
        outputs, jacobians = [], []
        with torch.enable_grad():
            out = self.bank.forward_worlds(inputs)
            for state in states:
                result = out[self.bank.world(state.name)]
                loc = result["loc"]
                x = [inputs[state.name].get(key) for key in STATE_KEYS]
                outputs.append(result.detach())
                jacobians.append(state_jacobian(loc, x).to(torch.float64))
        return outputs, jacobians

    @staticmethod
    def _record_action_gap(state: WorldState) -> None:
        """Diagnostic: the sampling controllers' mean action vs the policy's, at the samples, as
        they ask (``action_gap``) and as the arm applies them, both clipped to the torque limits
        (``action_gap_applied``: where the controllers ask for more than the limit, what the
        network can match)."""
        controllers = state.current.gains.mean_actions(state.samples.X)
        gap = controllers - state.policy_mean
        limit = TORQUE_LIMIT
        applied = controllers.clamp(-limit, limit) - state.policy_mean.clamp(-limit, limit)
        state.diagnostics["action_gap"] = float(gap.norm(dim=-1).mean())
        state.diagnostics["action_gap_applied"] = float(applied.norm(dim=-1).mean())

    def _forward_samples(
        self, states: Sequence[WorldState], obs: Sequence[TensorDictBase] | None = None
    ) -> list[TensorDictBase]:
        """The bank's outputs at every world's samples ``[M, N, T]`` (or at ``obs``, one per
        world): one pass from states; from images ``PIXEL_ROWS_PER_PASS`` rows per world at a
        time (a whole iteration's activations would take gigabytes, and large passes are
        slower per image)."""
        obs = [s.samples.obs for s in states] if obs is None else obs
        rows = PIXEL_ROWS_PER_PASS if self.pixels else None
        batches = {s.name: o for s, o in zip(states, obs, strict=True)}
        out = self.bank.forward_worlds(batches, rows_per_pass=rows)
        return [out[self.bank.world(s.name)] for s in states]

    def _adapt_step(self, state: WorldState) -> None:
        """Step-size rule from the improvement predicted by the last C-step vs the one sampled."""
        prev, cur = state.previous, state.current
        if prev is None:
            return
        before = laplace_cost(prev.gains, prev.dynamics, prev.cost)
        predicted = before - laplace_cost(cur.gains, prev.dynamics, prev.cost)
        actual = before - laplace_cost(cur.gains, cur.dynamics, cur.cost)
        state.step_mult = adapt_step_mult(state.step_mult, predicted, actual, self.config.lqr())

    @staticmethod
    def _dynamics_note(
        state: WorldState, m: int | None, dynamics: LinearGaussianDynamics | None = None
    ) -> str:
        """Condition ``m``'s fitted dynamics (``dynamics``, by default the iteration's) described,
        as a clause to append to a message: how fast they let a deviation grow and in which state
        entry; empty where there is nothing to describe. An LQR that cannot meet its KL bound or
        keep ``Q_uu`` PD at any eta usually has dynamics that blow up (radius well above 1)."""
        if dynamics is None and state.current is not None:
            dynamics = state.current.dynamics
        if m is None or dynamics is None or not bool(dynamics.F[m].isfinite().all()):
            return ""  # a NaN in the fit is its own message
        radius = dynamics.spectral_radius()[m, :-1]  # the last step has no successor
        t = int(radius.argmax())
        label = state.sampler.world.state_labels[dynamics.dominant_mode(m, t)]
        return (
            f"; the fitted dynamics of this condition let a deviation grow by up to "
            f"{float(radius[t]):.3g}x a step (step {t}, fed mostly by {label}; above 1.05 at "
            f"{int((radius > 1.05).sum())} of {radius.numel()} steps)"
        )

    @classmethod
    def _with_dynamics_note(
        cls, error: NumericalError, state: WorldState, dynamics: LinearGaussianDynamics | None = None
    ) -> NumericalError:
        """``error`` with its condition's fitted dynamics described (``_dynamics_note``)."""
        note = cls._dynamics_note(state, error.condition, dynamics)
        if not note:
            return error
        return NumericalError(
            error.reason + note, world=error.world, condition=error.condition, iteration=error.iteration
        )

    def _c_step(self, state: WorldState, cost: QuadraticCost, prev: LinearGaussianGains, omega=0.0) -> None:
        config = self.config.lqr()
        config.omega = omega
        with self._timed("lqr"):
            try:
                result = c_step(
                    cost,
                    state.current.dynamics,
                    prev,
                    step_mult=state.step_mult,
                    eta=state.eta,
                    config=config,
                    world=state.name,
                    iteration=self.iteration,
                )
            except NumericalError as err:
                raise self._with_dynamics_note(err, state) from err
        held = result.at_cap
        if bool(held.any()):
            for m in held.nonzero().flatten().tolist():
                log.warning(
                    "eta reached its cap %g without meeting the KL target (last KL %.4g, target %.4g)%s%s; "
                    "the condition keeps the controllers its KL is measured from",
                    config.max_eta, float(result.kl[m]), float(result.kl_target[m]),
                    self._dynamics_note(state, m),
                    location_suffix(world=state.name, condition=m, iteration=self.iteration),
                )
            result = held_at_centre(result, prev, state.current.dynamics, cost, eta=state.eta)
        state.held |= held  # BADMM runs several C-steps an iteration
        state.diagnostics["held_conditions"] = int(state.held.sum())
        state.eta = result.eta
        self._adopt(state, result)

    def _count_holds(self, state: WorldState) -> None:
        """Count the iterations in a row each condition was held at its centre; one held
        ``max_held_iterations`` times is not being repaired, and the run stops on it."""
        state.held_streak = torch.where(state.held, state.held_streak + 1, 0)
        m = int(state.held_streak.argmax())
        streak = int(state.held_streak[m])
        if streak >= self.config.max_held_iterations:
            error = NumericalError(
                f"held at its centre {streak} iterations in a row (gps.max_held_iterations="
                f"{self.config.max_held_iterations}): no eta up to the cap {self.config.max_eta:g} "
                "meets its KL bound",
                world=state.name,
                condition=m,
                iteration=self.iteration,
            )
            raise self._with_dynamics_note(error, state)

    @staticmethod
    def _adopt(state: WorldState, result: LQRResult | PI2Result) -> None:
        """Take a C-step's controllers and record its figures (means over conditions and steps)."""
        state.controller.set_gains(result.gains)
        state.diagnostics.update(
            expected_cost=float(result.expected_cost.mean()),
            kl=float(result.kl.mean()),
            eta=float(result.eta.mean()),
            step_mult=float(state.step_mult.mean()),
        )

    def _pi2_step(self, state: WorldState) -> None:
        """PI2 on this iteration's samples: around the distribution that drew them (the
        controllers, or the policy's linearisation when it sampled), on their cost (plus the
        policy's term, :meth:`_pi2_costs`); or, with PILQR, around the LQR's new controllers, on
        the samples' cost less what the fitted model predicts for their noise (the LQR's
        figures stay, the share of the cost the model misses is added)."""
        c = self.config
        X, U = state.samples.X, state.samples.U
        options = dict(kl=c.pi2_kl, covariance_damping=c.pi2_covariance_damping)
        with self._timed("lqr"):
            try:
                if c.c_step == "pilqr":
                    model = (state.current.gains, state.current.dynamics, state.current.cost)
                    samples = (X, U, state.sampled_costs)
                    result = pilqr_update(state.controller.gains, *model, *samples, **options)
                else:
                    costs = self._pi2_costs(state)
                    smoothing = c.pi2_step_smoothing
                    result = pi2_update(state.current.gains, X, U, costs, step_smoothing=smoothing, **options)
            except NumericalError as err:  # a covariance that is not positive definite
                raise err.with_context(world=state.name, iteration=self.iteration) from err
        check_finite(f"{c.c_step} feed-forward", result.gains.k, world=state.name, iteration=self.iteration)
        if c.c_step == "pilqr":
            state.controller.set_gains(result.gains)
            state.diagnostics["residual_share"] = float(result.residual_share.mean())
        else:
            self._adopt(state, result)
            if c.pi2_policy_feedback:
                state.controller.set_gains(self._with_policy_feedback(state))

    def _with_policy_feedback(self, state: WorldState) -> LinearGaussianGains:
        """The controllers with the policy's feedback (``pi2_policy_feedback``): ``K_t`` the
        network's Jacobian at their noise-free path (zero where its torque is beyond the limit,
        which the arm clips), the feed-forward moved so that the path stays. Records how far
        the controllers' feedback had come from the network's (``feedback_gap``: the mean
        Frobenius norm of the difference over conditions and steps)."""
        gains = state.controller.gains
        with self._timed("sampling"):
            path = self._draw_mean(state, state.controller)
        with self._timed("policy"), self._acting():
            (out,), (jacobian,) = self._outputs_and_jacobians([state], [path.obs])
        mean = out["loc"].to(torch.float64)
        K = _as_applied(jacobian, mean)[:, 0]  # [M, T, dU, dX]
        check_finite("policy feedback", K, world=state.name, iteration=self.iteration)
        state.diagnostics["feedback_gap"] = float((gains.K - K).norm(dim=(-2, -1)).mean())
        return gains.with_feedback(K, path.X[:, 0])

    def _pi2_costs(self, state: WorldState) -> torch.Tensor:
        """The samples' costs for PI2; with ``pi2_policy_weight``, plus that times each sample's
        log-likelihood ratio of the controllers that drew it over the policy, in the torques the
        arm applies. Its mean, ``policy_kl`` (a sum over steps, a mean over conditions), is
        recorded under every PI2 step, with the weight or without."""
        X, U = state.samples.X, state.samples.U
        ratio = policy_log_ratio(state.current.gains, X, U, state.policy_mean, limit=TORQUE_LIMIT)
        state.diagnostics["policy_kl"] = float(ratio.sum(-1).mean())
        weight = self.config.pi2_policy_weight
        return state.sampled_costs + weight * ratio if weight else state.sampled_costs

    def _mdgps_update(self, states: Sequence[WorldState], outputs_ready: bool = False) -> None:
        """Mirror-descent GPS: C-step in a KL trust region around the linearised policy
        (computed here unless ``outputs_ready``: the policy is unchanged since it was)."""
        if not outputs_ready:
            self._policy_outputs(states)
        for state in states:
            if self.config.c_step == "pi2":
                self._pi2_step(state)
                continue
            self._adapt_step(state)
            self._c_step(state, state.current.cost, state.policy)
            if self.config.c_step == "pilqr":
                self._pi2_step(state)
        targets = {s.name: self._controller_targets(s) for s in states}
        if self.config.relabel_policy_states != "off":
            for state in states:
                targets[state.name] = torch.cat([targets[state.name], self._relabelled_targets(state)])
        self._s_step(self.config.sgd_steps, targets)

    def _badmm_update(self, states: Sequence[WorldState], outputs_ready: bool = False) -> None:
        """BADMM: alternate S-step, dual step and C-step ``inner_iterations`` times (a round
        that starts without an S-step, the first of the first iteration, reuses the policy's
        outputs when ``outputs_ready``)."""
        cfg = self.config.badmm
        for state in states:
            self._adapt_step(state)
        sampling_gains = {s.name: s.current.gains for s in states}
        for inner in range(cfg.inner_iterations):
            trains_first = self.iteration > 0 or inner > 0
            if trains_first:
                targets = {s.name: self._badmm_targets(s) for s in states}
                self._s_step(max(1, self.config.sgd_steps // cfg.inner_iterations), targets)
            if trains_first or not outputs_ready:  # the S-step has changed the outputs
                self._policy_outputs(states)
            for state in states:
                gains = state.controller.gains
                if trains_first:
                    kl = kl_divergence(gains, state.policy, lqr_forward(gains, state.current.dynamics), True)
                    state.duals = dual_step(
                        state.duals,
                        gains,
                        state.policy,
                        state.samples.X,
                        state.policy_mean,
                        kl,
                        cfg,
                        update_weights=inner == cfg.inner_iterations - 1,
                    )
                cost = badmm_cost(state.current.cost, state.policy, state.duals)
                self._c_step(state, cost, sampling_gains[state.name], omega=state.duals.nu)
                state.diagnostics["nu"] = float(state.duals.nu.mean())

    # --- the S-step ---------------------------------------------------------------------------
    def _controller_targets(self, state: WorldState) -> TensorDictBase:
        gains = state.controller.gains
        weights = torch.ones(state.samples.X.shape[:-1], dtype=torch.float64)
        feedback = gains.K if self.config.feedback_weight else None
        return self._targets(state, gains.mean_actions(state.samples.X), weights, feedback=feedback)

    def _relabelled_targets(self, state: WorldState) -> TensorDictBase:
        """The composed policy rolled out alone, its states labelled with the controllers' mean
        actions (``relabel_policy_states``; with ``relabel_tracking_weight``, the controllers'
        with their feedback fitted anew); records where it ended (``policy_distance``) and
        how far its actions were from those labels (``relabel_gap``, against ``action_gap`` at
        the controllers' samples)."""
        with self._timed("sampling"):
            if self.config.relabel_policy_states == "mean":
                visited = self._draw_mean(state, self._composed(state))
            else:
                visited = self._draw(state, self._composed(state))
        tracks = self.config.relabel_tracking_weight is not None
        expert = self._tracking(state) if tracks else state.controller.gains
        target = expert.mean_actions(visited.X)
        with self._timed("policy"), self._acting(), torch.no_grad():
            (out,) = self._forward_samples([state], [visited.obs])
        mean = out["loc"].to(torch.float64)
        state.diagnostics["policy_distance"] = float(visited.distance.mean())
        state.diagnostics["relabel_gap"] = float((target - mean).norm(dim=-1).mean())
        weights = torch.ones(visited.X.shape[:-1], dtype=torch.float64)
        return self._targets(state, target, weights, obs=visited.obs)

    def _draw_mean(self, state: WorldState, actor) -> Samples:
        """One trajectory per condition of ``actor``'s mean actions, in an env of its own (so
        the samples' random stream is left as it was)."""
        if state.mean_sampler is None:
            world = state.sampler.world
            state.mean_sampler = self._new_sampler(world.robot.name, world.task.name, 1)
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            return self._draw(state, actor, state.mean_sampler)

    def _tracking(self, state: WorldState) -> LinearGaussianGains:
        """The controllers with feedback gains fitted anew (``relabel_tracking_weight``): an LQR
        tracking their noise-free path on :meth:`iteration_dynamics`, the states scaled by their
        spread over the iteration's samples."""
        gains = state.controller.gains
        with self._timed("sampling"):
            path = self._draw_mean(state, state.controller).X[:, 0]
        dynamics = self.iteration_dynamics(state)
        with self._timed("lqr"):
            try:
                K = tracking_feedback(
                    dynamics,
                    state.samples.X,
                    gains,
                    self.config.relabel_tracking_weight,
                    world=state.name,
                    iteration=self.iteration,
                )
            except NumericalError as err:
                raise self._with_dynamics_note(err, state, dynamics) from err
        return gains.with_feedback(K, path)

    def _badmm_targets(self, state: WorldState) -> TensorDictBase:
        target, weights = badmm_targets(state.controller.gains, state.duals, state.samples.X)
        return self._targets(state, target, weights)

    def _targets(
        self,
        state: WorldState,
        target: torch.Tensor,
        weights: torch.Tensor,
        obs: TensorDictBase | None = None,
        feedback: torch.Tensor | None = None,
    ) -> TensorDictBase:
        """The S-step's training set of one world, flattened ``[M * N * T]``: ``target`` at the
        observations ``obs`` (this iteration's samples' when None), weighed by ``precision``
        (the controllers', divided by ``precision_scale``: 1, or its mean diagonal with
        ``s_step_precision="normalized"``); with ``feedback [M, T, dU, dX]``, the controllers'
        gains at each sample in units of the state's spread over the samples (``feedback_weight``)."""
        precision = state.controller.gains.precision  # [M, T, dU, dU]
        precision_scale = torch.ones(precision.shape[:2], dtype=precision.dtype)
        if self.config.s_step_precision == "normalized":
            precision_scale = precision.diagonal(dim1=-2, dim2=-1).mean(-1)
        precision = precision / precision_scale[..., None, None]
        precision = precision[:, None].expand(*target.shape[:-1], -1, -1)
        weights = weights * weights.numel() / weights.sum()  # mean 1 ...
        median = weights[weights > 1e-2].median()
        weights = weights.clamp_max(2 * median) / median  # ... at most twice the robust median
        obs = state.samples.obs if obs is None else obs
        data = obs.select(*POLICY_KEYS, strict=False)  # a new TD, shared leaves
        if self.config.clip_targets:
            target = target.clamp(-TORQUE_LIMIT, TORQUE_LIMIT)
        data["target_action"] = target.to(torch.float32)
        data["precision"] = precision.to(torch.float32)
        data["precision_scale"] = precision_scale[:, None].expand(target.shape[:-1]).to(torch.float32)
        data["weight"] = weights.to(torch.float32)
        if feedback is not None:
            scale = state_spread(state.samples.X)  # [dX]
            scaled = feedback[:, None] * scale  # [M, 1, T, dU, dX]
            data["feedback_target"] = scaled.expand(*target.shape, -1).to(torch.float32)
            data["state_scale"] = scale.expand(*target.shape[:-1], -1).to(torch.float32)
        return data.reshape(-1)

    def _s_step(self, steps: int, targets: dict[str, TensorDictBase]) -> None:
        c = self.config
        with self._timed("s_step"):
            buffers = {}
            for name, data in targets.items():
                state = self.states[name]
                if state.regression_data is None or state.regression_data.storage.max_size != data.shape[0]:
                    state.regression_data = ReplayBuffer(
                        storage=LazyTensorStorage(data.shape[0]), batch_size=c.batch_per_world
                    )
                buffers[name] = state.regression_data
                buffers[name].empty()
                buffers[name].extend(data)
            self.bank.train()
            for _ in range(steps):
                batch = TensorDict({name: buf.sample() for name, buf in buffers.items()}, batch_size=[])
                losses = self.loss(batch)
                loss = losses["loss_regression"]
                if not torch.isfinite(loss):
                    bad = [w for w, v in losses["world_loss"].items() if not torch.isfinite(v)]
                    raise NumericalError(
                        "policy regression loss is not finite", world=", ".join(bad), iteration=self.iteration
                    )
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                self.optimizer.step()
            self._fit_policy_covariance(targets)
        for name, data in targets.items():
            self.states[name].diagnostics["precision_top_share"] = _top_share(_controllers_weight(data))
            self.states[name].diagnostics["regression_loss"] = float(losses["world_loss"][name])
            if name in losses["feedback_loss"].keys():
                self.states[name].diagnostics["feedback_loss"] = float(losses["feedback_loss"][name])

    @torch.no_grad()
    def _fit_policy_covariance(self, targets: dict[str, TensorDictBase]) -> None:
        """``var_j = sum w / (sum_i w_i P_i,jj + 2 N T ent_reg)``, pooled over the worlds that
        share the module owning the action distribution."""
        pooled: dict[int, list] = {}
        for name, data in targets.items():
            module = list(self.bank.parts(self.bank.world(name)).values())[-1]
            entry = pooled.setdefault(id(module), [module, 0.0, 0.0])
            w = data["weight"].to(torch.float64)
            precision = _controllers_precision_diagonal(data)
            entry[1] = entry[1] + (w[:, None] * precision).sum(0) + 2 * w.numel() * self.config.ent_reg
            entry[2] = entry[2] + w.sum()
        for module, precision_sum, weight_sum in pooled.values():
            module.set_std((weight_sum / precision_sum).sqrt().to(torch.float32))

    # --- reporting ----------------------------------------------------------------------------------
    @property
    def samples(self) -> dict[str, int]:
        """Environment samples drawn so far over every world: trajectories and control steps,
        counting those of an iteration that stopped on a numerical error."""
        return dict(self.drawn)

    def _diagnose(self, state: WorldState) -> dict[str, float]:
        """The iteration's figures; the prediction once, for the controllers the last C-step left
        (with fitted dynamics: not under PI2)."""
        if state.current.dynamics is not None:
            predicted = laplace_cost(state.controller.gains, state.current.dynamics, state.current.cost)
            state.diagnostics["predicted_cost"] = float(predicted.mean())
        variance = state.controller.gains.cov.diagonal(dim1=-2, dim2=-1).mean()
        state.diagnostics["exploration"] = float(variance.sqrt())
        return dict(sorted(state.diagnostics.items()))

    # --- checkpoints --------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """Everything needed to continue training: bank, optimizer, controllers, priors, RNGs,
        iteration and history.  Plain tensors, lists, dicts and numbers only, so it loads with
        ``torch.load(..., weights_only=True)``."""
        return {
            "iteration": self.iteration,
            "seconds": self.seconds,
            "drawn": dict(self.drawn),
            "bank": self.bank.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "torch_rng": torch.get_rng_state(),
            "history": self.history,
            "worlds": {name: _world_state_dict(state) for name, state in self.states.items()},
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`; the trainer must have been built with the same worlds."""
        if set(state["worlds"]) != set(self.states):
            raise ValueError(
                f"checkpoint trains worlds {sorted(state['worlds'])}, this trainer {sorted(self.states)}"
            )
        for name, world_state in state["worlds"].items():  # before anything is loaded
            saved = tuple(world_state["controller"]["K"].shape[:2])
            here = tuple(self.states[name].controller.gains.K.shape[:2])
            if saved != here:
                raise ValueError(
                    f"checkpoint's {name} has {saved[0]} conditions x {saved[1]} steps, this trainer "
                    f"{here[0]} x {here[1]}: gps.num_conditions and gps.horizon must match"
                )
        self.bank.load_state_dict(state["bank"])
        self.optimizer.load_state_dict(state["optimizer"])
        torch.set_rng_state(state["torch_rng"])
        self.iteration = int(state["iteration"])
        self.seconds = float(state.get("seconds", 0.0))  # checkpoints before it was kept: unknown
        samplers = [s.sampler for s in self.states.values()]
        finished = {  # checkpoints before the count was kept: every finished iteration's samples
            "trajectories": self.iteration * sum(s.env.batch_size[0] for s in samplers),
            "env_steps": self.iteration * sum(s.env.batch_size[0] * s.horizon for s in samplers),
        }
        self.drawn = {key: int(value) for key, value in state.get("drawn", finished).items()}
        self.history = list(state["history"])
        for name, world_state in state["worlds"].items():
            _load_world_state(self.states[name], world_state)


def _controllers_precision_diagonal(data: TensorDictBase) -> torch.Tensor:
    """The diagonal ``[rows, dU]`` of each row's controllers' precision in an S-step training set
    (:meth:`GPSTrainer._targets`), whatever ``precision_scale`` the regression divided it by."""
    diagonal = data["precision"].to(torch.float64).diagonal(dim1=-2, dim2=-1)
    return diagonal * data["precision_scale"].to(torch.float64)[:, None]


def _controllers_weight(data: TensorDictBase) -> torch.Tensor:
    """Each row of an S-step training set's weight times the trace of its controllers' precision."""
    return data["weight"].to(torch.float64) * _controllers_precision_diagonal(data).sum(-1)


def _top_share(weight: torch.Tensor, fraction: float = 0.1) -> float:
    """The share of ``weight``'s sum held by its largest ``fraction`` of entries: ``fraction``
    when they are equal, near 1 when a few hold it all.

    Examples:
        >>> _top_share(torch.ones(20)), round(_top_share(torch.tensor([1.0] * 18 + [1e6, 1e6])), 5)
        (0.1, 0.99999)
    """
    weight = weight.flatten().to(torch.float64)
    top = weight.topk(max(1, round(fraction * weight.numel()))).values
    return float(top.sum() / weight.sum())


def _as_applied(jacobian: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
    """The Jacobian ``[..., dU, dX]`` of the torques the arm applies: zero in the rows whose mean
    action ``[..., dU]`` is beyond the torque limit, where a clipped torque does not move with
    the state."""
    return jacobian * (mean.abs() <= TORQUE_LIMIT).unsqueeze(-1)


def _fields_dict(obj) -> dict | None:
    return None if obj is None else {f.name: getattr(obj, f.name) for f in fields(obj)}


_gains_dict = _fields_dict  # every factor exactly: a recomputed Cholesky factor would drift


def _gains_from(d: dict) -> LinearGaussianGains:
    return LinearGaussianGains(**d)


def _linearised_dict(lin: Linearised | None) -> dict | None:
    if lin is None:
        return None
    return {
        "gains": _gains_dict(lin.gains),
        "dynamics": _fields_dict(lin.dynamics),
        "cost": _fields_dict(lin.cost),
    }


def _linearised_from(d: dict | None) -> Linearised | None:
    if d is None:
        return None
    dynamics, cost = d["dynamics"], d["cost"]  # None under PI2
    return Linearised(
        _gains_from(d["gains"]),
        None if dynamics is None else LinearGaussianDynamics(**dynamics),
        None if cost is None else QuadraticCost(**cost),
    )


def _prior_dict(prior) -> dict | list[dict]:
    if isinstance(prior, list):
        return [_prior_dict(p) for p in prior]
    gmm = prior.gmm
    return {
        "X": prior.X,
        "U": prior.U,
        "mu": gmm.mu,
        "sigma": gmm.sigma,
        "log_weights": gmm.log_weights,
        "num_points": gmm.num_points,
    }


def _load_prior(prior, d: dict | list[dict]) -> None:
    if isinstance(prior, list) != isinstance(d, list):
        raise ValueError(
            "checkpoint and trainer differ in gps.dynamics_prior_per_condition "
            f"(checkpoint: {isinstance(d, list)}, trainer: {isinstance(prior, list)})"
        )
    if isinstance(prior, list):
        for p, one in zip(prior, d, strict=True):
            _load_prior(p, one)
        return
    prior.X, prior.U = d["X"], d["U"]
    gmm = prior.gmm
    gmm.mu, gmm.log_weights, gmm.num_points = d["mu"], d["log_weights"], d["num_points"]
    if d["sigma"] is not None:
        gmm._set_covariances(d["sigma"])


def _world_state_dict(state: WorldState) -> dict:
    return {
        "controller": _gains_dict(state.controller.gains),
        "eta": state.eta,
        "step_mult": state.step_mult,
        "held_streak": state.held_streak,
        "duals": _fields_dict(state.duals),
        "current": _linearised_dict(state.current),
        "dynamics_prior": _prior_dict(state.dynamics_prior),
        "policy_prior": _prior_dict(state.policy_prior),
        "prior_rng": state.policy_prior.gmm.generator.get_state(),  # one generator for all priors
    }


def _load_world_state(state: WorldState, d: dict) -> None:
    state.controller.set_gains(_gains_from(d["controller"]))
    state.eta, state.step_mult = d["eta"], d["step_mult"]
    state.held_streak = d.get("held_streak", torch.zeros_like(state.held_streak))  # older checkpoints lack it
    state.duals = None if d["duals"] is None else Multipliers(**d["duals"])
    state.current, state.previous = _linearised_from(d["current"]), None
    _load_prior(state.dynamics_prior, d["dynamics_prior"])
    _load_prior(state.policy_prior, d["policy_prior"])
    state.policy_prior.gmm.generator.set_state(d["prior_rng"])
