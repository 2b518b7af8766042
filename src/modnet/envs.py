"""The batched TorchRL environment: B copies of one compiled world, stepped with raw ``mujoco``.

This is the hot path of guided policy search (thousands of short fixed-horizon rollouts
from fixed initial conditions), so the step loop holds nothing but ``mujoco`` calls on
``B`` ``MjData`` copies of one ``MjModel``; observations are read in one go from each
copy's ``sensordata`` and the reward is the world's torch cost, batched.
"""

from __future__ import annotations

import atexit
import gc
import os
import weakref
from concurrent.futures import ThreadPoolExecutor

import mujoco
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from modnet.render_process import RenderProcess, render_positions
from modnet.specs import EE_DIM, PIXELS_SHAPE, TORQUE_LIMIT
from modnet.worlds import CONDITION_SETS, World, get_world

_OPEN_RENDERERS: weakref.WeakSet = weakref.WeakSet()
CAMERA = "top"  # the camera every scene defines and a vision policy sees through
FINAL_STEPS = 5  # the paper's metric: the task's distance averaged over the last 5 steps


def _close_open_renderers() -> None:
    for renderer in list(_OPEN_RENDERERS):
        renderer.close()


class Renderer(mujoco.Renderer):
    """``mujoco.Renderer`` that frees its GL objects in its own GL context.

    mujoco's ``close`` (also run when a renderer is garbage-collected) frees the rendering
    context in whichever GL context is current.  Once a newer renderer exists, that is the
    newer one's: its framebuffer is deleted and it draws black frames from then on.  So a
    pixel env dropped after another was made (``benchmarks/score_bank.py`` scoring world
    after world, a fine-tuning start after the previous one) blinded the live one.
    """

    def close(self) -> None:
        context = getattr(self, "_gl_context", None)  # None after close, or without a GL backend
        if context is not None:
            context.make_current()
        super().close()


def open_renderer(model: mujoco.MjModel, height: int, width: int) -> mujoco.Renderer:
    """A :class:`Renderer` that is closed at exit before mujoco tears its EGL display down.

    Unreachable renderers are collected first: freeing one releases the thread's current
    GL context, and a collection that ran in the middle of building the new renderer
    (between making its context current and creating its rendering context) would leave
    it drawing black frames.
    """
    gc.collect()
    renderer = Renderer(model, height, width)
    if not _OPEN_RENDERERS:
        # registered after mujoco's own exit hook, so it runs first (atexit is last-in first-out)
        atexit.unregister(_close_open_renderers)
        atexit.register(_close_open_renderers)
    _OPEN_RENDERERS.add(renderer)
    return renderer


