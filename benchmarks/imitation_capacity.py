"""Whether a policy that sees only the state can do what fine-tuning's controllers do.

GPS's S-step regresses the network onto its controllers' mean actions ``K_t x + k_t`` at
their samples. The controllers are time-varying and one per training condition; the network
sees the state alone. Where the network stays far from controllers that succeed, either the
S-step falls short (too few steps, dropout, the modular bottleneck) or no function of the
state can do what the controllers do: their feed-forward ``k_t`` may depend on the time step
and the scene in a way the state does not tell apart.

This reruns ``--iterations`` fine-tuning iterations of a start (as ``run.py finetune=true``
does, with the run's options unless ``--algo`` or ``--c-step`` is given; MDGPS only, whose
S-step regresses onto the controllers' mean actions) on a finished run's bank, then
takes the last iteration's samples, the S-step's own training set, and fits to the same
targets (clipped to the torque limits where the run's ``gps.clip_targets`` clips them), from
scratch and without dropout (on their squared error, where the S-step weights it by the
controllers' precision), one plain network per set of inputs:

- ``state``: the state ``x`` (what the composed modules read, together);
- ``state_time``: ``x`` and the time step ``t / T``;
- ``state_scene_time``: ``x``, ``t / T`` and the condition (one-hot), which can hold each
  scene's feed-forward step by step.

Each has ``--hidden`` ReLU layers (default five of 80 units: the composed pair's depth and
width) and is fitted by Adam for ``--sgd-steps`` steps. Beside them ``network`` is the bank's
network after the run's S-steps, and ``network_refit`` a copy of it trained on the same way
(dropout off, the same targets, steps and schedule). For each:

- ``gap_fit``: the mean norm of its mean action less the target, both clipped to the torque
  limits, on the training set;
- ``gap_fresh``: the same on a fresh draw of the controllers' samples (``fit_drawn_by`` says
  which policy drew the training set: the network, when the last iteration sampled it, as
  the first of a transferred start does);
- ``gap_own``: the same at the states it visits itself, acting alone (what DAgger would label);
- ``distance``: where it ends when it acts (mean actions) on the held-out world's training
  conditions; beside ``controllers`` (the controllers the iteration ends with, mean actions)
  and ``untouched``;
- ``distance_test``: where it ends at the test positions (not for ``state_scene_time``, which
  knows only the training conditions); ``distance_random``, where it ends on the run's
  ``eval.random_conditions`` further random positions (when the run drew any), a steadier
  figure than four positions give.

``takeover`` asks whether the controllers are an expert at the network's states, as DAgger's
relabelling (``gps.relabel_policy_states``) assumes: the bank's network acts (mean actions) for
the first quarter, half or three quarters of the horizon on the training conditions, then the
controllers' mean actions take over; where they end, by the step at which they take over.
Under PI2 the controllers keep the feedback gains ``K_t`` of the distribution that first drew
samples (the network's linearisation) and learn only their feed-forward, so ``takeover`` may
fail for want of feedback. ``takeover_refitted`` tries others: the gains of an LQR on dynamics
fitted to the last iteration's samples (the C-step's own, where it fits a model), with the
feed-forward moved so that the controllers' noise-free path stays the same (``with_feedback``;
its ``controllers`` figure repeats theirs). ``track_<w>`` tracks that path
(:func:`~modnet.gps.lqr.tracking_feedback`: states scaled by their spread over the fresh draw
of the controllers' samples, torques weighted ``w``); ``task`` is the KL-constrained LQR on
the task's cost around the controllers, at the C-step's KL budget. ``feedback_norm`` is each
one's mean ``|K_t|`` (Frobenius). Its ``departure`` says how far from that path the network
has led the arm when they take over, beside the width of the controllers' own tube of samples,
the fresh draw (:func:`departure`).

``saturated`` is the share of the controllers' mean torques at the samples beyond the limits;
``within_cell_share`` is the share of the targets' variance that lies within (condition, time
step) cells, between one cell's samples: what the controllers' feedback ``K_t`` adds to
their feed-forward at the samples' spread of states. ``jitter_share`` is the share in the
cells' means less those means filtered along time (a Gaussian of 2 steps): what changes from
one step to the next (the cell means also carry a 1/N share of the spread between samples,
so this overstates it by at most ``within_cell_share / N``).

``rerun_curve`` is the bank's network at the test positions after each iteration, beside the
run's own fine-tuning curve ``run_curve``: the two are equal when this reran the run.

Prints a line per network, then ONE JSON object on its last line.

    python benchmarks/imitation_capacity.py outputs/manipulation --iterations 10 --algo mdgps --c-step pi2
    python benchmarks/imitation_capacity.py outputs/manipulation --iterations 30 --c-step pi2 \
        --pi2-covariance-damping 2 --refit-weights 0.01 0.1 1
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from pathlib import Path

import torch
from _run_dir import FINISHED, finished_run
from action_gap import clipped_gaps, network_mean_actions
from first_finetune_iteration import TRANSFERRED, controller_distance, controller_rollout, start_trainer
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn

from modnet.bank import ModuleBank
from modnet.config import held_out_env, saved_run, validate
from modnet.envs import WorldEnv
from modnet.evaluate import evaluating, rollout, score, training_env
from modnet.gps.controller import LinearGaussianGains, time_filtered
from modnet.gps.cost import state_spread
from modnet.gps.lqr import solve_kl_constrained_lqr, tracking_feedback
from modnet.gps.sampling import STATE_KEYS, state_of
from modnet.gps.trainer import C_STEPS, GPSTrainer
from modnet.specs import TORQUE_LIMIT

#: the Gaussian (steps) that :func:`variance_shares` filters the targets along time with
JITTER_SIGMA = 2.0

#: the regressors' inputs beside the state: (time step, condition)
INPUTS = {"state": (False, False), "state_time": (True, False), "state_scene_time": (True, True)}


class Regressor(nn.Module):
    """A ReLU network from the state (and, by ``inputs``, the time step and the condition) to
    the action, its inputs z-scored by :meth:`fit_normalization`. Reads what the controllers
    read, so it acts in a :class:`~modnet.envs.WorldEnv` as they do.

    Examples:
        >>> net = Regressor("state_time", state_dim=3, action_dim=2, conditions=4, horizon=10, hidden=(8,))
        >>> net(torch.zeros(5, 1), torch.zeros(5, 2), torch.zeros(5, dtype=torch.long),
        ...     torch.zeros(5, 1, dtype=torch.long)).shape
        torch.Size([5, 2])
    """

    def __init__(
        self, inputs: str, *, state_dim: int, action_dim: int, conditions: int, horizon: int, hidden: tuple
    ) -> None:
        super().__init__()
        if inputs not in INPUTS:
            raise ValueError(f"unknown inputs {inputs!r}; valid: {', '.join(INPUTS)}")
        self.time, self.scene = INPUTS[inputs]
        self.conditions, self.horizon = conditions, horizon
        width = state_dim + self.time + conditions * self.scene
        self.register_buffer("mean", torch.zeros(width))
        self.register_buffer("std", torch.ones(width))
        layers: list[nn.Module] = []
        for units in hidden:
            layers += [nn.Linear(width, units), nn.ReLU()]
            width = units
        self.net = nn.Sequential(*layers, nn.Linear(width, action_dim))

    def features(self, *inputs: torch.Tensor) -> torch.Tensor:
        """``(*state parts, condition, step_count)`` -> the network's unnormalised inputs."""
        *state_parts, condition, step_count = inputs
        parts = [torch.cat(state_parts, -1).float()]
        if self.time:
            parts.append(step_count.float() / self.horizon)
        if self.scene:
            parts.append(nn.functional.one_hot(condition.long(), self.conditions).float())
        return torch.cat(parts, -1)

    def fit_normalization(self, features: torch.Tensor) -> None:
        self.mean.copy_(features.mean(0))
        self.std.copy_(features.std(0).clamp_min(1e-6))

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return self.net((self.features(*inputs) - self.mean) / self.std)


