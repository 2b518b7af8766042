"""The module bank: sizes from specs, sharing, composition in real rollouts, files, errors."""

import json
import os
import pickle
import subprocess
import sys
import typing

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor

from modnet.bank import BankConfig, BankError, ModuleBank
from modnet.envs import make_env
from modnet.modules import ACTIVATIONS, Activation, BankModule, ModuleArch
from modnet.worlds import robot_spec, task_spec

ROBOTS = ["three_link", "four_link"]
TASKS = ["reach_red", "reach_black"]
DETERMINISTIC = ExplorationType.DETERMINISTIC




def observations(world, batch=(6,), seed=0, pixels=False) -> TensorDict:
    """Random observations of a (robot, task) world, sized from the specs."""
    robot, task = robot_spec(world[0]), task_spec(world[1])
    g = torch.Generator().manual_seed(seed)
    td = TensorDict(
        {
            ("robot", "state"): torch.randn(*batch, robot.state_dim, generator=g),
            ("task", "state"): torch.randn(*batch, task.state_dim, generator=g),
        },
        batch_size=batch,
    )
    if pixels:
        td["task", "pixels"] = torch.randint(0, 256, (*batch, 64, 80, 3), generator=g, dtype=torch.uint8)
        td["task", "ee"] = td["task", "state"][..., :4]
    return td


def linear_shapes(module) -> list[tuple[int, int]]:
    return [(m.in_features, m.out_features) for m in module.modules() if isinstance(m, torch.nn.Linear)]


def mean_action(policy, td) -> torch.Tensor:
    with set_exploration_type(DETERMINISTIC), torch.no_grad():
        return policy(td.clone())["action"]


# --- building from specs --------------------------------------------------------------------------
def test_build_reads_every_size_from_the_specs():
    robots, tasks = ROBOTS + ["five_link"], TASKS + ["push", "peg"]
    bank = ModuleBank.build(robots, tasks, interface_dim=8)
    assert bank.factors == ("task", "robot") and bank.world_factors == ("robot", "task")
    assert bank.names("robot") == tuple(robots) and bank.names("task") == tuple(tasks)
    for name in robots:
        spec, module = robot_spec(name), bank.get("robot", name)
        assert module.arch.inputs == {("interface", "task"): 8, ("robot", "state"): spec.state_dim}
        assert module.arch.outputs == {"loc": spec.action_dim, "scale": spec.action_dim}
    for name in tasks:
        module = bank.get("task", name)
        assert module.arch.inputs == {("task", "state"): task_spec(name).state_dim}
        assert module.arch.outputs == {("interface", "task"): 8}


def test_default_layout_is_the_papers():
    bank = ModuleBank.build(["four_link"], ["reach_black"])
    assert linear_shapes(bank.get("task", "reach_black")) == [(12, 80), (80, 80), (80, 80), (80, 12)]
    assert linear_shapes(bank.get("robot", "four_link")) == [(12 + 8, 80), (80, 80), (80, 4)]
    assert bank.get("robot", "four_link").log_std.shape == (4,)
    vision = ModuleBank.build(["four_link"], ["reach_black"], pixels=True)
    task = vision.get("task", "reach_black")
    # the image and the end-effector (position, velocity), never the block positions
    assert task.in_keys == [("task", "ee"), ("task", "pixels")]
    assert linear_shapes(task) == [(40 + 4, 80), (80, 12)]  # 20 feature points (x, y) + end-effector
    convs = [m for m in task.modules() if isinstance(m, torch.nn.Conv2d)]
    layout = [(c.out_channels, c.kernel_size, c.stride) for c in convs]
    assert layout == [(10, (3, 3), (2, 2)), (20, (3, 3), (1, 1))]


def test_vision_bank_runs_in_a_pixel_env():
    bank = ModuleBank.build(["three_link"], ["reach_red"], pixels=True)
    env = make_env("three_link", "reach_red", num_envs=2, pixels=True, horizon=3)
    td = env.rollout(3, bank.compose("three_link", "reach_red"))
    assert td["interface", "task"].shape == (2, 3, 12) and td["action"].shape == (2, 3, 3)


def test_a_vision_policy_sees_the_targets_only_through_its_pixels():
    """Moving the blocks in the state (not in the image) leaves the vision policy's action as it was."""
    bank = ModuleBank.build(["three_link"], ["reach_red"], pixels=True, dropout=0.0)
    policy = bank.compose("three_link", "reach_red")
    td = observations(("three_link", "reach_red"), pixels=True)
    moved = td.clone()
    moved["task", "state"][..., 4:] += 1.0  # every block, not the end-effector
    torch.testing.assert_close(mean_action(policy, td), mean_action(policy, moved), rtol=0, atol=0)
    moved["task", "ee"] = moved["task", "ee"] + 1.0
    assert not torch.equal(mean_action(policy, td), mean_action(policy, moved))