class WorldEnv(EnvBase):
    """``num_envs`` copies of the world ``robot``/``task``, each reset to an initial condition.

    Copy ``i`` starts from condition ``i % num_conditions`` of the chosen set unless the
    reset tensordict carries a ``"condition"`` entry.  An episode lasts the task's horizon
    ``T`` (or ``horizon``) control steps, then ``truncated`` and ``done`` are set.

    Keys: ``("robot", "state")`` joint angles and velocities; ``("task", "state")``
    end-effector and object/target/goal positions (and velocities); when ``pixels=True``,
    ``("task", "pixels")`` uint8 ``64x80x3`` from the top camera and ``("task", "ee")``, the
    end-effector's position and velocity (what a vision policy may read besides the image:
    the state of the targets and objects is for the trajectory optimiser only); ``"condition"``;
    ``"step_count"``; ``"action"`` (torques, clipped to +-2); ``"reward"`` = -cost of the
    reached state and the action.

    The copies are stepped on ``num_threads`` threads (default: up to 2, one per 8 copies);
    results do not depend on the number of threads.  Their frames are drawn in this process
    and ``render_processes`` others (:class:`~modnet.render_process.RenderProcess`; default:
    one per 16 copies, up to one less than the cores and at most 3), with the same pixels.

    Examples:
        >>> env = WorldEnv("four_link", "reach_black", num_envs=8)
        >>> td = env.rollout(50)
        >>> td["next", "robot", "state"].shape, td["next", "task", "state"].shape
        (torch.Size([8, 50, 8]), torch.Size([8, 50, 12]))
        >>> bool(td["next", "done"][:, -1].all())
        True
    """

    def __init__(
        self,
        robot: str,
        task: str,
        num_envs: int = 1,
        pixels: bool = False,
        conditions: str = "train",
        seed: int = 0,
        num_conditions: int | None = None,
        shaping: bool = True,
        horizon: int | None = None,
        num_threads: int | None = None,
        render_processes: int | None = None,
    ):
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if horizon is not None and horizon < 1:
            raise ValueError(f"horizon must be at least 1, got {horizon}")
        if conditions not in CONDITION_SETS:
            raise ValueError(f"unknown condition set {conditions!r}; valid sets: {', '.join(CONDITION_SETS)}")
        if render_processes is not None and (not isinstance(render_processes, int) or render_processes < 0):
            raise ValueError(f"render_processes must be a non-negative integer, got {render_processes!r}")
        if render_processes and not pixels:
            raise ValueError("render_processes draw frames: they need pixels=True")
        self.world: World = get_world(robot, task)
        self.condition_params = self.world.conditions(conditions, seed, num_conditions)
        self.horizon = horizon or self.world.task.horizon
        self.shaping = shaping
        self.pixels = pixels
        super().__init__(batch_size=torch.Size([num_envs]), device="cpu")

        model = self.world.model
        self._datas = [mujoco.MjData(model) for _ in range(num_envs)]
        self._sensordata = np.zeros((num_envs, model.nsensordata))
        self._condition = np.arange(num_envs) % len(self.condition_params)
        self._step_count = np.zeros(num_envs, dtype=np.int64)
        self._renderer = open_renderer(model, *PIXELS_SHAPE[:2]) if pixels else None
        self._picture_renderers: dict[tuple[int, int], mujoco.Renderer] = {}  # render_frames' sizes
        self._frames = np.zeros((num_envs, *PIXELS_SHAPE), dtype=np.uint8) if pixels else None
        self._camera = CAMERA
        if render_processes is None:
            render_processes = min((os.cpu_count() or 1) - 1, num_envs // 16, 3) if pixels else 0
        self._render_processes = [
            RenderProcess(model, self._camera, *PIXELS_SHAPE[:2], name=self.world.name)
            for _ in range(render_processes)
        ]
        for process in self._render_processes:
            weakref.finalize(self, process.close)
        task_def = self.world.task
        self._ee_index = torch.as_tensor(np.r_[task_def.slot("ee", "pos"), task_def.slot("ee", "vel")])
        # mujoco releases the GIL while stepping: split the copies over a few threads
        threads = num_threads or min(2, os.cpu_count() or 1, max(1, num_envs // 8))
        self._chunks = np.array_split(np.arange(num_envs), threads)
        self._pool = ThreadPoolExecutor(threads, "modnet-physics") if threads > 1 else None
        if self._pool is not None:
            weakref.finalize(self, self._pool.shutdown)
        self._make_specs()

    # --- specs ---------------------------------------------------------------------------
    def _make_specs(self) -> None:
        B = self.batch_size
        robot, task = self.world.robot, self.world.task
        task_spec = Composite(state=Unbounded((*B, task.state_dim)), shape=B)
        if self.pixels:
            task_spec["pixels"] = Bounded(0, 255, (*B, *PIXELS_SHAPE), dtype=torch.uint8)
            task_spec["ee"] = Unbounded((*B, EE_DIM))
        self.observation_spec = Composite(
            robot=Composite(state=Unbounded((*B, robot.state_dim)), shape=B),
            task=task_spec,
            condition=Bounded(0, len(self.condition_params) - 1, B, dtype=torch.int64),
            step_count=Bounded(0, self.horizon, (*B, 1), dtype=torch.int64),
            shape=B,
        )
        self.action_spec = Bounded(-TORQUE_LIMIT, TORQUE_LIMIT, (*B, robot.action_dim))
        self.reward_spec = Unbounded((*B, 1))
        self.done_spec = Composite(
            done=Categorical(2, (*B, 1), dtype=torch.bool),
            terminated=Categorical(2, (*B, 1), dtype=torch.bool),
            truncated=Categorical(2, (*B, 1), dtype=torch.bool),
            shape=B,
        )

    # --- the hot path -----------------------------------------------------------------------
    def _observation(self) -> TensorDict:
        robot_state, task_state = self.world.observe(self._sensordata)
        task = {"state": torch.as_tensor(task_state, dtype=torch.float32)}
        if self.pixels:
            task["pixels"] = torch.from_numpy(self._frames.copy())
            task["ee"] = task["state"][:, self._ee_index]
        return TensorDict(
            {
                "robot": {"state": torch.as_tensor(robot_state, dtype=torch.float32)},
                "task": task,
                "condition": torch.from_numpy(self._condition.copy()),
                "step_count": torch.from_numpy(self._step_count[:, None].copy()),
            },
            batch_size=self.batch_size,
        )

    def _render(self, indices) -> None:
        if self._renderer is None:
            return
        indices = np.asarray(indices, dtype=np.int64)
        own, *shares = np.array_split(indices, 1 + len(self._render_processes))
        for process, share in zip(self._render_processes, shares, strict=True):
            process.submit(render_positions([self._datas[i] for i in share]))
        for i in own:  # GL work stays on this thread
            self._renderer.update_scene(self._datas[i], camera=self._camera)
            self._renderer.render(out=self._frames[i])
        for process, share in zip(self._render_processes, shares, strict=True):
            self._frames[share] = process.collect()

    def _advance(self, indices: np.ndarray, controls: np.ndarray) -> None:
        for i in indices:
            data = self._datas[i]
            data.ctrl[:] = controls[i]
            self.world.step_data(data)
            self._sensordata[i] = data.sensordata

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = np.ones(self.batch_size[0], dtype=bool)
        if tensordict is not None:
            if "_reset" in tensordict.keys():
                mask = tensordict["_reset"].reshape(-1).numpy()
            if "condition" in tensordict.keys():
                chosen = tensordict["condition"].reshape(-1).numpy()
                if chosen.min() < 0 or chosen.max() >= len(self.condition_params):
                    raise ValueError(f"condition out of range: valid are 0..{len(self.condition_params) - 1}")
                self._condition[mask] = chosen[mask]
        reset = np.flatnonzero(mask)
        for i in reset:
            data = self._datas[i]
            self.world.reset_data(data, self.condition_params[self._condition[i]])
            self._sensordata[i] = data.sensordata
        self._render(reset)
        self._step_count[mask] = 0
        out = self._observation()
        out.update(self.full_done_spec.zero())
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict["action"]
        if action.shape != self.action_spec.shape:
            raise ValueError(
                f"action of shape {tuple(action.shape)} for {self.world.name}: "
                f"expected {tuple(self.action_spec.shape)} (num_envs, action_dim)"
            )
        action = action.clamp(-TORQUE_LIMIT, TORQUE_LIMIT)
        controls = action.detach().numpy().astype(np.float64)
        if self._pool is None:
            self._advance(self._chunks[0], controls)
        else:
            for future in [self._pool.submit(self._advance, c, controls) for c in self._chunks]:
                future.result()
        self._render(range(len(self._datas)))
        self._step_count += 1
        out = self._observation()
        cost = self.world.cost(out["robot", "state"], out["task", "state"], action, self.shaping)
        truncated = torch.from_numpy(self._step_count >= self.horizon)[:, None]
        out["reward"] = -cost.to(torch.float32)[:, None]
        out["done"] = truncated.clone()
        out["truncated"] = truncated
        out["terminated"] = torch.zeros_like(truncated)
        return out

    def _set_seed(self, seed: int | None) -> None:
        # The dynamics are deterministic; the seed only chose the condition sets.
        return None

    def close(self, *, raise_if_closed: bool = True) -> None:
        """End the render processes (frames are drawn here from then on), then close as TorchRL does."""
        for process in getattr(self, "_render_processes", []):  # a half-built env has none
            process.close()
        self._render_processes = []
        super().close(raise_if_closed=raise_if_closed)

    @property
    def num_render_processes(self) -> int:
        """How many processes besides this one draw the frames (0 without pixels)."""
        return len(self._render_processes)

    # --- for evaluation and pictures --------------------------------------------------------------
    def final_distance(self, rollout: TensorDictBase, last: int = FINAL_STEPS) -> torch.Tensor:
        """The paper's metric: the task's distance averaged over the last ``last`` steps, ``[B]``.

        ``rollout`` is a ``[B, T]`` tensordict from :meth:`rollout` (its ``"next"`` states).
        """
        task_state = rollout["next", "task", "state"].to(torch.float64)
        return self.world.task.distance(task_state)[:, -last:].mean(-1)

    def start_distance(self, rollout: TensorDictBase) -> torch.Tensor:
        """The task's distance at the rollout's first state, ``[B]``: where an object nobody
        touches stays (for reaching, where the arm starts)."""
        task_state = rollout["task", "state"][:, 0].to(torch.float64)
        return self.world.task.distance(task_state)

    def render_frames(self, height: int = PIXELS_SHAPE[0], width: int = PIXELS_SHAPE[1]) -> np.ndarray:
        """RGB frames ``[B, height, width, 3]`` of every copy from the top camera."""
        if (height, width) not in self._picture_renderers:
            self._picture_renderers[height, width] = open_renderer(self.world.model, height, width)
        renderer = self._picture_renderers[height, width]
        frames = []
        for data in self._datas:
            renderer.update_scene(data, camera=self._camera)
            frames.append(renderer.render())
        return np.stack(frames)


def make_env(
    robot: str,
    task: str,
    num_envs: int = 1,
    pixels: bool = False,
    conditions: str = "train",
    seed: int = 0,
    num_conditions: int | None = None,
    shaping: bool = True,
    horizon: int | None = None,
    num_threads: int | None = None,
    render_processes: int | None = None,
) -> WorldEnv:
    """The batched TorchRL environment of ``robot`` doing ``task``; see :class:`WorldEnv`.

    Examples:
        >>> env = make_env("three_link", "reach_red", num_envs=4, conditions="test")
        >>> env.rollout(5)["next", "reward"].shape
        torch.Size([4, 5, 1])
    """
    return WorldEnv(
        robot, task, num_envs, pixels, conditions, seed, num_conditions, shaping, horizon, num_threads,
        render_processes,
    )
