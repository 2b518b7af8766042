"""Typed run config, the conf/ groups, universes and their validation (all in-process, seconds)."""

import dataclasses
import functools
import logging

import pytest
from commands import ROOT
from hydra import compose, initialize_config_dir
from test_run import composed_run as composed
from test_run import load_run_module

from modnet.bank import BankConfig
from modnet.config import (
    BankSchema,
    ConfigError,
    EvalConfig,
    GPSSchema,
    RunConfig,
    flatten,
    register_configs,
    validate,
)
from modnet.gps.trainer import GPSConfig
from modnet.universes import UNIVERSES, Universe, UniverseError, get_universe, main, parse_world


# --- schemas derived from the library's dataclasses --------------------------------------------------
def test_schemas_hold_every_library_field_with_its_default():
    gps_fields = {f.name for f in dataclasses.fields(GPSSchema)}
    assert {f.name for f in dataclasses.fields(GPSConfig)} - gps_fields == {"init_from_policy"}
    assert {f.name for f in dataclasses.fields(BankConfig)} <= {
        f.name for f in dataclasses.fields(BankSchema)
    }
    run = RunConfig(universe="tiny")
    assert run.gps_config() == GPSConfig()
    assert run.bank_config() == BankConfig()


#: the tiny universe samples 2 per condition, and PI2 at its default KL of 1 needs 3
PI2_SAMPLES = "gps.samples_per_condition=3"


