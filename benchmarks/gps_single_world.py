"""Train one world with GPS and report the neural-network policy's final distances.

    python benchmarks/gps_single_world.py --robot three_link --task reach [--algo mdgps --iterations 10]
    python benchmarks/gps_single_world.py --task push --conditions 4 --trace   # where the block goes
    python benchmarks/gps_single_world.py --noise-smoothing 2 --dynamics-prior-per-condition  # GPS code's
    python benchmarks/gps_single_world.py --task push --conditions 4 --trajectory-only  # no policy pull
    python benchmarks/gps_single_world.py --task push --max-policy-weight 1e-3 --evaluate-on train
    python benchmarks/gps_single_world.py --task push --width 256 --sgd-steps 3000  # a larger network
    python benchmarks/gps_single_world.py --task push --algo mdgps --sample-on-policy  # on-policy MDGPS
    python benchmarks/gps_single_world.py --task push --conditions 4 --algo mdgps --c-step pilqr  # or pi2
    python benchmarks/gps_single_world.py --clip-targets  # regress onto the torques the arm applies
    python benchmarks/gps_single_world.py --task push --cost-ramp quadratic --final-cost-multiplier 1

The distance is the task's (end-effector or object to goal) averaged over the last 5 steps
of a deterministic rollout of the composed policy (not the local controllers) from each
test condition (or, with ``--evaluate-on train``, from each training condition; with
``random``, from further random ones).  Beside it, ``start_distance`` is where each
rollout started (an untouched object stays there); ``closer`` and ``farther`` count the
conditions where the policy ends more than 1 cm closer or farther than it started.  Each
iteration prints the trainer's diagnostics (``predicted_cost`` against the next iteration's
``sampled_cost`` says how far the fitted dynamics can be trusted).
``--trace`` adds, for the last iteration's samples, each training condition's end effector to
object and object to goal distances (means over the samples) at a few time steps.
The last line is one JSON object:
``{"final_distance": [...], "success_distance": ..., "controllers_distance": [per iteration],
"controllers_final_distance": [per training condition, the last iteration's samples],
"controllers_final_joints", "final_joints": [the arm's joint angles at the last step], ...}``.
"""

from __future__ import annotations

import argparse
import json
import time
from typing import get_args

import torch

from modnet.bank import ModuleBank
from modnet.evaluate import evaluation_env, rollout
from modnet.gps.badmm import BADMMConfig
from modnet.gps.cost import Ramp
from modnet.gps.sampling import state_of
from modnet.gps.trainer import C_STEPS, GPSConfig, GPSTrainer
from modnet.worlds import get_world, task_spec

MOVED = 0.01  # a final distance this much below or above the start counts as closer or farther