def test_config_options_and_their_errors():
    bank = ModuleBank.build(["three_link"], ["reach"], config=BankConfig(robot_hidden=(32,)), dropout=0.0)
    assert bank.config.robot_hidden == (32,) and bank.config.dropout == 0.0
    assert linear_shapes(bank.get("robot", "three_link")) == [(18, 32), (32, 3)]
    # lists, as JSON or a notebook gives them, are the tuples they stand for
    listed = ModuleBank.build(["three_link"], ["reach"], robot_hidden=[32], conv_strides=[2, 1])
    assert listed.config == BankConfig(robot_hidden=(32,))
    assert hash(listed.config) == hash(BankConfig(robot_hidden=(32,)))
    with pytest.raises(ValueError, match=r"interface_dim must hold positive integers, got \(0,\)"):
        BankConfig(interface_dim=0)
    with pytest.raises(ValueError, match=r"dropout must be a probability in \[0, 1\), got 1.5"):
        BankConfig(dropout=1.5)
    with pytest.raises(TypeError, match=r"unknown bank options \['widht'\]"):
        ModuleBank.build(ROBOTS, TASKS, widht=3)


def test_a_smooth_activation_runs_through_every_layer_saves_and_loads(tmp_path):
    """``activation`` sets every fully connected layer's nonlinearity, interface included; the
    network's Jacobian then changes with the state everywhere, where ReLU's is constant
    between kinks; the manifest keeps it, and a manifest from before the option is ReLU."""
    world = ("four_link", "reach_black")
    bank = ModuleBank.build(["four_link"], ["reach_black"], activation="softplus", seed=0).eval()
    nonlinear = (torch.nn.ReLU, torch.nn.Softplus)
    for name, factor in (("four_link", "robot"), ("reach_black", "task")):
        kinds = {type(m) for m in bank.get(factor, name).modules() if isinstance(m, nonlinear)}
        assert kinds == {torch.nn.Softplus}
    relu = ModuleBank.build(["four_link"], ["reach_black"], seed=0).eval()
    state = observations(world, batch=(1,))

    def jacobian(b: ModuleBank, shift: float) -> torch.Tensor:
        loc = lambda x: b.compose(*world)(state.clone().set(("robot", "state"), x))["loc"]
        return torch.autograd.functional.jacobian(loc, state["robot", "state"] + shift)

    assert torch.equal(jacobian(relu, 0.0), jacobian(relu, 1e-6))  # no unit switches
    assert not torch.equal(jacobian(bank, 0.0), jacobian(bank, 1e-6))
    with pytest.raises(ValueError, match="activation must be one of relu, tanh, elu, softplus, silu"):
        BankConfig(activation="gelu")
    assert typing.get_args(Activation) == tuple(ACTIVATIONS)  # run.py's choices are the library's

    path = bank.save(tmp_path / "bank")
    loaded = ModuleBank.load(path).eval()
    assert loaded.config.activation == "softplus"
    assert torch.equal(mean_action(bank.compose(*world), state), mean_action(loaded.compose(*world), state))
    assert bank.fresh_copy(seed=1).config.activation == "softplus"  # scratch starts keep it
    manifest = json.loads((path / "manifest.json").read_text())
    del manifest["config"]["activation"]
    for module in manifest["modules"]:
        module.get("arch", {}).pop("activation", None)
    (path / "manifest.json").write_text(json.dumps(manifest))
    older = ModuleBank.load(path)
    assert older.config.activation == "relu"
    kinds = {type(m) for m in older.modules() if isinstance(m, nonlinear)}
    assert kinds == {torch.nn.ReLU}


def test_seed_makes_initialisation_reproducible_and_per_module():
    state = lambda bank: bank.state_dict()
    a, b = ModuleBank.build(ROBOTS, TASKS, seed=0), ModuleBank.build(ROBOTS, TASKS, seed=0)
    assert all(torch.equal(a.state_dict()[k], v) for k, v in state(b).items())
    c = ModuleBank.build(ROBOTS, TASKS, seed=1)
    assert not all(torch.equal(a.state_dict()[k], v) for k, v in state(c).items())
    alone = ModuleBank.build(["four_link"], ["reach_black"], seed=0)  # other modules do not matter
    for name in ("robot", "task"):
        module = alone.get(name, "four_link" if name == "robot" else "reach_black")
        other = a.get(name, "four_link" if name == "robot" else "reach_black")
        assert all(torch.equal(p, q) for p, q in zip(module.parameters(), other.parameters(), strict=True))
    torch.manual_seed(5)
    expected = torch.rand(3)
    torch.manual_seed(5)
    ModuleBank.build(ROBOTS, TASKS, seed=0)
    assert torch.equal(torch.rand(3), expected)  # the global RNG is left alone