def test_overrides_reach_the_library_configs():
    run = composed(
        "universe=tiny",
        "gps.sgd_steps=7",
        "gps.dynamics_prior.max_clusters=3",
        "bank.task_hidden=[16]",
        "algo=badmm",
        "seed=4",
    )
    config = run.gps_config()
    assert (config.sgd_steps, config.dynamics_prior.max_clusters, config.algo, config.seed) == (
        7,
        3,
        "badmm",
        4,
    )
    assert run.bank_config().task_hidden == (16,)
    assert run.finetune_gps_config() == config  # fine-tuning samples as training does, by default
    tuned = composed("universe=tiny", "gps.sgd_steps=7", "eval.finetune_samples_per_condition=9")
    assert tuned.finetune_gps_config() == dataclasses.replace(tuned.gps_config(), samples_per_condition=9)
    assert tuned.gps_config().samples_per_condition == 2  # the tiny universe's training budget stays
    on_policy = composed("universe=tiny", "eval.finetune_sample_on_policy=true")
    expected = dataclasses.replace(on_policy.gps_config(), sample_on_policy=True)
    assert on_policy.finetune_gps_config() == expected
    assert not on_policy.gps_config().sample_on_policy  # training samples the controllers
    small_steps = composed("universe=tiny", "eval.finetune_kl_step=0.2")
    assert small_steps.finetune_gps_config() == dataclasses.replace(small_steps.gps_config(), kl_step=0.2)
    assert small_steps.gps_config().kl_step == GPSConfig.kl_step  # training keeps its trust region
    long_s_step = composed("universe=tiny", "eval.finetune_sgd_steps=4000")
    assert long_s_step.finetune_gps_config() == dataclasses.replace(long_s_step.gps_config(), sgd_steps=4000)
    assert long_s_step.gps_config().sgd_steps != 4000  # training keeps its S-step
    per_condition = composed("universe=tiny", "eval.finetune_dynamics_prior_per_condition=true")
    assert per_condition.finetune_gps_config() == dataclasses.replace(
        per_condition.gps_config(), dynamics_prior_per_condition=True
    )
    assert not per_condition.gps_config().dynamics_prior_per_condition  # training keeps one per world
    inherited = composed("universe=tiny", "gps.dynamics_prior_per_condition=true")
    assert inherited.finetune_gps_config().dynamics_prior_per_condition  # null: training's choice
    exact = composed("universe=tiny", "eval.finetune_policy_linearization=jacobian")
    by_jacobian = dataclasses.replace(exact.gps_config(), policy_linearization="jacobian")
    assert exact.finetune_gps_config() == by_jacobian
    assert exact.gps_config().policy_linearization == "regression"  # training regresses, as the GPS code
    pi2 = composed(
        "universe=tiny", "algo=badmm", "eval.finetune_algo=mdgps", "eval.finetune_c_step=pi2", PI2_SAMPLES
    )
    assert pi2.finetune_gps_config() == dataclasses.replace(pi2.gps_config(), algo="mdgps", c_step="pi2")
    assert (pi2.gps_config().algo, pi2.gps_config().c_step) == ("badmm", "lqr")  # training's own
    wider = composed("universe=tiny", "eval.finetune_num_conditions=8")
    assert wider.finetune_gps_config() == dataclasses.replace(wider.gps_config(), num_conditions=8)
    robot_only = composed("universe=tiny", "eval.finetune_train_modules=robot")
    by_robot = dataclasses.replace(robot_only.gps_config(), train_modules="robot")
    assert robot_only.finetune_gps_config() == by_robot
    assert robot_only.gps_config().train_modules == "all"  # training trains every module
    dagger = composed("universe=tiny", "algo=mdgps", "eval.finetune_relabel_policy_states=mean")
    by_mean = dataclasses.replace(dagger.gps_config(), relabel_policy_states="mean")
    assert dagger.finetune_gps_config() == by_mean
    assert dagger.gps_config().relabel_policy_states == "off"  # training imitates at the controllers' samples
    wide = composed("universe=tiny", "eval.finetune_init_variance=5.0")
    assert wide.finetune_gps_config() == dataclasses.replace(wide.gps_config(), init_variance=5.0)
    assert wide.gps_config().init_variance == GPSConfig.init_variance  # training's first controllers
    exploring = composed("universe=tiny", "eval.finetune_pi2_covariance_damping=1e6")
    kept = dataclasses.replace(exploring.gps_config(), pi2_covariance_damping=1e6)
    assert exploring.finetune_gps_config() == kept
    assert exploring.gps_config().pi2_covariance_damping == GPSConfig.pi2_covariance_damping
    tracking = composed(
        "universe=tiny",
        "algo=mdgps",
        "eval.finetune_relabel_policy_states=mean",
        "eval.finetune_relabel_tracking_weight=1e-5",
    )
    assert tracking.finetune_gps_config() == dataclasses.replace(by_mean, relabel_tracking_weight=1e-5)
    assert tracking.gps_config().relabel_tracking_weight is None
    held = composed(
        "universe=tiny",
        "algo=mdgps",
        "eval.finetune_c_step=pi2",
        "eval.finetune_pi2_policy_weight=0.1",
        PI2_SAMPLES,
    )
    assert held.finetune_gps_config().pi2_policy_weight == 0.1
    assert held.gps_config().pi2_policy_weight == 0.0
    smoothed = composed(
        "universe=tiny",
        "algo=mdgps",
        "eval.finetune_c_step=pi2",
        "eval.finetune_pi2_step_smoothing=5",
        PI2_SAMPLES,
    )
    assert smoothed.finetune_gps_config().pi2_step_smoothing == 5.0
    assert smoothed.gps_config().pi2_step_smoothing == 0.0
    stepped = composed(
        "universe=tiny", "algo=mdgps", "eval.finetune_c_step=pi2", "eval.finetune_pi2_kl=0.25", PI2_SAMPLES
    )
    assert stepped.finetune_gps_config().pi2_kl == 0.25
    assert stepped.gps_config().pi2_kl == GPSConfig.pi2_kl
    fed_back = composed(
        "universe=tiny",
        "algo=mdgps",
        "eval.finetune_c_step=pi2",
        "eval.finetune_pi2_policy_feedback=true",
        PI2_SAMPLES,
    )
    assert fed_back.finetune_gps_config().pi2_policy_feedback is True
    assert fed_back.gps_config().pi2_policy_feedback is False
    sobolev = composed("universe=tiny", "algo=mdgps", "eval.finetune_feedback_weight=10")
    assert sobolev.finetune_gps_config().feedback_weight == 10.0
    assert sobolev.gps_config().feedback_weight == 0.0
    evened = composed("universe=tiny", "eval.finetune_s_step_precision=normalized")
    assert evened.finetune_gps_config().s_step_precision == "normalized"
    assert evened.gps_config().s_step_precision == "controllers"
    redrawn = composed("universe=tiny", "seed=3", "eval.finetune_seed=7")
    assert redrawn.finetune_gps_config().seed == 7
    assert redrawn.gps_config().seed == 3
    assert redrawn.finetune_gps_config().condition_seed == redrawn.gps_config().condition_seed


