"""The benchmark scripts: each ends with one JSON line; the single-world GPS run succeeds (slow)."""

import json
import subprocess
import sys

import mujoco
import numpy as np
import pytest
import torch
from commands import BENCHMARKS, load_script, run_py, run_script
from tensordict import TensorDict

from modnet.bank import ModuleBank
from modnet.evaluate import evaluating, evaluation_env, rollout, training_env
from modnet.gps.sampling import state_of
from modnet.gps.trainer import PHASES, PIXEL_ROWS_PER_PASS, GPSConfig, GPSTrainer
from modnet.worlds import get_world


def benchmark_lines(*args: str, timeout: float = 600) -> list[str]:
    """``python benchmarks/<args>`` in a fresh interpreter, as a user runs it: its output lines."""
    out = subprocess.run(
        [sys.executable, *args], capture_output=True, text=True, timeout=timeout, check=True, cwd=BENCHMARKS
    )
    return out.stdout.strip().splitlines()


def last_json(*args: str, timeout: float = 600) -> dict:
    return json.loads(benchmark_lines(*args, timeout=timeout)[-1])


@pytest.mark.slow
def test_gps_on_one_world_brings_the_policy_within_the_success_distance():
    """Issue 4's check, at seed 0 and the defaults. On the AMD EPYC of the later sessions it
    fails at test position 4: it rests on two wide-swing training scenes (RESULTS, "What did
    not match", "Which scenes decide it"), and we neither pick a seed nor change a default."""
    figures = last_json("gps_single_world.py", "--robot", "three_link", "--task", "reach", timeout=1200)
    assert len(figures["final_distance"]) == 4
    assert max(figures["final_distance"]) < figures["success_distance"], figures


def test_lqr_benchmark_reports_a_ratio_against_numpy():
    figures = last_json("lqr.py", "--repeats", "3")
    assert figures["max_abs_diff_K_k_chol"] < 1e-9 and figures["speedup_numpy_over_batched"] > 0


def test_pi2_benchmark_agrees_with_the_gps_codes_dual_minimised_step_by_step():
    """The bisection puts the weights at the KL bound, which is where scipy's minimum of REPS's
    dual puts them (its derivative is the bound less the weights' KL); PILQR's batched model
    costs are the GPS code's per-sample loop's."""
    figures = last_json("pi2.py", "--conditions", "2", "--repeats", "1")
    assert figures["max_kl_from_bound"] < 1e-9 and figures["max_rel_diff_eta"] < 1e-4
    assert figures["max_abs_diff_k"] < 1e-4 and figures["max_rel_diff_cov"] < 1e-4
    assert figures["speedup_loop_over_batched"] > 0
    assert figures["max_rel_diff_model_costs"] < 1e-12
    assert figures["speedup_model_costs_loop_over_batched"] > 0 and figures["pilqr_over_pi2"] > 0


def test_gps_iteration_benchmark_times_the_grid_a_run_trains_from_images():
    """The run's own grid and budget (here color_reach, shrunk): every phase, the policy's
    forward passes over the samples among them, with shares of the iteration that add up."""
    overrides = ["universe=color_reach", "gps.num_conditions=4", "gps.samples_per_condition=1"]
    overrides += ["gps.sgd_steps=4", "gps.initial_sgd_steps=4", "gps.horizon=10"]
    figures = last_json("gps_iteration.py", "--iterations", "2", *overrides)
    assert figures["pixels"] is True and figures["worlds"] == 11 and figures["sgd_steps"] == 4
    assert figures["samples_per_iteration"] == 11 * 4 * 1
    assert list(figures["share"]) == list(PHASES)
    assert all(v > 0 for v in figures["share"].values()), figures
    assert -0.01 <= figures["unaccounted_share"] < 0.5, figures
    assert 0 < figures["sampling_vs_raw_mj_step"] < 1  # rendering and TorchRL cost more than mj_step


def test_pixel_sgd_benchmark_times_one_and_two_threads_against_the_state_bank():
    figures = last_json("pixel_sgd.py", "--batch-per-world", "2", "--repeats", "1")
    assert set(figures["median_ms"]) == {"state", "pixels_stride1", "pixels", "pixels_2_threads"}
    assert figures["threads"] == 1 and figures["one_vs_two_threads"] > 0 and figures["pixels_vs_state"] > 0


def test_policy_passes_benchmark_gives_the_trainers_outputs_at_every_pass_size():
    figures = last_json("policy_passes.py", "--rows", "16", "--images", "40", "--repeats", "1")
    assert figures["trainer_rows_per_pass"] == PIXEL_ROWS_PER_PASS
    assert set(figures["same_outputs"]) == {"16", str(PIXEL_ROWS_PER_PASS), "512"}
    assert all(figures["same_outputs"].values()) and figures["reference_vs_trainer"] > 0


@pytest.mark.parametrize(
    "args, message",
    [
        (["--iterations", "1", "universe=tiny"], "--iterations must be at least 2"),
        (["universe=nope"], "Available options in 'universe': color_reach color_reach_state"),
        (["holdout=four_link/nope"], "task 'nope' not in its grid"),
    ],
)
def test_gps_iteration_benchmark_refuses_bad_input_in_one_line(args, message):
    done = run_script(BENCHMARKS / "gps_iteration.py", *args)  # an exception would end the test here
    assert done.returncode == 2 and message in done.stderr, done.stderr


def test_pretrain_benchmark_reports_every_vision_module_and_a_ratio_against_mj_step():
    figures = last_json(
        "pretrain_vision.py", "universe=color_reach", "pretrain.images=40", "pretrain.epochs=1", timeout=300
    )
    assert set(figures["modules"]) == {f"task/reach_{c}" for c in ("red", "green", "yellow", "black")}
    for module in figures["modules"].values():
        assert list(module["object_errors"]) == ["red", "green", "yellow", "black"]
    assert figures["render_scene_vs_mj_step"] > 1  # a frame costs more than a physics step


def test_gps_single_world_traces_where_the_object_goes():
    """``--trace`` reads the right state slots: at step 0 every block is where its condition put it.
    (Run with the GPS code's smoothed noise and per-condition priors, which the JSON echoes.)"""
    options = "--task push --conditions 4 --samples 2 --iterations 1 --sgd-steps 20 --trace".split()
    options += ["--noise-smoothing", "2", "--dynamics-prior-per-condition"]
    figures = last_json("gps_single_world.py", *options, timeout=600)
    assert figures["noise_smoothing"] == 2.0 and figures["dynamics_prior_per_condition"] is True
    trace = figures["trace"]
    assert trace["steps"] == [0, 20, 40, 60, 99]
    params = get_world("three_link", "push").conditions("train", 0, 4)[:, 3:]  # block (x, y), goal (x, y)
    start = np.hypot(*(params[:, :2] - params[:, 2:]).T)
    np.testing.assert_allclose([row[0] for row in trace["object_to_goal"]], start, atol=2e-3)
    assert all(len(row) == 5 and row[0] > 0.9 for row in trace["ee_to_object"])  # the arm starts far away


def single_world(*options: str) -> tuple[dict, list[float]]:
    """``gps_single_world.py``'s JSON figures and BADMM's policy weight (mean nu) per iteration."""
    out = benchmark_lines("gps_single_world.py", *options)
    nu = [float(line.split("nu=")[1].split()[0]) for line in out if line.startswith("iteration")]
    return json.loads(out[-1]), nu


def single_world_refusal(*options: str) -> str:
    """What ``gps_single_world.py`` says when it refuses ``options`` (before any training)."""
    refused = run_script(BENCHMARKS / "gps_single_world.py", *options)
    assert refused.returncode == 2, refused
    return refused.stderr