def last_samples_trace(trainer: GPSTrainer, robot: str, task: str) -> dict:
    """End effector to object and object to goal distance ``[conditions][steps]`` in the last samples."""
    world = get_world(robot, task)
    X = trainer.states[f"{robot}/{task}"].samples.X  # [M, N, T, dX]
    task_state = X[..., world.robot.state_dim :]
    steps = sorted({t for t in (0, 20, 40, 60, X.shape[2] - 1) if t < X.shape[2]})
    table = {
        "ee_to_object": world.task.shaping_offset(task_state).norm(dim=-1).mean(1),
        "object_to_goal": world.task.target_offset(task_state).norm(dim=-1).mean(1),
    }
    for name, values in table.items():
        for m, row in enumerate(values[:, steps].tolist()):
            print(f"condition {m} {name} at steps {steps}: " + " ".join(f"{v:.3f}" for v in row))
    rounded = {name: values[:, steps].round(decimals=3).tolist() for name, values in table.items()}
    return {"steps": steps} | rounded


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--robot", default="three_link")
    parser.add_argument("--task", default="reach")
    parser.add_argument("--algo", default=GPSConfig.algo, choices=["mdgps", "badmm"])
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--samples", type=int, default=5, help="samples per condition")
    parser.add_argument("--conditions", type=int, default=16, help="training conditions")
    parser.add_argument(
        "--dropout",
        type=float,
        default=0.0,
        help="the modules' dropout (none; universe manipulation uses 0.2, the colour and visual ones 0.1)",
    )
    parser.add_argument("--dynamics-ridge", type=float, default=GPSConfig.dynamics_ridge)
    parser.add_argument(
        "--noise-smoothing",
        type=float,
        default=GPSConfig.noise_smoothing,
        help="sigma, in steps, of the exploration noise's filter along time (0: white)",
    )
    parser.add_argument(
        "--dynamics-prior-per-condition",
        action="store_true",
        help="one dynamics prior per condition (the GPS code's), not one per world",
    )
    parser.add_argument(
        "--trajectory-only",
        action="store_true",
        help="switch the policy's pull off (BADMM's policy weight held at 1e-6, no dual ascent, "
        "4 SGD steps): trajectory optimisation alone; the network it reports is then untrained",
    )
    parser.add_argument(
        "--max-policy-weight",
        type=float,
        default=None,
        help=f"cap on BADMM's policy weight nu_t (default {BADMMConfig.max_policy_weight:g}; the initial "
        "weight is lowered to it if above): how hard the policy may pull the controllers",
    )
    parser.add_argument(
        "--evaluate-on",
        choices=["test", "train", "random"],
        default="test",
        help="score the network at the task's 4 test positions (default), at its training conditions, "
        "or at --random-conditions further random ones",
    )
    parser.add_argument(
        "--random-conditions",
        type=int,
        default=20,
        help="how many random conditions --evaluate-on random draws (run.py's eval.random_conditions)",
    )
    parser.add_argument(
        "--width",
        type=int,
        default=None,
        help="units in every hidden layer of both modules (default: the authors' 80; the depths, "
        "3 task and 2 robot layers, and the 12-unit interface are kept)",
    )
    parser.add_argument(
        "--sgd-steps",
        type=int,
        default=None,
        help=f"SGD steps of the S-step, every iteration including the first (default {GPSConfig.sgd_steps})",
    )
    parser.add_argument(
        "--sample-on-policy",
        action="store_true",
        help="from the second iteration on, sample the network instead of the controllers (the GPS "
        "code's sample_on_policy, with --algo mdgps its on-policy variant): the S-step then learns "
        "at the states the network itself reaches",
    )
    parser.add_argument(
        "--c-step",
        default=GPSConfig.c_step,
        choices=list(C_STEPS),
        help="the C-step: the KL-constrained LQR on fitted dynamics, PI2's reweighting of the "
        "samples by their cost to go (model-free), or PILQR, the LQR then PI2 on the cost its "
        "model misses (both with --algo mdgps)",
    )
    parser.add_argument(
        "--pi2-kl",
        type=float,
        default=GPSConfig.pi2_kl,
        help="PI2, PILQR: the KL of each step's sample weights",
    )
    parser.add_argument(
        "--min-step-mult",
        type=float,
        default=GPSConfig.min_step_mult,
        help="floor of the C-step's step multiplier (the GPS code's: 0.01)",
    )
    parser.add_argument(
        "--max-step-mult",
        type=float,
        default=GPSConfig.max_step_mult,
        help="cap of the C-step's step multiplier (the GPS code's: 10)",
    )
    parser.add_argument(
        "--clip-targets",
        action="store_true",
        help="regress the network onto the torques the arm applies (clipped to its limits), "
        "not the controllers' (gps.clip_targets)",
    )
    parser.add_argument(
        "--cost-ramp",
        default=GPSConfig.cost_ramp,
        choices=list(get_args(Ramp)),
        help="the cost's weight along time (gps.cost_ramp; the authors' push and drawer costs: quadratic)",
    )
    parser.add_argument(
        "--final-cost-multiplier",
        type=float,
        default=GPSConfig.final_cost_multiplier,
        help="the last step's cost weight times this (gps.final_cost_multiplier; the authors' push: 1)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--trace", action="store_true", help="where the object goes, per condition")
    args = parser.parse_args()
    if args.trajectory_only and args.algo != "badmm":
        parser.error("--trajectory-only holds BADMM's policy weight; use it with --algo badmm")
    if args.trajectory_only and args.sgd_steps is not None:
        parser.error("--trajectory-only fixes the SGD steps at 4; leave --sgd-steps out")
    if args.max_policy_weight is not None and (args.algo != "badmm" or args.trajectory_only):
        parser.error("--max-policy-weight caps BADMM's policy weight; use it with --algo badmm alone")
    torch.set_num_threads(1)
    start = time.perf_counter()
    pull = {}  # BADMMConfig options: how hard the policy pulls the controllers
    sgd = {}  # the S-step's length
    if args.trajectory_only:
        weight = BADMMConfig.min_policy_weight
        pull = dict(
            dual_rate=0.0, initial_policy_weight=weight, min_policy_weight=weight, max_policy_weight=weight
        )
        sgd = dict(sgd_steps=4, initial_sgd_steps=4)
    if args.max_policy_weight is not None:
        weight = args.max_policy_weight
        initial = min(BADMMConfig.initial_policy_weight, weight)  # lowered to the cap if above it
        pull = dict(initial_policy_weight=initial, max_policy_weight=weight)
    if args.sgd_steps is not None:
        sgd = dict(sgd_steps=args.sgd_steps, initial_sgd_steps=args.sgd_steps)
    size = {} if args.width is None else dict(task_hidden=(args.width,) * 3, robot_hidden=(args.width,) * 2)
    count = {"train": args.conditions, "random": args.random_conditions}.get(args.evaluate_on)
    try:  # the library's own checks of every option, before any training
        bank = ModuleBank.build([args.robot], [args.task], seed=args.seed, dropout=args.dropout, **size)
        config = GPSConfig(
            algo=args.algo,
            samples_per_condition=args.samples,
            num_conditions=args.conditions,
            seed=args.seed,
            dynamics_ridge=args.dynamics_ridge,
            noise_smoothing=args.noise_smoothing,
            dynamics_prior_per_condition=args.dynamics_prior_per_condition,
            sample_on_policy=args.sample_on_policy,
            c_step=args.c_step,
            pi2_kl=args.pi2_kl,
            min_step_mult=args.min_step_mult,
            max_step_mult=args.max_step_mult,
            clip_targets=args.clip_targets,
            cost_ramp=args.cost_ramp,
            final_cost_multiplier=args.final_cost_multiplier,
            badmm=BADMMConfig(**pull),
            **sgd,
        )
        env = evaluation_env(
            args.robot,
            args.task,
            conditions=args.evaluate_on,
            num_conditions=count,
            seed=config.condition_seed,
        )
    except ValueError as err:  # unknown robot or task, a width or step count below 1, a cap below the floor
        parser.error(str(err))
    trainer = GPSTrainer(bank, [(args.robot, args.task)], config)
    name = f"{args.robot}/{args.task}"
    for i in range(args.iterations):
        diag = trainer.step()[name]
        print(f"iteration {i}: " + " ".join(f"{k}={v:.3g}" for k, v in diag.items()), flush=True)
    trace = last_samples_trace(trainer, args.robot, args.task) if args.trace else None
    last = trainer.states[name].samples  # the last iteration's samples: the controllers per condition
    joints = get_world(args.robot, args.task).robot.n_joints  # the robot state starts with its angles
    td, _ = rollout(bank, args.robot, args.task, env)
    distance = env.final_distance(td)
    start_distance = env.start_distance(td)
    wall = time.perf_counter() - start
    print(
        json.dumps(
            {
                "world": name,
                "algo": args.algo,
                "noise_smoothing": args.noise_smoothing,
                "dynamics_prior_per_condition": args.dynamics_prior_per_condition,
                "trajectory_only": args.trajectory_only,
                "sample_on_policy": args.sample_on_policy,
                "c_step": args.c_step,
                **({"pi2_kl": args.pi2_kl} if args.c_step != "lqr" else {}),
                "max_policy_weight": config.badmm.max_policy_weight,
                "step_mult_bounds": [config.min_step_mult, config.max_step_mult],
                "clip_targets": config.clip_targets,
                "cost_ramp": config.cost_ramp,
                "final_cost_multiplier": config.final_cost_multiplier,
                "evaluated_on": args.evaluate_on,
                "width": bank.config.task_hidden[0],
                "sgd_steps": config.sgd_steps,
                "network_parameters": sum(p.numel() for p in bank.parameters()),
                "controllers_distance": [round(h[name]["distance"], 4) for h in trainer.history],
                "controllers_final_distance": [round(float(d), 4) for d in last.distance.mean(1)],
                "controllers_final_joints": last.X[:, :, -1, :joints].mean(1).round(decimals=3).tolist(),
                "final_joints": state_of(td)[:, -1, :joints].round(decimals=3).tolist(),
                "final_distance": [round(float(d), 4) for d in distance],
                "start_distance": [round(float(d), 4) for d in start_distance],
                "closer": int((distance < start_distance - MOVED).sum()),
                "farther": int((distance > start_distance + MOVED).sum()),
                "success_distance": task_spec(args.task).success_distance,
                "iterations": args.iterations,
                "samples": trainer.samples["trajectories"],
                "env_steps": trainer.samples["env_steps"],
                "wall_s": round(wall, 1),
                **({"trace": trace} if trace else {}),
            }
        )
    )


if __name__ == "__main__":
    main()
