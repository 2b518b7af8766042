"""Push a white block onto a red goal.  The block slides on damped planar joints."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from modnet.specs import TaskDefinition


@dataclass(frozen=True)
class Push(TaskDefinition):
    @property
    def param_dim(self) -> int:
        return 4  # block (x, y), goal (x, y)

    def sample_params(self, rng: np.random.Generator) -> np.ndarray:
        # the goal lies 0.2-0.35 beyond the block, pushing away from or across the base
        while True:
            block = self.sample_points(rng, 1, 0.0, region=(-0.7, 0.7, 0.35, 0.75))[0]
            angle = np.arctan2(block[1], block[0]) + rng.uniform(-0.8, 0.8)
            goal = block + rng.uniform(0.2, 0.35) * np.array([np.cos(angle), np.sin(angle)])
            if np.hypot(*goal) <= 1.0 and goal[1] >= 0.3:
                return np.concatenate([block, goal])

    def apply_params(self, data, index, params: np.ndarray) -> None:
        data.qpos[index.qpos("block_x")] = params[0]
        data.qpos[index.qpos("block_y")] = params[1]
        data.mocap_pos[index.mocap("goal"), :2] = params[2:]


TASKS = {
    "push": Push(
        name="push",
        scene="push.xml",
        observables=(
            ("ee", "pos"),
            ("ee", "vel"),
            ("block", "pos"),
            ("block", "vel"),
            ("goal", "pos"),
        ),
        moved="block",
        goal="goal",
        horizon=100,
        success_distance=0.1,
        shaping_weight=0.5,
    )
}