def inputs_of(obs: TensorDictBase) -> tuple[torch.Tensor, ...]:
    """What a :class:`Regressor` reads, from samples' ``obs``, flattened."""
    flat = obs.reshape(-1)
    return (*(flat.get(key) for key in STATE_KEYS), flat.get("condition"), flat.get("step_count"))


def fit(net: Regressor, inputs: tuple, target: torch.Tensor, *, steps: int, seed: int) -> None:
    """``net``'s normalisation from ``inputs``, then :func:`minimise` its squared error."""
    net.fit_normalization(net.features(*inputs))
    minimise(net.parameters(), lambda rows: net(*(x[rows] for x in inputs)), target, steps=steps, seed=seed)


def minimise(parameters, predict, target: torch.Tensor, *, steps: int, seed: int) -> None:
    """Adam on the mean squared error of ``predict(rows)`` against ``target[rows]``, minibatches
    of 1,024 rows, the learning rate 1e-3 annealed to zero (cosine) over ``steps``."""
    generator = torch.Generator().manual_seed(seed)
    optimizer = torch.optim.Adam(parameters, lr=1e-3)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, max(steps, 1))
    for _ in range(steps):
        rows = torch.randint(target.shape[0], (min(1024, target.shape[0]),), generator=generator)
        loss = (predict(rows) - target[rows]).square().sum(-1).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        schedule.step()