def test_gps_single_world_trajectory_only_holds_the_policy_weight_at_its_floor():
    """``--trajectory-only``: BADMM's policy weight never leaves its floor, so the controllers
    are optimised without the policy's pull; it is refused with MDGPS, which has no such weight."""
    figures, nu = single_world(*"--conditions 4 --samples 2 --iterations 2 --trajectory-only".split())
    assert figures["trajectory_only"] is True and len(figures["controllers_distance"]) == 2
    assert nu == [1e-6, 1e-6], nu
    assert "use it with --algo badmm" in single_world_refusal("--algo", "mdgps", "--trajectory-only")


def test_gps_single_world_caps_the_policy_weight_and_scores_the_training_conditions():
    """``--max-policy-weight`` bounds BADMM's nu_t (the initial weight is lowered to it);
    ``--evaluate-on train`` scores the network at each of the world's training conditions."""
    options = "--conditions 5 --samples 2 --iterations 2 --sgd-steps 20"
    options += " --max-policy-weight 1e-3 --evaluate-on train"
    figures, nu = single_world(*options.split())
    assert figures["max_policy_weight"] == 1e-3 and figures["evaluated_on"] == "train"
    assert len(figures["final_distance"]) == 5  # one per training condition, not the 4 test positions
    assert len(nu) == 2 and all(1e-6 <= v <= 1e-3 for v in nu), nu
    refusal = single_world_refusal("--trajectory-only", "--max-policy-weight", "1e-3")
    assert "use it with --algo badmm alone" in refusal
    assert "min_policy_weight" in single_world_refusal("--max-policy-weight", "1e-8")  # below the floor


def test_gps_single_world_samples_the_network_from_the_second_iteration_with_sample_on_policy():
    """``--sample-on-policy``: the first iteration samples the controllers either way, the second
    the network (so the two runs part there), and the JSON says which was run."""
    options = "--algo mdgps --conditions 4 --samples 2 --iterations 2 --sgd-steps 20".split()
    off = last_json("gps_single_world.py", *options, timeout=600)
    on = last_json("gps_single_world.py", *options, "--sample-on-policy", timeout=600)
    assert off["sample_on_policy"] is False and on["sample_on_policy"] is True
    assert on["controllers_distance"][0] == off["controllers_distance"][0]
    assert on["controllers_distance"][1] != off["controllers_distance"][1]


def test_gps_single_world_bounds_the_step_multiplier():
    """``--min-step-mult``/``--max-step-mult`` reach the C-step's rule (adapted from the second
    iteration on) and the JSON; bounds out of order are refused before any training."""
    options = "--conditions 4 --samples 2 --iterations 2 --sgd-steps 9".split()
    out = benchmark_lines("gps_single_world.py", *options, "--min-step-mult", "0.7", "--max-step-mult", "0.7")
    mults = [float(line.split("step_mult=")[1].split()[0]) for line in out if line.startswith("iteration")]
    assert mults == [1.0, 0.7] and json.loads(out[-1])["step_mult_bounds"] == [0.7, 0.7]
    refusal = single_world_refusal("--min-step-mult", "2", "--max-step-mult", "1")
    assert "gps.min_step_mult must be positive and at most gps.max_step_mult" in refusal


def test_gps_single_world_weighs_the_cost_along_time_as_asked():
    """``--cost-ramp`` and ``--final-cost-multiplier`` reach the trainer and the JSON: the first
    samples are the same, their time-weighted cost is not."""
    options = "--task push --conditions 4 --samples 2 --iterations 1 --sgd-steps 9".split()
    runs = []
    for flags in ([], ["--cost-ramp", "quadratic", "--final-cost-multiplier", "1"]):
        out = benchmark_lines("gps_single_world.py", *options, *flags)
        first = next(line for line in out if line.startswith("iteration 0"))
        runs.append((json.loads(out[-1]), float(first.split("sampled_cost=")[1].split()[0])))
    (default, default_cost), (authors, authors_cost) = runs
    assert (default["cost_ramp"], default["final_cost_multiplier"]) == ("constant", 5.0)
    assert (authors["cost_ramp"], authors["final_cost_multiplier"]) == ("quadratic", 1.0)
    assert authors["controllers_distance"] == default["controllers_distance"]
    assert 0 < authors_cost < default_cost  # (t/T)^2 <= 1 at every step, and the last weighs 1, not 5


def test_gps_single_world_clips_the_targets_and_reports_the_controllers_per_condition():
    """``--clip-targets`` reaches the S-step: the first samples are the same, the regression
    onto clipped torques is not; the controllers' final distance per training condition
    averages to the iteration's ``distance``; the final joint angles come one row per
    condition, and the network's are not where the arm started."""
    options = "--conditions 4 --samples 2 --iterations 1 --sgd-steps 9".split()
    runs = []
    for flags in ([], ["--clip-targets"]):
        out = benchmark_lines("gps_single_world.py", *options, *flags)
        first = next(line for line in out if line.startswith("iteration 0"))
        runs.append((json.loads(out[-1]), first.split("regression_loss=")[1].split()[0]))
    (off, off_loss), (on, on_loss) = runs
    assert (off["clip_targets"], on["clip_targets"]) == (False, True)
    assert on["controllers_distance"] == off["controllers_distance"] and on_loss != off_loss
    for figures in (off, on):
        per_condition, mean = figures["controllers_final_distance"], figures["controllers_distance"][-1]
        assert len(per_condition) == 4 and np.mean(per_condition) == pytest.approx(mean, abs=1e-3)
        assert np.shape(figures["controllers_final_joints"]) == np.shape(figures["final_joints"]) == (4, 3)
    start = get_world("three_link", "reach").conditions("test", 0)[:, :3]  # where the arm's joints start
    assert not np.allclose(off["final_joints"], start, atol=0.05)  # the network moved the arm


@pytest.mark.parametrize("c_step", ["pi2", "pilqr"])
def test_gps_single_world_runs_a_pi2_c_step_with_mdgps_and_refuses_it_with_badmm(c_step):
    options = "--algo mdgps --pi2-kl 0.5 --conditions 4 --samples 3 --iterations 2 --sgd-steps 9"
    figures = last_json("gps_single_world.py", "--c-step", c_step, *options.split(), timeout=600)
    assert (figures["c_step"], figures["pi2_kl"], len(figures["controllers_distance"])) == (c_step, 0.5, 2)
    assert "use algo=mdgps" in single_world_refusal("--c-step", c_step)  # BADMM, the default


def test_gps_single_world_sizes_the_network_and_scores_random_conditions():
    """``--width`` sets every hidden layer of both modules (depths and interface kept) and
    ``--sgd-steps`` the S-step's length; ``--evaluate-on random`` scores further random
    conditions, each beside the distance it started at (where an untouched object stays)."""

    def parameters(bank: ModuleBank) -> int:
        return sum(p.numel() for p in bank.parameters())

    options = "--conditions 4 --samples 2 --iterations 1 --width 32 --sgd-steps 3 --evaluate-on random"
    figures, _ = single_world(*options.split(), "--random-conditions", "3")
    narrow = ModuleBank.build(["three_link"], ["reach"], task_hidden=(32,) * 3, robot_hidden=(32,) * 2)
    assert figures["width"] == 32 and figures["sgd_steps"] == 3
    assert figures["network_parameters"] == parameters(narrow)
    assert parameters(narrow) < parameters(ModuleBank.build(["three_link"], ["reach"]))
    env = evaluation_env("three_link", "reach", conditions="random", num_conditions=3)
    start = env.world.task.distance(env.reset()["task", "state"].to(torch.float64))
    assert figures["start_distance"] == pytest.approx(start.tolist(), abs=1e-4)
    assert len(figures["final_distance"]) == 3 and figures["closer"] + figures["farther"] <= 3
    assert "leave --sgd-steps out" in single_world_refusal("--trajectory-only", "--sgd-steps", "10")
    assert "hidden must hold positive integers" in single_world_refusal("--width", "0")
    assert "valid robots: three_link" in single_world_refusal("--robot", "six_link")  # before any training


