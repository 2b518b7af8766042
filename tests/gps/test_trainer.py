"""GPS over several worlds: training lowers every world's cost, errors name their place, state resumes."""

import copy
import dataclasses
import io
import math
import re

import pytest
import torch
from tensordict import TensorDict

import modnet.gps.trainer as trainer_module
from modnet.bank import ModuleBank
from modnet.evaluate import evaluating, training_env
from modnet.gps.cost import state_spread, time_weights
from modnet.gps.errors import NumericalError
from modnet.gps.pi2 import policy_log_ratio
from modnet.gps.sampling import STATE_KEYS, WorldSampler
from modnet.gps.trainer import GPSConfig, GPSTrainer
from modnet.specs import TORQUE_LIMIT

ROBOTS, TASKS = ["three_link", "four_link"], ["reach_red", "reach_black"]
GRID = [(r, t) for r in ROBOTS for t in TASKS]




def small_config(**overrides) -> GPSConfig:
    options = dict(
        samples_per_condition=3, num_conditions=4, horizon=20, sgd_steps=150, initial_sgd_steps=200,
        batch_per_world=32, kl_step=2.0, seed=0,
    )
    options.update(overrides)
    return GPSConfig(**options)


def trainer_for(worlds=GRID, **overrides) -> GPSTrainer:
    robots = sorted({r for r, _ in worlds})
    tasks = sorted({t for _, t in worlds})
    bank = ModuleBank.build(robots, tasks, seed=0, dropout=0.0)
    return GPSTrainer(bank, worlds, small_config(**overrides))


@pytest.mark.parametrize("algo", ["mdgps", "badmm"])
def test_multi_world_training_lowers_every_worlds_cost(algo):
    trainer = trainer_for(algo=algo)
    first = trainer.step()
    for _ in range(2):
        last = trainer.step()
    for world in first:
        assert last[world]["sampled_cost"] < 0.8 * first[world]["sampled_cost"], (world, first, last)
        assert last[world]["distance"] < first[world]["distance"], world
    expected = {"distance", "sampled_cost", "predicted_cost", "expected_cost"}
    expected |= {"kl", "eta", "step_mult", "action_gap"}
    assert expected <= set(last["three_link/reach_red"])
    if algo == "badmm":
        assert "nu" in last["three_link/reach_red"]
    # 3 iterations x 4 worlds x 4 conditions x 3 samples, 20 steps each
    assert trainer.samples == {"trajectories": 144, "env_steps": 144 * 20}


def test_the_per_condition_figures_count_the_conditions_within_and_name_the_farthest(monkeypatch):
    """``distance`` averages every sample; ``distance_worst_condition`` and ``conditions_within``
    say whether a falling mean is every condition moving or some moving while others stay put."""
    world = [("three_link", "reach_red")]
    reference = trainer_for(world)
    first = reference.step()["three_link/reach_red"]
    assert first["conditions_within"] == 0  # the arm starts far from every target
    per_condition = reference.states["three_link/reach_red"].samples.distance.mean(-1).sort().values
    assert per_condition.shape == (4,) and bool((per_condition.diff() > 0).all())
    # the same seeds again, with a success distance between the second and third conditions'
    # means: exactly two count as within
    trainer = trainer_for(world)
    sampler = trainer.states["three_link/reach_red"].sampler
    between = float(per_condition[1:3].mean())
    task = dataclasses.replace(sampler.world.task, success_distance=between)
    monkeypatch.setattr(sampler, "world", dataclasses.replace(sampler.world, task=task))
    diagnostics = trainer.step()["three_link/reach_red"]
    assert diagnostics["distance"] == first["distance"]  # the same samples
    assert diagnostics["conditions_within"] == 2
    assert diagnostics["distance_worst_condition"] == pytest.approx(float(per_condition[-1]))
    assert diagnostics["distance_worst_condition"] > diagnostics["distance"]


def test_on_a_contact_free_world_the_predicted_cost_is_what_the_new_controllers_then_sample():
    """``predicted_cost`` is the task cost alone, under the fitted dynamics: on reaching (smooth
    dynamics) it is within a factor of 2 of the next iteration's sampled cost, while BADMM's
    C-step objective (``expected_cost``, with its dual and policy terms) is not."""
    trainer = trainer_for([("three_link", "reach_red")], algo="badmm")
    history = [trainer.step()["three_link/reach_red"] for _ in range(4)]
    for before, after in zip(history[:-1], history[1:], strict=True):
        assert 0.5 < before["predicted_cost"] / after["sampled_cost"] < 2.0, (before, after)
    assert any(abs(d["expected_cost"] - d["predicted_cost"]) > 0.5 * d["sampled_cost"] for d in history)


def test_a_pixel_bank_trains_its_conv_task_modules_from_rendered_samples(monkeypatch):
    """From images (the paper's colour reach): the samples render, the S-step regresses on them."""
    bank = ModuleBank.build(["three_link"], ["reach_red", "reach_black"], pixels=True, seed=0)
    worlds = [("three_link", "reach_red"), ("three_link", "reach_black")]
    conv = bank.get("task", "reach_red").module.pixels.convs
    before = [p.detach().clone() for p in conv.parameters()]
    config = small_config(horizon=8, samples_per_condition=2, sgd_steps=3, initial_sgd_steps=3)
    trainer = GPSTrainer(bank, worlds, config, pixels=True)
    diagnostics = trainer.step()
    assert set(diagnostics) == {"three_link/reach_red", "three_link/reach_black"}
    pixels = trainer.states["three_link/reach_red"].samples.obs["task", "pixels"]
    assert pixels.dtype == torch.uint8 and pixels.shape[-3:] == (64, 80, 3) and pixels.float().std() > 10
    assert not any(torch.equal(p, b) for p, b in zip(conv.parameters(), before, strict=True))

    # the policy at every sample, a few rows at a time (bounded memory; 5 leaves a ragged last
    # pass), is the one-pass result
    monkeypatch.setattr(trainer_module, "PIXEL_ROWS_PER_PASS", 5)
    states = list(trainer.states.values())
    trainer.bank.eval()
    with torch.no_grad():
        chunked = trainer._forward_samples(states)
        whole = trainer.bank.forward_worlds({s.name: s.samples.obs for s in states})
    for part, one_pass in zip(chunked, whole.values(), strict=True):
        assert part.shape == one_pass.shape == (4, 2, 8)
        torch.testing.assert_close(part["loc"], one_pass["loc"])


def test_the_policy_at_the_samples_of_worlds_with_different_horizons(monkeypatch):
    """From images, reach (50 steps) beside push (100): the passes run out of reach's rows
    first, and every world still gets its own outputs in its samples' shape ``[M, N, T]``."""
    worlds = [("three_link", "reach"), ("three_link", "push")]
    bank = ModuleBank.build(["three_link"], ["reach", "push"], pixels=True, seed=0, dropout=0.0)
    config = small_config(horizon=None, samples_per_condition=1, sgd_steps=1, initial_sgd_steps=1)
    trainer = GPSTrainer(bank, worlds, config, pixels=True)
    states = list(trainer.states.values())
    for state in states:
        trainer._sample_and_fit(state)
    monkeypatch.setattr(trainer_module, "PIXEL_ROWS_PER_PASS", 64)
    with torch.no_grad():
        chunked = trainer._forward_samples(states)
        for state, part in zip(states, chunked, strict=True):
            alone = bank.forward_worlds({state.name: state.samples.obs})[bank.world(state.name)]
            assert part.shape == state.samples.obs.shape == alone.shape
            torch.testing.assert_close(part["loc"], alone["loc"])
    assert [s.samples.obs.shape[-1] for s in states] == [50, 100]