def test_the_lqr_step_under_pi2_is_named_as_unread_and_the_pi2_step_given(caplog):
    """PI2 steps by gps.pi2_kl, not gps.kl_step: a gps.kl_step or eval.finetune_kl_step it will
    not read is said so before any work (a warning, since published PI2 commands carry one)."""
    pi2 = ("universe=tiny", "algo=mdgps", "eval.finetune_c_step=pi2", "eval.finetune_kl_step=0.2")
    with caplog.at_level(logging.WARNING, logger="modnet.config"):
        composed(*pi2, PI2_SAMPLES).check()
    assert "eval.finetune_kl_step=0.2 is the LQR's step" in caplog.text
    assert "eval.finetune_pi2_kl (now 1.0)" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="modnet.config"):
        composed("universe=tiny", "algo=mdgps", "gps.c_step=pi2", "gps.kl_step=0.5", PI2_SAMPLES).check()
    assert "gps.kl_step=0.5 is the LQR's step" in caplog.text and "gps.pi2_kl (now 1.0)" in caplog.text
    assert "eval.finetune_kl_step" not in caplog.text  # fine-tuning inherits it: said once
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="modnet.config"):
        composed(*pi2[:2], "eval.finetune_c_step=pilqr", "eval.finetune_kl_step=0.2", PI2_SAMPLES).check()
        composed(*pi2[:3], "eval.finetune_pi2_kl=0.5", PI2_SAMPLES).check()
        composed("universe=tiny", "algo=mdgps", "gps.c_step=pi2", PI2_SAMPLES).check()
        composed("universe=tiny", "gps.kl_step=0.5").check()
    assert caplog.text == ""


def test_mdgps_only_options_under_badmm_are_refused_before_any_work_naming_the_fix():
    refused = (["gps.c_step=pi2", "algo=badmm"], ["algo=badmm", "eval.finetune_c_step=pi2"])
    relabelled = ["algo=badmm", "eval.finetune_relabel_policy_states=sampled"]
    for overrides in (*refused, ["algo=badmm", "eval.finetune_c_step=pilqr"], relabelled):
        run = composed("universe=tiny", *overrides)
        with pytest.raises(ConfigError, match="use algo=mdgps"):
            validate(run)
    validate(composed("universe=tiny", "algo=mdgps", "gps.c_step=pi2", PI2_SAMPLES))


def test_training_one_factors_modules_is_refused_for_a_monolithic_bank_before_any_work():
    for override in ("gps.train_modules=task", "eval.finetune_train_modules=robot"):
        run = composed("universe=tiny", "policy=monolithic", override)
        with pytest.raises(ConfigError, match=r"train_modules=(task|robot) trains one factor's modules"):
            validate(run)
    validate(composed("universe=tiny", "eval.finetune_train_modules=robot"))