def load_benchmark(name: str):
    return load_script(BENCHMARKS / f"{name}.py", f"benchmark_{name}")


def test_object_contact_measures_approach_displacement_and_progress_towards_the_goal():
    """A block pushed 0.1 towards its goal, then one pushed 0.1 away: both moved, one progressed."""
    contact = load_benchmark("object_contact").contact
    task = get_world("three_link", "push").task
    T = 10

    def xy(x: float, y: float) -> torch.Tensor:
        return torch.tensor([x, y], dtype=torch.float64)

    state = torch.zeros(2, T + 1, task.state_dim, dtype=torch.float64)
    state[..., task.slot("goal")] = xy(0.5, 0.5)
    block = xy(0.2, 0.5) + torch.linspace(0, 0.1, T + 1, dtype=torch.float64)[:, None] * xy(1.0, 0.0)
    state[0, :, task.slot("block")] = block
    state[1, :, task.slot("block")] = 2 * block[0] - block  # moves 0.1 the other way
    state[..., task.slot("ee")] = state[..., task.slot("block")] - xy(0.06, 0.0)
    state[:, 0, task.slot("ee")] = xy(0.0, 0.0)  # starts far away
    td = TensorDict(
        {"task": {"state": state[:, :-1]}, "next": {"task": {"state": state[:, 1:]}}}, batch_size=[2, T]
    )
    found = contact(task, td)
    torch.testing.assert_close(found["closest_approach"], torch.full((2,), 0.06, dtype=torch.float64))
    torch.testing.assert_close(found["offset_at_closest"], -xy(0.06, 0.0).expand(2, 2))  # behind it
    torch.testing.assert_close(found["object_moved"], torch.full((2,), 0.1, dtype=torch.float64))
    assert found["progress"][0] == pytest.approx(0.1) and found["progress"][1] < 0
    torch.testing.assert_close(found["object_from_base"], xy(0.2, 0.5).norm().expand(2))
    torch.testing.assert_close(found["end_effector_from_base"][0], xy(0.24, 0.5).norm())


def test_object_contact_reports_where_the_training_worlds_objects_start():
    """From the run's own training conditions: three_link/push's blocks, as its condition set has them."""
    objects_seen = load_benchmark("object_contact").objects_seen
    gps = GPSConfig(num_conditions=8, condition_seed=3)
    results = {"training_worlds": ["three_link/push", "three_link/reach", "four_link/push"]}
    seen = objects_seen(gps, results, "three_link")
    assert list(seen) == ["three_link/push"]  # not reach (it moves nothing), not another robot
    blocks = get_world("three_link", "push").conditions("train", 3, 8)[:, 3:5]
    radius = np.hypot(*blocks.T)
    np.testing.assert_allclose(seen["three_link/push"], [radius.min(), radius.max()], atol=1e-4)


def test_object_contact_on_real_physics_moves_nothing_it_does_not_touch():
    """An untrained network in three_link/push: wherever the tip stays out of reach of the block
    (half-width 0.05 plus the tip's 0.02), the block does not move."""
    contact = load_benchmark("object_contact").contact
    bank = ModuleBank.build(["three_link"], ["push"], seed=0)
    env = evaluation_env("three_link", "push", horizon=30)
    td, _ = rollout(bank, "three_link", "push", env)
    found = contact(env.world.task, td)
    far = found["closest_approach"] > 0.1
    assert far.any()
    assert (found["object_moved"][far] == 0).all(), found


def test_reachable_finds_a_torque_sequence_that_reaches_a_test_target_and_replays_it():
    """The open-loop search on real physics: a few hundred rollouts bring the three-link tip
    within reach's success distance of a test target it starts 1.8 away from, and
    the knots it returns reproduce that distance when played again."""
    reachable = load_benchmark("reachable")
    world = get_world("three_link", "reach")
    params = world.conditions("test", 0)[0]
    found = reachable.cem(world, params, population=40, elites=8, iterations=8)
    assert found.zero_torque > 1.5  # the untouched arm stays far from the target
    assert found.best < world.task.success_distance
    data = mujoco.MjData(world.model)
    replay = reachable.final_distance(
        world, data, params, reachable.interpolate(found.knots, world.task.horizon)
    )
    assert replay == pytest.approx(found.best, abs=1e-12)
    # the same torques through modnet's TorchRL env (test condition 0 is its first copy)
    env = evaluation_env("three_link", "reach")
    table = torch.as_tensor(reachable.interpolate(found.knots, world.task.horizon), dtype=torch.float32)
    td = env.rollout(
        world.task.horizon, lambda td: td.set("action", table[td["step_count"][:, 0]].expand(4, -1))
    )
    assert env.final_distance(td)[0].item() == pytest.approx(found.best, abs=1e-4)
    with pytest.raises(ValueError, match="elites"):
        reachable.cem(world, params, population=4, elites=5)


def test_reachable_clips_knots_to_the_motors_limits():
    torques = load_benchmark("reachable").interpolate(np.array([[0.0, -9.0], [4.0, 9.0]]), horizon=5)
    np.testing.assert_allclose(torques[:, 0], [0.0, 1.0, 2.0, 2.0, 2.0])
    np.testing.assert_allclose(torques[:, 1], [-2.0, -2.0, 0.0, 2.0, 2.0])


def test_action_gap_splits_the_gap_by_part_of_the_episode_and_at_the_torque_limits():
    action_gap = load_benchmark("action_gap")
    asked = torch.zeros(1, 1, 5, 2, dtype=torch.float64)
    asked[..., 0] = torch.tensor([3.0, 0.5, 0.5, 0.5, 0.5])  # the first step asks beyond the limit
    network = torch.zeros_like(asked)
    figures = action_gap.gap_figures(asked, network, torch.tensor([[0.25]]))
    assert figures["gap"] == pytest.approx((3.0 + 4 * 0.5) / 5)
    assert figures["gap_clipped"] == pytest.approx((2.0 + 4 * 0.5) / 5)  # 3 acts as 2 does
    assert figures["gap_by_part"] == {"first_fifth": 2.0, "to_half": 0.5, "second_half": 0.5}
    assert figures["saturated"] == pytest.approx(1 / 10)  # one of ten torques
    assert figures["controller_distance"] == 0.25
    beyond = action_gap.gap_figures(asked, network + 2.5, torch.tensor([[0.25]]))
    assert beyond["gap_by_part"]["first_fifth"] == pytest.approx(2.0)  # (2, 0) against (2, 2)


def published_run(seed: int, ours: list[float], command_extra: str = "") -> dict:
    """A docs/results JSON of one color_reach seed, as publish_results.py zero-shot writes it."""
    random, wrong = [1.8, 1.6, 1.1, 0.8], [0.4, 1.0, 0.3, 0.9]
    return {
        "universe": "color_reach",
        "holdout": "four_link/reach_black",
        "seed": seed,
        "command": f"python run.py universe=color_reach eval.random_conditions=20{command_extra} seed={seed}",
        "success_distance": 0.1,
        "positions": [
            {"ours": o, "random": r, "wrong_task": w, "start": r}
            for o, r, w in zip(ours, random, wrong, strict=True)
        ],
        "means": {"composed": sum(ours) / 4, "random": 1.325, "wrong_task": 0.65, "start": 1.325},
        "paper": {
            "universe": "color_reach",
            "ours": [0.12, 0.28, 0.21, 0.08],
            "random": [1.16, 1.29, 1.35, 1.29],
            "wrong_task": [2.34, 1.75, 1.65, 2.41],
        },
        "extended": {
            "n": 20,
            "ours_mean": 0.2,
            "ours_ci95": [0.1, 0.3],
            "random_mean": 1.3,
            "wrong_task_mean": 0.5,
        },
    }


