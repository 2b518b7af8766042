"""Worlds: a robot (arm MJCF) attached to a task scene, compiled once, plus its conditions.

:func:`get_world` returns the cached :class:`World` of a (robot, task) pair: the compiled
``mujoco.MjModel``, where the robot and task states sit in ``MjData.sensordata``, how to
put an ``MjData`` into an initial condition, and the world's torch cost.
:func:`make_world` wraps it as a dm_control ``control.Environment`` (what TorchRL's
``DMControlWrapper`` accepts); :func:`modnet.make_env` steps many copies of the same
compiled model with raw ``mujoco`` calls.

Examples:
    >>> import modnet
    >>> world = modnet.get_world("three_link", "reach_red")
    >>> world.robot.state_dim, world.task.state_dim, world.task.horizon
    (6, 12, 50)
    >>> world.conditions("train").shape  # 4 conditions: 3 joint angles + 4 block positions
    (4, 11)
"""

from __future__ import annotations

import collections
import functools
from dataclasses import dataclass

import mujoco
import numpy as np
import torch
from dm_control import mjcf
from dm_control.rl import control
from dm_control.suite import base
from dm_env import specs as dm_specs

from modnet.domains.arms import ARMS
from modnet.domains.tasks import TASKS as _TASKS
from modnet.specs import CONTROL_SUBSTEPS, TORQUE_LIMIT, RobotSpec, TaskDefinition

ROBOTS: tuple[str, ...] = tuple(ARMS)
TASKS: tuple[str, ...] = tuple(_TASKS)
CONDITION_SETS = ("train", "test", "random")
NUM_FIXED_CONDITIONS = 4  # train and test sets, as in the paper
_SPLIT_STREAM = {name: i for i, name in enumerate(CONDITION_SETS)}
#: the random stream of the scenes rendered to pretrain vision modules (modnet.pretrain),
#: apart from every condition set's, so no evaluation scene is ever a pretraining one
SCENE_STREAM = len(_SPLIT_STREAM)


def robot_spec(name: str) -> RobotSpec:
    """The :class:`~modnet.specs.RobotSpec` of an arm; ``ValueError`` naming the valid ones."""
    if name not in ARMS:
        raise ValueError(f"unknown robot {name!r}; valid robots: {', '.join(ROBOTS)}")
    return ARMS[name]


def task_spec(name: str) -> TaskDefinition:
    """The :class:`~modnet.specs.TaskDefinition` of a task; ``ValueError`` naming the valid ones."""
    if name not in _TASKS:
        raise ValueError(f"unknown task {name!r}; valid tasks: {', '.join(TASKS)}")
    return _TASKS[name]


class SceneIndex:
    """Looks up a compiled model's mocap bodies and joints by their MJCF names."""

    def __init__(self, model: mujoco.MjModel):
        self._model = model

    def mocap(self, body: str) -> int:
        return int(self._model.body(body).mocapid[0])

    def qpos(self, joint: str) -> int:
        return int(self._model.jnt_qposadr[self._model.joint(joint).id])


def _compose(robot: RobotSpec, task: TaskDefinition) -> tuple[mjcf.RootElement, int]:
    """Attach the arm to the scene and add the sensors the states are read from.

    Returns the MJCF root and the number of robot sensor values (they come first).
    """
    arena = mjcf.from_path(str(task.scene_path))
    arm = mjcf.from_path(str(robot.xml_path))
    arm.model = "robot"  # joint names become "robot/joint0", ... for every arm
    ee_site = task.decorate_arm(arm) or "tip"
    arena.find("site", "arm_base").attach(arm)

    joints = [arm.find("joint", f"joint{i}") for i in range(robot.n_joints)]
    for joint in joints:
        arena.sensor.add("jointpos", name=f"q_{joint.name}", joint=joint)
    for joint in joints:
        arena.sensor.add("jointvel", name=f"qd_{joint.name}", joint=joint)
    for name, kind in task.observables:
        if name == "ee":
            obj, objtype = arm.find("site", ee_site), "site"
        elif arena.find("site", name) is not None:
            obj, objtype = arena.find("site", name), "site"
        else:
            obj, objtype = arena.find("body", name), "xbody"
        sensor = "framepos" if kind == "pos" else "framelinvel"
        arena.sensor.add(sensor, name=f"{name}_{kind}", objtype=objtype, objname=obj)
    return arena, 2 * robot.n_joints


