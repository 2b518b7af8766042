"""Insert a peg, held at the arm's tip, into a slot marked by a black square.

The task gives the arm's last link a 0.1-long peg; the end-effector is the peg's tip.
The slot opens towards the arm's base; the goal is the black square at its bottom.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from modnet.specs import TaskDefinition, yaw_quat

PEG_LENGTH = 0.1


@dataclass(frozen=True)
class Peg(TaskDefinition):
    @property
    def param_dim(self) -> int:
        return 2

    def sample_params(self, rng: np.random.Generator) -> np.ndarray:
        return self.sample_points(rng, 1, 0.0, region=(-0.7, 0.7, 0.45, 0.95)).reshape(-1)

    def apply_params(self, data, index, params: np.ndarray) -> None:
        hole = index.mocap("hole")
        data.mocap_pos[hole, :2] = params
        data.mocap_quat[hole] = yaw_quat(np.arctan2(-params[1], -params[0]))

    def decorate_arm(self, arm) -> str:
        tip = arm.find("site", "tip")
        x = float(tip.pos[0])
        tip.parent.add(
            "geom",
            name="peg",
            type="capsule",
            size=[0.015],
            fromto=[x, 0, 0, x + PEG_LENGTH, 0, 0],
            rgba=[0.9, 0.5, 0.1, 1],
        )
        tip.parent.add("site", name="peg_tip", pos=[x + PEG_LENGTH + 0.015, 0, 0], size=[0.01])
        return "peg_tip"


TASKS = {
    "peg": Peg(
        name="peg",
        scene="peg.xml",
        observables=(("ee", "pos"), ("ee", "vel"), ("hole", "pos")),
        moved="ee",
        goal="hole",
        horizon=100,
        success_distance=0.05,
    )
}