def test_literal_choices_and_values_no_type_rules_out_fail_with_the_key():
    run = RunConfig(universe="tiny")
    run.gps.cost_ramp = "cubic"
    with pytest.raises(ConfigError, match=r"gps\.cost_ramp must be one of 'constant', 'linear'"):
        run.gps_config()
    for key, value, message in [
        ("bank.policy", "hybrid", "bank.policy must be"),
        ("logger.backend", "mlflow", "logger.backend must be one of wandb, csv"),
        ("gps.iterations", 0, "gps.iterations must be at least 1"),
        ("threads", 0, "threads must be at least 1, got 0"),
        ("bank.dropout", 1.5, "dropout must be a probability"),
        ("bank.activation", "gelu", r"bank\.activation must be one of 'relu', 'tanh', 'elu', 'softplus'"),
        ("gps.badmm.max_policy_weight", 1e-3, r"gps\.badmm: .*max_policy_weight, got 1e-06 / 0.005 / 0.001"),
        (
            "eval.finetune_samples_per_condition",
            0,
            r"eval\.finetune_samples_per_condition=0: gps\.samples_per_condition must be at least 1",
        ),
        ("eval.finetune_kl_step", 0.0, r"eval\.finetune_kl_step=0\.0: gps\.kl_step must be positive"),
        ("eval.finetune_sgd_steps", 0, r"eval\.finetune_sgd_steps=0: gps\.sgd_steps must be at least 1"),
        ("eval.finetune_num_conditions", 2, r"eval\.finetune_num_conditions=2: gps\.num_conditions must"),
        (
            "eval.finetune_train_modules",
            "arm",
            r"eval\.finetune_train_modules=arm: gps\.train_modules must be one of all, task, robot",
        ),
        ("gps.kl_step", -1.0, r"gps\.kl_step must be positive, got -1\.0"),
        ("eval.finetune_init_variance", 0.0, r"finetune_init_variance=0\.0: gps\.init_variance must be"),
        ("eval.finetune_pi2_kl", 0.0, r"finetune_pi2_kl=0\.0: gps\.pi2_kl and gps\.pi2_covariance_damp"),
        (
            "eval.finetune_pi2_covariance_damping",
            -1.0,
            r"finetune_pi2_covariance_damping=-1\.0: gps\.pi2_kl and gps\.pi2_covariance_damping must be",
        ),
        ("gps.relabel_policy_states", "yes", r"gps\.relabel_policy_states must be one of 'off', 'sampled'"),
        (
            "eval.finetune_relabel_tracking_weight",
            0.1,
            r"finetune_relabel_tracking_weight=0\.1: gps\.relabel_tracking_weight .* sampled or mean",
        ),
        (
            "eval.finetune_pi2_policy_weight",
            0.1,
            r"finetune_pi2_policy_weight=0\.1: gps\.pi2_policy_weight .* positive only with gps\.c_step=pi2",
        ),
        (
            "eval.finetune_pi2_step_smoothing",
            5.0,
            r"finetune_pi2_step_smoothing=5\.0: gps\.pi2_step_smoothing .* positive only with gps\.c_step",
        ),
        (
            "eval.finetune_pi2_policy_feedback",
            True,
            r"finetune_pi2_policy_feedback=True: gps\.pi2_policy_feedback .* needs gps\.c_step=pi2",
        ),
        (
            "eval.finetune_feedback_weight",
            1.0,
            r"finetune_feedback_weight=1\.0: gps\.feedback_weight .* positive only with algo=mdgps",
        ),
        (
            "eval.finetune_s_step_precision",
            "even",
            r"finetune_s_step_precision=even: gps\.s_step_precision must be one of controllers, normalized",
        ),
    ]:
        run = RunConfig(universe="tiny")
        *path, name = key.split(".")
        setattr(functools.reduce(getattr, path, run), name, value)
        with pytest.raises(ConfigError, match=message):
            run.check()


def test_fine_tuning_pi2_on_too_few_samples_is_refused_before_any_work():
    """PI2's weights of 2 samples can be at most log 2 = 0.69 from uniform: asked for its
    default 1.0 it put all the weight on one sample and a 2-sample fine-tuning's regression loss
    went infinite after the training. Now the command is refused, naming the options."""
    overrides = ("universe=manipulation", "gps.samples_per_condition=2")
    pi2 = ("eval.finetune_algo=mdgps", "eval.finetune_c_step=pi2")
    message = r"eval\.finetune_algo=mdgps, eval\.finetune_c_step=pi2: gps\.pi2_kl=1\.0 needs more than 2"
    with pytest.raises(ConfigError, match=message):
        validate(composed(*overrides, *pi2))
    validate(composed(*overrides))  # the LQR's C-step weighs no samples
    validate(composed(*overrides, *pi2, "eval.finetune_samples_per_condition=3"))


