"""Frames drawn by render processes are the very pixels the env draws itself."""

import gc

import pytest
import torch
from tensordict import TensorDict

import modnet


def frames_of(env, actions: torch.Tensor) -> torch.Tensor:
    """Every frame of one episode driven by ``actions`` ``[T, B, dU]``, the reset's first."""
    td = env.reset()
    frames = [td["task", "pixels"].clone()]
    for action in actions:
        td["action"] = action
        td = env.step(td)["next"]
        frames.append(td["task", "pixels"].clone())
    return torch.stack(frames)


@pytest.mark.parametrize(("robot", "task"), [("four_link", "reach_black"), ("three_link", "push")])
def test_render_processes_draw_the_same_pixels(robot, task):
    """Arms moving, blocks pushed (push's object is a joint, reach's blocks are mocap bodies)."""
    envs = [modnet.make_env(robot, task, num_envs=7, pixels=True, render_processes=k) for k in (0, 1, 2)]
    assert [env.num_render_processes for env in envs] == [0, 1, 2]
    generator = torch.Generator().manual_seed(0)
    actions = torch.rand(6, 7, envs[0].action_spec.shape[-1], generator=generator) * 4 - 2
    own, one, two = (frames_of(env, actions) for env in envs)
    assert own.float().std() > 10  # not blank
    assert not torch.equal(own[0], own[-1])  # the arms moved
    assert torch.equal(one, own)
    assert torch.equal(two, own)


def test_a_partial_reset_is_drawn_by_the_render_process_too():
    env = modnet.make_env("three_link", "reach_red", num_envs=4, pixels=True, render_processes=1)
    own = modnet.make_env("three_link", "reach_red", num_envs=4, pixels=True, render_processes=0)
    for e in (env, own):
        td = e.reset()
        td["action"] = torch.full((4, 3), 1.5)
        e.step(td)
    chosen = TensorDict(
        {"_reset": torch.tensor([[False], [True], [False], [True]]), "condition": torch.tensor([2, 3, 0, 1])},
        batch_size=[4],
    )
    drawn = env.reset(chosen.clone())["task", "pixels"]
    assert torch.equal(drawn, own.reset(chosen.clone())["task", "pixels"])


def test_the_default_is_one_render_process_per_16_copies_on_a_spare_core(monkeypatch):
    monkeypatch.setattr(modnet.envs.os, "cpu_count", lambda: 2)
    assert modnet.make_env("three_link", "reach_red", num_envs=15, pixels=True).num_render_processes == 0
    assert modnet.make_env("three_link", "reach_red", num_envs=64, pixels=True).num_render_processes == 1
    assert modnet.make_env("three_link", "reach_red", num_envs=64).num_render_processes == 0
    monkeypatch.setattr(modnet.envs.os, "cpu_count", lambda: 1)
    assert modnet.make_env("three_link", "reach_red", num_envs=64, pixels=True).num_render_processes == 0


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"pixels": True, "render_processes": -1}, "non-negative integer"),
        ({"pixels": True, "render_processes": 1.5}, "non-negative integer"),
        ({"pixels": False, "render_processes": 1}, "need pixels=True"),
    ],
)
def test_bad_render_processes_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        modnet.make_env("three_link", "reach_red", num_envs=2, **kwargs)


def test_closing_the_env_ends_its_render_processes_and_it_still_draws():
    env = modnet.make_env("three_link", "reach_red", num_envs=4, pixels=True, render_processes=1)
    child = env._render_processes[0]._child
    before = env.reset()["task", "pixels"].clone()
    env.close()
    assert child.wait(timeout=10) == 0
    assert env.num_render_processes == 0
    assert torch.equal(env._reset()["task", "pixels"], before)  # drawn here now


def test_dropping_the_env_ends_its_render_processes():
    env = modnet.make_env("three_link", "reach_red", num_envs=4, pixels=True, render_processes=1)
    child = env._render_processes[0]._child
    del env
    gc.collect()
    assert child.wait(timeout=10) == 0


def test_a_render_process_that_died_is_named():
    env = modnet.make_env("four_link", "reach_black", num_envs=4, pixels=True, render_processes=1)
    env.reset()
    env._render_processes[0]._child.kill()
    env._render_processes[0]._child.wait()
    with pytest.raises(RuntimeError, match="render process of four_link/reach_black died"):
        env.reset()
