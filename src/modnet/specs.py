"""What a robot and a task are, independent of any simulator object.

A world is a (robot, task) pair.  Its full state is ``x = [robot_state, task_state]``:

* ``robot_state`` (intrinsic, paper section "Preliminaries"): the arm's joint
  angles then joint velocities, ``2 * n_joints`` numbers.
* ``task_state`` (extrinsic): planar (x, y) positions and velocities of the
  end-effector and of the task's objects, targets and goals, in the order the task
  lists its :attr:`TaskDefinition.observables`.  Its size depends on the task only,
  so one task module serves every robot.

Its cost splits the same way, ``c(x, u) = c_robot(robot_state, u) + c_task(task_state)``;
both terms are differentiable torch functions (guided policy search differentiates them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Literal

import numpy as np
import torch

PIXELS_SHAPE = (64, 80, 3)  # (H, W, C), as in the paper's 80x64 RGB images
#: what a vision policy reads of the task state: the end-effector's position and velocity
#: (the paper feeds the end-effector to the task module; targets and objects come from pixels)
EE_DIM = 4
CONTROL_SUBSTEPS = 5  # physics dt 0.01, control dt 0.05
TORQUE_LIMIT = 2.0

Observable = tuple[str, str]  # (element name, "pos" | "vel"); "ee" is the end-effector


def _domain_file(kind: str, name: str) -> Path:
    # `domains/` ships as the package `modnet.domains` (see pyproject.toml), editable or not.
    return Path(str(resources.files(f"modnet.domains.{kind}") / name))


def distance_cost(
    offset: torch.Tensor,
    l2: float = 1.0,
    l1: float = 0.0,
    alpha: float = 1e-5,
    norm: Literal["l1l2", "log"] = "l1l2",
) -> torch.Tensor:
    """GPS's distance costs over the last dim, ``0.5 l2 |d|^2`` plus a term sharp at ``d = 0``.

    ``"l1l2"``: ``l1 sqrt(alpha + |d|^2)`` (convex: a smoothed L1 pull that stays strong
    near the goal); ``"log"``: ``0.5 l1 log(alpha + |d|^2)`` (concave near the goal, so
    the LQR must repair its Hessian there).

    Examples:
        >>> distance_cost(torch.tensor([[3.0, 4.0]]))
        tensor([12.5000])
        >>> distance_cost(torch.tensor([[3.0, 4.0]]), l2=0.0, l1=1.0, alpha=0.0)
        tensor([5.])
    """
    sq = offset.pow(2).sum(-1)
    cost = 0.5 * l2 * sq
    if l1 and norm == "l1l2":
        cost = cost + l1 * torch.sqrt(alpha + sq)
    elif l1 and norm == "log":
        cost = cost + 0.5 * l1 * torch.log(alpha + sq)
    elif l1:
        raise ValueError(f"unknown distance norm {norm!r}; valid: l1l2, log")
    return cost


@dataclass(frozen=True)
class RobotSpec:
    """A planar torque-controlled arm (``domains/arms/<name>.xml``).

    Examples:
        >>> import modnet
        >>> spec = modnet.robot_spec("four_link")
        >>> spec.state_dim, spec.action_dim
        (8, 4)
    """

    name: str
    link_lengths: tuple[float, ...]
    action_cost_weight: float = 1e-2

    @property
    def n_joints(self) -> int:
        return len(self.link_lengths)

    @property
    def state_dim(self) -> int:
        return 2 * self.n_joints

    @property
    def action_dim(self) -> int:
        return self.n_joints

    @property
    def reach(self) -> float:
        return float(sum(self.link_lengths))

    @property
    def xml_path(self) -> Path:
        return _domain_file("arms", f"{self.name}.xml")

    def cost(self, robot_state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The intrinsic cost term: a torque penalty ``0.5 w_u |u|^2``."""
        del robot_state  # the arms' cost depends on the action only
        return 0.5 * self.action_cost_weight * action.pow(2).sum(-1)

    def joint_points(self, qpos: np.ndarray) -> np.ndarray:
        """Planar forward kinematics: the (x, y) of every joint and of the tip, ``[n + 1, 2]``."""
        angles = np.cumsum(qpos)
        steps = np.stack([np.cos(angles), np.sin(angles)], -1) * np.asarray(self.link_lengths)[:, None]
        return np.concatenate([np.zeros((1, 2)), np.cumsum(steps, 0)], 0)

    def sample_qpos(self, rng: np.random.Generator) -> np.ndarray:
        """An initial arm configuration lying along the +x axis, clear of the workspace (y > 0.3).

        Joint 0 points the arm sideways; the others bend it a little.  Rejection keeps every
        point of the arm below y = 0.15 so no configuration starts in contact with an object.
        """
        while True:
            qpos = np.concatenate([rng.uniform(-0.35, 0.05, 1), rng.uniform(-0.3, 0.3, self.n_joints - 1)])
            if self.joint_points(qpos)[:, 1].max() < 0.15:
                return qpos