def test_convolutions_kept_as_they_start_with_train_convolutions_false():
    """``train_convolutions=False``: the S-step leaves every convolution as it was (pretraining's
    weights) and still trains the layers after the feature points and the robot module."""
    bank = ModuleBank.build(["three_link"], ["reach_red", "reach_black"], pixels=True, seed=0)
    worlds = [("three_link", "reach_red"), ("three_link", "reach_black")]
    before = {k: v.clone() for k, v in bank.state_dict().items()}
    config = small_config(horizon=8, samples_per_condition=2, sgd_steps=3, initial_sgd_steps=3)
    trainer = GPSTrainer(bank, worlds, dataclasses.replace(config, train_convolutions=False), pixels=True)
    trainer.step()
    changed = {k for k, v in bank.state_dict().items() if not torch.equal(v, before[k])}
    assert not {k for k in changed if ".pixels.convs." in k}
    assert {k for k in changed if k.startswith("factor_modules.task.reach_red.") and ".pixels." not in k}
    assert {k for k in changed if k.startswith("factor_modules.robot.three_link.")}
    assert all(p.requires_grad != (".pixels." in n) for n, p in bank.named_parameters())


def test_scenes_per_world_gives_each_arm_its_own_scenes_where_the_trainer_and_scoring_agree():
    """``scenes_per_world``: two arms on one task train on different block layouts (the same
    ones without it), and ``training_env`` serves each world the very scenes its trainer samples."""
    worlds = [("three_link", "reach_black"), ("four_link", "reach_black")]

    def black_blocks(env) -> torch.Tensor:  # where each copy's black block starts
        return env.world.task.part(env.reset()["task", "state"], "black")

    for per_world in (False, True):
        trainer = trainer_for(worlds=worlds, scenes_per_world=per_world)
        layouts = []
        for robot, task in worlds:
            scored = black_blocks(training_env(robot, task, trainer.config))
            sampler = trainer.states[f"{robot}/{task}"].sampler
            trained = black_blocks(sampler.env)[: sampler.num_conditions]
            torch.testing.assert_close(trained, scored, rtol=0, atol=0)
            layouts.append(scored)
        gap = (layouts[0] - layouts[1]).norm(dim=-1)
        assert (gap.min() > 0.01) if per_world else (gap.max() == 0), gap


def test_clip_targets_regresses_onto_the_torques_the_arms_apply():
    """``clip_targets``: the S-step's targets are the controllers' actions clipped to the torque
    limits (stiff first controllers ask for more), and training keeps to them."""
    trainer = trainer_for(worlds=GRID[:1], init_kp=20.0, clip_targets=True, sgd_steps=5, initial_sgd_steps=5)
    state = trainer.states["three_link/reach_red"]
    trainer._sample_and_fit(state)
    asked = state.controller.gains.mean_actions(state.samples.X)
    assert asked.abs().max() > TORQUE_LIMIT and (asked.abs() < TORQUE_LIMIT).any()
    targets = trainer._controller_targets(state)["target_action"]
    expected = asked.clamp(-TORQUE_LIMIT, TORQUE_LIMIT).to(torch.float32).reshape(-1, asked.shape[-1])
    torch.testing.assert_close(targets, expected, rtol=0, atol=0)
    unclipped = trainer_for(worlds=GRID[:1], init_kp=20.0)
    unclipped._sample_and_fit(unclipped.states["three_link/reach_red"])
    raw = unclipped._controller_targets(unclipped.states["three_link/reach_red"])["target_action"]
    assert raw.abs().max() > TORQUE_LIMIT
    trainer.step()  # BADMM's targets as well
    assert state.regression_data[:]["target_action"].abs().max() <= TORQUE_LIMIT


def test_seeded_runs_are_reproducible():
    a = trainer_for(worlds=GRID[:2]).step()
    b = trainer_for(worlds=GRID[:2]).step()
    assert a == b


@pytest.mark.parametrize("per_condition", [False, True])
def test_checkpoint_state_resumes_exactly(per_condition):
    """Continuing after a save/load round trip gives the same iteration as never stopping."""
    options = dict(worlds=GRID[:1], algo="badmm", dynamics_prior_per_condition=per_condition)
    original = trainer_for(**options)
    original.step()
    buffer = io.BytesIO()
    torch.save(original.state_dict(), buffer)
    buffer.seek(0)
    expected = original.step()  # the global RNG is shared: continue the original first
    state = torch.load(buffer, weights_only=True)
    other = dict(options, dynamics_prior_per_condition=not per_condition)
    with pytest.raises(ValueError, match="differ in gps.dynamics_prior_per_condition"):
        trainer_for(**other).load_state_dict(state)
    with pytest.raises(ValueError, match="4 conditions x 20 steps, this trainer 5 x 20: gps.num_conditions"):
        trainer_for(**options, num_conditions=5).load_state_dict(state)
    resumed = trainer_for(**options)
    resumed.load_state_dict(state)
    assert resumed.iteration == 1 and resumed.history == original.history[:1]
    first = float(state["seconds"])
    assert resumed.seconds == first > 0  # the wall time of the iteration before the save
    resumed_samples = {"trajectories": 12, "env_steps": 12 * 20}  # 4 conditions x 3 samples
    assert resumed.samples == resumed_samples
    assert resumed.step() == expected
    assert resumed.seconds > first and resumed.samples == original.samples
    with pytest.raises(ValueError, match="checkpoint trains worlds"):
        trainer_for(worlds=GRID[1:2]).load_state_dict(state)
    # a checkpoint from before the trainer kept its wall time and sample count still resumes,
    # from 0 s and the samples of its finished iterations
    older = {k: v for k, v in state.items() if k not in ("seconds", "drawn")}
    legacy = trainer_for(**options)
    legacy.load_state_dict(older)
    assert legacy.iteration == 1 and legacy.seconds == 0.0 and legacy.samples == resumed_samples


def test_planted_nan_names_world_condition_and_iteration(monkeypatch):
    trainer = trainer_for(worlds=GRID[:2])
    trainer.step()
    sampler = trainer.states["three_link/reach_black"].sampler
    sample = sampler.sample

    def poisoned(policy=None):
        samples = sample(policy)
        samples.X[1, 0, 5, 0] = float("nan")  # one state of condition 1
        return samples

    monkeypatch.setattr(sampler, "sample", poisoned)
    with pytest.raises(NumericalError, match=r"world=three_link/reach_black, condition=1, iteration=1"):
        trainer.step()


def test_the_dynamics_ridge_reaches_every_fit(monkeypatch):
    fit, ridges = trainer_module.fit_dynamics, []

    def recording(*args, **kwargs):
        ridges.append(kwargs["ridge"])
        return fit(*args, **kwargs)

    monkeypatch.setattr(trainer_module, "fit_dynamics", recording)
    trainer_for(worlds=GRID[:2], dynamics_ridge=1e-3, sgd_steps=10, initial_sgd_steps=10).step()
    assert ridges == [1e-3, 1e-3]  # one fit per world
    with pytest.raises(ValueError, match="gps.dynamics_ridge must be positive"):
        small_config(dynamics_ridge=0.0)


def test_pi2_is_refused_a_kl_its_samples_cannot_reach():
    """The weights of N samples are at most log N from uniform: asked for more, PI2 puts all the
    weight on one sample and its covariance collapses. 3 samples reach the default KL of 1."""
    with pytest.raises(ValueError, match=r"gps\.pi2_kl=1\.0 needs more than 2 samples .* at least 3,"):
        GPSConfig(algo="mdgps", c_step="pi2", samples_per_condition=2)
    GPSConfig(algo="mdgps", c_step="pi2", samples_per_condition=3)
    with pytest.raises(ValueError, match=r"at least 8, or a gps\.pi2_kl below 1\.95"):  # log 7 < 2 < log 8
        GPSConfig(algo="mdgps", c_step="pilqr", samples_per_condition=7, pi2_kl=2.0)
    GPSConfig(algo="mdgps", c_step="pilqr", samples_per_condition=8, pi2_kl=2.0)
    GPSConfig(samples_per_condition=2)  # the LQR's C-step weighs no samples


