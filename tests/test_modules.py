"""The parts of a bank module: normalisation, spatial softmax, pixel encoder, heads, dropout."""

import pytest
import torch
from tensordict import TensorDict

from modnet.modules import (
    BankModule,
    ModuleArch,
    ModuleNet,
    Normalizer,
    PixelEncoder,
    SpatialSoftmax,
    interface_key,
    key_from_str,
    key_to_str,
)
from modnet.specs import PIXELS_SHAPE


def task_arch(**overrides) -> ModuleArch:
    options = dict(factor="task", head="interface", out_dim=12, observations=((("task", "state"), 6),))
    return ModuleArch(**(options | overrides))


def robot_arch(**overrides) -> ModuleArch:
    options = dict(
        factor="robot",
        head="gaussian",
        out_dim=3,
        observations=((("robot", "state"), 6),),
        reads=(("task", 12),),
    )
    return ModuleArch(**(options | overrides))


# --- spatial softmax and pixels ----------------------------------------------------------------------
@pytest.mark.parametrize("row, col", [(0, 0), (1, 6), (3, 7), (2, 3)])
def test_spatial_softmax_finds_a_single_bright_pixel(row, col):
    height, width = 4, 8
    maps = torch.zeros(2, 3, height, width)
    maps[1, 2, row, col] = 100.0  # sample 1, channel 2
    points = SpatialSoftmax()(maps)
    assert points.shape == (2, 6)
    expected = torch.tensor([col / width - 0.5, row / height - 0.5])
    torch.testing.assert_close(points[1, 4:], expected)
    # uniform maps: every pixel equally likely, the mean of the grid
    uniform = torch.tensor([-0.5 / width, -0.5 / height])
    torch.testing.assert_close(points[0, :2], uniform)


def test_spatial_softmax_coordinates_stay_in_half_open_unit_box():
    points = SpatialSoftmax()(torch.randn(5, 4, 64, 80) * 50)
    assert points.min() >= -0.5 and points.max() < 0.5
    corner = torch.zeros(1, 1, 64, 80)
    corner[..., -1, -1] = 1e4
    torch.testing.assert_close(SpatialSoftmax()(corner), torch.tensor([[79 / 80 - 0.5, 63 / 64 - 0.5]]))


def test_pixel_encoder_reads_uint8_hwc_images_at_the_right_place():
    """A 1x1 conv that picks the red channel: the feature point is where the red pixel is."""
    encoder = PixelEncoder(channels=(1,), kernel_size=1)
    conv = encoder.convs[0]
    with torch.no_grad():
        conv.weight.zero_()
        conv.weight[0, 0] = 40.0  # red only; 255 -> 1.0 -> logit 40
        conv.bias.zero_()
    images = torch.zeros(2, *PIXELS_SHAPE, dtype=torch.uint8)
    images[0, 10, 70, 0] = 255  # red at row 10, column 70
    images[1, 50, 5, 0] = 255
    images[1, 20, 20, 1] = 255  # green elsewhere: ignored
    points = encoder(images)
    height, width = PIXELS_SHAPE[:2]
    expected = torch.tensor([[70 / width - 0.5, 10 / height - 0.5], [5 / width - 0.5, 50 / height - 0.5]])
    torch.testing.assert_close(points, expected, atol=1e-4, rtol=0)


def test_a_strided_first_conv_keeps_the_image_coordinates():
    """Stride 2 reads every other pixel: a 2x2 red patch is found where it is in the full image."""
    encoder = PixelEncoder(channels=(1, 1), kernel_size=1, strides=(2, 1))
    with torch.no_grad():
        for conv in encoder.convs[::2]:
            conv.weight.zero_()
            conv.bias.zero_()
        encoder.convs[0].weight[0, 0] = 1.0  # red
        encoder.convs[2].weight[0, 0] = 40.0
    images = torch.zeros(1, *PIXELS_SHAPE, dtype=torch.uint8)
    images[0, 20:22, 60:62, 0] = 255
    height, width = PIXELS_SHAPE[:2]
    expected = torch.tensor([[60 / width - 0.5, 20 / height - 0.5]])
    torch.testing.assert_close(encoder(images), expected, atol=1e-4, rtol=0)
    with pytest.raises(ValueError, match=r"conv_strides needs one stride per convolution \(2\), got \(2,\)"):
        ModuleArch(factor="task", head="interface", out_dim=4, pixels=("task", "pixels"), conv_strides=(2,))


def test_a_sharper_spatial_softmax_is_part_of_the_architecture_and_old_manifests_default_to_1():
    arch = ModuleArch(
        factor="task", head="interface", out_dim=4, pixels=("task", "pixels"), softmax_temperature=0.05
    )
    assert BankModule(arch).module.pixels.points.temperature == 0.05
    assert ModuleArch.from_json(arch.to_json()) == arch
    old = arch.to_json()
    del old["softmax_temperature"]  # a manifest written before the field existed
    assert ModuleArch.from_json(old).softmax_temperature == 1.0
    for bad in (0.0, -1.0, float("inf"), True):
        with pytest.raises(ValueError, match="softmax_temperature must be"):
            ModuleArch(
                factor="task",
                head="interface",
                out_dim=4,
                softmax_temperature=bad,
                observations=((("task", "state"), 2),),
            )