@pytest.mark.parametrize("universe", list(UNIVERSES))
def test_every_universe_option_composes_and_validates(universe):
    run = composed(f"universe={universe}")
    loaded, split = validate(run)
    assert loaded is UNIVERSES[universe] and "/".join(split.holdout) == loaded.holdout
    assert len(split.training) == len(loaded.robots) * len(loaded.tasks) - 1


@pytest.mark.parametrize(
    "override, key, value",
    [
        ("algo=badmm", "gps.algo", "badmm"),
        ("policy=monolithic", "bank.policy", "monolithic"),
        ("logger=csv", "logger.backend", "csv"),
        ("logger=none", "logger.backend", "none"),
        ("logger=tensorboard", "logger.backend", "tensorboard"),
    ],
)
def test_config_groups_set_their_keys(override, key, value):
    run = composed("universe=tiny", override)
    part, name = key.split(".")
    assert getattr(getattr(run, part), name) == value


def test_launchers_for_parallel_and_slurm_sweeps_compose():
    register_configs()
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
        slurm = compose("config", overrides=["hydra/launcher=slurm"], return_hydra_config=True)
        joblib = compose("config", overrides=["hydra/launcher=joblib"], return_hydra_config=True)
    assert slurm.hydra.launcher._target_.endswith("SlurmLauncher") and slurm.hydra.launcher.cpus_per_task == 2
    assert joblib.hydra.launcher._target_.endswith("JoblibLauncher")


def test_defaults_are_the_paper_universe_wandb_offline_and_the_gps_seed_follows_the_run_seed():
    run = composed()
    assert (run.universe, run.holdout, run.logger.backend, run.logger.mode) == (
        "color_reach_state",
        None,
        "wandb",
        "offline",
    )
    assert composed("seed=3").gps_config().seed == 3
    tiny = composed("universe=tiny")
    assert (tiny.gps.horizon, tiny.gps.iterations) == (15, 2)


def test_a_finetune_seed_configures_fine_tuning_alike_at_every_run_seed():
    """With ``eval.finetune_seed`` set, fine-tuning's config does not depend on the run's seed;
    a scratch start reads nothing of the bank (tests/test_evaluate.py), so it is one run per
    ``eval.finetune_seed`` at every bank seed, as RESULTS reports."""
    drawn = [composed("universe=tiny", f"seed={seed}", "eval.finetune_seed=100") for seed in (3, 7)]
    assert drawn[0].gps_config().seed != drawn[1].gps_config().seed
    assert drawn[0].finetune_gps_config() == drawn[1].finetune_gps_config()
    assert drawn[0].finetune_gps_config().seed == 100
    unset = [composed("universe=tiny", f"seed={seed}") for seed in (3, 7)]
    assert unset[0].finetune_gps_config() != unset[1].finetune_gps_config()


def test_flatten_gives_dotted_keys():
    assert flatten({"gps": {"lr": 0.1, "badmm": {"dual_rate": 0.2}}, "seed": 0}) == {
        "gps.lr": 0.1,
        "gps.badmm.dual_rate": 0.2,
        "seed": 0,
    }