# --- sharing --------------------------------------------------------------------------------------
def test_compose_holds_the_banks_own_modules():
    bank = ModuleBank.build(ROBOTS, TASKS)
    policy = bank.compose("four_link", "reach_black")
    assert isinstance(policy, ProbabilisticActor)
    assert list(policy[0].module.keys()) == ["task", "robot"]
    assert policy[0]["task"] is bank.get("task", "reach_black")
    assert policy[0]["robot"] is bank.get("robot", "four_link")
    assert bank.compose("three_link", "reach_black")[0]["task"] is policy[0]["task"]
    assert bank.compose(task="reach_black", robot="four_link")[0]["robot"] is policy[0]["robot"]
    wrong_task = bank.compose("four_link", "reach_red")  # the "wrong task module" baseline
    assert wrong_task[0]["robot"] is policy[0]["robot"]
    td = observations(("four_link", "reach_black"))
    assert not torch.allclose(mean_action(wrong_task, td), mean_action(policy, td))


def test_gradient_of_one_world_reaches_exactly_its_modules():
    bank = ModuleBank.build(ROBOTS, TASKS, dropout=0.0)
    out = bank.compose("three_link", "reach_red")(observations(("three_link", "reach_red")))
    (out["loc"].pow(2).sum() + out["scale"].sum()).backward()
    for factor in bank.factors:
        for name in bank.names(factor):
            grads = [p.grad for p in bank.get(factor, name).parameters()]
            if name in ("three_link", "reach_red"):
                assert all(g is not None and g.abs().sum() > 0 for g in grads), (factor, name)
            else:
                assert all(g is None or not g.any() for g in grads), (factor, name)


def test_bank_parameters_have_no_duplicates():
    bank = ModuleBank.build(ROBOTS + ["five_link"], TASKS)
    policies = [bank.compose(r, k) for r in bank.names("robot") for k in bank.names("task")]
    params = list(bank.parameters())
    assert len({id(p) for p in params}) == len(params)
    per_module = [p for f in bank.factors for n in bank.names(f) for p in bank.get(f, n).parameters()]
    assert {id(p) for p in params} == {id(p) for p in per_module} and len(per_module) == len(params)
    seen = {id(p) for policy in policies for p in policy.parameters()}
    assert seen == {id(p) for p in params}  # every world's actor trains the bank's own tensors
    optimizer = torch.optim.Adam(bank.parameters())
    assert sum(len(g["params"]) for g in optimizer.param_groups) == len(params)


@pytest.mark.parametrize("name", ["train", "eval", "type", "reach.red", "", "a/b"])
def test_names_that_cannot_key_a_module_are_refused(name):
    with pytest.raises(BankError, match="cannot key a module"):
        ModuleBank(("task", name))
    bank = ModuleBank.build(["three_link"], ["reach"])
    with pytest.raises(BankError, match="cannot key a module"):
        bank.add("task", name, BankModule(bank.config.task_arch(6, pixels=False)))


# --- the policy -----------------------------------------------------------------------------------
def test_deterministic_exploration_gives_the_mean_and_random_samples():
    bank = ModuleBank.build(ROBOTS, TASKS).eval()
    policy = bank.compose("four_link", "reach_black")
    td = observations(("four_link", "reach_black"), batch=(2000,))
    with set_exploration_type(DETERMINISTIC), torch.no_grad():
        out = policy(td.clone())
    torch.testing.assert_close(out["action"], out["loc"])
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        sampled = policy(td.clone())
    z = (sampled["action"] - sampled["loc"]) / sampled["scale"]
    assert abs(float(z.mean())) < 0.1 and abs(float(z.std()) - 1) < 0.1  # Normal, not TanhNormal
    with torch.no_grad():
        default = policy(td.clone())["action"]
    assert not torch.allclose(default, out["loc"])  # samples unless asked for the mean
    bank.get("robot", "four_link").set_std(torch.full((4,), 0.05))
    torch.testing.assert_close(policy(td.clone())["scale"], torch.full((2000, 4), 0.05))


