"""Zero-shot protocol, baselines, rollouts with frames, fine-tuning starts (in-process, tiny worlds)."""

import numpy as np
import pytest
import torch

from modnet.bank import ModuleBank
from modnet.evaluate import (
    FINETUNE_STARTS,
    Scores,
    _start_bank,
    bank_tasks,
    evaluation_env,
    finetune,
    rollout,
    score,
    start_config,
    zero_shot,
)
from modnet.gps.trainer import GPSConfig
from modnet.report import final_positions_strip, plot_zero_shot, write_zero_shot_csv, zero_shot_table

ROBOTS, TASKS = ["three_link", "four_link"], ["reach_red", "reach_black"]
HELD_OUT = ("four_link", "reach_black")




@pytest.fixture(scope="module")
def bank():
    return ModuleBank.build(ROBOTS, TASKS, seed=0)


@pytest.fixture(scope="module")
def env():
    return evaluation_env(*HELD_OUT, horizon=12)


def test_scores_mean_success_rate_and_student_t_interval():
    scores = Scores([0.05, 0.2, 0.07, 0.4], success_distance=0.1)
    assert scores.mean == pytest.approx(0.18) and scores.success_rate == 0.5
    low, high = scores.ci95
    half = 3.182446305284263 * np.std(scores.distance, ddof=1) / 2  # t(0.975, 3) * s / sqrt(4)
    assert (low, high) == pytest.approx((0.18 - half, 0.18 + half))
    assert Scores([0.3], 0.1).ci95 is None
    assert Scores([0.3], 0.1).to_json() == {"distance": [0.3], "mean": 0.3, "ci95": None, "success_rate": 0.0}


def test_zero_shot_scores_every_method_on_every_test_condition(bank, env):
    result = zero_shot(bank, *HELD_OUT, env)
    assert len(result.composed.distance) == len(result.random.distance) == 4
    assert list(result.wrong_task_each) == ["reach_red"]
    assert result.wrong_task == ("reach_red", result.wrong_task_each["reach_red"])
    assert result.random.distance != result.composed.distance  # a different network
    reset = env.world.task.distance(env.reset()["task", "state"].double())
    assert result.start.distance == pytest.approx(reset.tolist())  # before any action
    assert result.start.distance != result.composed.distance  # the arm moved
    methods = result.to_json()
    assert methods["start"] == result.start.to_json()
    assert methods["wrong_task"]["task"] == "reach_red"
    assert methods["wrong_task"]["distance"] == methods["wrong_task_each"]["reach_red"]["distance"]


def test_evaluation_is_deterministic_uses_eval_mode_and_restores_the_bank_mode(bank, env):
    bank.train()
    first = score(bank, *HELD_OUT, env).distance
    assert bank.training  # restored
    second = score(bank, *HELD_OUT, env).distance
    assert first == second  # mean actions, dropout off: same rollout twice
    td, _ = rollout(bank, *HELD_OUT, env)
    assert env.final_distance(td).tolist() == first


def test_the_best_wrong_task_is_the_lowest_mean_distance():
    bank = ModuleBank.build(
        ["four_link"], ["reach_red", "reach_green", "reach_yellow", "reach_black"], seed=1
    )
    env = evaluation_env(*HELD_OUT, horizon=8)
    result = zero_shot(bank, *HELD_OUT, env)
    assert set(result.wrong_task_each) == {"reach_red", "reach_green", "reach_yellow"}
    best = min(result.wrong_task_each, key=lambda t: np.mean(result.wrong_task_each[t].distance))
    assert result.wrong_task[0] == best


def test_wrong_task_modules_that_cannot_read_the_world_are_skipped_with_the_reason():
    bank = ModuleBank.build(["four_link"], ["reach", "push", "drawer_vertical"], seed=0)
    env = evaluation_env("four_link", "push", horizon=5)
    result = zero_shot(bank, "four_link", "push", env)
    assert list(result.wrong_task_each) == ["drawer_vertical"]  # 10-dim task state, like push
    assert result.skipped == {"reach": "it reads a task/state of size 6, the held-out world has 10"}
    assert result.to_json()["wrong_task_skipped"] == result.skipped


def test_rollout_frames_hold_the_first_and_last_step_of_every_condition(bank, env):
    _, frames = rollout(bank, *HELD_OUT, env, frames=(32, 40, 5))
    assert frames.dtype == np.uint8 and frames.shape[1:] == (4, 32, 40, 3)
    assert 5 <= frames.shape[0] <= 6 and frames[-1].std() > 0
    assert final_positions_strip(frames).shape == (32, 4 * 40 + 3 * 4, 3)


def test_report_table_csv_and_figure_from_results(bank, env, tmp_path):
    results = {
        "holdout": "four_link/reach_black",
        "success_distance": 0.1,
        "methods": zero_shot(bank, *HELD_OUT, env).to_json(),
    }
    table = zero_shot_table(results).splitlines()
    assert table[1].split() == [
        "condition", "at", "start", "random", "network", "wrong", "task", "(reach_red)", "composed"
    ]
    assert len(table) == 2 + 4 + 2
    rows = write_zero_shot_csv(results, tmp_path / "z.csv").read_text().splitlines()
    assert rows[0] == "condition,start,random,wrong_task,wrong_task:reach_red,composed" and len(rows) == 7
    assert rows[1].split(",")[1] == f"{results['methods']['start']['distance'][0]:.6f}"
    plot_zero_shot(results, tmp_path / "z.png")
    assert (tmp_path / "z.png").stat().st_size > 1000