def refitted(bank: ModuleBank, world, obs: TensorDictBase, target: torch.Tensor, **schedule) -> ModuleBank:
    """A copy of ``bank`` whose ``world`` network :func:`minimise` trains on, dropout off."""
    bank = copy.deepcopy(bank).eval()
    flat = obs.reshape(-1)

    def predict(rows: torch.Tensor) -> torch.Tensor:
        return bank.forward_worlds({world: flat[rows]})[world]["loc"]

    minimise(bank.parameters(), predict, target, **schedule)
    return bank


def clipped_gap(actions: torch.Tensor, target: torch.Tensor) -> float:
    """Mean norm of ``actions - target``, both clipped to the torque limits the arms apply."""
    return round(float(clipped_gaps(actions, target).mean()), 4)


def acting(scenes: WorldEnv, policy, gains: LinearGaussianGains) -> dict[str, float]:
    """``policy`` acting on ``scenes`` (one copy per condition, in order), mean actions: its
    mean final ``distance``, and ``gap_own``, the gap to the controllers ``gains`` at the
    states it visits itself."""
    with torch.no_grad():
        td = scenes.rollout(scenes.horizon, policy, break_when_any_done=False)
    return {"gap_own": own_gap(td, gains), "distance": round(float(scenes.final_distance(td).mean()), 4)}


class Takeover(TensorDictModuleBase):
    """``first`` acts at the steps before ``step``, ``then`` from it on (each writes ``"action"``).

    Examples:
        >>> from tensordict import TensorDict
        >>> zero = TensorDictModule(lambda s: s * 0, in_keys=["s"], out_keys=["action"])
        >>> one = TensorDictModule(lambda s: s * 0 + 1, in_keys=["s"], out_keys=["action"])
        >>> td = TensorDict({"s": torch.ones(3, 1), "step_count": torch.tensor([[0], [1], [2]])}, [3])
        >>> Takeover(zero, one, step=2)(td)["action"].flatten().tolist()
        [0.0, 0.0, 1.0]
    """

    def __init__(self, first, then, step: int) -> None:
        super().__init__()
        self.first, self.then, self.step = first, then, step
        self.in_keys = list(dict.fromkeys([*first.in_keys, *then.in_keys, "step_count"]))
        self.out_keys = ["action"]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        early = td["step_count"] < self.step  # [B, 1]
        first, then = self.first(td.clone())["action"], self.then(td.clone())["action"]
        td["action"] = torch.where(early, first.to(then.dtype), then)
        return td


def takeover_steps(horizon: int) -> tuple[int, int, int]:
    """The steps at which the controllers take over: a quarter, half and three quarters in.

    Examples:
        >>> takeover_steps(100)
        (25, 50, 75)
    """
    return horizon // 4, horizon // 2, 3 * horizon // 4