def test_the_step_multiplier_stays_within_its_bounds_and_bad_bounds_are_refused():
    bounds = dict(min_step_mult=0.7, max_step_mult=0.7)
    trainer = trainer_for(worlds=GRID[:1], **bounds, sgd_steps=10, initial_sgd_steps=10)
    assert trainer.config.lqr().min_mult == trainer.config.lqr().max_mult == 0.7
    history = [trainer.step()["three_link/reach_red"]["step_mult"] for _ in range(3)]
    assert history[0] == 1.0 and history[1:] == pytest.approx([0.7, 0.7])  # adapted from the second on
    for low, high in ((0.0, 1.0), (2.0, 1.0)):
        with pytest.raises(ValueError, match="min_step_mult must be positive and at most gps.max_step_mult"):
            GPSConfig(min_step_mult=low, max_step_mult=high)


@pytest.mark.parametrize(("ramp", "final"), [("constant", 5.0), ("quadratic", 1.0), ("final_only", 1.0)])
def test_the_cost_ramp_and_final_multiplier_weigh_the_samples_cost_along_time(ramp, final):
    """``gps.cost_ramp`` and ``gps.final_cost_multiplier`` weigh each step's cost of the samples
    (and so what the C-step plans on); the samples themselves are the same. A ramp the library
    does not know, or a multiplier that is not positive, is refused."""
    trainer = trainer_for(worlds=GRID[:1], cost_ramp=ramp, final_cost_multiplier=final, sgd_steps=9)
    trainer.step()
    state = trainer.states["three_link/reach_red"]
    raw = state.sampler.world.state_cost(state.samples.X, state.samples.U, trainer.config.shaping)
    weights = time_weights(20, ramp, final)
    torch.testing.assert_close(state.sampled_costs, raw * weights)
    first = {"constant": 1.0, "quadratic": 1 / 400, "final_only": 0.0}[ramp]  # 20 steps
    assert (float(weights[0]), float(weights[-1])) == pytest.approx((first, final))
    default = trainer_for(worlds=GRID[:1], sgd_steps=9)
    default.step()
    torch.testing.assert_close(default.states["three_link/reach_red"].samples.X, state.samples.X)
    ramps = "constant, linear, quadratic, final_only"
    with pytest.raises(ValueError, match=f"gps.cost_ramp must be one of {ramps}, got 'cubic'"):
        GPSConfig(cost_ramp="cubic")
    with pytest.raises(ValueError, match="gps.final_cost_multiplier must be positive, got 0.0"):
        GPSConfig(final_cost_multiplier=0.0)


@pytest.mark.parametrize("trained", ["robot", "task"])
def test_the_s_step_trains_only_the_modules_of_the_factor_it_is_given(trained):
    """``train_modules``: the other factor's modules get no gradient and act as before through
    the S-steps (their input normalisation is refitted, which their first layer absorbs)."""
    trainer = trainer_for(worlds=GRID[:1], train_modules=trained, sgd_steps=10, initial_sgd_steps=10)
    parts = trainer.bank.parts(trainer.bank.world(*GRID[0]))
    trainer.step()  # samples to run the modules on
    obs = trainer.states["three_link/reach_red"].samples.obs.reshape(-1)[:64].clone()
    obs["interface", "task"] = torch.randn(64, parts["task"].arch.outputs["interface", "task"])

    def outputs() -> dict[str, torch.Tensor]:
        """Each module on the same inputs (the robot module on a fixed interface)."""
        with evaluating(trainer.bank):
            return {factor: module(obs.clone()).get(module.out_keys[0]) for factor, module in parts.items()}

    before = outputs()
    for _ in range(2):
        trainer.step()
    after = outputs()
    for factor, module in parts.items():
        kept = torch.allclose(after[factor], before[factor], atol=1e-5)
        assert kept == (factor != trained), factor
        assert all(p.requires_grad == (factor == trained) for p in module.parameters()), factor


def test_training_one_factor_of_a_monolithic_bank_is_refused():
    bank = ModuleBank.build(ROBOTS[:1], TASKS[:1], seed=0, policy="monolithic")
    refusal = "gps.train_modules=task trains one factor's modules, and bank.policy=monolithic has one network"
    with pytest.raises(ValueError, match=refusal):
        GPSTrainer(bank, GRID[:1], small_config(train_modules="task"))
    with pytest.raises(ValueError, match="gps.train_modules must be one of all, task, robot, got 'arm'"):
        small_config(train_modules="arm")


def test_training_a_factor_the_bank_lacks_is_refused_before_any_world_is_built():
    """A bank whose factors are not (task, robot) names its own; the empty bank would otherwise
    fail on the world's missing modules, so the message proves the check comes first."""
    bank = ModuleBank(("task", "arm"))
    with pytest.raises(ValueError, match="gps.train_modules='robot': valid for this bank: all, arm, task"):
        GPSTrainer(bank, GRID[:1], small_config(train_modules="robot"))


@pytest.mark.parametrize("algo", ["mdgps", "badmm"])
def test_a_condition_no_eta_brings_to_its_kl_bound_keeps_its_centre_and_training_goes_on(
    algo, monkeypatch, caplog
):
    """No eta below the cap meets a KL bound of 1e-9: every condition keeps the controllers its
    KL is measured from (the policy's linearisation in MDGPS, the sampling controllers in
    BADMM), says so in the log with its place and the last KL, and the next iteration runs."""
    solve, centres = trainer_module.c_step, []

    def recording(cost, dynamics, prev, **kwargs):
        centres.append(prev)
        return solve(cost, dynamics, prev, **kwargs)

    monkeypatch.setattr(trainer_module, "c_step", recording)
    trainer = trainer_for(worlds=GRID[:1], algo=algo, kl_step=1e-9, max_eta=1e-3)
    with caplog.at_level("WARNING", logger="modnet.gps.trainer"):
        first = trainer.step()
    kept, centre = trainer.states["three_link/reach_red"].controller.gains, centres[-1]
    for name in ("K", "k", "cov"):  # the controller keeps chol; its cov is chol chol' again
        torch.testing.assert_close(getattr(kept, name), getattr(centre, name).double(), rtol=0, atol=1e-12)
    world = first["three_link/reach_red"]
    assert world["held_conditions"] == 4 and world["kl"] < 1e-12
    warned = [r.getMessage() for r in caplog.records if r.name == "modnet.gps.trainer"]
    place = r"\[world=three_link/reach_red, condition=(\d), iteration=0\]; the condition keeps the"
    held = {re.search(place, w).group(1) for w in warned}  # BADMM: once per inner C-step
    assert held == {"0", "1", "2", "3"}, warned
    assert all("eta reached its cap 0.001 without meeting the KL target (last KL" in w for w in warned)
    assert trainer.step()["three_link/reach_red"]["held_conditions"] == 4 and trainer.iteration == 2


def test_a_condition_that_meets_its_kl_bound_is_not_held():
    diagnostics = trainer_for(worlds=GRID[:1]).step()["three_link/reach_red"]
    assert diagnostics["held_conditions"] == 0 and diagnostics["kl"] > 0


@pytest.mark.parametrize("algo", ["mdgps", "badmm"])
def test_a_condition_held_max_held_iterations_in_a_row_stops_the_run_even_across_a_resume(algo):
    """The count of iterations a condition has been held in a row goes into the checkpoint; the
    iteration that brings it to ``max_held_iterations`` raises, naming the condition and its
    dynamics. BADMM's several C-steps an iteration count once."""
    options = dict(worlds=GRID[:1], algo=algo, kl_step=1e-9, max_eta=1e-3, max_held_iterations=2)
    trainer = trainer_for(**options)
    assert trainer.step()["three_link/reach_red"]["held_conditions"] == 4
    resumed = trainer_for(**options)
    resumed.load_state_dict(trainer.state_dict())
    stopped = (
        r"held at its centre 2 iterations in a row \(gps.max_held_iterations=2\): no eta up to the cap "
        r"0.001 meets its KL bound; the fitted dynamics of this condition let a deviation grow .*"
        r"\[world=three_link/reach_red, condition=0, iteration=1\]$"
    )
    with pytest.raises(NumericalError, match=stopped):
        resumed.step()
    with pytest.raises(ValueError, match="gps.max_held_iterations must be at least 1, got 0"):
        small_config(max_held_iterations=0)