def test_finetuning_starts_set_up_the_held_out_world_as_described(tmp_path):
    bank = ModuleBank.build(ROBOTS, TASKS, seed=7)  # stands for a trained bank: not seed 0's weights
    bank.save(tmp_path / "bank")
    saved = {name: bank.get("task", name).state_dict() for name in TASKS}

    def same(module, state):
        return all(torch.equal(v, state[k]) for k, v in module.state_dict().items())

    composed = _start_bank(tmp_path / "bank", "composed", *HELD_OUT, "reach_red", seed=0)
    assert same(composed.get("task", "reach_black"), saved["reach_black"])
    wrong = _start_bank(tmp_path / "bank", "wrong_task", *HELD_OUT, "reach_red", seed=0)
    assert same(wrong.get("task", "reach_black"), saved["reach_red"])
    scratch = _start_bank(tmp_path / "bank", "scratch_shaping", *HELD_OUT, None, seed=0)
    assert not same(scratch.get("task", "reach_black"), saved["reach_black"])


def test_a_scratch_start_reads_nothing_the_bank_learned(tmp_path):
    """Both scratch starts depend on the bank's architecture and the seed only: two saved banks
    with different weights and input normalisation give the same start. RESULTS leans on this
    to run scratch starts from a bank trained for a single GPS iteration."""
    scratch = ("scratch_shaping", "scratch_no_shaping")
    starts = {}
    for bank_seed in (3, 7):
        bank = ModuleBank.build(ROBOTS, TASKS, seed=bank_seed)
        shifted = {k: v + bank_seed if "normalizers" in k else v for k, v in bank.state_dict().items()}
        bank.load_state_dict(shifted)  # as if its inputs were fitted to other samples
        bank_dir = tmp_path / f"bank{bank_seed}"
        bank.save(bank_dir)
        for start in scratch:
            starts[bank_seed, start] = _start_bank(bank_dir, start, *HELD_OUT, None, seed=0).state_dict()
    for start in scratch:
        one, other = starts[3, start], starts[7, start]
        assert one.keys() == other.keys()
        assert all(torch.equal(value, other[key]) for key, value in one.items()), start
    saved, fresh = ModuleBank.load(tmp_path / "bank7").state_dict(), starts[7, "scratch_shaping"]
    assert not any(torch.equal(saved[k], fresh[k]) for k in fresh if "normalizers" in k and k.endswith("loc"))


def test_a_monolithic_wrong_task_start_is_the_same_robot_s_network_for_the_wrong_task(tmp_path):
    bank = ModuleBank.build(ROBOTS, TASKS, policy="monolithic", seed=7)
    bank.save(tmp_path / "bank")
    assert bank_tasks(bank) == tuple(TASKS)
    wrong = _start_bank(tmp_path / "bank", "wrong_task", *HELD_OUT, "reach_red", seed=0)
    expected = bank.get("world", "four_link-reach_red").state_dict()
    loaded = wrong.get("world", "four_link-reach_black").state_dict()
    own = bank.get("world", "four_link-reach_black").state_dict()
    assert not torch.equal(own["module.trunk.0.weight"], expected["module.trunk.0.weight"])
    assert all(torch.equal(v, expected[k]) for k, v in loaded.items())


def test_only_scratch_with_shaping_keeps_the_shaping_term():
    """The paper's protocol: the transferred starts fine-tune on the task's cost alone."""
    config = GPSConfig(shaping=True)
    shaping = [start for start in FINETUNE_STARTS if start_config(config, start).shaping]
    assert shaping == ["scratch_shaping"]
    from_policy = [start for start in FINETUNE_STARTS if start_config(config, start).init_from_policy]
    assert from_policy == ["composed", "wrong_task"]
    assert not start_config(GPSConfig(shaping=False), "scratch_shaping").shaping
    with pytest.raises(ValueError, match="valid starts: composed, wrong_task"):
        start_config(config, "pretrained")


def test_finetune_gives_one_curve_per_start_from_before_training(bank, env, tmp_path):
    bank.save(tmp_path / "bank")
    config = GPSConfig(horizon=12, samples_per_condition=2, sgd_steps=10, initial_sgd_steps=10)
    tuning = finetune(tmp_path / "bank", *HELD_OUT, env, config, iterations=1, wrong_task="reach_red")
    curves = tuning.curves
    assert list(curves) == list(FINETUNE_STARTS)
    trajectories = config.num_conditions * config.samples_per_condition  # one iteration of one world
    assert all(
        s == {"trajectories": trajectories, "env_steps": trajectories * config.horizon}
        for s in tuning.samples.values()
    )
    assert all(len(c) == 2 and np.isfinite(c).all() for c in curves.values())
    assert list(tuning.sampled) == list(curves)
    assert all(len(c) == 1 and np.isfinite(c).all() and min(c) >= 0 for c in tuning.sampled.values())
    assert curves["composed"][0] == pytest.approx(score(bank, *HELD_OUT, env).mean)  # entry 0: the saved bank
    assert list(tuning.training) == list(curves) and all(len(c) == 2 for c in tuning.training.values())
    scenes = evaluation_env(*HELD_OUT, num_conditions=config.num_conditions, horizon=12, conditions="train")
    assert tuning.training["composed"][0] == pytest.approx(score(bank, *HELD_OUT, scenes).mean)  # its scenes
    assert tuning.training["composed"][0] != pytest.approx(curves["composed"][0])  # not the test positions
    # each iteration's GPS diagnostics, whose distance is the samples' curve
    assert list(tuning.diagnostics) == list(curves)
    for start, iterations in tuning.diagnostics.items():
        assert [d["distance"] for d in iterations] == tuning.sampled[start]
        assert all({"sampled_cost", "kl", "step_mult", "action_gap"} <= set(d) for d in iterations), start
        assert all(np.isfinite(list(d.values())).all() for d in iterations), start
    assert "wrong_task" not in finetune(
        tmp_path / "bank", *HELD_OUT, env, config, iterations=0, wrong_task=None
    ).curves
