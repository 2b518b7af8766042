"""The batched environment: specs, keys, horizon, exact agreement with dm_control, pixels, errors."""

import gc

import numpy as np
import pytest
import torch
from tensordict.nn import TensorDictModule
from torchrl.envs.utils import check_env_specs

import modnet
from modnet.envs import WorldEnv


@pytest.mark.parametrize("robot", modnet.ROBOTS)
@pytest.mark.parametrize("task", modnet.TASKS)
def test_every_world_builds_steps_and_passes_check_env_specs(robot, task):
    env = modnet.make_env(robot, task, num_envs=2, horizon=5)
    check_env_specs(env)
    td = env.rollout(5)
    assert torch.isfinite(td["next", "task", "state"]).all()


def test_keys_sizes_and_horizon():
    env = modnet.make_env("four_link", "reach_black", num_envs=8)
    td = env.rollout(100, break_when_any_done=True)
    assert td.shape == (8, 50)  # reach tasks last 50 steps
    assert td["next", "robot", "state"].shape == (8, 50, 8)
    assert td["next", "task", "state"].shape == (8, 50, 12)
    assert td["action"].shape == (8, 50, 4)
    assert ("task", "pixels") not in td.keys(True)
    assert td["condition"][:, 0].tolist() == [0, 1, 2, 3, 0, 1, 2, 3]
    assert td["next", "step_count"][:, -1].flatten().tolist() == [50] * 8
    done = td["next", "done"].squeeze(-1)
    assert done[:, -1].all() and not done[:, :-1].any()
    assert (td["next", "truncated"] == td["next", "done"]).all() and not td["next", "terminated"].any()
    assert modnet.make_env("three_link", "push").rollout(200).shape == (1, 100)  # manipulation: 100


def test_batched_env_reproduces_sequential_dm_control_rollouts_exactly():
    """Same actions, same world: B raw-mujoco copies == B dm_control episodes, one after another."""
    robot, task, T = "four_link", "push", 30
    env = modnet.make_env(robot, task, num_envs=4, horizon=T)
    actions = torch.rand(4, T, 4, generator=torch.Generator().manual_seed(0)) * 5 - 2.5
    td = env.reset()
    batched = []
    for t in range(T):
        td["action"] = actions[:, t]
        td = env.step(td)
        batched.append(td["next", "task", "state"])
        td = td["next"]
    batched = torch.stack(batched, 1)

    world = modnet.make_world(robot, task, horizon=T)  # cycles through the same 4 conditions
    for i in range(4):
        world.reset()
        states = [world.step(a.double().numpy()).observation["task_state"] for a in actions[i]]
        sequential = torch.as_tensor(np.stack(states), dtype=torch.float32)
        torch.testing.assert_close(batched[i], sequential, rtol=0, atol=0)


def test_threads_do_not_change_results():
    actions = torch.rand(16, 10, 3, generator=torch.Generator().manual_seed(1)) * 4 - 2
    states = []
    for threads in (1, 2):
        env = modnet.make_env("three_link", "push", num_envs=16, horizon=10, num_threads=threads)
        td, steps = env.reset(), []
        for t in range(10):
            td = env.step(td.set("action", actions[:, t]))
            steps.append(td["next", "task", "state"])
            td = td["next"]
        states.append(torch.stack(steps))
    assert torch.equal(states[0], states[1])


def test_rewards_are_the_negative_world_cost():
    env = modnet.make_env("three_link", "reach_red", num_envs=3, horizon=4)
    td = env.rollout(4)
    cost = env.world.cost(td["next", "robot", "state"], td["next", "task", "state"], td["action"])
    torch.testing.assert_close(td["next", "reward"].squeeze(-1), -cost)


def test_start_distance_is_where_an_untouched_object_stays():
    def constant(torque):
        def act(step):
            return torch.full((*step.shape[:-1], 4), torque)

        return TensorDictModule(act, in_keys=["step_count"], out_keys=["action"])

    push = modnet.make_env("four_link", "push", num_envs=4, horizon=10, conditions="test")
    still = push.rollout(10, constant(0.0))
    start = push.start_distance(still)
    torch.testing.assert_close(start, push.world.task.distance(push.reset()["task", "state"].double()))
    torch.testing.assert_close(push.final_distance(still), start)  # nobody touched the block
    reach = modnet.make_env("four_link", "reach", num_envs=4, horizon=10, conditions="test")
    moving = reach.rollout(10, constant(1.0))
    assert (reach.start_distance(moving) - reach.final_distance(moving)).abs().min() > 0.01  # the arm moved


def test_partial_reset_and_chosen_conditions():
    env = modnet.make_env("three_link", "reach", num_envs=3, horizon=3, conditions="test")
    td = env.rollout(2)
    last = td[:, -1]["next"]
    reset = env.reset(last.set("_reset", torch.tensor([[True], [False], [False]])))
    assert reset["step_count"].flatten().tolist() == [0, 2, 2]
    chosen = env.reset(env.reset().set("condition", torch.tensor([3, 3, 0])))
    assert chosen["condition"].tolist() == [3, 3, 0]
    torch.testing.assert_close(chosen["task", "state"][0], chosen["task", "state"][1])
    with pytest.raises(ValueError, match="condition out of range: valid are 0..3"):
        env.reset(env.reset().set("condition", torch.tensor([4, 0, 0])))