def test_the_bank_acts_without_dropout_and_trains_again_even_when_sampling_fails(monkeypatch):
    trainer = trainer_for(worlds=GRID[:1])
    state = trainer.states["three_link/reach_red"]
    modes = []

    def failing(actor):
        modes.append(trainer.bank.training)
        raise RuntimeError("the simulator stopped")

    monkeypatch.setattr(state.sampler, "sample", failing)
    with pytest.raises(RuntimeError, match="the simulator stopped"):
        trainer.step()
    assert modes == [False] and trainer.bank.training


def test_a_c_step_failure_describes_the_fitted_dynamics_that_blew_up(monkeypatch, caplog):
    """A fit whose joint-velocity entry grows 30x a step (as a contact's fit carried to a
    condition without the contact did on the drawer) leaves no eta with a PD Q_uu, or none that
    meets the KL bound; the error, or the warning, names the condition and says how fast, and
    from which state entry, the fit blows up."""
    fit, fits = trainer_module.fit_dynamics, []

    def unstable_from_the_second_fit(*args, **kwargs):
        dynamics = fit(*args, **kwargs)
        fits.append(dynamics)
        if len(fits) == 1:
            return dynamics
        F = dynamics.F.clone()
        F[1, 5:-1, 3, 3] = 30.0  # qd_joint0 of condition 1 feeds itself from step 5 on
        return dataclasses.replace(dynamics, F=F)

    monkeypatch.setattr(trainer_module, "fit_dynamics", unstable_from_the_second_fit)
    trainer = trainer_for(worlds=GRID[:1], sgd_steps=10, initial_sgd_steps=10)
    trainer.step()
    message = (
        r" grow by up to 30x a step \(step \d+, fed mostly by qd_joint0; above 1.05 at \d+ of 19 steps\) "
        r"\[world=three_link/reach_red, condition=1, iteration=1\]"
    )
    # which of the two the C-step hits first depends on rounding (it differs by CPU): no PD Q_uu
    # at any eta stops the run; no eta meeting the KL bound holds the condition with a warning
    with caplog.at_level("WARNING", logger="modnet.gps.trainer"):
        try:
            trainer.step()
        except NumericalError as error:
            assert re.search("positive-definite Q_uu.*" + message, str(error)), error
            assert trainer.iteration == 1  # the failed iteration did not finish
        else:
            warned = " ".join(r.getMessage() for r in caplog.records if r.name == "modnet.gps.trainer")
            assert re.search("eta reached its cap.*" + message, warned), warned
            assert trainer.iteration == 2
    assert trainer.samples == {"trajectories": 2 * 12, "env_steps": 2 * 12 * 20}  # 4 conditions x 3
    assert fits[0].spectral_radius()[1, 5:-1].max() < 2  # the fit as it came: no such growth
    state = trainer.states["three_link/reach_red"]
    state.current.dynamics.F[1, 7, 0, 0] = float("nan")
    nan_error = NumericalError("LQR K contains 1 NaN", world=state.name, condition=1, iteration=1)
    assert GPSTrainer._with_dynamics_note(nan_error, state) is nan_error  # no note from a NaN fit


def test_fine_tuning_starts_from_the_composed_policy():
    """init_from_policy: the first samples come from the trained modules, not from scratch."""
    teacher = trainer_for(worlds=GRID[:1])
    for _ in range(3):
        teacher.step()
    scratch = trainer_for(worlds=GRID[:1]).step()["three_link/reach_red"]
    tuned = GPSTrainer(teacher.bank, GRID[:1], small_config(init_from_policy=True))
    first = tuned.step()["three_link/reach_red"]
    assert first["distance"] < 0.7 * scratch["distance"]


@pytest.mark.parametrize("algo", ["mdgps", "badmm"])
def test_sample_on_policy_samples_the_network_after_the_first_iteration(algo):
    """sample_on_policy (the GPS code's option): from the second iteration on the samples come
    from the composed policy, not the controllers, and the C-step is centred on the policy's
    linearisation as it acts; the first iteration is the start's (the policy when fine-tuning,
    the controllers from scratch). Without it, only fine-tuning's first iteration samples the policy."""
    teacher = trainer_for(worlds=GRID[:1])
    teacher.step()
    cases = [
        (dict(init_from_policy=True, sample_on_policy=True), ["policy", "policy", "policy"]),
        (dict(init_from_policy=False, sample_on_policy=True), ["controllers", "policy", "policy"]),
        (dict(init_from_policy=True, sample_on_policy=False), ["policy", "controllers", "controllers"]),
    ]
    for options, expected in cases:
        trainer = GPSTrainer(copy.deepcopy(teacher.bank), GRID[:1], small_config(algo=algo, **options))
        (state,) = trainer.states.values()
        sample, actors = state.sampler.sample, []

        def spy(actor=None, sample=sample, actors=actors, state=state):
            actors.append("controllers" if actor is state.controller else "policy")
            return sample(actor)

        state.sampler.sample = spy
        for _ in range(3):
            diagnostics = trainer.step()[state.name]
            assert math.isfinite(diagnostics["distance"]) and math.isfinite(diagnostics["kl"]), diagnostics
        assert actors == expected, options
        if options["sample_on_policy"]:  # the trust region's centre is what was sampled
            sampled_with = state.current.gains.mean_actions(state.samples.X)
            assert not torch.allclose(sampled_with, state.controller.gains.mean_actions(state.samples.X))
            assert sampled_with.abs().max() <= 1.25 * TORQUE_LIMIT  # the policy as it acts: clipped


@pytest.mark.parametrize("algo", ["mdgps", "badmm"])
def test_fine_tuning_starts_from_the_policy_as_it_acts_in_the_world(algo):
    """A composed policy that asks for far more torque than the arm has (untrained on its world,
    as in fine-tuning) starts the controllers from what it applies: its clipped actions; and the
    first C-step stays near those, with a moderate eta.

    Linearising what it asks for gave controllers with huge gains and, while the dynamics were
    fitted to the clipped torques (before commit 9faa745), a first C-step whose eta ran to
    thousands (here, MDGPS) or past its cap (three_link/drawer_horizontal from a transferred
    bank). Fitted to the torques asked for, the unclipped start no longer blows up here (eta
    0.12), but it still starts from torque the arm does not have.
    """
    bank = ModuleBank.build(["three_link"], ["reach_red"], seed=0, dropout=0.0)
    with torch.no_grad():
        bank.factor_modules["robot"]["three_link"].module.head.mean.weight.mul_(300.0)
    untouched = copy.deepcopy(bank)  # the step's S-step trains the bank
    config = small_config(init_from_policy=True, algo=algo, sgd_steps=8, horizon=10)
    trainer = GPSTrainer(bank, GRID[:1], config)
    first = trainer.step()["three_link/reach_red"]
    (state,) = trainer.states.values()
    (asked,) = untouched.eval().forward_worlds({state.name: state.samples.obs}).values()
    assert asked["loc"].abs().max() > 10 * TORQUE_LIMIT  # the network does saturate
    started = state.current.gains.mean_actions(state.samples.X)  # the controllers' first gains
    assert started.abs().max() < 1.25 * TORQUE_LIMIT
    assert first["eta"] < 100, first
    if algo == "mdgps":  # reported against the controllers it sampled with: that linearisation
        assert first["action_gap"] < 0.5, first


def obs_of(state, X: torch.Tensor, dtype=torch.float64):
    """The observation a state policy reads at states ``X [..., dX]``: its robot and task parts."""
    n = 2 * state.sampler.world.robot.n_joints
    parts = {("robot", "state"): X[..., :n].to(dtype), ("task", "state"): X[..., n:].to(dtype)}
    return TensorDict(parts, batch_size=X.shape[:-1])