def test_dropout_is_on_in_train_mode_and_off_in_eval_mode():
    bank = ModuleBank.build(ROBOTS, TASKS, dropout=0.5)
    policy = bank.compose("three_link", "reach_black")
    td = observations(("three_link", "reach_black"), batch=(32,))
    assert not torch.allclose(mean_action(policy, td), mean_action(policy, td))
    bank.eval()
    torch.testing.assert_close(mean_action(policy, td), mean_action(policy, td))
    quiet = ModuleBank.build(ROBOTS, TASKS, dropout=0.0)  # configurable: no dropout at all
    policy = quiet.compose("three_link", "reach_black")
    torch.testing.assert_close(mean_action(policy, td), mean_action(policy, td))


def test_untrained_pair_runs_in_a_real_rollout_and_a_collector():
    bank = ModuleBank.build(ROBOTS, TASKS)
    bank.mark_trained("three_link", "reach_black")
    bank.mark_trained("four_link", "reach_red")
    policy = bank.compose("four_link", "reach_black")  # never trained together
    env = make_env("four_link", "reach_black", num_envs=8)
    td = env.rollout(50, policy)
    assert td.shape == (8, 50) and td["action"].shape == (8, 50, 4)
    assert torch.isfinite(td["next", "task", "state"]).all() and td["next", "done"][:, -1].all()
    bank.eval()
    with set_exploration_type(DETERMINISTIC):
        first, second = env.rollout(10, policy), env.rollout(10, policy)
    torch.testing.assert_close(first["action"], first["loc"])
    torch.testing.assert_close(first["next", "task", "state"], second["next", "task", "state"])

    collector = Collector(
        make_env("four_link", "reach_black", num_envs=4),
        policy,
        frames_per_batch=16,
        total_frames=32,
        auto_register_policy_transforms=False,
    )
    batches = list(collector)
    collector.shutdown()
    assert len(batches) == 2
    assert all(b.numel() == 16 and b["action"].shape[-1] == 4 and "loc" in b.keys() for b in batches)


# --- many worlds in one pass ----------------------------------------------------------------------
def test_forward_worlds_equals_the_per_world_loop_values_and_gradients():
    robots, tasks = ["three_link", "three_link_short", "four_link"], ["reach_red", "reach_green", "reach"]
    bank = ModuleBank.build(robots, tasks, dropout=0.0)
    worlds = [(r, k) for r in robots for k in tasks if (r, k) != ("four_link", "reach")]
    batches = {w: observations(w, batch=(i % 3 + 1, 4), seed=i) for i, w in enumerate(worlds)}
    batches["three_link/reach"] = batches.pop(("three_link", "reach"))  # "robot/task" keys work too
    out = bank.forward_worlds(batches)
    assert set(out) == set(worlds)
    grouped = sum(o["loc"].pow(2).sum() + o["scale"].sum() for o in out.values())
    grouped.backward()
    grads = {k: p.grad.clone() for k, p in bank.named_parameters()}
    bank.zero_grad()
    loop = 0
    for w in worlds:
        td = batches[w] if w in batches else batches["/".join(w)]
        ref = bank.compose(*w)[0](td.clone())
        for key in ("loc", "scale", ("interface", "task")):
            torch.testing.assert_close(out[w][key], ref[key])
        assert out[w].batch_size == td.batch_size
        loop = loop + ref["loc"].pow(2).sum() + ref["scale"].sum()
    loop.backward()
    torch.testing.assert_close(grouped, loop)
    for k, p in bank.named_parameters():
        torch.testing.assert_close(grads[k], p.grad, msg=k)


def test_forward_worlds_in_passes_gives_the_one_pass_outputs_in_each_batchs_shape():
    """``rows_per_pass``: batches of different sizes and shapes, cut into passes of 5 rows per
    world (the smaller batch runs out first), come back as the one-pass result; 0 is refused."""
    bank = ModuleBank.build(ROBOTS, TASKS, dropout=0.0)
    a, b = ("three_link", "reach_red"), ("four_link", "reach_red")
    batches = {a: observations(a, batch=(3, 4), seed=1), b: observations(b, batch=(2, 3, 4), seed=2)}
    whole = bank.forward_worlds(batches)
    passes = bank.forward_worlds(batches, rows_per_pass=5)
    for world, td in batches.items():
        assert passes[world].batch_size == td.batch_size
        for key in ("loc", "scale", ("interface", "task")):
            torch.testing.assert_close(passes[world][key], whole[world][key])
    with pytest.raises(ValueError, match="rows_per_pass must be at least 1"):
        bank.forward_worlds(batches, rows_per_pass=0)
    empty = {a: observations(a, batch=(0, 4), seed=1), b: batches[b]}  # an empty batch comes back empty
    out = bank.forward_worlds(empty, rows_per_pass=5)
    assert out[a].batch_size == (0, 4) and out[a]["loc"].shape == (0, 4, 3)
    torch.testing.assert_close(out[b]["loc"], whole[b]["loc"])
    alone = bank.forward_worlds({a: empty[a]}, rows_per_pass=5)
    assert alone[a]["loc"].shape == (0, 4, 3)