@dataclass(frozen=True)
class TaskDefinition:
    """One task: a scene, what it observes, its cost, its evaluation distance and its conditions.

    Subclasses (in ``domains/tasks/``) define :meth:`sample_params` and :meth:`apply_params`;
    the cost and the evaluation distance follow from :attr:`moved` and :attr:`goal`.
    """

    name: str
    scene: str  # file name in domains/tasks/
    observables: tuple[Observable, ...]
    moved: str  # the observable the task moves: "ee" for reaching, else the object
    goal: str  # the observable where ``moved`` must end up
    horizon: int
    success_distance: float
    # distance cost 0.5 l2 |d|^2 + l1 sqrt(alpha + |d|^2) (the GPS MuJoCo examples' weights)
    l2: float = 10.0
    l1: float = 0.1
    shaping_weight: float = 0.0  # 0: the task has no shaping term (relative to l2)
    workspace: tuple[float, float, float, float] = field(default=(-0.6, 0.9, 0.3, 1.0))  # x0, x1, y0, y1

    @property
    def scene_path(self) -> Path:
        return _domain_file("tasks", self.scene)

    @property
    def state_dim(self) -> int:
        return 2 * len(self.observables)

    def slot(self, name: str, kind: str = "pos") -> slice:
        """Where ``(name, kind)`` sits in the task state."""
        i = self.observables.index((name, kind))
        return slice(2 * i, 2 * i + 2)

    def part(self, task_state: torch.Tensor, name: str, kind: str = "pos") -> torch.Tensor:
        return task_state[..., self.slot(name, kind)]

    # --- what subclasses define -------------------------------------------------------
    @property
    def param_dim(self) -> int:
        raise NotImplementedError

    def sample_params(self, rng: np.random.Generator) -> np.ndarray:
        """The task part of one initial condition (object, target and goal placements)."""
        raise NotImplementedError

    def apply_params(self, data, index, params: np.ndarray) -> None:
        """Write ``params`` into a ``mujoco.MjData`` (mocap poses, object joints)."""
        raise NotImplementedError

    def decorate_arm(self, arm) -> str | None:
        """Change the arm's MJCF (e.g. give it a peg); return the end-effector site's name."""
        del arm
        return None

    # --- derived ----------------------------------------------------------------------
    def target_offset(self, task_state: torch.Tensor) -> torch.Tensor:
        """The vector the task drives to zero: what it moves minus where that must go."""
        return self.part(task_state, self.moved) - self.part(task_state, self.goal)

    def shaping_offset(self, task_state: torch.Tensor) -> torch.Tensor:
        """End-effector minus the object it must move (the optional shaping term's offset)."""
        return self.part(task_state, "ee") - self.part(task_state, self.moved)

    def distance(self, task_state: torch.Tensor) -> torch.Tensor:
        """The distance the evaluation reports (paper: averaged over the last 5 steps)."""
        return self.target_offset(task_state).norm(dim=-1)

    def cost(self, task_state: torch.Tensor, shaping: bool = True) -> torch.Tensor:
        """The extrinsic cost term: distance cost to the goal, plus the shaping term if on."""
        cost = distance_cost(self.target_offset(task_state), self.l2, self.l1)
        if shaping and self.shaping_weight:
            shaping_cost = distance_cost(self.shaping_offset(task_state), self.l2, self.l1)
            cost = cost + self.shaping_weight * shaping_cost
        return cost

    # --- helpers for subclasses ---------------------------------------------------------
    def sample_points(
        self, rng: np.random.Generator, n: int, min_separation: float, region=None
    ) -> np.ndarray:
        """``n`` planar points in the reachable workspace, pairwise at least ``min_separation`` apart."""
        x0, x1, y0, y1 = region or self.workspace
        points: list[np.ndarray] = []
        while len(points) < n:
            p = rng.uniform((x0, y0), (x1, y1))
            if not 0.45 <= np.hypot(*p) <= 1.0:
                continue
            if all(np.hypot(*(p - q)) >= min_separation for q in points):
                points.append(p)
        return np.stack(points)


def yaw_quat(angle: float) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation by ``angle`` about +z."""
    return np.array([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)])