def test_policy_jacobians_are_the_networks_derivatives():
    """``gps.policy_linearization=jacobian`` differentiates the composed network at the samples
    (autograd through the bank): central differences agree. (A ReLU network's slope holds over
    a small neighbourhood only: the differences are taken in float64, 1e-6 apart.)"""
    teacher = trainer_for(worlds=GRID[:1])
    teacher.step()
    config = small_config(init_from_policy=True, policy_linearization="jacobian")
    trainer = GPSTrainer(teacher.bank, GRID[:1], config)
    (state,) = trainer.states.values()
    state.samples = state.sampler.sample(trainer._composed(state))
    trainer.bank.eval()
    (out,), (jacobian,) = trainer._outputs_and_jacobians([state])
    (plain,) = trainer._forward_samples([state])
    torch.testing.assert_close(out["loc"], plain["loc"])  # the outputs of the same pass
    X = state.samples.X[:1, :2, :3]  # a few samples suffice
    assert jacobian.shape == (*state.samples.X.shape[:3], 3, X.shape[-1])
    bank = copy.deepcopy(trainer.bank).double()
    policy = lambda x: bank.forward_worlds({state.name: obs_of(state, x)})[bank.world(state.name)]["loc"]
    eps = 1e-6
    steps = eps * torch.eye(X.shape[-1], dtype=X.dtype)
    with torch.no_grad():
        differences = torch.stack([(policy(X + e) - policy(X - e)) / (2 * eps) for e in steps], dim=-1)
    assert differences.abs().max() > 1.0  # the network does depend on the state
    torch.testing.assert_close(jacobian[:1, :2, :3], differences, atol=1e-4, rtol=1e-4)


def test_a_jacobian_linearisation_predicts_the_network_off_its_samples():
    """Fine-tuning's first linearisation, by the network's Jacobian, holds near the samples:
    at states one sample spread away from them it predicts the network's action better than
    the regression over 3 samples per step, which fits those samples (0.003 against 0.009
    there) and little else (0.08 against 0.02 here)."""
    teacher = trainer_for(worlds=GRID[:1])
    for _ in range(2):
        teacher.step()
    errors = {}
    for linearization in ("regression", "jacobian"):
        config = small_config(init_from_policy=True, policy_linearization=linearization, sgd_steps=1)
        trainer = GPSTrainer(copy.deepcopy(teacher.bank), GRID[:1], config)
        bank = copy.deepcopy(trainer.bank).eval()  # the network the controllers start from
        trainer.step()
        (state,) = trainer.states.values()
        g = torch.Generator().manual_seed(0)
        X = state.samples.X
        nearby = X + X.std(dim=1, keepdim=True) * torch.randn(X.shape, generator=g, dtype=X.dtype)
        with torch.no_grad():
            network = bank.forward_worlds({state.name: obs_of(state, nearby, torch.float32)})
            network = network[bank.world(state.name)]["loc"]
        network = network.double().clamp(-TORQUE_LIMIT, TORQUE_LIMIT)
        missed = state.current.gains.mean_actions(nearby) - network
        errors[linearization] = float(missed.norm(dim=-1).mean())
    assert errors["jacobian"] < 0.5 * errors["regression"], errors


def test_a_jacobian_trainer_fits_no_policy_prior_and_resumes_exactly():
    """The Jacobian needs no GMM over the policy's samples, so none is fitted; the checkpoint,
    with that prior empty, resumes to the same next iteration."""
    original = trainer_for(worlds=GRID[:1], policy_linearization="jacobian")
    original.step()
    (state,) = original.states.values()
    assert state.policy_prior.X is None and state.policy_prior.gmm.mu is None
    assert_resumes_exactly(original, worlds=GRID[:1], policy_linearization="jacobian")


def assert_resumes_exactly(original: GPSTrainer, **options) -> None:
    """``original``'s checkpoint, loaded into a fresh ``trainer_for(**options)``, takes the same
    next iteration as ``original`` itself."""
    buffer = io.BytesIO()
    torch.save(original.state_dict(), buffer)
    buffer.seek(0)
    expected = original.step()
    resumed = trainer_for(**options)
    resumed.load_state_dict(torch.load(buffer, weights_only=True))
    assert resumed.step() == expected


def test_a_jacobian_linearisation_needs_a_policy_that_reads_the_state():
    bank = ModuleBank.build(["three_link"], ["reach_red"], pixels=True, seed=0)
    with pytest.raises(ValueError, match="policy_linearization=jacobian needs a policy that reads the state"):
        GPSTrainer(bank, GRID[:1], small_config(policy_linearization="jacobian"), pixels=True)


def test_unknown_algorithm_and_missing_modules():
    bank = ModuleBank.build(["three_link"], ["reach_red"])
    with pytest.raises(ValueError, match="unknown GPS algorithm 'ilqr'; valid: mdgps, badmm"):
        GPSTrainer(bank, [("three_link", "reach_red")], GPSConfig(algo="ilqr"))
    with pytest.raises(ValueError, match="no task module 'reach_black'"):
        GPSTrainer(bank, [("three_link", "reach_black")], GPSConfig())


@pytest.mark.parametrize("sigma", [0.0, 2.0])
def test_noise_smoothing_shapes_the_exploration_of_the_samples(sigma):
    """``gps.noise_smoothing`` reaches the controllers the worlds are sampled with: what the
    samples' actions add to the controllers' means is white, or correlated over steps."""
    trainer = trainer_for(worlds=GRID[:1], noise_smoothing=sigma, horizon=40)
    trainer.step()
    state = trainer.states["three_link/reach_red"]
    samples = state.samples  # drawn with the gains ``current`` holds
    noise = samples.U - state.current.gains.mean_actions(samples.X)  # [M, N, T, dU]
    noise = noise - noise.mean(2, keepdim=True)
    lag1 = float(((noise[:, :, 1:] * noise[:, :, :-1]).sum(2) / noise.pow(2).sum(2)).mean())
    assert (lag1 > 0.8) if sigma else (abs(lag1) < 0.2), lag1
    with pytest.raises(ValueError, match="gps.noise_smoothing must be non-negative"):
        GPSConfig(noise_smoothing=-1.0)


def test_per_condition_priors_each_buffer_their_own_conditions_trajectories(monkeypatch):
    """With ``gps.dynamics_prior_per_condition`` each condition's dynamics fit is informed by a
    prior over that condition's latest trajectories only (the GPS code's arrangement), kept up
    to the buffer's size across iterations; the shared prior mixes all conditions."""
    fit, priors = trainer_module.fit_dynamics, []

    def recording(X, U, prior, **kwargs):
        priors.append(prior)
        return fit(X, U, prior, **kwargs)

    monkeypatch.setattr(trainer_module, "fit_dynamics", recording)
    trainer = trainer_for(worlds=GRID[:1], dynamics_prior_per_condition=True)  # M=4, N=3
    state = trainer.states["three_link/reach_red"]
    trainer.step()
    X1 = state.samples.X
    trainer.step()
    X2 = state.samples.X
    assert len(priors) == 2 and all(isinstance(p, list) and len(p) == 4 for p in priors)
    for m, prior in enumerate(state.dynamics_prior):
        torch.testing.assert_close(prior.X, torch.cat([X1[m], X2[m]]))  # 6 of at most 20
    shared = trainer_for(worlds=GRID[:1])
    shared.step()
    shared_prior = shared.states["three_link/reach_red"].dynamics_prior
    assert shared_prior.X.shape[0] == 12  # every condition's 3 samples in one buffer


