"""Pose-regression pretraining of the vision task modules (modnet.pretrain)."""

import numpy as np
import pytest
import torch

import modnet.pretrain as pretrain
from modnet.bank import BankConfig, ModuleBank
from modnet.pretrain import PretrainConfig, object_slots, pretrain_vision, render_scenes
from modnet.specs import PIXELS_SHAPE
from modnet.worlds import get_world

SHARP = BankConfig(softmax_temperature=0.05)


def red_pixels(images):
    """Where the red block is drawn in uint8 ``[..., H, W, 3]`` images: ``[..., H, W]`` booleans."""
    return (images[..., 0] > 200) & (images[..., 1] < 80) & (images[..., 2] < 80)


def test_the_regression_targets_are_the_objects_not_the_end_effector():
    assert object_slots(get_world("three_link", "reach")) == [4, 5]  # the target
    colours = get_world("four_link", "reach_black")
    assert len(object_slots(colours)) == 8  # four blocks
    assert not {0, 1, 2, 3} & set(object_slots(colours))  # ee position and velocity


def test_rendered_scenes_are_labelled_with_where_the_objects_are():
    """The red block's pixels sit where its label says, in the image coordinates of the top camera."""
    world = get_world("three_link", "reach_red")
    images, positions = render_scenes(world, 6, np.random.default_rng(0))
    assert images.shape == (6, *PIXELS_SHAPE) and images.dtype == np.uint8
    again, same = render_scenes(world, 6, np.random.default_rng(0))
    np.testing.assert_array_equal(images, again)
    np.testing.assert_array_equal(positions, same)
    red = red_pixels(images)
    columns = np.array([np.nonzero(r)[1].mean() for r in red])
    # the camera looks straight down: image column grows with x
    assert np.corrcoef(columns, positions[:, 0])[0, 1] > 0.95


def test_pretraining_teaches_the_convolutions_to_find_the_target():
    """On scenes it never trained on, the encoder locates the target far better than the mean guess;
    only the convolutions keep what they learnt."""
    bank = ModuleBank.build(["three_link", "four_link"], ["reach"], pixels=True, seed=0, config=SHARP)
    before = {k: v.clone() for k, v in bank.state_dict().items()}
    worlds = [("three_link", "reach"), ("four_link", "reach")]
    report = pretrain_vision(bank, worlds, PretrainConfig(images=800, epochs=40, lr=3e-3))
    figures = report["task/reach"]
    assert figures["images"] == 800 and list(figures["object_errors"]) == ["target"]
    assert figures["val_error"] < 0.3 * figures["baseline_error"]
    changed = {k for k, v in bank.state_dict().items() if not torch.equal(v, before[k])}
    assert changed and all(k.startswith("factor_modules.task.reach.module.pixels.convs.") for k in changed)


def test_pretraining_renders_the_training_worlds_only(monkeypatch):
    shown = []

    def recording(world, n, rng):
        shown.append((world.name, n))
        return render_scenes(world, n, rng)

    monkeypatch.setattr(pretrain, "render_scenes", recording)
    bank = ModuleBank.build(["three_link", "four_link"], ["reach_red", "reach_black"], pixels=True, seed=0)
    training = [("three_link", "reach_red"), ("three_link", "reach_black"), ("four_link", "reach_red")]
    report = pretrain_vision(bank, training, PretrainConfig(images=21, epochs=1))
    assert sorted(shown) == [
        ("four_link/reach_red", 11),
        ("three_link/reach_black", 21),
        ("three_link/reach_red", 10),
    ]
    assert set(report) == {"task/reach_red", "task/reach_black"}


def test_a_monolithic_baseline_gets_the_same_pretraining_per_world_network():
    bank = ModuleBank.build(["three_link"], ["reach_red"], pixels=True, policy="monolithic", seed=0)
    report = pretrain_vision(bank, [("three_link", "reach_red")], PretrainConfig(images=20, epochs=1))
    assert list(report) == ["world/three_link-reach_red"]
    assert list(report["world/three_link-reach_red"]["object_errors"]) == ["red", "green", "yellow", "black"]


def test_state_banks_and_zero_images_are_left_alone():
    bank = ModuleBank.build(["three_link"], ["reach"], pixels=False, seed=0)
    before = {k: v.clone() for k, v in bank.state_dict().items()}
    assert pretrain_vision(bank, [("three_link", "reach")], PretrainConfig(images=40)) == {}
    assert pretrain_vision(bank, [("three_link", "reach")], PretrainConfig()) == {}
    assert all(torch.equal(v, before[k]) for k, v in bank.state_dict().items())


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("images", 5, "images must be 0 \\(off\\) or at least 20"),
        ("images", -1, "images must be a non-negative integer"),
        ("epochs", 0, "epochs must hold positive integers"),
        ("lr", 0.0, "lr must be a positive finite number"),
        ("lr", True, "lr must be a positive finite number"),
        ("seed", -1, "seed must be a non-negative integer"),
        ("batch_size", 0, "batch_size must hold positive integers"),
    ],
)
def test_bad_pretraining_options_are_refused(field, value, message):
    with pytest.raises(ValueError, match=message):
        PretrainConfig(**{field: value})


class RedCentroid(torch.nn.Module):
    """A stand-in encoder that finds the red block exactly as a person would: its pixels' centroid."""

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        red = red_pixels(images)
        rows = torch.arange(images.shape[-3], dtype=torch.float32)[:, None].expand(red.shape[-2:])
        cols = torch.arange(images.shape[-2], dtype=torch.float32)[None, :].expand(red.shape[-2:])
        count = red.sum((-2, -1)).clamp_min(1)
        return torch.stack([(red * cols).sum((-2, -1)) / count, (red * rows).sum((-2, -1)) / count], -1)


class Blind(torch.nn.Module):
    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return torch.zeros(*images.shape[:-3], 2)


def test_the_probe_measures_what_the_feature_points_show():
    """Features that track the red block locate it to a few millimetres on scenes the probe did not
    fit, and nothing else; features that show nothing do no better than guessing the mean."""
    bank = ModuleBank.build(["three_link", "four_link"], ["reach_red"], pixels=True, seed=0)
    worlds = [("three_link", "reach_red"), ("four_link", "reach_red")]
    bank.get("task", "reach_red").module.pixels = RedCentroid()
    report = pretrain.probe_vision(bank, worlds, scenes=200)["task/reach_red"]
    assert report["scenes"] == 400
    assert list(report["worlds"]) == ["three_link/reach_red", "four_link/reach_red"]
    for errors in report["worlds"].values():
        assert list(errors) == ["red", "green", "yellow", "black"]
        assert errors["red"] < 0.03 < 0.5 * report["baseline_error"]
        assert min(errors["green"], errors["yellow"], errors["black"]) > 0.5 * report["baseline_error"]
    bank.get("task", "reach_red").module.pixels = Blind()
    blind = pretrain.probe_vision(bank, worlds, scenes=200)["task/reach_red"]
    for errors in blind["worlds"].values():
        for error in errors.values():
            assert error == pytest.approx(blind["baseline_error"], rel=0.15)


def test_the_probe_needs_scenes_to_fit_and_to_test():
    bank = ModuleBank.build(["three_link"], ["reach"], pixels=True, seed=0)
    with pytest.raises(ValueError, match="scenes must be at least 2"):
        pretrain.probe_vision(bank, [("three_link", "reach")], scenes=1)