def takeover_distances(bank: ModuleBank, robot: str, task: str, scenes: WorldEnv, controller) -> dict:
    """:class:`Takeover` of the bank's network by ``controller`` (both mean actions: the
    controller's too, under :func:`~modnet.evaluate.evaluating`) on ``scenes`` at a quarter,
    half and three quarters of the horizon: where each ends."""
    out = {}
    with evaluating(bank):
        for step in takeover_steps(scenes.horizon):
            actor = Takeover(bank.compose(robot, task), controller, step)
            td = scenes.rollout(scenes.horizon, actor, break_when_any_done=False)
            out[str(step)] = round(float(scenes.final_distance(td).mean()), 4)
    return out


def departure(visited: torch.Tensor, path: torch.Tensor, X: torch.Tensor, steps, labels) -> dict:
    """How far states ``visited [M, T, dX]`` are from the controllers' noise-free ``path [M, T, dX]``
    at each of ``steps``, in units of the samples' spread of each entry (:func:`state_spread` of
    ``X [M, N, T, dX]``, the entries' range of motion): the root mean square over entries, mean
    over conditions (``network``); the same for the samples themselves (``samples``, the width
    of their tube); and the entry (``labels``) farthest away on average (``farthest``).

    Examples:
        >>> path = torch.zeros(1, 3, 2)
        >>> X = torch.tensor([-1.0, 1.0]).reshape(1, 2, 1, 1).expand(1, 2, 3, 2)  # spread 1.095
        >>> visited = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [0.0, 3.0]]])
        >>> out = departure(visited, path, X, [1, 2], ["a", "b"])
        >>> out["network"], out["samples"], out["farthest"]
        ({'1': 0.6455, '2': 1.9365}, {'1': 0.9129, '2': 0.9129}, {'1': 'a', '2': 'b'})
    """
    spread = state_spread(X)  # float64, so the ratios are too
    away = (visited - path) / spread  # [M, T, dX]
    tube = (X - path.unsqueeze(1)) / spread  # [M, N, T, dX]
    rms = lambda d: d.square().mean(-1).sqrt()  # noqa: E731
    return {
        "network": {str(t): round(float(rms(away[:, t]).mean()), 4) for t in steps},
        "samples": {str(t): round(float(rms(tube[:, :, t]).mean()), 4) for t in steps},
        "farthest": {str(t): labels[int(away[:, t].abs().mean(0).argmax())] for t in steps},
    }


def refitted_feedback(trainer: GPSTrainer, X: torch.Tensor, weights: list[float]) -> dict[str, torch.Tensor]:
    """Feedback gains for the held-out world's controllers from an LQR on the last iteration's
    model (:meth:`~modnet.gps.trainer.GPSTrainer.iteration_dynamics` and ``iteration_cost``):
    ``track_<w>``, :func:`~modnet.gps.lqr.tracking_feedback` of torque weight ``w``, the states
    scaled by their spread over the controllers' samples ``X [M, N, T, dX]``; ``task`` the
    KL-constrained LQR on the task's cost around the controllers, at the C-step's KL budget
    (``kl_step`` times its step multiplier)."""
    (state,) = trainer.states.values()
    gains, dynamics = state.controller.gains, trainer.iteration_dynamics(state)
    feedback = {f"track_{w:g}": tracking_feedback(dynamics, X, gains, w) for w in weights}
    budget = dict(step_mult=state.step_mult, config=trainer.config.lqr())
    task = solve_kl_constrained_lqr(trainer.iteration_cost(state), dynamics, gains, **budget)
    feedback["task"] = task.gains.K
    return feedback


