"""How close can the arm get at all? An open-loop search for the best final distance.

When GPS (or a composed policy) ends short of a goal, the physics may be why (horizon too
short, torques too weak, a scene out of reach) or the optimisation may be. This answers the
first question for each initial condition of a world: the cross-entropy method searches
open-loop torque sequences (``--knots`` values per joint, linearly interpolated over the
task's horizon, clipped to the motors' limits) for the lowest final distance, the paper's
metric: the task's distance averaged over the last 5 steps. It runs the world's own MuJoCo
model through :meth:`~modnet.worlds.World.reset_data` and :meth:`~modnet.worlds.World.step_data`,
the arithmetic of every rollout in modnet.

What it finds is achievable (it is a real rollout), so it bounds the best distance from
above; a low bound says the task is feasible and any miss is the learner's. A high one
proves nothing on its own (the search may have missed). It knows the condition's state,
which a policy must find from its observations, and spends ``--population x --iterations``
rollouts per condition, so it is not a baseline for GPS's sample counts.

Prints a line per condition, then ONE JSON object on its last line.

    python benchmarks/reachable.py --robot three_link --task reach --split train --conditions 16
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass

import mujoco
import numpy as np
import torch

from modnet.envs import FINAL_STEPS
from modnet.specs import TORQUE_LIMIT
from modnet.worlds import CONDITION_SETS, World, get_world


def interpolate(knots: np.ndarray, horizon: int) -> np.ndarray:
    """Torques ``[horizon, nu]`` through ``knots [K, nu]`` (evenly spaced, linear in between),
    clipped to the motors' limits."""
    grid = np.linspace(0, horizon - 1, knots.shape[0])
    steps = np.arange(horizon)
    torques = np.stack([np.interp(steps, grid, knots[:, j]) for j in range(knots.shape[1])], -1)
    return np.clip(torques, -TORQUE_LIMIT, TORQUE_LIMIT)


def final_distance(world: World, data: mujoco.MjData, params: np.ndarray, torques: np.ndarray) -> float:
    """Play ``torques [T, nu]`` open loop from condition ``params``; the distance averaged over
    the last 5 steps (as :meth:`modnet.envs.WorldEnv.final_distance` measures a rollout)."""
    world.reset_data(data, params)
    horizon = torques.shape[0]
    distances = []
    for t, u in enumerate(torques):
        data.ctrl[:] = u
        world.step_data(data)
        if t >= horizon - FINAL_STEPS:
            distances.append(world.observe(data.sensordata)[1])
    task_state = torch.as_tensor(np.stack(distances), dtype=torch.float64)
    return float(world.task.distance(task_state).mean())


@dataclass
class Search:
    """The cross-entropy method's result for one condition."""

    zero_torque: float  # the final distance if the arm applies no torque (the untouched scene)
    best: float  # the lowest final distance of any rollout
    knots: np.ndarray  # the torque knots that reached it


def cem(
    world: World,
    params: np.ndarray,
    *,
    population: int = 200,
    elites: int = 20,
    iterations: int = 40,
    knots: int = 11,
    seed: int = 0,
) -> Search:
    """Search torque knots ``[knots, nu]`` for the lowest final distance from ``params``.

    Examples:
        >>> from modnet.worlds import get_world
        >>> world = get_world("three_link", "reach")
        >>> params = world.conditions("test", 0)[0]
        >>> found = cem(world, params, population=16, elites=4, iterations=2)
        >>> bool(found.best < found.zero_torque)
        True
    """
    if not 0 < elites <= population:
        raise ValueError(f"need 0 < elites <= population, got elites={elites}, population={population}")
    if knots < 2 or iterations < 1:
        raise ValueError(f"need at least 2 knots and 1 iteration, got {knots} and {iterations}")
    rng = np.random.default_rng(seed)
    data = mujoco.MjData(world.model)
    horizon, nu = world.task.horizon, world.model.nu
    mean, std = np.zeros((knots, nu)), np.full((knots, nu), TORQUE_LIMIT)
    best, best_knots = np.inf, mean
    for _ in range(iterations):
        candidates = mean + std * rng.standard_normal((population, knots, nu))
        scores = np.array([final_distance(world, data, params, interpolate(c, horizon)) for c in candidates])
        order = np.argsort(scores)
        if scores[order[0]] < best:
            best, best_knots = float(scores[order[0]]), candidates[order[0]]
        elite = candidates[order[:elites]]
        mean, std = elite.mean(0), elite.std(0) + 0.05 * TORQUE_LIMIT  # a floor keeps it exploring
    zero = final_distance(world, data, params, np.zeros((horizon, nu)))
    return Search(zero_torque=zero, best=best, knots=best_knots)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robot", default="three_link")
    parser.add_argument("--task", default="reach")
    parser.add_argument("--split", default="test", choices=CONDITION_SETS)
    parser.add_argument("--conditions", type=int, default=None, help="size of the condition set (None: 4)")
    parser.add_argument("--condition-seed", type=int, default=0, help="as gps.condition_seed")
    parser.add_argument("--population", type=int, default=200)
    parser.add_argument("--elites", type=int, default=20)
    parser.add_argument("--iterations", type=int, default=40)
    parser.add_argument("--knots", type=int, default=11, help="torque values per joint over the horizon")
    parser.add_argument("--seed", type=int, default=0, help="the search's random stream")
    args = parser.parse_args()

    world = get_world(args.robot, args.task)
    conditions = world.conditions(args.split, args.condition_seed, args.conditions)
    start = time.perf_counter()
    rows = []
    for i, params in enumerate(conditions):
        found = cem(
            world,
            params,
            population=args.population,
            elites=args.elites,
            iterations=args.iterations,
            knots=args.knots,
            seed=args.seed + i,
        )
        rows.append(
            {"condition": i, "zero_torque": round(found.zero_torque, 4), "best": round(found.best, 4)}
        )
        print(f"{args.split} condition {i}: no torque {found.zero_torque:.3f}, best found {found.best:.3f}")
    success = world.task.success_distance
    print(
        json.dumps(
            {
                "world": world.name,
                "split": args.split,
                "condition_seed": args.condition_seed,
                "conditions": rows,
                "success_distance": success,
                "within_success": sum(r["best"] < success for r in rows),
                "rollouts_per_condition": args.population * args.iterations,
                "search": {
                    "population": args.population,
                    "elites": args.elites,
                    "knots": args.knots,
                    "seed": args.seed,
                },
                "wall_s": round(time.perf_counter() - start, 1),
            }
        )
    )


if __name__ == "__main__":
    main()
