"""Whether a policy that sees only the state can do what fine-tuning's controllers do.

GPS's S-step regresses the network onto its controllers' mean actions ``K_t x + k_t`` at
their samples. The controllers are time-varying and one per training condition; the network
sees the state alone. Where the network stays far from controllers that succeed, either the
S-step falls short (too few steps, dropout, the modular bottleneck) or no function of the
state can do what the controllers do: their feed-forward ``k_t`` may depend on the time step
and the scene in a way the state does not tell apart.

This reruns ``--iterations`` fine-tuning iterations of a start (as ``run.py finetune=true``
does, with the run's options unless ``--c-step`` is given) on a finished run's bank, then
takes the last iteration's samples, the S-step's own training set, and fits to the same
targets (clipped to the torque limits where the run's ``gps.clip_targets`` clips them), from
scratch and without dropout, one plain network per set of inputs:

- ``state``: the state ``x`` (what the composed modules read, together);
- ``state_time``: ``x`` and the time step ``t / T``;
- ``state_scene_time``: ``x``, ``t / T`` and the condition (one-hot), which can hold each
  scene's feed-forward step by step.

Each has ``--hidden`` ReLU layers (default five of 80 units: the composed pair's depth and
width) and is fitted by Adam for ``--sgd-steps`` steps. For each, and for the bank's network
after the run's S-steps:

- ``gap_fit``: the mean norm of its mean action less the target, both clipped to the torque
  limits, on the training set;
- ``gap_fresh``: the same on a fresh draw of the controllers' samples;
- ``gap_own``: the same at the states it visits itself, acting alone (what DAgger would label);
- ``distance``: where it ends when it acts (mean actions) on the held-out world's training
  conditions; beside ``controllers`` (the controllers the iteration ends with, mean actions)
  and ``untouched``;
- ``distance_test``: where it ends at the test positions (not for ``state_scene_time``, which
  knows only the training conditions).

``saturated`` is the share of the controllers' mean torques at the samples beyond the limits;
``within_cell_share`` is the share of the targets' variance that lies within (condition, time
step) cells, between one cell's samples: what the controllers' feedback ``K_t`` adds to
their feed-forward at the samples' spread of states.

``rerun_curve`` is the bank's network at the test positions after each iteration, beside the
run's own fine-tuning curve ``run_curve``: the two are equal when this reran the run.

Prints a line per network, then ONE JSON object on its last line.

    python benchmarks/imitation_capacity.py outputs/manipulation --iterations 10 --c-step pi2
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
from _run_dir import FINISHED, finished_run
from first_finetune_iteration import TRANSFERRED, controller_distance, start_trainer
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn

from modnet.config import saved_run
from modnet.envs import WorldEnv
from modnet.evaluate import evaluating, evaluation_env, rollout, score, training_env
from modnet.gps.controller import LinearGaussianGains
from modnet.gps.sampling import STATE_KEYS, state_of
from modnet.gps.trainer import C_STEPS, GPSTrainer
from modnet.specs import TORQUE_LIMIT

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
        layers: list[nn.Module] = []
        for units in hidden:
            layers += [nn.Linear(width, units), nn.ReLU()]
            width = units
        self.net = nn.Sequential(*layers, nn.Linear(width, action_dim))
        self.register_buffer("mean", torch.zeros(state_dim + self.time + conditions * self.scene))
        self.register_buffer("std", torch.ones_like(self.mean))

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
    """Adam on the mean squared error, minibatches of 1,024, the learning rate 1e-3 annealed to
    zero (cosine) over ``steps``."""
    net.fit_normalization(net.features(*inputs))
    generator = torch.Generator().manual_seed(seed)
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-3)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, max(steps, 1))
    rows = target.shape[0]
    for _ in range(steps):
        batch = torch.randint(rows, (min(1024, rows),), generator=generator)
        loss = (net(*(x[batch] for x in inputs)) - target[batch]).square().sum(-1).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        schedule.step()


def clipped_gap(actions: torch.Tensor, target: torch.Tensor) -> float:
    """Mean norm of ``actions - target``, both clipped to the torque limits the arms apply."""
    gap = actions.clamp(-TORQUE_LIMIT, TORQUE_LIMIT) - target.clamp(-TORQUE_LIMIT, TORQUE_LIMIT)
    return round(float(gap.norm(dim=-1).mean()), 4)


def acting(scenes: WorldEnv, policy, gains: LinearGaussianGains) -> dict[str, float]:
    """``policy`` acting on ``scenes`` (one copy per condition, in order), mean actions: its
    mean final ``distance``, and ``gap_own``, the gap to the controllers ``gains`` at the
    states it visits itself."""
    with torch.no_grad():
        td = scenes.rollout(scenes.horizon, policy, break_when_any_done=False)
    return {"gap_own": own_gap(td, gains), "distance": round(float(scenes.final_distance(td).mean()), 4)}


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


def within_cell_share(target: torch.Tensor) -> float:
    """The share of the variance of ``target [M, N, T, dU]`` (clipped to the torque limits)
    within its (condition, time step) cells, across their ``N`` samples."""
    target = target.clamp(-TORQUE_LIMIT, TORQUE_LIMIT)
    within = (target - target.mean(1, keepdim=True)).square().sum(-1).mean()
    total = (target - target.mean((0, 1, 2))).square().sum(-1).mean()
    return round(float(within / total), 4)


def network_actions(trainer: GPSTrainer, obs: TensorDictBase) -> torch.Tensor:
    """The bank's composed network's mean actions at ``obs``, flattened."""
    (name,) = trainer.states
    with evaluating(trainer.bank):
        out = trainer.bank.forward_worlds({name: obs})
    loc = out[trainer.bank.world(name)]["loc"]
    return loc.reshape(-1, loc.shape[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a finished run.py run directory with finetune=true")
    parser.add_argument("--start", choices=TRANSFERRED, default="composed")
    parser.add_argument("--iterations", type=int, default=10, help="fine-tuning iterations before the fits")
    parser.add_argument("--c-step", choices=C_STEPS, default=None, help="default: the run's")
    parser.add_argument("--sgd-steps", type=int, default=5000, help="Adam steps of each regressor")
    parser.add_argument("--hidden", type=int, nargs="+", default=[80] * 5, help="the regressors' layers")
    args = parser.parse_args()
    if args.iterations < 1 or args.sgd_steps < 0 or min(args.hidden) < 1:
        parser.error("--iterations and every --hidden must be positive, --sgd-steps not negative")

    results = finished_run(parser, args.run_dir, (*FINISHED, ".hydra/config.yaml"))
    if args.start == "wrong_task" and "wrong_task" not in results["methods"]:
        parser.error(f"{args.run_dir}'s bank has no wrong task module; valid starts: composed")
    run = saved_run(args.run_dir)
    torch.set_num_threads(run.threads)
    options = {"c_step": args.c_step} if args.c_step else {}
    robot, task = results["holdout"].split("/")
    # the envs first, then the trainer (which seeds torch), as run.py's fine-tuning builds them
    test_positions = evaluation_env(robot, task, horizon=results["horizon"])
    scenes = training_env(robot, task, run.finetune_gps_config(), horizon=results["horizon"])
    try:
        trainer = start_trainer(args.run_dir, run, results, args.start, **options)
    except ValueError as err:  # e.g. PI2 under a BADMM run, refused before any work
        parser.error(str(err))

    started = time.perf_counter()
    curve = []
    for iteration in range(args.iterations + 1):  # scored as run.py scores it, between iterations
        if iteration:
            trainer.step()
        curve.append(round(score(trainer.bank, robot, task, test_positions).mean, 4))
        score(trainer.bank, robot, task, scenes)
    finetuned_s = time.perf_counter() - started
    (state,) = trainer.states.values()
    gains = state.controller.gains

    def targets(X: torch.Tensor) -> torch.Tensor:  # the S-step's
        asked = gains.mean_actions(X)
        return (asked.clamp(-TORQUE_LIMIT, TORQUE_LIMIT) if trainer.config.clip_targets else asked).float()

    training = (state.samples.obs, targets(state.samples.X))
    asked = gains.mean_actions(state.samples.X)
    fresh_samples = state.sampler.sample(state.controller)
    fresh = (fresh_samples.obs, targets(fresh_samples.X))
    flat = {
        part: (inputs_of(obs), target.reshape(-1, target.shape[-1]))
        for part, (obs, target) in (("fit", training), ("fresh", fresh))
    }

    after, _ = rollout(trainer.bank, robot, task, scenes)
    networks = {
        "network": {
            "gap_fit": clipped_gap(network_actions(trainer, training[0]), flat["fit"][1]),
            "gap_fresh": clipped_gap(network_actions(trainer, fresh[0]), flat["fresh"][1]),
            "gap_own": own_gap(after, gains),
            "distance": round(float(scenes.final_distance(after).mean()), 4),
            "distance_test": curve[-1],
        }
    }
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
        fit(net, *flat["fit"], steps=args.sgd_steps, seed=trainer.config.seed + seed)
        with torch.no_grad():
            gaps = {f"gap_{part}": clipped_gap(net(*x), target) for part, (x, target) in flat.items()}
        policy = TensorDictModule(net, in_keys=[*STATE_KEYS, "condition", "step_count"], out_keys=["action"])
        networks[inputs] = {**gaps, **acting(scenes, policy, gains)}
        if not net.scene:  # the test positions are not among the conditions it knows
            networks[inputs]["distance_test"] = round(score_policy(policy, test_positions), 4)
    for name, f in networks.items():
        gaps = f"gap {f['gap_fit']:.3f} (fresh samples {f['gap_fresh']:.3f}, own states {f['gap_own']:.3f})"
        test = f"; at the test positions {f['distance_test']:.3f}" if "distance_test" in f else ""
        print(f"{name:18s} {gaps}  ends {f['distance']:.3f}{test}")

    out = {
        "benchmark": "imitation_capacity",
        "run_dir": str(args.run_dir),
        "holdout": results["holdout"],
        "start": args.start,
        "c_step": trainer.config.c_step,
        "iterations": args.iterations,
        "sgd_steps": args.sgd_steps,
        "hidden": args.hidden,
        "controllers": round(controller_distance(scenes, trainer, gains), 4),
        "sampled": round(float(state.samples.distance.mean()), 4),
        "untouched": round(float(scenes.start_distance(after).mean()), 4),
        "saturated": round(float((asked.abs() > TORQUE_LIMIT).double().mean()), 4),
        "within_cell_share": within_cell_share(training[1]),
        "target_norm": round(float(flat["fit"][1].clamp(-TORQUE_LIMIT, TORQUE_LIMIT).norm(dim=-1).mean()), 4),
        "rerun_curve": curve,
        "run_curve": [round(d, 4) for d in results.get("finetune", {}).get(args.start, [])[: len(curve)]],
        "finetune_s": round(finetuned_s, 1),
        "networks": networks,
    }
    print(f"controllers end {out['controllers']:.3f}, untouched {out['untouched']:.3f}")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
