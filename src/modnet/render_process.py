"""A second process that renders part of a pixel env's frames, so two cores draw at once.

A pixel env spends nearly all of its step drawing (llvmpipe: about 3.8 ms a 64x80 frame, the
physics 0.03 ms), and ``mujoco.Renderer`` holds the GIL while it draws, so threads cannot
share the work.  A :class:`RenderProcess` owns a copy of the world's model and a renderer of
its own in a child process; the env sends it the positions of the copies it should draw
(joint positions and mocap poses, all a frame depends on), draws its own share meanwhile,
then reads the child's frames back.  The frames are the very pixels the env would draw
itself: same model, same renderer, same camera, the same forward pass from the same positions.

The child is this file run as a script: it imports ``mujoco`` and ``numpy`` only (no torch),
talks over its stdin and stdout, and exits when its stdin closes (also when the parent dies).

Examples:
    >>> import numpy as np
    >>> from modnet.envs import make_env
    >>> env = make_env("three_link", "reach_red", num_envs=4, pixels=True, render_processes=1)
    >>> env.reset()["task", "pixels"].shape
    torch.Size([4, 64, 80, 3])
    >>> own = make_env("three_link", "reach_red", num_envs=4, pixels=True, render_processes=0)
    >>> bool(np.array_equal(own.reset()["task", "pixels"].numpy(), env.reset()["task", "pixels"].numpy()))
    True
"""

from __future__ import annotations

import os
import sys

_HERE = os.path.dirname(os.path.abspath(__file__))
if __name__ == "__main__" and sys.path and os.path.abspath(sys.path[0]) == _HERE:
    del sys.path[0]  # run as a script: keep modnet's own module names (specs, files...) off the path

import pickle  # noqa: E402 (after the path fix above)
import struct  # noqa: E402 (after the path fix above)
import subprocess  # noqa: E402 (after the path fix above)

import mujoco  # noqa: E402 (after the path fix above)
import numpy as np  # noqa: E402 (after the path fix above)

_COUNT = struct.Struct("<q")  # frames asked for in one request


def _read_exactly(stream, size: int) -> bytes:
    chunks, left = [], size
    while left:
        chunk = stream.read(left)
        if not chunk:
            raise EOFError
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def render_positions(datas) -> np.ndarray:
    """What a frame depends on, one row per copy: joint positions, then mocap positions and quaternions."""
    return np.stack([np.concatenate([d.qpos, d.mocap_pos.ravel(), d.mocap_quat.ravel()]) for d in datas])


def set_render_positions(model: mujoco.MjModel, data: mujoco.MjData, row: np.ndarray) -> None:
    """The inverse of :func:`render_positions` for one copy, then the position stage a frame reads."""
    nq, nmocap = model.nq, model.nmocap
    data.qpos[:] = row[:nq]
    data.mocap_pos[:] = row[nq : nq + 3 * nmocap].reshape(nmocap, 3)
    data.mocap_quat[:] = row[nq + 3 * nmocap :].reshape(nmocap, 4)
    mujoco.mj_fwdPosition(model, data)


class RenderProcess:
    """A child process drawing frames of ``model`` from ``camera``, ``height`` x ``width``.

    :meth:`submit` sends it positions (one row per copy, as :func:`render_positions` lays them out)
    and returns at once; :meth:`collect` waits for the frames, ``[n, height, width, 3]`` uint8.
    """

    def __init__(self, model: mujoco.MjModel, camera: str, height: int, width: int, name: str = "") -> None:
        self.name = name or "a pixel env"
        self.frame_shape = (height, width, 3)
        self._pending = 0
        self._child = subprocess.Popen(
            [sys.executable, os.path.abspath(__file__)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")},
        )
        self._send(pickle.dumps((model, camera, height, width)))
        self._expect_ready()

    def _send(self, payload: bytes) -> None:
        try:
            self._child.stdin.write(_COUNT.pack(len(payload)) + payload)
            self._child.stdin.flush()
        except (BrokenPipeError, ValueError) as error:  # the child is gone (ValueError: stdin closed)
            raise self._died("died") from error

    def _died(self, what: str) -> RuntimeError:
        return RuntimeError(f"the render process of {self.name} {what} (exit code {self._child.wait()})")

    def _expect_ready(self) -> None:
        try:
            _read_exactly(self._child.stdout, 1)
        except EOFError as error:
            raise self._died("did not start") from error

    def submit(self, positions: np.ndarray) -> None:
        """Ask for the frames of ``positions`` (``[n, nq + 7 nmocap]`` float64)."""
        positions = np.ascontiguousarray(positions, dtype=np.float64)
        self._send(positions.tobytes())
        self._pending = len(positions)

    def collect(self) -> np.ndarray:
        """The frames of the last :meth:`submit`, ``[n, height, width, 3]`` uint8."""
        n, self._pending = self._pending, 0
        try:
            raw = _read_exactly(self._child.stdout, n * int(np.prod(self.frame_shape)))
        except EOFError as error:
            raise self._died("died") from error
        return np.frombuffer(raw, dtype=np.uint8).reshape(n, *self.frame_shape)

    def close(self) -> None:
        """End the child (it exits when its stdin closes)."""
        if self._child.poll() is None:
            try:
                self._child.stdin.close()
            except OSError:
                pass
            try:
                self._child.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self._child.kill()
                self._child.wait()
        if self._child.stdout is not None:
            self._child.stdout.close()


def _serve(stdin, stdout) -> None:
    """The child's loop: read the model, then draw each request's frames until stdin closes."""
    (size,) = _COUNT.unpack(_read_exactly(stdin, _COUNT.size))
    model, camera, height, width = pickle.loads(_read_exactly(stdin, size))
    data = mujoco.MjData(model)
    renderer = mujoco.Renderer(model, height, width)
    row = model.nq + 7 * model.nmocap
    stdout.write(b"r")
    stdout.flush()
    while True:
        try:
            (size,) = _COUNT.unpack(_read_exactly(stdin, _COUNT.size))
            rows = np.frombuffer(_read_exactly(stdin, size), dtype=np.float64).reshape(-1, row)
        except EOFError:
            break
        frames = np.empty((len(rows), height, width, 3), dtype=np.uint8)
        for i, positions in enumerate(rows):
            set_render_positions(model, data, positions)
            renderer.update_scene(data, camera=camera)
            renderer.render(out=frames[i])
        stdout.write(frames.tobytes())  # all at once: the parent reads after drawing its own share
        stdout.flush()
    renderer.close()


if __name__ == "__main__":
    _serve(sys.stdin.buffer, sys.stdout.buffer)