@dataclass(frozen=True)
class World:
    """One compiled (robot, task) world; get it from :func:`get_world`."""

    robot: RobotSpec
    task: TaskDefinition
    xml: str
    model: mujoco.MjModel
    robot_index: np.ndarray  # where the robot state sits in sensordata
    task_index: np.ndarray  # where the task state sits in sensordata (x, y of each 3-vector)

    @property
    def name(self) -> str:
        return f"{self.robot.name}/{self.task.name}"

    @property
    def state_dim(self) -> int:
        return self.robot.state_dim + self.task.state_dim

    @property
    def state_labels(self) -> tuple[str, ...]:
        """A name for each entry of the state ``[robot_state, task_state]``, for messages: the
        sensor it is read from (as :func:`_compose` names them), with its axis for 3-vectors.

        Examples:
            >>> get_world("three_link", "push").state_labels[2:8]
            ('q_joint2', 'qd_joint0', 'qd_joint1', 'qd_joint2', 'ee_pos_x', 'ee_pos_y')
        """
        m = self.model
        labels = []
        for index in (*self.robot_index, *self.task_index):
            sensor = int(np.searchsorted(m.sensor_adr, index, side="right")) - 1
            name, offset = m.sensor(sensor).name, int(index - m.sensor_adr[sensor])
            labels.append(name if m.sensor_dim[sensor] == 1 else f"{name}_{'xyz'[offset]}")
        return tuple(labels)

    @property
    def param_dim(self) -> int:
        return self.robot.n_joints + self.task.param_dim

    def conditions(self, split: str = "train", seed: int = 0, n: int | None = None) -> np.ndarray:
        """Initial conditions ``[n, n_joints + task.param_dim]``: arm angles, then the task's placements.

        ``"train"`` and ``"test"`` hold 4 conditions each (a larger ``n`` extends a set; its
        first 4 stay the same); ``"random"`` draws ``n`` (default 4) from a third stream.  All
        are deterministic per ``seed``; object placements do not depend on the robot, so
        condition ``i`` of a task is the same scene for every arm.
        """
        if split not in CONDITION_SETS:
            raise ValueError(f"unknown condition set {split!r}; valid sets: {', '.join(CONDITION_SETS)}")
        if split != "random" and n is not None and n < NUM_FIXED_CONDITIONS:
            raise ValueError(f"the {split!r} set has at least {NUM_FIXED_CONDITIONS} conditions, not {n}")
        n = NUM_FIXED_CONDITIONS if n is None else n
        if n < 1:
            raise ValueError(f"need at least one condition, got n={n}")
        stream = _SPLIT_STREAM[split]
        task_rng = np.random.default_rng([seed, stream, 0])
        arm_rng = np.random.default_rng([seed, stream, 1])
        params = np.stack(
            [
                np.concatenate([self.robot.sample_qpos(arm_rng), self.task.sample_params(task_rng)])
                for _ in range(n)
            ]
        )
        if params.shape[-1] != self.param_dim:  # a task definition out of step with its layout
            raise ValueError(f"{self.name}: conditions of size {params.shape[-1]}, declared {self.param_dim}")
        return params

    def reset_data(self, data: mujoco.MjData, params: np.ndarray) -> None:
        """Put ``data`` into the initial condition ``params`` (arm at rest) and run the forward pass."""
        mujoco.mj_resetData(self.model, data)
        data.qpos[: self.robot.n_joints] = params[: self.robot.n_joints]
        self.task.apply_params(data, SceneIndex(self.model), params[self.robot.n_joints :])
        mujoco.mj_forward(self.model, data)

    def step_data(self, data: mujoco.MjData, substeps: int = CONTROL_SUBSTEPS) -> None:
        """Advance one control step (``data.ctrl`` already set) and leave positions up to date.

        Same arithmetic as dm_control's ``Physics.step``: the first half-step reuses the
        forward pass done at the end of the previous step, so ``sensordata`` always
        describes the current state.
        """
        mujoco.mj_step2(self.model, data)
        if substeps > 1:
            mujoco.mj_step(self.model, data, substeps - 1)
        mujoco.mj_step1(self.model, data)

    def observe(self, sensordata: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Split ``sensordata`` (``[..., nsensordata]``) into robot and task states."""
        return sensordata[..., self.robot_index], sensordata[..., self.task_index]

    def cost(
        self,
        robot_state: torch.Tensor,
        task_state: torch.Tensor,
        action: torch.Tensor,
        shaping: bool = True,
    ) -> torch.Tensor:
        """``c(x, u) = c_robot(robot_state, u) + c_task(task_state)``, differentiable, batched."""
        return self.robot.cost(robot_state, action) + self.task.cost(task_state, shaping)

    def state_cost(self, x: torch.Tensor, u: torch.Tensor, shaping: bool = True) -> torch.Tensor:
        """The same cost on the full state ``x = [robot_state, task_state]``."""
        split = self.robot.state_dim
        return self.cost(x[..., :split], x[..., split:], u, shaping)


@functools.cache
def get_world(robot: str, task: str) -> World:
    """The compiled world of ``robot`` doing ``task`` (cached: one compilation per pair)."""
    robot_def, task_def = robot_spec(robot), task_spec(task)
    arena, n_robot = _compose(robot_def, task_def)
    xml = arena.to_xml_string()
    model = mujoco.MjModel.from_xml_string(xml, arena.get_assets())
    task_sensors = n_robot + 3 * np.arange(len(task_def.observables))
    task_index = np.stack([task_sensors, task_sensors + 1], -1).reshape(-1)
    return World(robot_def, task_def, xml, model, np.arange(n_robot), task_index)


class WorldTask(base.Task):
    """dm_control task over a :class:`World`: episodes cycle through the given conditions."""

    def __init__(self, world: World, conditions: np.ndarray, shaping: bool = True, random=None):
        super().__init__(random=random)
        self._world, self._conditions, self._shaping = world, conditions, shaping
        self._episode = 0

    def initialize_episode(self, physics) -> None:
        params = self._conditions[self._episode % len(self._conditions)]
        self._episode += 1
        self._world.reset_data(physics.data.ptr, params)

    def action_spec(self, physics):
        n = self._world.robot.action_dim
        return dm_specs.BoundedArray((n,), np.float64, -TORQUE_LIMIT, TORQUE_LIMIT, name="action")

    def before_step(self, action, physics) -> None:
        physics.set_control(np.clip(action, -TORQUE_LIMIT, TORQUE_LIMIT))

    def get_observation(self, physics) -> collections.OrderedDict:
        robot_state, task_state = self._world.observe(physics.data.sensordata)
        return collections.OrderedDict(robot_state=robot_state.copy(), task_state=task_state.copy())

    def get_reward(self, physics) -> float:
        robot_state, task_state = self._world.observe(physics.data.sensordata)
        as_tensor = lambda a: torch.as_tensor(np.array(a), dtype=torch.float64)
        cost = self._world.cost(
            as_tensor(robot_state), as_tensor(task_state), as_tensor(physics.data.ctrl), self._shaping
        )
        return -float(cost)


def make_world(
    robot: str,
    task: str,
    conditions: str = "train",
    seed: int = 0,
    num_conditions: int | None = None,
    shaping: bool = True,
    horizon: int | None = None,
) -> control.Environment:
    """A dm_control ``control.Environment`` of ``robot`` doing ``task``.

    Episodes last the task's horizon (or ``horizon``) control steps of 0.05 s and cycle
    through the chosen condition set.  The reference path; :func:`modnet.make_env` is fast.

    Examples:
        >>> from torchrl.envs import DMControlWrapper
        >>> env = DMControlWrapper(make_world("three_link", "reach"))
        >>> env.rollout(3)["next", "task_state"].shape
        torch.Size([3, 6])
    """
    world = get_world(robot, task)
    params = world.conditions(conditions, seed, num_conditions)
    physics = mjcf.Physics.from_xml_string(world.xml)
    steps = horizon or world.task.horizon
    return control.Environment(
        physics,
        WorldTask(world, params, shaping),
        time_limit=steps * CONTROL_SUBSTEPS * world.model.opt.timestep,
        n_sub_steps=CONTROL_SUBSTEPS,
    )
