"""Drawers: pull one out horizontally, or push one up vertically, to a marked target.

The cabinet is placed per condition; the drawer slides on a damped joint (0 = shut,
0.3 = fully open).  The goal is where the handle must end up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from modnet.specs import TaskDefinition, yaw_quat


@dataclass(frozen=True)
class Drawer(TaskDefinition):
    #: world direction the drawer opens towards: -x (pull horizontally) or -y (pushed up to close)
    opens_towards: str = "-x"

    @property
    def param_dim(self) -> int:
        return 4  # cabinet front (x, y), initial opening, target opening

    @property
    def _axis(self) -> np.ndarray:
        return np.array([-1.0, 0.0]) if self.opens_towards == "-x" else np.array([0.0, -1.0])

    def sample_params(self, rng: np.random.Generator) -> np.ndarray:
        if self.opens_towards == "-x":  # cabinet on the right, drawer starts shut, pull it out
            front = np.array([rng.uniform(0.9, 1.0), rng.uniform(0.35, 0.6)])
            start, target = rng.uniform(0.0, 0.05), rng.uniform(0.15, 0.25)
        else:  # cabinet at the top, drawer starts open, push it up
            front = np.array([rng.uniform(-0.3, 0.3), rng.uniform(0.95, 1.05)])
            start, target = rng.uniform(0.2, 0.25), rng.uniform(0.0, 0.08)
        return np.array([front[0], front[1], start, target])

    def apply_params(self, data, index, params: np.ndarray) -> None:
        front, start, target = params[:2], params[2], params[3]
        cabinet = index.mocap("cabinet")
        data.mocap_pos[cabinet, :2] = front
        data.mocap_quat[cabinet] = yaw_quat(np.arctan2(self._axis[1], self._axis[0]))
        data.qpos[index.qpos("drawer_slide")] = start
        handle_at_target = front + (0.04 + target) * self._axis
        data.mocap_pos[index.mocap("drawer_target"), :2] = handle_at_target


def make(name: str, opens_towards: str) -> Drawer:
    return Drawer(
        name=name,
        scene="drawer.xml",
        observables=(
            ("ee", "pos"),
            ("ee", "vel"),
            ("handle", "pos"),
            ("handle", "vel"),
            ("drawer_target", "pos"),
        ),
        moved="handle",
        goal="drawer_target",
        horizon=100,
        success_distance=0.05,
        shaping_weight=0.5,
        opens_towards=opens_towards,
    )


TASKS = {
    "drawer_horizontal": make("drawer_horizontal", "-x"),
    "drawer_vertical": make("drawer_vertical", "-y"),
}