def test_a_pi2_c_step_lowers_the_cost_from_the_samples_alone(monkeypatch):
    """``c_step="pi2"`` (MDGPS): the controllers move by reweighting their samples; no model is
    built (no cost expansion, no dynamics fit, no LQR), and the sampled cost falls on a real
    MuJoCo world."""

    def no_model(*args, **kwargs):
        raise AssertionError("the PI2 C-step needs no model of the world")

    for name in ("c_step", "fit_dynamics", "expand_cost"):
        monkeypatch.setattr(trainer_module, name, no_model)
    trainer = trainer_for([("three_link", "reach_red")], algo="mdgps", c_step="pi2", samples_per_condition=8)
    history = [trainer.step()["three_link/reach_red"] for _ in range(6)]
    assert history[-1]["sampled_cost"] < 0.8 * history[0]["sampled_cost"], history
    assert history[-1]["distance"] < history[0]["distance"], history
    assert all(0 < d["kl"] <= GPSConfig.pi2_kl + 1e-6 and d["step_mult"] == 1.0 for d in history)
    assert "predicted_cost" not in history[-1]  # nothing to predict with
    (state,) = trainer.states.values()
    assert state.sampled_costs.shape == (*state.samples.X.shape[:-1],)
    # reweighting around the controllers, it needs no linearisation of the policy: none is fitted
    assert state.policy is None and state.policy_prior.X is None


@pytest.mark.parametrize("damping", [2.0, 1e6])
def test_exploration_is_the_controllers_spread_which_pi2_shrinks_as_slowly_as_its_damping_says(damping):
    trainer = trainer_for(GRID[:1], algo="mdgps", c_step="pi2", pi2_covariance_damping=damping)
    spread = [trainer.step()["three_link/reach_red"]["exploration"] for _ in range(3)]
    cov = trainer.states["three_link/reach_red"].controller.gains.cov
    assert spread[-1] == pytest.approx(float(cov.diagonal(dim1=-2, dim2=-1).mean().sqrt()))
    if damping == 2.0:
        assert spread[0] < GPSConfig.init_variance**0.5 and spread[2] < spread[1] < spread[0]
    else:  # kept as the first controllers explored
        assert spread == pytest.approx([GPSConfig.init_variance**0.5] * 3, rel=1e-4)


def test_a_pi2_c_step_sampling_the_policy_reweights_around_its_linearisation():
    """With ``sample_on_policy`` PI2 keeps the gains ``K`` of the policy's linearisation, the
    distribution that drew the samples, and moves only the feed-forward term."""
    trainer = trainer_for([("three_link", "reach_red")], algo="mdgps", c_step="pi2", sample_on_policy=True)
    trainer.step()
    (state,) = trainer.states.values()
    trainer.step()  # samples the network
    assert state.policy is not None and torch.equal(state.current.gains.K, state.policy.K)
    assert torch.equal(state.controller.gains.K, state.policy.K)
    assert not torch.allclose(state.controller.gains.k, state.policy.k)


def test_a_policy_weight_holds_pi2s_controllers_near_the_network():
    """``pi2_policy_weight``: reweighting the samples also by how far each strayed from the
    composed policy gives controllers nearer the network's actions than PI2 alone, once the two
    have parted (at first the network has just been fitted to the controllers, and the term is
    nil). The term's mean is recorded under every PI2 step, and with the weight it does not
    grow as PI2 narrows the exploration (in the controllers' units it did, sixfold an
    iteration). Only PI2 sampling with the controllers takes the option."""
    gaps, kls = {}, {}
    for weight in (0.0, 10.0):
        trainer = trainer_for(GRID[:1], algo="mdgps", c_step="pi2", pi2_policy_weight=weight, sgd_steps=20)
        history = [trainer.step()["three_link/reach_red"] for _ in range(3)]
        (state,) = trainer.states.values()
        gap = state.controller.gains.mean_actions(state.samples.X) - state.policy_mean
        gaps[weight] = float(gap.norm(dim=-1).mean())
        kls[weight] = [d["policy_kl"] for d in history]
    X, U = state.samples.X, state.samples.U
    ratio = policy_log_ratio(state.current.gains, X, U, state.policy_mean, limit=TORQUE_LIMIT)
    assert kls[10.0][-1] == pytest.approx(float(ratio.sum(-1).mean()))
    assert gaps[10.0] < 0.9 * gaps[0.0], gaps
    assert history[-1]["exploration"] < 0.5 * history[0]["exploration"]  # PI2 narrows it
    assert kls[10.0][2] < 1.5 * kls[10.0][1], kls
    for refused in (
        dict(pi2_policy_weight=-1.0, c_step="pi2"),
        dict(pi2_policy_weight=float("nan"), c_step="pi2"),
        dict(pi2_policy_weight=1.0, c_step="lqr"),
        dict(pi2_policy_weight=1.0, c_step="pi2", sample_on_policy=True),
    ):
        with pytest.raises(ValueError, match="pi2_policy_weight .* positive only with gps.c_step=pi2"):
            GPSConfig(algo="mdgps", **refused)


def test_a_smoothed_pi2_step_changes_the_controllers_feed_forward_smoothly_along_time():
    """``pi2_step_smoothing`` on a real MuJoCo world: the C-step's change of the feed-forward
    (the controllers after it less those that sampled) moves far less from one time step to
    the next than PI2's raw change, and only PI2 takes the option."""
    roughness = {}
    for smoothing in (0.0, 3.0):
        options = dict(algo="mdgps", c_step="pi2", pi2_step_smoothing=smoothing, sgd_steps=20)
        trainer = trainer_for(GRID[:1], **options)
        trainer.step()
        (state,) = trainer.states.values()
        change = state.controller.gains.k - state.current.gains.k  # [M, T, dU]
        roughness[smoothing] = float(change.diff(dim=1).norm(dim=-1).mean() / change.norm(dim=-1).mean())
    assert roughness[3.0] < 0.3 * roughness[0.0], roughness
    for refused in (
        dict(pi2_step_smoothing=-1.0, c_step="pi2"),
        dict(pi2_step_smoothing=float("nan"), c_step="pi2"),
        dict(pi2_step_smoothing=float("inf"), c_step="pi2"),
        dict(pi2_step_smoothing=2.0, c_step="lqr"),
        dict(pi2_step_smoothing=2.0, c_step="pilqr"),
    ):
        with pytest.raises(ValueError, match="pi2_step_smoothing .* positive only with gps.c_step=pi2"):
            GPSConfig(algo="mdgps", **refused)