def test_paper_figure_draws_each_seed_beside_the_papers_table_and_counts_the_positions_at_or_below_it():
    publish = load_benchmark("publish_results")
    seeds = [published_run(1, [0.1, 0.1, 0.05, 0.08]), published_run(0, [0.1, 0.3, 0.2, 0.1], " threads=2")]
    fig, summary = publish.paper_figure(seeds)
    assert summary["seeds"] == [0, 1]  # sorted; threads= does not make another experiment
    assert summary["at_or_below_paper"] == [2, 4]  # seed 0 misses positions 2 and 4 (0.3 > 0.28, 0.1 > 0.08)
    assert summary["positions_mean_over_seeds"]["ours"] == pytest.approx(
        [0.1, 0.2, 0.125, 0.09, 0.12875], abs=1e-4
    )
    assert summary["ratio_to_random"] == pytest.approx([0.175 / 1.325, 0.0825 / 1.325], abs=1e-4)
    assert summary["paper"]["ours"][-1] == 0.1725
    left, right = fig.axes
    heights = [bar.get_height() for bar in left.patches]
    # the paper's composed bars, then ours (the mean over the seeds), per position and the mean
    assert heights[:10] == pytest.approx([0.12, 0.28, 0.21, 0.08, 0.1725, 0.1, 0.2, 0.125, 0.09, 0.12875])
    assert left.get_yscale() == "log" and right.get_title() == "20 random positions"


@pytest.mark.parametrize(
    ("runs", "message"),
    [
        (
            lambda: [published_run(0, [0.1] * 4), published_run(1, [0.1] * 4, " gps.clip_targets=true")],
            "not one",
        ),
        (lambda: [published_run(0, [0.1] * 4), published_run(0, [0.2] * 4)], "a seed is given twice"),
        (
            lambda: [{k: v for k, v in published_run(0, [0.1] * 4).items() if k != "paper"}],
            "the paper has no table",
        ),
    ],
)
def test_paper_figure_refuses_runs_of_different_experiments_repeated_seeds_and_tables_the_paper_lacks(
    tmp_path, runs, message
):
    paths = []
    for i, run in enumerate(runs()):
        paths.append(tmp_path / f"run{i}.json")
        paths[-1].write_text(json.dumps(run))
    args = ["figure", *map(str, paths), "--experiment", "x", "--docs", str(tmp_path)]
    done = run_script(BENCHMARKS / "publish_results.py", *args)
    assert done.returncode == 2 and message in done.stderr, done.stderr
    assert not (tmp_path / "x_vs_paper.png").exists()


def test_paper_figure_writes_the_png_and_ends_with_a_json_line(tmp_path):
    path = tmp_path / "seed0.json"
    path.write_text(json.dumps(published_run(0, [0.1, 0.3, 0.2, 0.1])))
    args = ["figure", str(path), "--experiment", "x", "--docs", str(tmp_path)]
    done = run_script(BENCHMARKS / "publish_results.py", *args)
    assert done.returncode == 0, done.stderr
    figures = json.loads(done.stdout.splitlines()[-1])
    assert figures["figure"] == str(tmp_path / "x_vs_paper.png") and figures["at_or_below_paper"] == [2]
    assert (tmp_path / "x_vs_paper.png").read_bytes().startswith(b"\x89PNG")


def test_first_finetune_iteration_reruns_the_runs_first_iteration_without_noise(tiny_run):
    run_dir, _, _ = tiny_run
    results = json.loads((run_dir / "results.json").read_text())
    out = last_json("first_finetune_iteration.py", str(run_dir), "--kl-step", "1.0", "0.05")
    assert out["run_kl_step"] == 1.0 and out["holdout"] == results["holdout"]
    at_run, small = out["by_kl_step"]["1.0"], out["by_kl_step"]["0.05"]
    # the run's own first iteration, redone: its network scores what the run's curve says
    assert at_run["network_after_test"] == pytest.approx(results["finetune"]["composed"][1], abs=1e-4)
    assert small["network_before"] == at_run["network_before"]  # the same bank, noise-free
    assert small["linearisation"] == at_run["linearisation"]  # and the same first samples
    assert small["kl"] < at_run["kl"]  # the C-steps kept nearer the network
    # the fitted model's view of the same controllers: the linearisation is the LQR's centre,
    # and a wider trust region lets it promise more
    assert small["linearisation_predicted"] == at_run["linearisation_predicted"]
    promised = {
        kl: f["linearisation_predicted"] - f["first_c_step_predicted"] for kl, f in out["by_kl_step"].items()
    }
    assert promised["1.0"] > promised["0.05"] > 0, promised
    names = {"network_before", "linearisation", "first_c_step", "last_c_step", "network_after", "untouched"}
    assert names <= set(at_run) and all(at_run[name] >= 0 for name in names)
    assert out["policy_linearization"] == "regression"  # the run's
    by_jacobian = last_json("first_finetune_iteration.py", str(run_dir), "--policy-linearization", "jacobian")
    exact = by_jacobian["by_kl_step"]["1.0"]
    assert by_jacobian["policy_linearization"] == "jacobian"
    assert exact["network_before"] == at_run["network_before"]  # the same bank and samples,
    assert exact["linearisation"] != at_run["linearisation"]  # linearised another way


def test_first_finetune_iteration_separates_pilqrs_lqr_step_from_pi2s_correction(tiny_run):
    run_dir, _, _ = tiny_run
    out = last_json("first_finetune_iteration.py", str(run_dir), "--algo", "mdgps", "--c-step", "pilqr")
    figures = out["by_kl_step"]["1.0"]
    assert (out["algo"], out["c_step"]) == ("mdgps", "pilqr")
    assert figures["first_lqr_part"] != figures["first_c_step"]  # PI2 moved the LQR's controllers
    assert figures["first_c_step"] == figures["last_c_step"]  # MDGPS: one C-step per iteration
    done = run_script(BENCHMARKS / "first_finetune_iteration.py", str(run_dir), "--c-step", "pi2")
    assert done.returncode != 0 and "use algo=mdgps" in done.stderr  # the run's BADMM, refused


def test_first_finetune_iteration_can_regress_onto_the_networks_own_linearisation(tiny_run):
    """The control puts the controllers back after each C-step: the C-steps are those of the
    plain rerun, and only what the S-step regresses onto, so the network after, changes."""
    run_dir, _, _ = tiny_run
    plain = last_json("first_finetune_iteration.py", str(run_dir))["by_kl_step"]["1.0"]
    out = last_json("first_finetune_iteration.py", str(run_dir), "--s-step-onto", "linearisation")
    control = out["by_kl_step"]["1.0"]
    assert out["s_step_onto"] == "linearisation"
    assert control["first_c_step"] == plain["first_c_step"]
    assert control["linearisation"] == plain["linearisation"]
    assert control["network_after"] != plain["network_after"]