def takeover_refitted(
    trainer: GPSTrainer, robot: str, task: str, scenes: WorldEnv, X: torch.Tensor, alone: TensorDictBase,
    weights: list[float],
) -> dict:
    """:func:`takeover_distances` by the held-out world's controllers ``with_feedback`` on their
    mean path with each of :func:`refitted_feedback`'s gains (``kept``: their own), with where
    those controllers end alone and their mean ``|K_t|``; and under ``departure``, how far the
    network is from that path at the steps they take over (:func:`departure` of its rollout
    ``alone`` on ``scenes``, mean actions, against the controllers' samples ``X``)."""
    (state,) = trainer.states.values()
    controller, gains = state.controller, state.controller.gains
    path = state_of(controller_rollout(scenes, trainer, gains))
    visited = state_of(alone)
    steps = takeover_steps(scenes.horizon)
    labels = state.sampler.world.state_labels
    out = {"departure": departure(visited, path, X, steps, labels)}
    feedback = {"kept": gains.K, **refitted_feedback(trainer, X, weights)}
    try:
        for name, K in feedback.items():
            new = gains.with_feedback(K, path)
            ends = controller_distance(scenes, trainer, new)
            controller.set_gains(new)
            out[name] = {
                "controllers": round(ends, 4),
                "takeover": takeover_distances(trainer.bank, robot, task, scenes, controller),
                "feedback_norm": round(float(K.norm(dim=(-2, -1)).mean()), 4),
            }
    finally:
        controller.set_gains(gains)
    return out


def score_policy(policy, env: WorldEnv) -> float:
    """Mean final distance of ``policy`` acting on ``env``."""
    with torch.no_grad():
        return float(env.final_distance(env.rollout(env.horizon, policy, break_when_any_done=False)).mean())


def own_gap(td: TensorDictBase, gains: LinearGaussianGains) -> float:
    """:func:`clipped_gap` of a rollout's actions ``[M, T]`` against ``gains``' at its states."""
    if not torch.equal(td["condition"][:, 0].reshape(-1), torch.arange(gains.num_conditions)):
        raise ValueError("the rollout must hold one copy per condition, in order")
    asked = gains.mean_actions(state_of(td)[:, None])[:, 0]
    return clipped_gap(td["action"], asked)


def variance_shares(target: torch.Tensor, sigma: float = JITTER_SIGMA) -> dict[str, float]:
    """Where the variance of ``target [M, N, T, dU]`` (clipped to the torque limits) lies:
    ``within_cell_share`` within its (condition, time step) cells, across their ``N`` samples;
    ``jitter_share`` in the cells' means less those means filtered along time (a Gaussian of
    ``sigma`` steps), what changes from one step to the next."""
    target = target.clamp(-TORQUE_LIMIT, TORQUE_LIMIT).to(torch.float64)
    means = target.mean(1)  # [M, T, dU]
    parts = {
        "within_cell_share": target - means[:, None],
        "jitter_share": means - time_filtered(means, sigma),
        "total": target - target.mean((0, 1, 2)),
    }
    variance = {name: part.square().sum(-1).mean() for name, part in parts.items()}
    return {name: round(float(variance[name] / variance["total"]), 4) for name in parts if name != "total"}


