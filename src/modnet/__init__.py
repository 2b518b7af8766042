"""modnet: modular policy networks (Devin et al., ICRA 2017) on TorchRL.

A policy for robot ``r`` doing task ``k`` is ``f_r(g_k(o_task), o_robot)``: task modules
are shared by every robot, robot modules by every task.

Examples:
    >>> import modnet
    >>> modnet.ROBOTS
    ('three_link', 'three_link_short', 'four_link', 'five_link')
    >>> env = modnet.make_env("four_link", "reach_black", num_envs=8)
    >>> env.batch_size
    torch.Size([8])
"""

import os
import sys


def _default_to_egl() -> None:
    """Render without a display (Mesa's EGL works on CPUs) unless the user chose a backend."""
    if "MUJOCO_GL" in os.environ:
        return
    os.environ["MUJOCO_GL"] = "egl"
    if "mujoco" in sys.modules and sys.platform.startswith("linux"):
        # mujoco was imported (torchrl does) before the default could be read: switch now
        from mujoco.egl import GLContext
        from mujoco.rendering.classic import gl_context

        gl_context.GLContext = GLContext


_default_to_egl()

__version__ = "0.1.0"

from modnet.bank import BankConfig, BankError, ModuleBank  # noqa: E402
from modnet.envs import WorldEnv, make_env  # noqa: E402
from modnet.worlds import (  # noqa: E402
    ROBOTS,
    TASKS,
    World,
    get_world,
    make_world,
    robot_spec,
    task_spec,
)

__all__ = [
    "BankConfig",
    "BankError",
    "ModuleBank",
    "ROBOTS",
    "TASKS",
    "World",
    "WorldEnv",
    "get_world",
    "make_env",
    "make_world",
    "robot_spec",
    "task_spec",
]