def test_forward_worlds_runs_each_module_once():
    bank = ModuleBank.build(ROBOTS, TASKS, dropout=0.0)
    calls = []
    for factor in bank.factors:
        for name in bank.names(factor):
            bank.get(factor, name).module.register_forward_hook(lambda m, i, o, n=name: calls.append(n))
    worlds = [(r, k) for r in ROBOTS for k in TASKS]
    bank.forward_worlds({w: observations(w) for w in worlds})
    assert sorted(calls) == sorted(ROBOTS + TASKS)


# --- normalisation --------------------------------------------------------------------------------
def test_fit_normalization_pools_the_worlds_of_each_module():
    bank = ModuleBank.build(ROBOTS, TASKS)
    a, b = ("three_link", "reach_red"), ("four_link", "reach_red")
    batches = {a: observations(a, batch=(50, 4), seed=1), b: observations(b, batch=(30,), seed=2)}
    batches[a]["task", "state"][..., 0] = 7.0  # a constant dimension in one world ...
    batches[b]["task", "state"][..., 0] = 7.0  # ... and the other
    bank.fit_normalization(batches)
    pooled = torch.cat([batches[a]["task", "state"].reshape(-1, 12), batches[b]["task", "state"]])
    mean, std = bank.get("task", "reach_red").normalization()
    torch.testing.assert_close(mean, pooled.mean(0))
    torch.testing.assert_close(std[1:], pooled.std(0, correction=0)[1:])
    assert std[0] == pytest.approx(1e-3)  # the floor
    robot_mean, _ = bank.get("robot", "four_link").normalization()
    torch.testing.assert_close(robot_mean, batches[b]["robot", "state"].mean(0))
    untouched_mean, untouched_std = bank.get("task", "reach_black").normalization()
    assert not untouched_mean.any() and (untouched_std == 1).all()


# --- save and load --------------------------------------------------------------------------------
@pytest.fixture
def saved(tmp_path):
    bank = ModuleBank.build(ROBOTS, TASKS, seed=3)
    worlds = [("three_link", "reach_red"), ("three_link", "reach_black"), ("four_link", "reach_red")]
    bank.fit_normalization({w: observations(w, batch=(40,), seed=i) for i, w in enumerate(worlds)})
    for world in worlds:
        bank.mark_trained(*world)
    return bank.eval(), bank.save(tmp_path / "bank")


def test_save_then_load_gives_identical_actions_and_the_manifest(saved):
    bank, path = saved
    loaded = ModuleBank.load(path).eval()
    for world in [("four_link", "reach_black"), ("three_link", "reach_red")]:
        td = observations(world, batch=(5, 7))
        assert torch.equal(mean_action(bank.compose(*world), td), mean_action(loaded.compose(*world), td))
    assert all(torch.equal(v, loaded.state_dict()[k]) for k, v in bank.state_dict().items())
    assert loaded.trained_on("robot", "three_link") == {
        ("three_link", "reach_red"),
        ("three_link", "reach_black"),
    }
    assert loaded.trained_on("robot", "four_link") == {("four_link", "reach_red")}
    assert loaded.config == bank.config

    manifest = json.loads((path / "manifest.json").read_text())
    assert manifest["factors"] == ["task", "robot"] and manifest["interface_dim"] == 12
    assert manifest["modnet_version"] and manifest["policy"] == "modular" and manifest["pixels"] is False
    assert manifest["config"]["dropout"] == 0.2 and manifest["config"]["task_hidden"] == [80, 80, 80]
    modules = {(m["factor"], m["name"]): m for m in manifest["modules"]}
    assert set(modules) == {("task", t) for t in TASKS} | {("robot", r) for r in ROBOTS}
    four = modules["robot", "four_link"]
    assert four["kind"] == "gaussian" and modules["task", "reach_red"]["kind"] == "interface"
    assert four["sizes"] == {"in interface/task": 12, "in robot/state": 8, "out loc": 4, "out scale": 4}
    assert modules["task", "reach_red"]["trained_on"] == [
        ["four_link", "reach_red"],
        ["three_link", "reach_red"],
    ]
    state = torch.load(path / "robot" / "four_link.pt", weights_only=True)
    assert {"module.normalizers.0.loc", "module.normalizers.0.scale", "module.head.log_std"} <= set(state)
    assert not [p for p in path.rglob("*") if p.name.endswith(".tmp")]  # temp files replaced