def test_pi2_with_the_policys_feedback_keeps_the_path_and_responds_off_it_as_the_network_does():
    """``pi2_policy_feedback`` on a real MuJoCo world: the controllers it gives act as PI2's on
    their noise-free path, and off it change their action as the network does (a finite
    difference of the network, not its autograd Jacobian); the step records how far PI2's
    feedback had come from the network's, and a trainer with the option changes the
    controllers' gains to the network's after each PI2 step. Only PI2 sampling with the
    controllers, on a policy that reads the state, takes the option."""
    trainer = trainer_for(GRID[:1], algo="mdgps", c_step="pi2", sgd_steps=20)
    trainer.step()
    (state,) = trainer.states.values()
    path = trainer._draw_mean(state, state.controller)
    old, new = state.controller.gains, trainer._with_policy_feedback(state)
    assert state.diagnostics["feedback_gap"] > 0
    on_path = path.X  # [M, 1, T, dX]
    assert torch.allclose(new.mean_actions(on_path), old.mean_actions(on_path), atol=1e-9)

    delta = 1e-4 * torch.randn(on_path.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    moved = path.obs.clone()
    sizes = [moved.get(key).shape[-1] for key in STATE_KEYS]
    for key, part in zip(STATE_KEYS, delta.split(sizes, dim=-1), strict=True):
        moved.set(key, moved.get(key) + part.to(moved.get(key).dtype))
    with trainer._acting(), torch.no_grad():
        (before,), (after,) = (trainer._forward_samples([state], [obs]) for obs in (path.obs, moved))
    network = (after["loc"] - before["loc"]).to(torch.float64)
    inside = before["loc"].abs() < 0.9 * TORQUE_LIMIT  # the network's Jacobian rows are zeroed beyond it
    assert inside.float().mean() > 0.5

    def miss(gains):  # how far the gains' response to ``delta`` is from the network's
        response = gains.mean_actions(on_path + delta) - gains.mean_actions(on_path)
        return float((response - network)[inside].norm() / network[inside].norm())

    assert miss(new) < 0.05 and miss(old) > 0.2, (miss(new), miss(old))  # PI2's feedback: otherwise

    with_feedback = trainer_for(GRID[:1], algo="mdgps", c_step="pi2", sgd_steps=20, pi2_policy_feedback=True)
    assert "feedback_gap" in with_feedback.step()["three_link/reach_red"]
    for refused in (
        dict(c_step="lqr"),
        dict(c_step="pilqr"),
        dict(c_step="pi2", sample_on_policy=True),
    ):
        with pytest.raises(ValueError, match="pi2_policy_feedback .* needs gps.c_step=pi2 and the control"):
            GPSConfig(algo="mdgps", pi2_policy_feedback=True, **refused)
    bank = ModuleBank.build(["three_link"], ["reach_red"], pixels=True, seed=0)
    config = small_config(algo="mdgps", c_step="pi2", pi2_policy_feedback=True)
    with pytest.raises(ValueError, match="pi2_policy_feedback differentiates a policy that reads the state"):
        GPSTrainer(bank, GRID[:1], config, pixels=True)


def test_a_feedback_weight_brings_the_networks_jacobian_to_the_controllers_gains():
    """``feedback_weight`` on a real MuJoCo world: after three MDGPS iterations with PI2 the
    network's Jacobian at the samples, in units of the state's spread, is far nearer the
    controllers' gains than the plain regression leaves it, and the term is recorded. Only
    MDGPS without relabelling, on a policy that reads the state, takes the option."""
    misses = {}
    for weight in (0.0, 100.0):
        trainer = trainer_for(GRID[:1], algo="mdgps", c_step="pi2", sgd_steps=100, feedback_weight=weight)
        diagnostics = [trainer.step()["three_link/reach_red"] for _ in range(3)]
        (state,) = trainer.states.values()
        with trainer._acting():
            _, (jacobian,) = trainer._outputs_and_jacobians([state])
        scale = state_spread(state.samples.X)
        gains = state.controller.gains.K[:, None] * scale
        misses[weight] = float((jacobian * scale - gains).norm() / gains.expand_as(jacobian).norm())
    assert misses[100.0] < 0.25 * misses[0.0], misses
    assert diagnostics[-1]["feedback_loss"] > 0
    for refused in (
        dict(feedback_weight=-1.0),
        dict(feedback_weight=float("inf")),
        dict(feedback_weight=1.0, algo="badmm"),
        dict(feedback_weight=1.0, relabel_policy_states="mean"),
    ):
        with pytest.raises(ValueError, match="feedback_weight .* positive only with algo=mdgps"):
            GPSConfig(**{"algo": "mdgps", **refused})
    bank = ModuleBank.build(["three_link"], ["reach_red"], pixels=True, seed=0)
    with pytest.raises(ValueError, match="feedback_weight differentiates a policy that reads the state"):
        GPSTrainer(bank, GRID[:1], small_config(algo="mdgps", feedback_weight=1.0), pixels=True)


def test_a_pi2_trainer_without_a_model_resumes_exactly():
    options = dict(worlds=GRID[:1], algo="mdgps", c_step="pi2")
    original = trainer_for(**options)
    original.step()
    assert original.states[GRID[0][0] + "/" + GRID[0][1]].current.dynamics is None
    assert_resumes_exactly(original, **options)


def test_a_pilqr_c_step_moves_the_lqrs_controllers_by_what_its_model_misses(monkeypatch):
    """``c_step="pilqr"`` (MDGPS): after each LQR step, PI2 on the residual cost moves its
    feed-forward and keeps its gains ``K``; the share of the cost the model misses is
    recorded, and the sampled cost falls on a real MuJoCo world."""
    lqr_steps, lqr = [], trainer_module.c_step

    def recording(*args, **kwargs):
        lqr_steps.append(lqr(*args, **kwargs))
        return lqr_steps[-1]

    monkeypatch.setattr(trainer_module, "c_step", recording)
    options = dict(algo="mdgps", c_step="pilqr", samples_per_condition=8)
    trainer = trainer_for([("three_link", "reach_red")], **options)
    history = [trainer.step()["three_link/reach_red"] for _ in range(6)]
    assert history[-1]["sampled_cost"] < 0.8 * history[0]["sampled_cost"], history
    assert all(0 < d["residual_share"] < 10 for d in history), history
    assert len(lqr_steps) == 6 and "predicted_cost" in history[-1]
    (state,) = trainer.states.values()
    assert torch.equal(state.controller.gains.K, lqr_steps[-1].gains.K)
    assert not torch.allclose(state.controller.gains.k, lqr_steps[-1].gains.k)


def test_pi2_and_pilqr_are_mdgps_c_steps():
    for c_step in ("pi2", "pilqr"):
        with pytest.raises(ValueError, match=f"c_step={c_step} is an MDGPS C-step.*algo=mdgps"):
            GPSConfig(c_step=c_step)
    with pytest.raises(ValueError, match="lqr, pi2, pilqr"):
        GPSConfig(c_step="cem", algo="mdgps")
    with pytest.raises(ValueError, match="must be positive"):
        GPSConfig(c_step="pi2", algo="mdgps", pi2_kl=0.0)


@pytest.mark.parametrize("relabel", ["sampled", "mean"])
def test_relabelling_adds_the_networks_own_states_labelled_by_the_controllers(relabel):
    """``relabel_policy_states`` (DAgger): after the C-step the network is rolled out alone, N
    times per condition with its noise ("sampled") or once with its mean actions ("mean"), and
    its states, labelled with the new controllers' mean actions, join the S-step's training set
    beside the controllers' samples; those rollouts are counted in the samples drawn."""
    trainer = trainer_for(worlds=GRID[:1], algo="mdgps", relabel_policy_states=relabel)
    (state,) = trainer.states.values()
    drawn = []
    original = WorldSampler.sample

    def spy(sampler, actor=None):
        out = original(sampler, actor)
        drawn.append(("controllers" if actor is state.controller else "policy", out))
        if relabel == "mean" and actor is not state.controller:  # the network's own mean actions
            with torch.no_grad():  # one float32 pass over the batch against step by step: the last
                # bits differ by CPU (1e-6 on a Xeon); the sampled noise would be 0.1 or more
                torch.testing.assert_close(actor(out.obs.clone())["loc"].double(), out.U, rtol=0, atol=1e-5)
        return out

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(WorldSampler, "sample", spy)
        for _ in range(2):
            diagnostics = trainer.step()[state.name]
    assert [who for who, _ in drawn] == ["controllers", "policy"] * 2
    visited = drawn[-1][1]
    M, N, T = state.samples.X.shape[:3]
    n_visited = N if relabel == "sampled" else 1
    assert visited.X.shape[:3] == (M, n_visited, T)
    assert trainer.samples["trajectories"] == 2 * M * (N + n_visited)
    data = state.regression_data.storage[:]
    assert data.shape == (M * (N + n_visited) * T,)
    relabelled = data[M * N * T :]
    labels = state.controller.gains.mean_actions(visited.X).reshape(-1, 3).to(torch.float32)
    torch.testing.assert_close(relabelled["target_action"], labels)
    torch.testing.assert_close(relabelled["robot", "state"], visited.obs["robot", "state"].reshape(-1, 6))
    assert not torch.allclose(relabelled["robot", "state"], data[: len(relabelled)]["robot", "state"])
    assert diagnostics["relabel_gap"] > 0 and 0 < diagnostics["policy_distance"] < 5
    assert trainer.bank.training  # the rollouts' eval mode is undone


@pytest.mark.parametrize("relabel", ["sampled", "mean"])
def test_relabelling_brings_the_network_nearer_the_controllers_where_it_acts_alone(relabel):
    """What relabelling is for: at the states the network visits by itself, its actions come
    nearer the controllers' than when it only imitates them at their own samples (seeds 0 to 3
    at these sizes: 0.48 to 0.79 times the gap, sampled or mean; an S-step long enough to fit, and a KL step
    small enough for the controllers' labels to hold near the network)."""
    gaps = {}
    for option in ("off", relabel):
        trainer = trainer_for(
            worlds=GRID[:1], algo="mdgps", relabel_policy_states=option, sgd_steps=400, kl_step=0.5
        )
        (state,) = trainer.states.values()
        for _ in range(3):
            trainer.step()
        trainer.bank.eval()
        torch.manual_seed(0)
        visited = state.sampler.sample(trainer.bank.compose(*GRID[0]))
        with torch.no_grad():
            (out,) = trainer._forward_samples([state], [visited.obs])
        gap = state.controller.gains.mean_actions(visited.X) - out["loc"].to(torch.float64)
        gaps[option] = float(gap.norm(dim=-1).mean())
    assert gaps[relabel] < 0.85 * gaps["off"], gaps


def test_relabelling_is_an_mdgps_s_step():
    with pytest.raises(ValueError, match="relabel_policy_states.*algo=mdgps"):
        GPSConfig(relabel_policy_states="sampled")


@pytest.mark.parametrize(("c_step", "relabel"), [("lqr", "mean"), ("pi2", "sampled")])
def test_a_tracking_weight_relabels_with_the_controllers_feedback_fitted_anew(c_step, relabel):
    """``relabel_tracking_weight``: the network's states are labelled by the controllers with
    feedback gains from an LQR tracking their noise-free path (one more mean rollout per
    condition, counted), on the C-step's model or, under PI2, one fitted to the samples: the
    same actions on that path, other ones off it."""
    relabelling = dict(relabel_policy_states=relabel, relabel_tracking_weight=1e-3)
    trainer = trainer_for(worlds=GRID[:1], algo="mdgps", c_step=c_step, **relabelling)
    (state,) = trainer.states.values()
    drawn, experts = [], []
    original_sample, original_tracking = WorldSampler.sample, GPSTrainer._tracking

    def spy(sampler, actor=None):
        out = original_sample(sampler, actor)
        drawn.append(("controllers" if actor is state.controller else "policy", out))
        return out

    def tracking(self, state):
        experts.append(original_tracking(self, state))
        return experts[-1]

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(WorldSampler, "sample", spy)
        patch.setattr(GPSTrainer, "_tracking", tracking)
        for _ in range(2):
            trainer.step()
    assert [who for who, _ in drawn] == ["controllers", "policy", "controllers"] * 2
    (_, samples), (_, visited), (_, path) = drawn[-3:]
    M, N, T = samples.X.shape[:3]
    n_visited = N if relabel == "sampled" else 1
    assert path.X.shape[:3] == (M, 1, T) and visited.X.shape[:3] == (M, n_visited, T)
    assert trainer.samples["trajectories"] == 2 * M * (N + n_visited + 1)
    expert, controllers = experts[-1], state.controller.gains
    torch.testing.assert_close(path.U, controllers.mean_actions(path.X))  # the noise-free path
    assert not torch.allclose(expert.K, controllers.K)
    torch.testing.assert_close(expert.mean_actions(path.X), controllers.mean_actions(path.X))  # on it
    labels = expert.mean_actions(visited.X)
    assert not torch.allclose(labels, controllers.mean_actions(visited.X))  # off it
    relabelled = state.regression_data.storage[:][M * N * T :]
    torch.testing.assert_close(relabelled["target_action"], labels.reshape(-1, 3).to(torch.float32))


def test_a_tracking_lqr_that_fails_under_pi2_describes_the_dynamics_it_fitted(monkeypatch):
    """Under PI2 the tracking LQR plans on dynamics fitted for it alone; where they blow up (a
    velocity entry growing 1e9x a step overflows the value function), the error names the world,
    condition and iteration and describes those dynamics, as the LQR's C-step's errors do."""
    fit = trainer_module.fit_dynamics

    def unstable(*args, **kwargs):
        dynamics = fit(*args, **kwargs)
        F = dynamics.F.clone()
        F[2, :-1, 3, 3] = 1e9
        return dataclasses.replace(dynamics, F=F)

    monkeypatch.setattr(trainer_module, "fit_dynamics", unstable)
    relabelling = dict(relabel_policy_states="mean", relabel_tracking_weight=1e-3)
    trainer = trainer_for(worlds=GRID[:1], algo="mdgps", c_step="pi2", **relabelling)
    message = (
        r"Q_uu is not positive definite.*; the fitted dynamics of this condition let a deviation grow by "
        r"up to 1e\+09x a step \(step \d+, fed mostly by qd_joint0.* \[world=three_link/reach_red, "
        r"condition=2, iteration=0\]"
    )
    with pytest.raises(NumericalError, match=message):
        trainer.step()


def test_a_tracking_weight_needs_relabelling_and_must_be_positive():
    with pytest.raises(ValueError, match="relabel_tracking_weight.*positive.*sampled or mean"):
        GPSConfig(algo="mdgps", relabel_tracking_weight=0.1)
    with pytest.raises(ValueError, match="relabel_tracking_weight.*got -1.0 with 'mean'"):
        GPSConfig(algo="mdgps", relabel_policy_states="mean", relabel_tracking_weight=-1.0)


def test_the_first_controllers_explore_with_init_variance_and_the_first_samples_spread_with_it():
    """``init_variance`` is the spread of a scratch start's first controllers (``eval.finetune_init_variance``
    widens fine-tuning's scratch starts): their covariance, and the spread of the torques they draw."""
    spreads = {}
    for variance in (1.0, 4.0):
        trainer = trainer_for(worlds=GRID[:1], init_variance=variance, samples_per_condition=8)
        (state,) = trainer.states.values()
        cov = state.controller.gains.cov
        torch.testing.assert_close(cov, variance * torch.eye(3, dtype=cov.dtype).expand_as(cov))
        samples = state.sampler.sample(state.controller)
        spreads[variance] = float((samples.U - state.controller.gains.mean_actions(samples.X)).std())
    assert 1.8 < spreads[4.0] / spreads[1.0] < 2.2, spreads  # the noise's std doubles
    with pytest.raises(ValueError, match="init_variance must be positive"):
        GPSConfig(init_variance=0.0)


def test_a_normalized_s_step_weighs_every_step_alike_and_keeps_the_controllers_spread():
    """``s_step_precision="normalized"``: where the controllers are a million times surer at a
    tenth of the (condition, step) pairs than at the rest, as PI2 can leave them late in
    fine-tuning, the S-step's precision has mean diagonal 1 at every sample (the
    controllers' own spans the million), ``precision_top_share`` reports the concentration
    either way, and the policy's fitted spread is the controllers' in both."""
    weighed, spreads = {}, {}
    for weighing in ("controllers", "normalized"):
        trainer = trainer_for(GRID[:1], algo="mdgps", c_step="pi2", s_step_precision=weighing)
        first = trainer.step()["three_link/reach_red"]
        assert first["action_gap_applied"] <= first["action_gap"]
        assert 0.1 <= first["precision_top_share"] < 0.5  # one PI2 step: nearly even
        (state,) = trainer.states.values()
        gains = state.controller.gains
        cov = gains.cov.clone()
        cov[:, :2] *= 1e-6  # 2 of 20 steps at every condition
        state.controller.set_gains(gains.from_covariance(gains.K, gains.k, cov))
        data = trainer._controller_targets(state)
        weighed[weighing] = data["precision"].diagonal(dim1=-2, dim2=-1).mean(-1)
        trainer._s_step(1, {state.name: data})
        assert state.diagnostics["precision_top_share"] > 0.9999
        module = list(trainer.bank.parts(trainer.bank.world(state.name)).values())[-1]
        spreads[weighing] = module.log_std.detach().exp()
    assert weighed["controllers"].max() / weighed["controllers"].min() > 1e5
    torch.testing.assert_close(weighed["normalized"], torch.ones_like(weighed["normalized"]))
    torch.testing.assert_close(spreads["normalized"], spreads["controllers"], rtol=1e-5, atol=0)
    with pytest.raises(ValueError, match="gps.s_step_precision must be one of controllers, normalized"):
        GPSConfig(s_step_precision="even")