def test_finetune_per_scene_keeps_each_sample_with_its_scene():
    """Samples ``[M, N, T]`` flattened for ``object_contact.contact`` and back: sample (m, n)
    pulls the handle its own distance, with the end effector its own offset below it."""
    per_scene = load_benchmark("finetune_per_scene")
    task = get_world("three_link", "drawer_horizontal").task
    M, N, T = 2, 3, 6
    pulled = 0.01 * torch.arange(1, M * N + 1, dtype=torch.float64).reshape(M, N)
    below = 0.02 + 0.01 * torch.arange(N, dtype=torch.float64).expand(M, N)
    along = torch.linspace(0, 1, T, dtype=torch.float64)
    states = torch.zeros(M, N, T, task.state_dim, dtype=torch.float64)
    states[..., task.slot("handle")] = torch.stack(
        [0.9 - along * pulled[..., None], torch.full((M, N, T), 0.4, dtype=torch.float64)], -1
    )
    states[..., task.slot("ee")] = states[..., task.slot("handle")]
    states[..., task.slot("ee")][..., 1] -= below[..., None]
    states[:, :, 0, task.slot("ee")] = 0.0  # each sample starts with the arm away
    found = per_scene.contact(task, per_scene._as_rollout(states))
    torch.testing.assert_close(found["object_moved"].reshape(M, N), pulled)
    torch.testing.assert_close(found["closest_approach"].reshape(M, N), below)
    offset = found["offset_at_closest"].reshape(M, N, 2)
    torch.testing.assert_close(offset, torch.stack([torch.zeros(M, N, dtype=torch.float64), -below], -1))


@pytest.fixture(scope="module")
def tiny_drawer_run(tmp_path_factory):
    """A few seconds of manipulation: 1 GPS iteration, then 2 of fine-tuning the composed start
    on three_link/drawer_horizontal's 4 drawers with MDGPS and PI2, as experiment 2 fine-tunes."""
    run_dir = tmp_path_factory.mktemp("tiny_drawer_run")
    done = run_py(
        "universe=manipulation",
        "logger=csv",
        "gps.iterations=1",
        "gps.horizon=20",
        "gps.samples_per_condition=2",
        "gps.sgd_steps=20",
        "gps.initial_sgd_steps=20",
        "finetune=true",
        "eval.finetune_iterations=2",
        "eval.finetune_starts=[composed]",
        "eval.finetune_algo=mdgps",
        "eval.finetune_c_step=pi2",
        "eval.finetune_samples_per_condition=4",
        "eval.finetune_num_conditions=4",
        "eval.random_conditions=0",
        f"hydra.run.dir={run_dir}",
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return run_dir


def test_finetune_per_scene_reruns_the_runs_fine_tuning_and_splits_its_figures_by_scene(tiny_drawer_run):
    results = json.loads((tiny_drawer_run / "results.json").read_text())
    done = run_script(BENCHMARKS / "finetune_per_scene.py", str(tiny_drawer_run))
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout.splitlines()[-1])
    diagnosed = results["finetune_diagnostics"]["composed"]
    assert out["matches_run"] and out["compared_iterations"] == out["iterations"] == 2
    scenes = out["scenes"]
    assert len(scenes) == 4 and len(out["touched_by_iteration"]) == 2
    # the per-scene figures average to the run's own, iteration by iteration
    for i, iteration in enumerate(diagnosed):
        mean = np.mean([scene["sampled"]["by_iteration"][i] for scene in scenes])
        assert mean == pytest.approx(iteration["distance"], abs=1e-4)
        worst = max(scene["sampled"]["by_iteration"][i] for scene in scenes)
        assert worst == pytest.approx(iteration["distance_worst_condition"], abs=1e-4)
    assert out["counts"]["within"] == diagnosed[-1]["conditions_within"]
    assert sum(out["counts"].values()) == 4
    network = np.mean([scene["network"]["final"] for scene in scenes])
    assert network == pytest.approx(results["finetune_training"]["composed"][0], abs=1e-4)
    for scene in scenes:
        assert len(scene["params"]) == 4 and len(scene["arm_qpos"]) == 3  # a drawer, three joints
        assert len(scene["network"]["offset_at_closest"]) == 2
        if scene["outcome"] == "never_moved":
            assert scene["sampled"]["most_moved"] < out["moved_threshold"]


def test_finetune_per_scene_refuses_a_world_without_an_object_and_no_iterations(tiny_run, tiny_drawer_run):
    run_dir, _, _ = tiny_run
    done = run_script(BENCHMARKS / "finetune_per_scene.py", str(run_dir))
    assert done.returncode == 2 and "moves nothing but the end effector" in done.stderr
    done = run_script(BENCHMARKS / "finetune_per_scene.py", str(tiny_drawer_run), "--iterations", "0")
    assert done.returncode == 2 and "--iterations must be at least 1, got 0" in done.stderr


def per_scene_output(seed: int, first_touched: list[int | None], outcomes: list[str]) -> dict:
    """What finetune_per_scene.py's last line holds, as much of it as the figure reads."""
    scenes = [
        {"sampled": {"first_touched": first, "by_iteration": [0.2, 0.1, 0.04]}, "outcome": outcome}
        for first, outcome in zip(first_touched, outcomes, strict=True)
    ]
    return {
        "run_command": f"python run.py universe=manipulation seed={seed} eval.finetune_seed=100",
        "holdout": "three_link/drawer_horizontal",
        "start": "composed",
        "success_distance": 0.05,
        "scenes": scenes,
    }


def test_per_scene_figure_counts_each_runs_scenes_by_when_they_were_first_moved(tmp_path):
    paths = []
    for seed, first, outcomes in (
        (4, [1, 1, 1], ["within", "within", "partly"]),
        (6, [1, 3, None], ["within", "within", "never_moved"]),
    ):
        paths.append(tmp_path / f"seed{seed}.json")
        paths[-1].write_text(json.dumps(per_scene_output(seed, first, outcomes)))
    args = ["per-scene-figure", *map(str, paths), "--experiment", "x", "--docs", str(tmp_path)]
    done = run_script(BENCHMARKS / "publish_results.py", *args)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout.splitlines()[-1])
    assert (tmp_path / "x.png").read_bytes().startswith(b"\x89PNG")
    first, second = (run["touched"] for run in summary["runs"])
    assert first["at the first iteration"] == {"scenes": 3, "within": 2} and first["never"]["scenes"] == 0
    assert second == {
        "at the first iteration": {"scenes": 1, "within": 1},
        "later": {"scenes": 1, "within": 1},
        "never": {"scenes": 1, "within": 0},
    }
    paths[0].write_text(json.dumps({"holdout": "x"}))  # not an output of finetune_per_scene.py
    done = run_script(BENCHMARKS / "publish_results.py", *args)
    assert done.returncode == 2 and "not an output of finetune_per_scene.py" in done.stderr


def test_interface_range_measures_the_held_out_interface_in_the_robot_modules_training_spreads():
    figures = load_script(BENCHMARKS / "interface_range.py", "interface_range").interface_figures
    seen = torch.randn(4000, 64, generator=torch.Generator().manual_seed(0))
    same = figures(seen[:2000], seen, seen)
    assert same["outside_heldout"] == same["outside_task_training"] == 0.0
    assert same["rms_heldout"] == pytest.approx(1.0, abs=0.03)
    assert same["rms_robot_training"] == pytest.approx(1.0, abs=0.03)
    # five spreads off in every entry: sqrt(1 + 5^2) in root mean square, and most entries
    # beyond the largest the robot module read (about 3.5 spreads up)
    shifted = figures(seen[:2000] + 5 * seen.std(0), seen, seen[:10] - 10)
    assert shifted["rms_heldout"] == pytest.approx(26**0.5, abs=0.1)
    assert shifted["outside_heldout"] > 0.8 and shifted["outside_task_training"] == 1.0