def bank_figures(bank: ModuleBank, name: str, data: dict, scenes: WorldEnv, tests: dict, gains) -> dict:
    """World ``name``'s network's figures: its gaps on ``data`` (``{part: (obs, target)}``) and
    at its own states, where it ends on ``scenes`` and on each of ``tests``
    (``{"distance_test": the test positions, ...}``)."""
    robot, task = bank.world(name)
    after, _ = rollout(bank, robot, task, scenes)
    gaps = {
        f"gap_{part}": clipped_gap(network_mean_actions(bank, name, x, pixels=False), t)
        for part, (x, t) in data.items()
    }
    return {
        **gaps,
        "gap_own": own_gap(after, gains),
        "distance": round(float(scenes.final_distance(after).mean()), 4),
        **{key: round(score(bank, robot, task, env).mean, 4) for key, env in tests.items()},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a finished run.py run directory with finetune=true")
    parser.add_argument("--start", choices=TRANSFERRED, default="composed")
    parser.add_argument("--iterations", type=int, default=10, help="fine-tuning iterations before the fits")
    parser.add_argument("--algo", choices=["badmm", "mdgps"], default=None, help="default: the run's")
    parser.add_argument("--c-step", choices=C_STEPS, default=None, help="default: the run's")
    parser.add_argument("--sgd-steps", type=int, default=5000, help="Adam steps of each regressor")
    parser.add_argument("--hidden", type=int, nargs="+", default=[80] * 5, help="the regressors' layers")
    parser.add_argument(
        "--pi2-covariance-damping", type=float, default=None, help="PI2's damping (default: the run's)"
    )
    parser.add_argument(
        "--refit-weights",
        type=float,
        nargs="+",
        default=[0.01, 0.1, 1.0],
        help="torque weights of the tracking LQRs that takeover_refitted tries",
    )
    args = parser.parse_args()
    if args.iterations < 1 or args.sgd_steps < 0 or min(args.hidden) < 1:
        parser.error("--iterations and every --hidden must be positive, --sgd-steps not negative")
    damping = args.pi2_covariance_damping
    if min(args.refit_weights) <= 0 or (damping is not None and damping <= 0):
        parser.error("every --refit-weights and --pi2-covariance-damping must be positive")

    results = finished_run(parser, args.run_dir, (*FINISHED, ".hydra/config.yaml"))
    if args.start == "wrong_task" and "wrong_task" not in results["methods"]:
        parser.error(f"{args.run_dir}'s bank has no wrong task module; valid starts: composed")
    run = saved_run(args.run_dir)
    torch.set_num_threads(run.threads)
    options = {"algo": args.algo or run.finetune_gps_config().algo}
    if args.c_step:
        options["c_step"] = args.c_step
    if args.pi2_covariance_damping is not None:
        options["pi2_covariance_damping"] = args.pi2_covariance_damping
    if options["algo"] != "mdgps":  # BADMM's duals shift its targets, and it C-steps after the S-step
        parser.error("only MDGPS's S-step regresses onto the controllers' mean actions; use --algo mdgps")
    universe, split = validate(run)
    if universe.pixels:
        parser.error(f"{args.run_dir} is a run from images; this compares networks of the state")
    robot, task = split.holdout
    # the envs first, then the trainer (which seeds torch), as run.py's fine-tuning builds them
    test_positions = held_out_env(run, universe, split)
    scenes = training_env(robot, task, run.finetune_gps_config(), horizon=results["horizon"])
    try:
        trainer = start_trainer(args.run_dir, run, universe, results, args.start, **options)
    except ValueError as err:  # e.g. PI2 under a BADMM run, refused before any work
        parser.error(str(err))

    started = time.perf_counter()
    curve = []
    for iteration in range(args.iterations + 1):  # the network at the test positions, as run.py's curve
        if iteration:
            trainer.step()
        curve.append(round(score(trainer.bank, robot, task, test_positions).mean, 4))
    finetuned_s = time.perf_counter() - started
    tests = {"distance_test": test_positions}
    if run.eval.random_conditions > 0:  # built after the rerun, which repeats the run's curve
        tests["distance_random"] = held_out_env(run, universe, split, random=True)
    (state,) = trainer.states.values()
    gains = state.controller.gains
    last = trainer.iteration - 1  # which policy drew the S-step's samples:
    drawn_by_network = trainer.config.init_from_policy if last == 0 else trainer.config.sample_on_policy

    asked = {"fit": gains.mean_actions(state.samples.X)}  # at the S-step's samples and a fresh draw
    samples = {"fit": state.samples, "fresh": state.sampler.sample(state.controller)}
    asked["fresh"] = gains.mean_actions(samples["fresh"].X)
    if trainer.config.clip_targets:  # the S-step's targets
        targets = {part: a.clamp(-TORQUE_LIMIT, TORQUE_LIMIT).float() for part, a in asked.items()}
    else:
        targets = {part: a.float() for part, a in asked.items()}
    flat = {part: t.reshape(-1, gains.action_dim) for part, t in targets.items()}

    world = trainer.bank.world(state.name)
    alone, _ = rollout(trainer.bank, robot, task, scenes)  # the network alone (mean actions)
    by_obs = {part: (samples[part].obs, targets[part]) for part in samples}
    networks = {"network": bank_figures(trainer.bank, state.name, by_obs, scenes, tests, gains)}
    schedule = dict(steps=args.sgd_steps, seed=trainer.config.seed)
    refit = refitted(trainer.bank, world, samples["fit"].obs, flat["fit"], **schedule)
    networks["network_refit"] = bank_figures(refit, state.name, by_obs, scenes, tests, gains)
    by_inputs = {part: (inputs_of(samples[part].obs), flat[part]) for part in samples}
    M, T = state.sampler.num_conditions, state.sampler.horizon
    for seed, inputs in enumerate(INPUTS):
        torch.manual_seed(trainer.config.seed + seed)
        net = Regressor(
            inputs,
            state_dim=gains.state_dim,
            action_dim=gains.action_dim,
            conditions=M,
            horizon=T,
            hidden=tuple(args.hidden),
        )
        fit(net, *by_inputs["fit"], steps=args.sgd_steps, seed=trainer.config.seed + seed)
        with torch.no_grad():
            gaps = {f"gap_{part}": clipped_gap(net(*x), target) for part, (x, target) in by_inputs.items()}
        policy = TensorDictModule(net, in_keys=[*STATE_KEYS, "condition", "step_count"], out_keys=["action"])
        networks[inputs] = {**gaps, **acting(scenes, policy, gains)}
        if not net.scene:  # the test positions are not among the conditions it knows
            networks[inputs].update({key: round(score_policy(policy, env), 4) for key, env in tests.items()})
    for name, f in networks.items():
        gaps = f"gap {f['gap_fit']:.3f} (fresh samples {f['gap_fresh']:.3f}, own states {f['gap_own']:.3f})"
        test = f"; at the test positions {f['distance_test']:.3f}" if "distance_test" in f else ""
        test += f", on random positions {f['distance_random']:.3f}" if "distance_random" in f else ""
        print(f"{name:18s} {gaps}  ends {f['distance']:.3f}{test}")

    out = {
        "benchmark": "imitation_capacity",
        "run_dir": str(args.run_dir),
        "holdout": results["holdout"],
        "start": args.start,
        "c_step": trainer.config.c_step,
        "iterations": args.iterations,
        "fit_drawn_by": "network" if drawn_by_network else "controllers",
        "sgd_steps": args.sgd_steps,
        "hidden": args.hidden,
        "controllers": round(controller_distance(scenes, trainer, gains), 4),
        "takeover": takeover_distances(trainer.bank, robot, task, scenes, state.controller),
        "takeover_refitted": takeover_refitted(
            trainer, robot, task, scenes, samples["fresh"].X, alone, args.refit_weights
        ),
        "sampled": round(float(state.samples.distance.mean()), 4),
        "untouched": round(float(scenes.start_distance(alone).mean()), 4),  # any policy's start
        "saturated": round(float((asked["fit"].abs() > TORQUE_LIMIT).double().mean()), 4),
        **variance_shares(targets["fit"]),
        "target_norm": round(float(flat["fit"].clamp(-TORQUE_LIMIT, TORQUE_LIMIT).norm(dim=-1).mean()), 4),
        "rerun_curve": curve,
        "run_curve": [round(d, 4) for d in results.get("finetune", {}).get(args.start, [])[: len(curve)]],
        "finetune_s": round(finetuned_s, 1),
        "networks": networks,
    }
    print(f"controllers end {out['controllers']:.3f}, untouched {out['untouched']:.3f}")
    takeover = ", ".join(f"at step {step} {d:.3f}" for step, d in out["takeover"].items())
    print(f"the network then the controllers from {takeover}")
    feedback = dict(out["takeover_refitted"])
    away = feedback.pop("departure")
    print(
        "the network's distance from the controllers' path (in the entries' spread): "
        + ", ".join(f"step {t} {d:.2f} ({away['farthest'][t]})" for t, d in away["network"].items())
        + "; their samples' " + ", ".join(f"{d:.2f}" for d in away["samples"].values())
    )
    for name, f in feedback.items():
        takeover = ", ".join(f"{step} {d:.3f}" for step, d in f["takeover"].items())
        alone = f"alone {f['controllers']:.3f}"
        print(f"feedback {name:11s} |K| {f['feedback_norm']:.3g}: {alone}, from step {takeover}")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
