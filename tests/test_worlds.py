"""Worlds: composition, conditions, costs, and the dm_control reference environment."""

import mujoco
import numpy as np
import pytest
import torch
from torchrl.envs import DMControlWrapper
from torchrl.envs.utils import check_env_specs

import modnet
from modnet.worlds import get_world


def test_registry_lists_the_papers_arms_and_tasks():
    assert modnet.ROBOTS == ("three_link", "three_link_short", "four_link", "five_link")
    assert set(modnet.TASKS) == {
        "reach_red", "reach_green", "reach_yellow", "reach_black", "reach", "push", "peg",
        "drawer_horizontal", "drawer_vertical",
    }  # fmt: skip


def test_unknown_names_list_the_valid_ones():
    with pytest.raises(ValueError, match="unknown robot 'six_link'; valid robots: three_link, "):
        modnet.make_env("six_link", "reach")
    with pytest.raises(ValueError, match="unknown task 'fly'; valid tasks: reach_red, .*drawer_vertical"):
        modnet.make_world("three_link", "fly")


def test_every_arm_reaches_every_task_workspace():
    # the farthest point any task needs (push goals, drawer handles) lies within 1.05 of the base
    for name in modnet.ROBOTS:
        assert modnet.robot_spec(name).reach >= 1.1


@pytest.mark.parametrize("robot", modnet.ROBOTS)
def test_state_sizes(robot):
    spec = modnet.robot_spec(robot)
    for task in modnet.TASKS:
        world = get_world(robot, task)
        data = mujoco.MjData(world.model)
        world.reset_data(data, world.conditions()[0])
        robot_state, task_state = world.observe(data.sensordata)
        assert robot_state.shape == (spec.state_dim,) == (2 * spec.n_joints,)
        assert task_state.shape == (modnet.task_spec(task).state_dim,)
        # joint angles come first and are the condition's arm configuration
        np.testing.assert_allclose(robot_state[: spec.n_joints], world.conditions()[0][: spec.n_joints])
        np.testing.assert_array_equal(robot_state[spec.n_joints :], 0.0)


def test_end_effector_observation_is_the_arm_tip():
    world = get_world("three_link", "reach")
    data = mujoco.MjData(world.model)
    params = world.conditions()[1]
    world.reset_data(data, params)
    tip = world.robot.joint_points(params[:3])[-1]
    np.testing.assert_allclose(world.observe(data.sensordata)[1][:2], tip, atol=1e-9)


def test_conditions_are_deterministic_per_seed_and_train_differs_from_test():
    world = get_world("four_link", "push")
    train, test = world.conditions("train", seed=3), world.conditions("test", seed=3)
    assert train.shape == test.shape == (4, 4 + 4)
    np.testing.assert_array_equal(train, world.conditions("train", seed=3))
    assert not np.allclose(train, test)
    assert not np.allclose(train, world.conditions("train", seed=4))
    extra = world.conditions("random", seed=3, n=20)
    assert extra.shape == (20, 8) and len(np.unique(extra.round(6), axis=0)) == 20
    # a task's placements do not depend on the arm: condition i is the same scene for every robot
    other = get_world("three_link", "push").conditions("train", seed=3)
    np.testing.assert_array_equal(other[:, 3:], train[:, 4:])


def test_bad_condition_requests():
    world = get_world("three_link", "reach")
    with pytest.raises(ValueError, match="unknown condition set 'val'; valid sets: train, test, random"):
        world.conditions("val")
    with pytest.raises(ValueError, match="the 'train' set has at least 4 conditions, not 2"):
        world.conditions("train", n=2)
    np.testing.assert_array_equal(world.conditions("train", n=9)[:4], world.conditions("train"))


@pytest.mark.parametrize("task", modnet.TASKS)
def test_cost_falls_towards_the_goal_and_is_smallest_there(task):
    spec = modnet.task_spec(task)
    world = get_world("three_link", task)
    data = mujoco.MjData(world.model)
    world.reset_data(data, world.conditions()[0])
    state = torch.as_tensor(world.observe(data.sensordata)[1])
    goal = spec.part(state, spec.goal)
    direction = torch.tensor([0.6, -0.8], dtype=state.dtype)
    costs = []
    for s in torch.linspace(0.5, 0.0, 11):
        moved = state.clone()
        moved[spec.slot(spec.moved)] = goal + s * direction
        if spec.moved != "ee":  # the gripper follows the object (shaping term at its minimum)
            moved[spec.slot("ee")] = moved[spec.slot(spec.moved)]
        costs.append(float(spec.cost(moved)))
        assert float(spec.distance(moved)) == pytest.approx(float(s), abs=1e-6)
    assert all(a > b for a, b in zip(costs, costs[1:], strict=False))


@pytest.mark.parametrize("task", ["push", "drawer_horizontal"])
def test_shaping_term_pulls_the_gripper_to_the_object_and_can_be_switched_off(task):
    spec = modnet.task_spec(task)
    state = torch.zeros(spec.state_dim)
    state[spec.slot(spec.moved)] = torch.tensor([0.5, 0.5])
    state[spec.slot(spec.goal)] = torch.tensor([0.5, 0.8])
    far = state.clone()
    far[spec.slot("ee")] = torch.tensor([0.0, 0.0])
    near = state.clone()
    near[spec.slot("ee")] = torch.tensor([0.45, 0.5])
    assert spec.cost(far) > spec.cost(near)
    assert spec.cost(far, shaping=False) == spec.cost(near, shaping=False)


def test_simulated_reach_cost_is_smallest_with_the_tip_on_the_block():
    """Real physics: put the red block under the tip of one arm pose; nearby poses cost more."""
    world = get_world("three_link", "reach_red")
    data = mujoco.MjData(world.model)
    params = world.conditions()[0].copy()
    pose = np.array([0.9, 0.4, 0.3])
    params[:3] = pose
    params[3:5] = world.robot.joint_points(pose)[-1]  # red block = the tip of `pose`
    costs = {}
    for delta in (-0.3, -0.1, 0.0, 0.1, 0.3):
        params[:3] = pose + [delta, 0.0, 0.0]
        world.reset_data(data, params)
        robot_state, task_state = (torch.as_tensor(a) for a in world.observe(data.sensordata))
        costs[delta] = float(world.cost(robot_state, task_state, torch.zeros(3)))
    assert min(costs, key=costs.get) == 0.0
    assert costs[-0.3] > costs[-0.1] > costs[0.0] < costs[0.1] < costs[0.3]


@pytest.mark.parametrize("robot", modnet.ROBOTS)
def test_dm_control_world_works_with_torchrl_wrapper(robot):
    env = DMControlWrapper(modnet.make_world(robot, "reach_black", horizon=4))
    check_env_specs(env)
    td = env.rollout(10, break_when_any_done=True)
    assert td.shape == (4,) and bool(td["next", "done"][-1])
    assert td["next", "robot_state"].shape[-1] == modnet.robot_spec(robot).state_dim