def test_interface_range_rolls_the_runs_held_out_world_out_as_its_zero_shot_table(tiny_run):
    run_dir, _, _ = tiny_run
    results = json.loads((run_dir / "results.json").read_text())
    lines = benchmark_lines("interface_range.py", str(run_dir), "--num-conditions", "3")
    out = json.loads(lines[-1])
    figures = out["runs"][str(run_dir)]
    assert lines[0].startswith(f"{run_dir}: relu, zero-shot")
    assert (out["num_conditions"], figures["activation"]) == (3, "relu")
    assert figures["holdout"] == results["holdout"]
    # the same random positions and policy as the run's own table of 3 random positions
    composed = results["random_conditions"]["methods"]["composed"]["mean"]
    assert figures["zero_shot"] == pytest.approx(composed, abs=1e-4)
    assert 0.5 < figures["rms_robot_training"] <= 1.0 + 1e-6  # standardised by itself
    assert figures["rms_heldout"] > 0 and 0 <= figures["outside_heldout"] <= 1
    done = run_script(BENCHMARKS / "interface_range.py", str(run_dir), "--num-conditions", "0")
    assert done.returncode == 2 and "--num-conditions must be at least 1, got 0" in done.stderr


def test_interface_range_refuses_a_monolithic_bank_in_one_line(tmp_path):
    (tmp_path / "bank").mkdir()
    (tmp_path / "bank" / "manifest.json").write_text("{}")
    (tmp_path / "results.json").write_text(json.dumps({"policy": "monolithic"}))
    done = run_script(BENCHMARKS / "interface_range.py", str(tmp_path))
    message = f"{tmp_path} trained a monolithic bank: only modular banks have an interface"
    assert done.returncode == 2 and message in done.stderr, done.stderr


@pytest.mark.parametrize(
    "script, missing",
    [
        ("score_bank.py", "no results.json, bank/manifest.json"),
        ("interface_range.py", "no results.json, bank/manifest.json"),
        ("object_contact.py", "no results.json, bank/manifest.json, .hydra/config.yaml"),
        ("first_finetune_iteration.py", "no results.json, bank/manifest.json, .hydra/config.yaml"),
        ("finetune_per_scene.py", "no results.json, bank/manifest.json, .hydra/config.yaml"),
        ("probe_vision.py", "no results.json, bank/manifest.json"),
    ],
)
def test_run_directory_benchmarks_name_what_an_unfinished_run_lacks_in_one_line(script, missing, tmp_path):
    (tmp_path / "bank").mkdir()
    done = run_script(BENCHMARKS / script, str(tmp_path))
    message = f"{tmp_path} is not a finished run.py run directory: {missing}"
    assert done.returncode == 2 and message in done.stderr, done.stderr


def test_imitation_capacity_fits_what_depends_on_scene_and_time_only_when_given_them():
    """Targets that depend on the condition and the time step alone, at one state: a network of
    the state can only fit their mean; one given the condition and the time fits them."""
    capacity = load_script(BENCHMARKS / "imitation_capacity.py", "imitation_capacity")
    M, N, T = 3, 2, 8
    condition = torch.arange(M)[:, None, None].expand(M, N, T)
    step = torch.arange(T)[None, None, :, None].expand(M, N, T, 1)
    phase = 2 * torch.pi * step / T + condition[..., None]
    target = torch.cat([phase.sin(), phase.cos()], -1).reshape(-1, 2)
    state = torch.zeros(M * N * T, 2)
    inputs = (state[:, :1], state[:, 1:], condition.reshape(-1), step.reshape(-1, 1))
    gaps = {}
    for name in ("state", "state_scene_time"):
        torch.manual_seed(0)
        net = capacity.Regressor(name, state_dim=2, action_dim=2, conditions=M, horizon=T, hidden=(32, 32))
        capacity.fit(net, inputs, target, steps=1500, seed=0)
        with torch.no_grad():
            gaps[name] = capacity.clipped_gap(net(*inputs), target)
    assert gaps["state"] == pytest.approx(float(target.norm(dim=-1).mean()), rel=0.05)  # the mean, 0
    assert gaps["state_scene_time"] < 0.1 * gaps["state"], gaps
    # where the targets' variance lies: none between one cell's samples or from step to step
    # here; all between the samples in noise with zero mean in every cell; all from step to
    # step in a flip every step (40 steps: away from the edges the filter leaves the mean)
    assert capacity.variance_shares(target.reshape(M, N, T, 2))["within_cell_share"] == 0.0
    by_scene = torch.arange(4.0)[:, None, None, None].expand(4, 2, 40, 2)
    assert capacity.variance_shares(by_scene) == {"within_cell_share": 0.0, "jitter_share": 0.0}
    noise = torch.randn(M, N, T, 2)
    assert capacity.variance_shares(noise - noise.mean(1, keepdim=True))["within_cell_share"] == 1.0
    flips = (torch.arange(40.0) % 2)[None, None, :, None].expand(4, 2, 40, 2)
    assert capacity.variance_shares(flips)["jitter_share"] > 0.95


def test_imitation_capacity_refits_the_networks_of_an_mdgps_fine_tuning(tiny_run):
    """On the run's bank and test positions (the same untouched curve point), two MDGPS
    iterations: the second's samples are the controllers'; the bank's network trained on
    without dropout fits their targets closer. The run's own BADMM is refused before any work."""
    run_dir, _, _ = tiny_run
    done = run_script(BENCHMARKS / "imitation_capacity.py", str(run_dir), "--iterations", "1")
    assert done.returncode != 0 and "use --algo mdgps" in done.stderr
    args = ["--algo", "mdgps", "--iterations", "2", "--sgd-steps", "200", "--hidden", "8"]
    out = last_json("imitation_capacity.py", str(run_dir), *args)
    assert out["rerun_curve"][0] == out["run_curve"][0] and len(out["rerun_curve"]) == 3
    assert out["fit_drawn_by"] == "controllers"  # the first iteration sampled the network
    assert set(out["networks"]) == {"network", "network_refit", "state", "state_time", "state_scene_time"}
    for name, figures in out["networks"].items():
        placed = name != "state_scene_time"  # that one knows only the training scenes
        tested = {"distance_test", "distance_random"} if placed else set()
        assert set(figures) == {"gap_fit", "gap_fresh", "gap_own", "distance"} | tested
    network, refit = out["networks"]["network"], out["networks"]["network_refit"]
    assert network["distance_test"] == out["rerun_curve"][-1]
    assert refit["gap_fit"] < network["gap_fit"], out["networks"]
    assert len(out["takeover"]) == 3 and all(0 <= d < 10 for d in out["takeover"].values()), out["takeover"]
    # other feedback gains, the controllers' noise-free path kept: alone they end where they did
    refitted = dict(out["takeover_refitted"])
    away = refitted.pop("departure")  # the network from the controllers' path, where they take over
    assert list(away["network"]) == list(away["samples"]) == list(away["farthest"]) == list(out["takeover"])
    assert all(d > 0 for d in away["samples"].values()), away  # the samples' noise
    assert all(d >= 0 for d in away["network"].values()), away
    assert set(refitted) == {"kept", "track_0.01", "track_0.1", "track_1", "task"}
    assert refitted["kept"]["takeover"] == out["takeover"]
    for name, figures in refitted.items():
        assert figures["controllers"] == pytest.approx(out["controllers"], abs=1e-3), (name, figures)
        assert list(figures["takeover"]) == list(out["takeover"]) and figures["feedback_norm"] >= 0
    assert len({figures["feedback_norm"] for figures in refitted.values()}) == len(refitted)
    # under PI2, which fits no model, the gains come from dynamics fitted to its samples
    pi2 = ["--c-step", "pi2", "--pi2-covariance-damping", "2", "--refit-weights", "0.1", "--hidden", "4"]
    out = last_json("imitation_capacity.py", str(run_dir), *args[:4], "--sgd-steps", "1", *pi2)
    refitted = out["takeover_refitted"]
    assert out["c_step"] == "pi2" and set(refitted) == {"departure", "kept", "track_0.1", "task"}
    for name in ("track_0.1", "task"):
        assert refitted[name]["controllers"] == pytest.approx(out["controllers"], abs=1e-3), refitted


