"""Sampling for GPS: N rollouts per condition of one world, through TorchRL, kept in TensorDict storage.

A :class:`WorldSampler` owns one batched env with ``M * N`` copies (copy ``i`` starts from
condition ``i % M``), rolls out any TorchRL policy for the horizon, and appends the
trajectories (states, actions, rewards; no pixels) in a :class:`~torchrl.data.ReplayBuffer`
over a ``LazyTensorStorage`` holding the latest iteration.
:class:`Samples` holds one iteration's trajectories in the ``[M, N, T, ...]`` layout the GPS
math uses.

Examples:
    >>> from modnet.gps.sampling import WorldSampler
    >>> sampler = WorldSampler("three_link", "reach", samples_per_condition=2, horizon=5)
    >>> samples = sampler.sample()          # random actions when no policy is given
    >>> samples.X.shape, samples.U.shape    # [M, N, T, dX], [M, N, T, dU]
    (torch.Size([4, 2, 5, 12]), torch.Size([4, 2, 5, 3]))
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import LazyTensorStorage, ReplayBuffer

from modnet.envs import make_env
from modnet.worlds import get_world

STATE_KEYS = (("robot", "state"), ("task", "state"))  # x = [robot_state, task_state]
#: every key a policy may read (a vision policy: the image and the end-effector, not the state)
POLICY_KEYS = (*STATE_KEYS, ("task", "ee"), ("task", "pixels"))


@dataclass
class Samples:
    """One iteration's trajectories of one world, laid out ``[M, N, T, ...]``.

    ``X`` are the states each action was taken in; ``U`` the actions as commanded, before the
    env clips them to the torque limit (as the original GPS code records them, MuJoCo's
    ctrlrange clipping inside its step). The dynamics fitted to them see that torque beyond
    the limit does little, so the LQR does not plan with torque the arm lacks. ``distance``
    is each trajectory's final distance (the paper's metric,
    :meth:`~modnet.envs.WorldEnv.final_distance`); ``obs`` the policy inputs (states, and
    pixels when the env renders) in the same layout.
    """

    X: torch.Tensor  # [M, N, T, dX] float64
    U: torch.Tensor  # [M, N, T, dU] float64
    distance: torch.Tensor  # [M, N] float64
    obs: TensorDictBase  # [M, N, T]


def to_condition_major(td: TensorDictBase, num_conditions: int) -> TensorDictBase:
    """``[M * N, T]`` rollouts with copy ``i`` on condition ``i % M`` -> ``[M, N, T]``."""
    batch, horizon = td.shape
    return td.reshape(batch // num_conditions, num_conditions, horizon).transpose(0, 1)


def state_of(td: TensorDictBase) -> torch.Tensor:
    """The full state ``x = [robot_state, task_state]`` (float64) of a tensordict."""
    return torch.cat([td.get(key) for key in STATE_KEYS], -1).to(torch.float64)


class WorldSampler:
    """Rolls out policies in one world, ``samples_per_condition`` times per condition.

    Args:
        robot, task: the world.
        conditions: the condition set ("train" for training, "test" for evaluation).
        samples_per_condition: N.
        horizon: T (the task's horizon when None).
        pixels: render ``("task", "pixels")`` (only when a pixel policy needs them).
        shaping: include the task's shaping term in the env's reward.
        seed: the condition sets' seed.
        num_conditions: the size of the condition set (M; the set's 4 when None).
    """

    def __init__(
        self,
        robot: str,
        task: str,
        *,
        conditions: str = "train",
        samples_per_condition: int = 5,
        horizon: int | None = None,
        pixels: bool = False,
        shaping: bool = True,
        seed: int = 0,
        num_conditions: int | None = None,
    ) -> None:
        if samples_per_condition < 1:
            raise ValueError(f"samples_per_condition must be at least 1, got {samples_per_condition}")
        world = get_world(robot, task)
        self.num_conditions = len(world.conditions(conditions, seed, num_conditions))
        self.samples_per_condition = samples_per_condition
        self.env = make_env(
            robot,
            task,
            num_envs=self.num_conditions * samples_per_condition,
            pixels=pixels,
            conditions=conditions,
            seed=seed,
            num_conditions=num_conditions,
            shaping=shaping,
            horizon=horizon,
        )
        self.world = self.env.world
        self.horizon = self.env.horizon
        self.buffer = ReplayBuffer(storage=LazyTensorStorage(self.env.batch_size[0]), batch_size=1)

    @property
    def name(self) -> str:
        return self.world.name

    @torch.no_grad()
    def rollout(self, policy: TensorDictModuleBase | None = None) -> TensorDictBase:
        """One ``[M * N, T]`` batch of trajectories; the replay buffer then holds exactly these."""
        td = self.env.rollout(self.horizon, policy, break_when_any_done=False)
        self.buffer.empty()
        self.buffer.extend(td.exclude(("task", "pixels"), ("next", "task", "pixels")))
        return td

    def sample(self, policy: TensorDictModuleBase | None = None) -> Samples:
        """Roll ``policy`` out (random actions when None) and return the iteration's samples."""
        rollout = self.rollout(policy)
        N, M = self.samples_per_condition, self.num_conditions
        distance = self.env.final_distance(rollout).reshape(N, M).T
        td = to_condition_major(rollout, M)
        U = td["action"].to(torch.float64)
        return Samples(
            X=state_of(td),
            U=U,
            distance=distance,
            obs=td.select(*POLICY_KEYS, "condition", "step_count", strict=False),
        )