def test_pixel_encoder_keeps_leading_batch_dims():
    encoder = PixelEncoder(channels=(10, 20), kernel_size=3)
    out = encoder(torch.randint(0, 256, (2, 3, *PIXELS_SHAPE), dtype=torch.uint8))
    assert out.shape == (2, 3, 40)


def test_vision_task_module_reads_pixels_and_task_state():
    arch = task_arch(pixels=("task", "pixels"), hidden=(80,))
    module = BankModule(arch)
    assert module.in_keys == [("task", "state"), ("task", "pixels")]
    assert arch.inputs[("task", "pixels")] == PIXELS_SHAPE
    td = TensorDict(
        {
            ("task", "state"): torch.randn(4, 6),
            ("task", "pixels"): torch.randint(0, 256, (4, *PIXELS_SHAPE), dtype=torch.uint8),
        },
        batch_size=[4],
    )
    out = module(td)["interface", "task"]
    assert out.shape == (4, 12) and (out >= 0).all()  # a ReLU bottleneck
    convs = [m for m in module.module.pixels.convs if isinstance(m, torch.nn.Conv2d)]
    assert [(c.out_channels, c.kernel_size) for c in convs] == [(10, (3, 3)), (20, (3, 3))]


# --- normalisation -----------------------------------------------------------------------------------
def test_normalizer_z_scores_with_a_std_floor():
    norm = Normalizer(3)
    columns = [torch.randn(1000) * 4 + 2, torch.randn(1000) * 0.5 - 1, torch.full((1000,), 7.0)]
    samples = torch.stack(columns, -1)
    norm.fit(samples)
    out = norm(samples)
    torch.testing.assert_close(out[:, :2].mean(0), torch.zeros(2), atol=1e-5, rtol=0)
    torch.testing.assert_close(out[:, :2].std(0, correction=0), torch.ones(2), atol=1e-4, rtol=0)
    assert norm.scale[2] == pytest.approx(1e-3)  # constant dimension: floored, not infinite
    assert torch.isfinite(out).all() and (out[:, 2] == 0).all()
    assert set(norm.state_dict()) == {"loc", "scale"}  # saved with the weights


def test_module_normalization_is_applied_and_checked():
    module = BankModule(robot_arch(dropout=0.0)).eval()
    td = TensorDict({interface_key("task"): torch.rand(5, 12), ("robot", "state"): torch.randn(5, 6)}, [5])
    before = module(td.clone())["loc"]
    module.set_normalization(torch.ones(6), torch.full((6,), 2.0))
    shifted = td.clone()
    shifted["robot", "state"] = td["robot", "state"] * 2.0 + 1.0  # what the new z-score undoes
    torch.testing.assert_close(module(shifted)["loc"], before)
    mean, std = module.normalization()
    assert (mean == 1).all() and (std == 2).all()
    with pytest.raises(ValueError, match=r"normalisation of size 6 given mean of shape \(4,\)"):
        module.set_normalization(torch.zeros(4), torch.ones(4))
    two = BankModule(robot_arch(observations=((("robot", "state"), 6), ("extra", 2))))
    with pytest.raises(ValueError, match=r"normalises \['robot/state', 'extra'\]; name one of them"):
        two.set_normalization(torch.zeros(6), torch.ones(6))
    two.set_normalization(torch.zeros(2), torch.full((2,), 3.0), key="extra")
    assert (two.normalization("extra")[1] == 3).all()


@pytest.mark.parametrize(
    "arch",
    [
        robot_arch(dropout=0.0, observations=((("robot", "state"), 6), ("extra", 2))),
        task_arch(hidden=()),  # no trunk: the head's layer reads the inputs
        task_arch(pixels=("task", "pixels"), image_shape=(16, 20, 3), conv_channels=(4,)),
    ],
    ids=["two observations after an interface", "head only", "with image features"],
)
def test_refit_normalization_keeps_the_function(arch):
    module = BankModule(arch).eval()
    td = TensorDict({}, [64])
    for key, width in arch.reads:
        td[interface_key(key)] = torch.rand(64, width)
    for i, (key, dim) in enumerate(arch.observations):
        td[key] = torch.randn(64, dim) * (3.0 + i) + 5.0  # far from the identity normalisation
    if arch.pixels is not None:
        td[arch.pixels] = torch.randint(0, 256, (64, *arch.image_shape), dtype=torch.uint8)
    key = module.out_keys[0]
    before = module(td.clone())[key]
    module.fit_normalization(td, keep_function=True)
    for obs_key, _ in arch.observations:
        z = (td[obs_key] - module.normalization(obs_key)[0]) / module.normalization(obs_key)[1]
        torch.testing.assert_close(z.mean(0), torch.zeros(z.shape[-1]), atol=1e-4, rtol=0)  # refitted ...
    torch.testing.assert_close(module(td.clone())[key], before, atol=1e-4, rtol=1e-4)  # ... same outputs
    plain = BankModule(arch).eval()
    plain.load_state_dict(module.state_dict())
    plain.fit_normalization(td.apply(lambda x: x * 2 if x.is_floating_point() else x))
    assert not torch.allclose(plain(td.clone())[key], before, atol=1e-3)  # a plain refit moves them