def published_finetuning(seed: int, sampled: dict, curves: dict, command_extra: str = "") -> dict:
    """A docs/results JSON of one manipulation fine-tuning seed, as publish_results.py zero-shot
    writes it (only what finetune-figure reads)."""
    return {
        "seed": seed,
        "command": f"python run.py universe=manipulation finetune=true{command_extra} seed={seed}",
        "success_distance": 0.05,
        "finetune": {"curves": curves, "sampled": sampled},
    }


def test_finetune_figure_groups_seeds_into_experiments_and_finds_each_starts_first_success(tmp_path):
    publish = load_benchmark("publish_results")
    runs = [
        # entry i of "sampled" is iteration i + 1's samples; of "curves", the network after i iterations
        published_finetuning(1, {"composed": [0.1, 0.04]}, {"composed": [0.15, 0.06, 0.04]}),
        published_finetuning(0, {"composed": [0.03, 0.02]}, {"composed": [0.15, 0.15, 0.15]}),
        published_finetuning(
            0, {"composed": [0.1, 0.1], "scratch_shaping": [0.1, 0.01]}, {"composed": [0.15] * 3}, " c=pi2"
        ),
    ]
    fig, summary = publish.finetune_figure(runs)
    default, pi2 = summary["experiments"]["(no further options)"], summary["experiments"]["c=pi2"]
    assert default["seeds"] == [0, 1]  # sorted within the experiment
    assert default["first_success"]["composed"] == {"samples": {0: 1, 1: 2}, "network": {0: None, 1: 2}}
    assert pi2["first_success"]["scratch_shaping"] == {"samples": {0: 2}}  # it has no network curve
    assert len(fig.axes) == 4  # samples above, the network below, one column per experiment
    # at two seeds of the same length a thick median is drawn beside each seed's thin line
    assert [line.get_linewidth() for line in fig.axes[0].get_lines()][:3] == [0.7, 0.7, 2.2]
    # each column's legend names the starts it drew, not only the first column's
    legends = [[text.get_text() for text in ax.get_legend().get_texts()] for ax in fig.axes[:2]]
    assert legends == [["composed", "success distance"], ["composed", "scratch shaping", "success distance"]]

    # a run of an older commit that spelt an option differently joins its experiment
    relabelled = [
        published_finetuning(0, {"composed": [0.1]}, {}, " eval.finetune_relabel_policy_states=true"),
        published_finetuning(1, {"composed": [0.1]}, {}, " eval.finetune_relabel_policy_states=sampled"),
    ]
    _, summary = publish.finetune_figure(relabelled)
    assert list(summary["experiments"]) == ["(no further options)"]
    assert summary["experiments"]["(no further options)"]["seeds"] == [0, 1]

    bad = [published_finetuning(0, {}, {"composed": [0.15]})]
    with pytest.raises(ValueError, match="recorded no samples"):
        publish.finetune_figure(bad)
    with pytest.raises(ValueError, match="a seed is given twice"):
        publish.finetune_figure([runs[0], runs[0]])
    path = tmp_path / "not_finetuning.json"
    path.write_text(json.dumps(published_run(0, [0.1] * 4)))
    done = run_script(BENCHMARKS / "publish_results.py", "finetune-figure", str(path), "--experiment", "x",
                      "--docs", str(tmp_path))
    assert done.returncode == 2 and "not a published fine-tuning result" in done.stderr, done.stderr
    path.write_text(json.dumps(runs[1]))
    done = run_script(BENCHMARKS / "publish_results.py", "finetune-figure", str(path), "--experiment", "x",
                      "--docs", str(tmp_path))
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.splitlines()[-1])["figure"] == str(tmp_path / "x.png")
    assert (tmp_path / "x.png").read_bytes().startswith(b"\x89PNG")


def test_finetune_table_gives_each_starts_network_figures_and_the_seeds_that_reached_success(tmp_path):
    publish = load_benchmark("publish_results")
    runs = [
        # the network after 0, 1, 2, 3 iterations (the samples of iterations 1, 2, 3); exactly the
        # success distance is not below it
        published_finetuning(
            1,
            {"composed": [0.12, 0.05, 0.04]},
            {"composed": [0.15, 0.05, 0.04, 0.06], "scratch_shaping": [0.15, 0.15, 0.1498, 0.15]},
        ),
        published_finetuning(0, {}, {"composed": [0.15, 0.05, 0.07, 0.06], "scratch_shaping": [0.15] * 4}),
        published_finetuning(0, {}, {"composed": [0.15, 0.03, 0.03, 0.2]}, " eval.finetune_seed=100"),
    ]
    text, summary = publish.finetune_table(runs)
    experiments = summary["experiments"]
    default, redrawn = experiments["(no further options)"], experiments["eval.finetune_seed=100"]
    composed = default["composed"]
    assert list(composed["seeds"]) == [0, 1]  # sorted within the experiment
    assert composed["seeds"][1] == {
        "best": 0.04, "best_iteration": 2, "mean": 0.075, "first_success": 2, "iterations_within": 1,
        "flat": False, "samples": {"first": 0.12, "last": 0.04, "first_success": 3},
    }
    assert composed["seeds"][0]["first_success"] is None and composed["reached"] == [1]
    assert composed["mean_of_means"] == pytest.approx((0.075 + 0.0825) / 2, abs=1e-4)
    assert default["scratch_shaping"]["reached"] == [] and default["scratch_shaping"]["seeds"][1]["flat"]
    assert "samples" not in default["scratch_shaping"]["seeds"][1]  # only where the run recorded them
    assert redrawn["composed"]["seeds"][0]["best_iteration"] == 1  # the first of equal bests
    assert list(redrawn) == ["composed"]  # only the starts that ran
    # a markdown table per experiment: a row per seed, then how many reached and the mean of means
    assert "| 1 | **0.040 (2)** / 0.075, first 2, 1 its; 0.120 -> 0.040, first 3 | 0.150 flat |" in text
    assert "| 0 | 0.050 (1) / 0.083 | 0.150 flat |" in text
    assert "| reached | 1 of 2 | 0 of 2 |" in text and "| reached | 1 of 1 |" in text
    # several experiments (say, draws of one setting): per start and seed, how many reached it
    across = summary["across"]
    assert across["composed"] == {"seeds": {0: (1, 2), 1: (1, 1)}, "reached": 2, "runs": 3}
    assert across["scratch_shaping"]["reached"] == 0 and across["scratch_shaping"]["runs"] == 2
    assert "| 0 | 1 of 2 | 0 of 1 |" in text and "| all | 2 of 3 | 0 of 2 |" in text
    assert "across" not in publish.finetune_table(runs[:2])[1]  # one experiment: nothing to add up

    with pytest.raises(ValueError, match="a seed is given twice"):
        publish.finetune_table([runs[0], runs[0]])
    paths = []
    for i, run in enumerate(runs):
        paths.append(tmp_path / f"{i}.json")
        paths[-1].write_text(json.dumps(run))
    done = run_script(BENCHMARKS / "publish_results.py", "finetune-table", *map(str, paths))
    assert done.returncode == 0, done.stderr
    assert "| reached | 1 of 2 | 0 of 2 |" in done.stdout
    printed = json.loads(done.stdout.splitlines()[-1])
    assert printed["experiments"]["(no further options)"]["composed"]["reached"] == [1]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["0.json", "1.json", "2.json"]  # it writes nothing
    path = tmp_path / "not_finetuning.json"
    path.write_text(json.dumps(published_run(0, [0.1] * 4)))
    done = run_script(BENCHMARKS / "publish_results.py", "finetune-table", str(path))
    assert done.returncode == 2 and "not a published fine-tuning result" in done.stderr, done.stderr
    # the kinds that write under docs/ need the name to write it under
    done = run_script(BENCHMARKS / "publish_results.py", "finetune-figure", str(paths[0]))
    assert done.returncode == 2 and "give its name with --experiment" in done.stderr, done.stderr