# --- universes and the held-out world ---------------------------------------------------------------------
def test_validation_names_what_is_missing_and_the_valid_choices():
    with pytest.raises(UniverseError, match="unknown universe 'colour'; valid universes: color_reach_state"):
        validate(RunConfig(universe="colour"))
    with pytest.raises(
        UniverseError, match="'five_link/reach_red' is not in universe 'tiny'.*robot 'five_link'"
    ):
        validate(RunConfig(universe="tiny", holdout="five_link/reach_red"))
    with pytest.raises(UniverseError, match="task 'push' not in its grid.*tasks: reach_red, reach_black"):
        validate(RunConfig(universe="tiny", holdout="four_link/push"))
    with pytest.raises(UniverseError, match="ROBOT/TASK"):
        validate(RunConfig(universe="tiny", holdout="four_link"))
    with pytest.raises(ConfigError, match="python run.py -m holdout=all"):
        validate(RunConfig(universe="tiny", holdout="all"))
    run = RunConfig(universe="tiny")
    run.pretrain.images = 100
    with pytest.raises(ConfigError, match="'tiny' has none: use an image universe or pretrain.images=0"):
        validate(run)
    with pytest.raises(ConfigError, match="finetune_policy_linearization=exact: gps.policy_linearization"):
        validate(RunConfig(universe="tiny", eval=EvalConfig(finetune_policy_linearization="exact")))
    for run in (
        RunConfig(universe="color_reach", eval=EvalConfig(finetune_policy_linearization="jacobian")),
        composed("universe=color_reach", "gps.policy_linearization=jacobian"),
    ):  # before any training: fine-tuning comes after it
        with pytest.raises(ConfigError, match="policy_linearization=jacobian .* 'color_reach' reads images"):
            validate(run)
    for prefix in ("eval.finetune_", "gps."):
        key = f"{prefix}pi2_policy_feedback"
        run = composed("universe=color_reach", "algo=mdgps", f"{prefix}c_step=pi2", f"{key}=true")
        with pytest.raises(ConfigError, match=f"{key}=true differentiates .* 'color_reach' reads images"):
            validate(run)
    run = composed("universe=color_reach", "algo=mdgps", "eval.finetune_feedback_weight=2")
    with pytest.raises(ConfigError, match="finetune_feedback_weight=2.0 differentiates .* reads images"):
        validate(run)


def test_a_held_out_robot_or_task_that_no_training_world_covers_is_refused():
    one_robot = Universe(
        "one_robot",
        robots=("four_link",),
        tasks=("reach_red", "reach_black"),
        holdout="four_link/reach_black",
    )
    with pytest.raises(UniverseError, match="no training world covers its task 'reach_black'"):
        one_robot.split()
    one_task = Universe(
        "one_task", robots=("three_link", "four_link"), tasks=("push",), holdout="four_link/push"
    )
    with pytest.raises(UniverseError, match="no training world covers its robot 'four_link', so"):
        one_task.split()
    lonely = Universe("lonely", robots=("four_link",), tasks=("push",), holdout="four_link/push")
    with pytest.raises(UniverseError, match="its robot 'four_link' or its task 'push'"):
        lonely.split()


def test_universes_are_valid_grids_and_unknown_robots_are_refused():
    for universe in UNIVERSES.values():
        universe.split()  # the default held-out world is always composable
    with pytest.raises(ValueError, match="unknown robot 'six_link'"):
        Universe("bad", robots=("six_link",), tasks=("push",), holdout="six_link/push")
    assert parse_world("four_link/push") == ("four_link", "push")
    assert get_universe("color_reach").pixels and not get_universe("color_reach_state").pixels


def test_universes_cli_lists_the_worlds_of_a_universe(capsys):
    main(["list-worlds", "tiny"])
    assert capsys.readouterr().out.strip() == (
        "three_link/reach_red,three_link/reach_black,four_link/reach_red,four_link/reach_black"
    )
    main(["list"])
    assert "manipulation: three_link, four_link, five_link" in capsys.readouterr().out


def test_holdout_all_expands_to_every_world_in_a_multirun_only():
    run = load_run_module()
    argv = ["run.py", "-m", "universe=tiny", "holdout=all"]
    assert run.expand_holdout_all(argv)[-1] == (
        "holdout=three_link/reach_red,three_link/reach_black,four_link/reach_red,four_link/reach_black"
    )
    assert run.expand_holdout_all(["run.py", "holdout=all"]) == ["run.py", "holdout=all"]
    default = run.expand_holdout_all(["run.py", "--multirun", "holdout=all"])[-1]
    assert default.count(",") == 11 and "three_link_short/reach_yellow" in default  # color_reach_state
    with pytest.raises(SystemExit, match="one universe"):
        run.expand_holdout_all(["run.py", "-m", "universe=tiny,manipulation", "holdout=all"])