def test_a_fresh_process_loads_the_same_actions(saved, tmp_path):
    bank, path = saved
    td = observations(("four_link", "reach_black"), batch=(9,))
    torch.save({"robot": td["robot", "state"], "task": td["task", "state"]}, tmp_path / "obs.pt")
    script = """
import sys, torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type
from modnet.bank import ModuleBank
bank = ModuleBank.load(sys.argv[1]).eval()
obs = torch.load(sys.argv[2], weights_only=True)
td = TensorDict({("robot", "state"): obs["robot"], ("task", "state"): obs["task"]}, batch_size=[9])
with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
    torch.save(bank.compose("four_link", "reach_black")(td)["action"], sys.argv[3])
"""
    subprocess.run(
        [sys.executable, "-c", script, str(path), str(tmp_path / "obs.pt"), str(tmp_path / "act.pt")],
        check=True,
        timeout=120,
        env=os.environ | {"OMP_NUM_THREADS": "1"},
    )
    actions = torch.load(tmp_path / "act.pt", weights_only=True)
    assert torch.equal(actions, mean_action(bank.compose("four_link", "reach_black"), td))


def test_a_module_loads_into_another_bank_with_the_same_interface(saved, tmp_path):
    bank, path = saved
    other = ModuleBank.build(["five_link"], ["push"], seed=9).eval()
    module = other.load_module(path, "robot", "four_link")
    other.load_module(path, "task", "reach_black")
    assert other.get("robot", "four_link") is module and module is not bank.get("robot", "four_link")
    td = observations(("four_link", "reach_black"))
    torch.testing.assert_close(
        mean_action(other.compose("four_link", "reach_black"), td),
        mean_action(bank.compose("four_link", "reach_black"), td),
    )
    assert other.trained_on("robot", "four_link") == {("four_link", "reach_red")}
    other.compose("four_link", "push")  # a module from another bank composes with this bank's own
    with pytest.raises(BankError, match=r"no task module 'peg' in the bank at .*; it holds: task/reach_red"):
        other.load_module(path, "task", "peg")


def test_load_module_refuses_a_mismatched_interface_or_robot_size(saved, tmp_path):
    _, path = saved
    narrow = ModuleBank.build(["three_link"], ["reach_red"], interface_dim=8)
    with pytest.raises(
        BankError,
        match=r"cannot load task module 'reach_red' from .* as task 'reach_red': "
        r"out interface/task is 12 there but 8 here",
    ):
        narrow.load_module(path, "task", "reach_red")
    with pytest.raises(BankError, match=r"as robot 'three_link': in interface/task is 12 there but 8 here"):
        narrow.load_module(path, "robot", "three_link")
    bank = ModuleBank.build(ROBOTS, TASKS)
    with pytest.raises(
        BankError,
        match=r"cannot load robot module 'three_link' from .* as robot 'four_link': "
        r"in robot/state is 6 there but 8 here; out loc is 3 there but 4 here",
    ):
        bank.load_module(path, "robot", "three_link", into="four_link")
    with pytest.raises(BankError, match=r"unknown factor 'object'; this bank's: task, robot"):
        bank.load_module(path, "object", "cube")