def test_out_of_range_actions_are_clipped_to_the_torque_limit():
    env = modnet.make_env("three_link", "reach", num_envs=2, horizon=3)
    td = env.reset()
    big = env.step(td.clone().set("action", torch.tensor([[50.0, -50.0, 9.0], [2.0, -2.0, 2.0]])))
    limit = env.step(env.reset().set("action", torch.tensor([[2.0, -2.0, 2.0], [2.0, -2.0, 2.0]])))
    torch.testing.assert_close(big["next", "robot", "state"], limit["next", "robot", "state"])
    assert not torch.equal(big["next", "robot", "state"], td["robot", "state"])


def test_bad_arguments():
    with pytest.raises(ValueError, match="num_envs must be a positive integer, got 0"):
        modnet.make_env("three_link", "reach", num_envs=0)
    with pytest.raises(ValueError, match="unknown condition set .validation.; valid sets: train, test"):
        modnet.make_env("three_link", "reach", conditions="validation")
    env = modnet.make_env("three_link", "reach", num_envs=2)
    with pytest.raises(ValueError, match=r"action of shape \(2, 4\) for three_link/reach: expected \(2, 3\)"):
        env.step(env.reset().set("action", torch.zeros(2, 4)))


def test_seeded_conditions_change_the_scene():
    a = modnet.make_env("three_link", "reach", seed=0).reset()["task", "state"]
    b = modnet.make_env("three_link", "reach", seed=1).reset()["task", "state"]
    assert not torch.equal(a, b)


COLOURS = {  # RGB ranges of the rendered blocks
    "red": lambda p: (p[..., 0] > 200) & (p[..., 1] < 80) & (p[..., 2] < 80),
    "green": lambda p: (p[..., 0] < 80) & (p[..., 1] > 180) & (p[..., 2] < 80),
    "yellow": lambda p: (p[..., 0] > 200) & (p[..., 1] > 200) & (p[..., 2] < 80),
    "black": lambda p: (p[..., 0] < 50) & (p[..., 1] < 50) & (p[..., 2] < 50),
}


def test_pixels_show_the_named_blocks():
    env = modnet.make_env("four_link", "reach_black", num_envs=4, pixels=True, horizon=2)
    td = env.rollout(2)
    pixels = td["next", "task", "pixels"]
    assert pixels.shape == (4, 2, 64, 80, 3) and pixels.dtype == torch.uint8
    assert pixels.float().std() > 10  # not blank
    for colour, is_colour in COLOURS.items():
        counts = is_colour(pixels[:, 0].int()).flatten(1).sum(1)
        assert (counts >= 4).all(), f"{colour} block not visible: {counts.tolist()} pixels"


def test_a_pixel_env_gives_the_end_effector_apart_from_the_state():
    env = modnet.make_env("four_link", "push", num_envs=2, pixels=True, horizon=3)
    td = env.rollout(3)
    task = env.world.task
    state = td["next", "task", "state"]
    expected = torch.cat([task.part(state, "ee", "pos"), task.part(state, "ee", "vel")], -1)
    torch.testing.assert_close(td["next", "task", "ee"], expected, rtol=0, atol=0)
    assert env.observation_spec["task", "ee"].shape == (2, 4)


def test_pixels_follow_the_block_position():
    """The red block's pixel centroid moves the way its (x, y) does (camera looks down, +y up)."""
    env = modnet.make_env("three_link", "reach_red", num_envs=4, pixels=True)
    td = env.reset()
    red = td["task", "state"][:, 4:6]  # ee pos, ee vel, then red
    centroids = []
    for frame in td["task", "pixels"]:
        rows, cols = np.nonzero(COLOURS["red"](frame.int()).numpy())
        centroids.append((cols.mean(), rows.mean()))
    centroids = torch.tensor(centroids)
    order_x, order_col = red[:, 0].argsort(), centroids[:, 0].argsort()
    assert order_x.tolist() == order_col.tolist()
    assert red[:, 1].argsort().tolist() == centroids[:, 1].argsort(descending=True).tolist()


def test_dropping_a_pixel_env_leaves_the_next_one_seeing():
    """mujoco frees a renderer's GL objects in the current GL context: dropping an env after
    another was made used to blank the newer one's frames for good."""
    first = WorldEnv("three_link", "reach_red", pixels=True)
    second = WorldEnv("four_link", "reach_red", pixels=True)
    seen = second.reset()["task", "pixels"].clone()
    del first
    gc.collect()
    after = second.reset()["task", "pixels"]
    assert seen.float().mean() > 100  # the grey floor
    assert torch.equal(after, seen)