# --- heads, dropout -----------------------------------------------------------------------------------
def test_gaussian_head_scale_is_learned_and_state_independent():
    module = BankModule(robot_arch(init_log_std=-1.0))
    td = TensorDict({interface_key("task"): torch.rand(7, 12), ("robot", "state"): torch.randn(7, 6)}, [7])
    out = module(td)
    assert out["loc"].shape == out["scale"].shape == (7, 3)
    torch.testing.assert_close(out["scale"], torch.full((7, 3), torch.e**-1.0))
    assert any(p is module.log_std for p in module.parameters())  # owned by the robot module
    out["scale"].sum().backward()
    assert module.log_std.grad is not None and (module.log_std.grad != 0).all()
    module.set_std(torch.tensor([0.1, 0.2, 0.3]))
    torch.testing.assert_close(module(td)["scale"][3], torch.tensor([0.1, 0.2, 0.3]))
    with pytest.raises(AttributeError, match="log_std"):
        _ = BankModule(task_arch()).log_std


def test_dropout_changes_outputs_in_train_mode_only():
    module = BankModule(robot_arch(dropout=0.5))
    assert sum(isinstance(m, torch.nn.Dropout) for m in module.modules()) == 2  # each hidden layer
    task = BankModule(task_arch(dropout=0.5, interface_dropout=0.5, hidden=(80,)))
    assert sum(isinstance(m, torch.nn.Dropout) for m in task.modules()) == 2  # hidden + interface
    td = TensorDict({interface_key("task"): torch.rand(64, 12), ("robot", "state"): torch.randn(64, 6)}, [64])
    first, second = module(td.clone())["loc"], module(td.clone())["loc"]
    assert not torch.allclose(first, second)
    observation = TensorDict({("task", "state"): torch.randn(64, 6)}, [64])
    interface = lambda: task(observation.clone())[interface_key("task")]
    assert not torch.equal(interface(), interface())
    module.eval(), task.eval()
    torch.testing.assert_close(module(td.clone())["loc"], module(td.clone())["loc"])
    torch.testing.assert_close(interface(), interface())


def test_network_layout_follows_the_architecture():
    net = ModuleNet(task_arch(hidden=(80, 80, 80)))
    linears = [m for m in net.modules() if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(6, 80), (80, 80), (80, 80), (80, 12)]
    net = ModuleNet(robot_arch(hidden=(80, 80)))
    linears = [m for m in net.modules() if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(18, 80), (80, 80), (80, 3)]


# --- the architecture record ---------------------------------------------------------------------------
def test_arch_round_trips_through_json():
    arch = task_arch(pixels=("task", "pixels"), hidden=(80,), conv_channels=(4, 8), dropout=0.1)
    assert ModuleArch.from_json(arch.to_json()) == arch
    assert arch.to_json()["observations"] == [["task/state", 6]]
    assert key_from_str(key_to_str(("a", "b", "c"))) == ("a", "b", "c")


@pytest.mark.parametrize(
    "overrides, message",
    [
        (dict(head="tanh"), "head must be one of interface, gaussian, got 'tanh'"),
        (dict(out_dim=0), r"out_dim must hold positive integers, got \(0,\)"),
        (dict(dropout=1.0), r"dropout must be a probability in \[0, 1\), got 1.0"),
        (dict(interface_dropout=-0.1), r"interface_dropout must be a probability"),
        (dict(hidden=(80, -1)), r"hidden must hold positive integers, got \(80, -1\)"),
        (dict(kernel_size=2), "kernel_size must be a positive odd integer, got 2"),
        (dict(observations=()), r"a module needs distinct inputs, got \[\]"),
        (dict(observations=((("task", "state"), 6), (("task", "state"), 6))), "distinct inputs"),
    ],
)
def test_arch_rejects_bad_options(overrides, message):
    with pytest.raises(ValueError, match=message):
        task_arch(**overrides)


def test_arch_from_json_rejects_unknown_fields():
    data = task_arch().to_json() | {"exec": "import os"}
    with pytest.raises(ValueError, match=r"unknown architecture fields \['exec'\]"):
        ModuleArch.from_json(data)
    with pytest.raises(ValueError, match="not a key"):
        ModuleArch.from_json(task_arch().to_json() | {"observations": [["task//state", 6]]})