def test_missing_and_corrupt_files_raise_one_clear_error(saved, tmp_path):
    bank, path = saved
    with pytest.raises(BankError, match=r"no saved bank at .*nowhere: manifest.json is missing"):
        ModuleBank.load(tmp_path / "nowhere")

    (path / "robot" / "four_link.pt").rename(tmp_path / "moved.pt")
    with pytest.raises(BankError, match=r"weights of robot module 'four_link' are missing: .*four_link.pt"):
        ModuleBank.load(path)
    (tmp_path / "moved.pt").rename(path / "robot" / "four_link.pt")

    (path / "task" / "reach_red.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(BankError, match=r"corrupt weights for task module 'reach_red'"):
        ModuleBank.load(path)
    torch.save(bank.get("task", "reach_black").module.state_dict(), path / "task" / "reach_red.pt")
    with pytest.raises(BankError, match=r"weights of task module 'reach_red' in .* do not fit"):
        ModuleBank.load(path)  # plain tensors, wrong key layout
    torch.save(bank.get("task", "reach_black").state_dict(), path / "task" / "reach_red.pt")

    manifest = json.loads((path / "manifest.json").read_text())
    manifest["modules"][0]["arch"]["out_dim"] = 7
    (path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BankError, match=r"weights of task module 'reach_red' .* do not fit its manifest"):
        ModuleBank.load(path)
    manifest["modules"][0]["arch"]["head"] = "lambda"
    (path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BankError, match=r"corrupt manifest .*head must be one of interface, gaussian"):
        ModuleBank.load(path)
    (path / "manifest.json").write_text("{ not json")
    with pytest.raises(BankError, match=r"corrupt manifest .*manifest.json: Expecting property name"):
        ModuleBank.load(path)
    (path / "manifest.json").write_text(json.dumps({"format": "something else"}))
    with pytest.raises(BankError, match=r"corrupt manifest .*: not a modnet.bank/1 manifest"):
        ModuleBank.load(path)


class _Payload:
    """Unpickling this would create a file: loading must refuse it, never run it."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_loading_never_executes_code_from_the_files(saved, tmp_path):
    _, path = saved
    marker = tmp_path / "executed"
    with open(path / "task" / "reach_red.pt", "wb") as f:
        pickle.dump({"module.net": _Payload(marker)}, f, protocol=2)
    with pytest.raises(BankError, match=r"corrupt weights for task module 'reach_red'"):
        ModuleBank.load(path)
    assert not marker.exists()
    manifest = json.loads((path / "manifest.json").read_text())
    manifest["modules"][0]["name"] = "../../escape"  # names become file paths: refused
    (path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BankError, match=r"corrupt manifest .*cannot key a module"):
        ModuleBank.load(path)
    assert not os.path.exists(marker)


# --- names ----------------------------------------------------------------------------------------
def test_unknown_names_raise_value_errors_naming_the_choices():
    with pytest.raises(ValueError, match=r"unknown robot 'six_link'; valid robots: three_link, "):
        ModuleBank.build(["six_link"], TASKS)
    with pytest.raises(ValueError, match=r"unknown task 'reach_blue'; valid tasks: reach_red, "):
        ModuleBank.build(ROBOTS, ["reach_blue"])
    bank = ModuleBank.build(ROBOTS, TASKS)
    with pytest.raises(ValueError, match=r"unknown robot 'six_link'; valid robots: three_link"):
        bank.compose("six_link", "reach_red")
    with pytest.raises(ValueError, match=r"unknown task 'reach_blue'; valid tasks"):
        bank.compose("four_link", "reach_blue")
    with pytest.raises(
        BankError, match=r"no robot module 'five_link'; its robot modules: three_link, four_link"
    ):
        bank.compose("five_link", "reach_red")
    with pytest.raises(BankError, match=r"a world names one module per factor \('robot', 'task'\)"):
        bank.compose("four_link")
    with pytest.raises(BankError, match="name one module per factor"):
        bank.compose("four_link", task="reach_red")
    with pytest.raises(BankError, match="is a task module; it cannot be a robot module"):
        bank.add("robot", "five_link", bank.get("task", "reach_red"))
    with pytest.raises(ValueError, match="non-empty list of robots"):
        ModuleBank.build("three_link", TASKS)


# --- baselines ------------------------------------------------------------------------------------
def test_fresh_copy_is_a_random_network_of_the_same_shape(saved):
    bank, _ = saved
    fresh = bank.fresh_copy(seed=11)
    assert fresh.names("robot") == bank.names("robot") and not fresh.trained_on("robot", "three_link")
    for key, value in bank.state_dict().items():
        assert fresh.state_dict()[key].shape == value.shape
        if "normalizers" in key:
            assert torch.equal(fresh.state_dict()[key], value)  # inputs scaled the same way
    assert not any(p is q for p in fresh.parameters() for q in bank.parameters())
    weights = [k for k in bank.state_dict() if k.endswith("weight")]
    assert not any(torch.equal(fresh.state_dict()[k], bank.state_dict()[k]) for k in weights)
    again = bank.fresh_copy(seed=11)
    assert all(torch.equal(v, again.state_dict()[k]) for k, v in fresh.state_dict().items())


def test_monolithic_baseline_has_one_network_per_world_and_the_same_interface(tmp_path):
    mono = ModuleBank.build(ROBOTS, TASKS, policy="monolithic", seed=0)
    modular = ModuleBank.build(ROBOTS, TASKS, seed=0)
    assert mono.names("world") == (
        "three_link-reach_red",
        "three_link-reach_black",
        "four_link-reach_red",
        "four_link-reach_black",
    )
    policy = mono.compose("four_link", "reach_black")
    network = policy[0]["world"]
    assert set(network.in_keys) == {("robot", "state"), ("task", "state")}
    size = lambda module: sum(p.numel() for p in module.parameters())
    pair = size(modular.get("robot", "four_link")) + size(modular.get("task", "reach_black"))
    assert 0.5 < size(network) / pair < 2  # comparable size
    td = make_env("four_link", "reach_black", num_envs=2, horizon=4).rollout(4, policy)
    assert td["action"].shape == (2, 4, 4)
    out = mono.forward_worlds({("four_link", "reach_black"): observations(("four_link", "reach_black"))})
    assert out["four_link", "reach_black"]["loc"].shape == (6, 4)
    mono.eval()
    loaded = ModuleBank.load(mono.save(tmp_path / "mono")).eval()
    td = observations(("three_link", "reach_red"))
    assert torch.equal(
        mean_action(loaded.compose("three_link", "reach_red"), td),
        mean_action(mono.compose("three_link", "reach_red"), td),
    )
    with pytest.raises(BankError, match="no world module 'three_link-push'"):
        mono.compose("three_link", "push")


# --- more than two degrees of variation -----------------------------------------------------------
def three_factor_bank() -> ModuleBank:
    """object -> task -> robot with synthetic sizes: objects read ("object", "state")."""
    bank = ModuleBank(("object", "task", "robot"))
    for name, dim in (("cube", 4), ("ball", 6)):
        obj = ModuleArch(
            factor="object",
            head="interface",
            out_dim=6,
            observations=((("object", "state"), dim),),
            hidden=(32,),
        )
        bank.add("object", name, BankModule(obj))
    for name in ("push", "lift"):
        arch = ModuleArch(
            factor="task",
            head="interface",
            out_dim=8,
            observations=((("task", "state"), 4),),
            reads=(("object", 6),),
            hidden=(32,),
        )
        bank.add("task", name, BankModule(arch))
    for name, joints in (("arm2", 2), ("arm3", 3)):
        arch = ModuleArch(
            factor="robot",
            head="gaussian",
            out_dim=joints,
            observations=((("robot", "state"), 2 * joints),),
            reads=(("task", 8),),
            hidden=(32,),
        )
        bank.add("robot", name, BankModule(arch))
    return bank


def test_three_factor_chain_composes_and_trains():
    torch.manual_seed(0)
    bank = three_factor_bank()
    sizes = {"cube": 4, "ball": 6, "arm2": 2, "arm3": 3}
    worlds = [
        ("arm2", "push", "cube"),
        ("arm3", "push", "ball"),
        ("arm2", "lift", "ball"),
        ("arm3", "lift", "cube"),
    ]
    batches, targets = {}, {}
    for robot, task, obj in worlds:
        td = TensorDict(
            {
                ("robot", "state"): torch.randn(64, 2 * sizes[robot]),
                ("task", "state"): torch.randn(64, 4),
                ("object", "state"): torch.randn(64, sizes[obj]),
            },
            batch_size=[64],
        )
        batches[robot, task, obj] = td
        signal = td["object", "state"][:, :1] + td["task", "state"][:, :1] + td["robot", "state"][:, :1]
        targets[robot, task, obj] = torch.tanh(signal).expand(64, sizes[robot])

    policy = bank.compose("arm3", "push", "cube")  # composes, also for a world never trained on
    assert list(policy[0].module.keys()) == ["object", "task", "robot"]
    assert policy[0]["object"] is bank.get("object", "cube")
    assert policy(batches["arm3", "lift", "cube"].clone())["action"].shape == (64, 3)

    before = {k: p.detach().clone() for k, p in bank.named_parameters()}
    optimizer = torch.optim.Adam(bank.parameters(), lr=3e-3)

    def loss() -> torch.Tensor:
        out = bank.forward_worlds(batches)
        return sum((out[w]["loc"] - targets[w]).pow(2).mean() for w in worlds)

    with torch.no_grad():
        start = float(loss())
    for _ in range(60):
        optimizer.zero_grad()
        loss().backward()
        optimizer.step()
    with torch.no_grad():
        assert float(loss()) < 0.5 * start
    for name, value in bank.named_parameters():
        if "log_std" not in name:
            assert not torch.equal(value, before[name]), name  # every module learned


def test_three_factor_chain_checks_its_interfaces():
    bank = three_factor_bank()
    wide = ModuleArch(
        factor="task",
        head="interface",
        out_dim=8,
        observations=((("task", "state"), 4),),
        reads=(("object", 5),),
    )
    bank.add("task", "stack", BankModule(wide))
    with pytest.raises(
        BankError, match=r"the task module 'stack' reads the object interface at width 5, but it is 6 wide"
    ):
        bank.compose("arm2", "stack", "cube")
    with pytest.raises(BankError, match="no object module 'plate'; its object modules: cube, ball"):
        bank.compose("arm2", "push", "plate")