def test_finetune_table_reads_a_shorter_budget_from_longer_runs(tmp_path):
    """``--iterations N``: each run's first N iterations, so a run of 100 gives the figures of 50."""
    publish = load_benchmark("publish_results")
    run = published_finetuning(
        0,
        {"composed": [0.12, 0.06, 0.04]},
        {"composed": [0.15, 0.06, 0.07, 0.04], "scratch_shaping": [0.15, 0.14, 0.13, 0.03]},
    )
    run["finetune"]["training_conditions"] = {"composed": [0.2, 0.1, 0.05, 0.01]}
    run["finetune"]["iterations_to_success"] = {"composed": 3, "scratch_shaping": 3}
    run["finetune"]["samples"] = {"composed": {"trajectories": 30, "env_steps": 600}}
    (cut,) = publish.first_iterations([run], 2)
    assert cut["finetune"]["iterations_to_success"] == {"composed": None, "scratch_shaping": None}
    assert cut["finetune"]["samples"] == {"composed": {"trajectories": 20, "env_steps": 400}}
    assert publish.first_iterations([run], 3)[0]["finetune"]["iterations_to_success"]["composed"] == 3
    curves = {"composed": [0.15, 0.06, 0.07], "scratch_shaping": [0.15, 0.14, 0.13]}
    assert cut["finetune"]["curves"] == curves
    assert cut["finetune"]["sampled"] == {"composed": [0.12, 0.06]}
    assert cut["finetune"]["training_conditions"] == {"composed": [0.2, 0.1, 0.05]}
    assert run["finetune"]["curves"]["composed"] == [0.15, 0.06, 0.07, 0.04]  # the run is left as it was
    composed = publish.finetune_table([cut])[1]["experiments"]["(no further options)"]["composed"]
    assert composed["reached"] == [] and composed["seeds"][0]["samples"]["first_success"] is None
    full = publish.finetune_table([run])[1]["experiments"]["(no further options)"]
    assert full["composed"]["reached"] == [0] and full["scratch_shaping"]["seeds"][0]["first_success"] == 3
    with pytest.raises(ValueError, match="seed 0's composed ran 3 iterations, fewer than 4"):
        publish.first_iterations([run], 4)

    path = tmp_path / "run.json"
    path.write_text(json.dumps(run))
    done = run_script(BENCHMARKS / "publish_results.py", "finetune-table", "--iterations", "2", str(path))
    assert done.returncode == 0, done.stderr
    assert "| 0 | 0.060 (1) / 0.093; 0.120 -> 0.060 | 0.130 (2) / 0.140 |" in done.stdout
    for bad, message in (("4", "fewer than 4"), ("0", "at least 1")):
        done = run_script(BENCHMARKS / "publish_results.py", "finetune-table", "--iterations", bad, str(path))
        assert done.returncode == 2 and message in done.stderr, done.stderr
    lowo = ("lowo", str(tmp_path), "--iterations", "2", "--experiment", "y")
    done = run_script(BENCHMARKS / "publish_results.py", *lowo)
    assert done.returncode == 2 and "lowo reads none" in done.stderr, done.stderr


def test_finetune_table_reads_the_network_on_its_training_conditions_where_asked(tmp_path):
    """``--network-on training``: the network run on the conditions its samples were drawn on
    (``training_conditions``), the figures of whether it follows its own samples."""
    publish = load_benchmark("publish_results")
    run = published_finetuning(0, {"composed": [0.12, 0.04]}, {"composed": [0.15, 0.09, 0.08]})
    run["finetune"]["training_conditions"] = {"composed": [0.16, 0.06, 0.03]}
    _, test = publish.finetune_table([run])
    text, training = publish.finetune_table([run], network_on="training")
    assert test["experiments"]["(no further options)"]["composed"]["reached"] == []
    composed = training["experiments"]["(no further options)"]["composed"]
    assert composed["reached"] == [0] and composed["seeds"][0]["best"] == 0.03
    assert composed["seeds"][0]["samples"] == {"first": 0.12, "last": 0.04, "first_success": 2}
    assert "the network on its training conditions" in text
    assert "| 0 | **0.030 (2)** / 0.083, first 2, 1 its; 0.120 -> 0.040, first 2 |" in text
    with pytest.raises(ValueError, match="recorded no network curve 'training_conditions'"):
        publish.finetune_table([published_finetuning(1, {}, {"composed": [0.15]})], network_on="training")
    with pytest.raises(ValueError, match="one of test, training, got 'train'"):
        publish.finetune_table([run], network_on="train")

    path = tmp_path / "run.json"
    path.write_text(json.dumps(run))
    script = BENCHMARKS / "publish_results.py"
    done = run_script(script, "finetune-table", "--network-on", "training", str(path))
    assert done.returncode == 0, done.stderr
    printed = json.loads(done.stdout.splitlines()[-1])["experiments"]["(no further options)"]
    assert printed["composed"]["reached"] == [0]
    done = run_script(script, "finetune-figure", str(path), "--network-on", "training", "--experiment", "x")
    assert done.returncode == 2 and "finetune-figure reads no other" in done.stderr, done.stderr


def test_imitation_capacity_takeover_hands_the_arm_from_the_network_to_the_controllers_at_its_step():
    """``takeover``: the network's mean actions before the step, then the controllers' mean
    actions at the states the network has led the arm to (DAgger's labels, acted out)."""
    capacity = load_script(BENCHMARKS / "imitation_capacity.py", "imitation_capacity")
    world, T, step = ("three_link", "reach_red"), 12, 6
    config = GPSConfig(samples_per_condition=1, num_conditions=4, horizon=T)
    trainer = GPSTrainer(ModuleBank.build(*[[name] for name in world], seed=0, dropout=0.0), [world], config)
    (state,) = trainer.states.values()
    gains, scenes = state.controller.gains, training_env(*world, config)
    network = trainer.bank.compose(*world)
    with evaluating(trainer.bank):  # mean actions, the controllers' too
        alone = scenes.rollout(T, network, break_when_any_done=False)
        takeover = capacity.Takeover(network, state.controller, step)
        handed = scenes.rollout(T, takeover, break_when_any_done=False)
    torch.testing.assert_close(handed["action"][:, :step], alone["action"][:, :step])
    asked = gains.mean_actions(state_of(handed)[:, None])[:, 0].to(handed["action"].dtype)
    torch.testing.assert_close(handed["action"][:, step:], asked[:, step:])
    assert not torch.allclose(handed["action"][:, step:], alone["action"][:, step:])
    distances = capacity.takeover_distances(trainer.bank, *world, scenes, state.controller)
    assert list(distances) == ["3", "6", "9"]
    assert distances["6"] == pytest.approx(float(scenes.final_distance(handed).mean()), abs=1e-4)
    assert trainer.bank.training  # the bank's mode is restored
