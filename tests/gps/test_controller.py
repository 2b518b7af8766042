"""LinearGaussianController: mean, sampling, RNG, constructors, TorchRL rollout."""

from __future__ import annotations

import pytest
import scipy.ndimage
import torch
from tensordict import TensorDict
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase, StepCounter, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from modnet.gps.controller import LinearGaussianController, LinearGaussianGains, smoothed_noise
from modnet.gps.cost import QuadraticCost
from modnet.gps.dynamics import LinearGaussianDynamics
from modnet.gps.errors import NumericalError

f64 = torch.float64
M, T, dU = 3, 5, 2
ROBOT, TASK = ("robot", "state"), ("task", "state")
dR, dT = 3, 1
dX = dR + dT


def random_gains(seed: int = 0) -> LinearGaussianGains:
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(M, T, dU, dU, dtype=f64, generator=g)
    return LinearGaussianGains.from_covariance(
        torch.randn(M, T, dU, dX, dtype=f64, generator=g),
        torch.randn(M, T, dU, dtype=f64, generator=g),
        A @ A.transpose(-1, -2) + 0.1 * torch.eye(dU, dtype=f64),
    )


def batch(condition: list[int], step: list[int], seed: int = 1) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    B = len(condition)
    return TensorDict(
        {
            ROBOT: torch.randn(B, dR, generator=g),
            TASK: torch.randn(B, dT, generator=g),
            "condition": torch.tensor(condition),
            "step_count": torch.tensor(step).unsqueeze(-1),
        },
        batch_size=[B],
    )


def test_deterministic_action_uses_right_condition_and_step():
    gains = random_gains()
    ctrl = LinearGaussianController(gains, [ROBOT, TASK], deterministic=True)
    conditions, steps = [0, 2, 1, 2, 0], [0, 4, 3, 9, 1]  # step 9 is clamped to T-1
    td = ctrl(batch(conditions, steps))
    x = torch.cat([td[ROBOT], td[TASK]], -1).double()
    for i, (c, t) in enumerate(zip(conditions, steps, strict=True)):
        t = min(t, T - 1)
        expected = gains.K[c, t] @ x[i] + gains.k[c, t]
        torch.testing.assert_close(td["action"][i], expected.float())
    assert td["action"].dtype == torch.float32
    # The state keys are concatenated in the order given.
    swapped = LinearGaussianController(gains, [TASK, ROBOT], deterministic=True)
    assert not torch.allclose(swapped(batch(conditions, steps))["action"], td["action"])


def test_exploration_type_selects_mean_or_sample():
    ctrl = LinearGaussianController(random_gains(), [ROBOT, TASK])
    td = batch([1, 1], [2, 2])
    mean = LinearGaussianController(random_gains(), [ROBOT, TASK], deterministic=True)(td.clone())
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        torch.testing.assert_close(ctrl(td.clone())["action"], mean["action"])
    with set_exploration_type(ExplorationType.RANDOM):
        assert not torch.allclose(ctrl(td.clone())["action"], mean["action"])
    assert not torch.allclose(ctrl(td.clone())["action"], mean["action"])  # default: sample


def test_sampled_actions_have_the_controller_covariance():
    gains = random_gains()
    ctrl = LinearGaussianController(gains, [ROBOT, TASK], action_dtype=f64)
    n = 40000
    td = batch([2] * n, [3] * n)
    td[ROBOT] = td[ROBOT][:1].expand(n, dR).clone()
    td[TASK] = td[TASK][:1].expand(n, dT).clone()
    torch.manual_seed(0)
    actions = ctrl(td)["action"]
    cov = torch.cov(actions.T)
    torch.testing.assert_close(cov, gains.cov[2, 3], rtol=0.05, atol=0.02)
    x = torch.cat([td[ROBOT][0], td[TASK][0]]).double()
    mean = gains.K[2, 3] @ x + gains.k[2, 3]
    torch.testing.assert_close(actions.mean(0), mean, atol=0.05, rtol=0)


def test_noise_is_reproducible_under_seed_or_generator():
    td = batch([0, 1, 2], [0, 1, 2])
    ctrl = LinearGaussianController(random_gains(), [ROBOT, TASK])
    torch.manual_seed(5)
    a = ctrl(td.clone())["action"]
    torch.manual_seed(5)
    torch.testing.assert_close(ctrl(td.clone())["action"], a)
    with_gen = lambda: LinearGaussianController(
        random_gains(), [ROBOT, TASK], generator=torch.Generator().manual_seed(3)
    )(td.clone())["action"]
    torch.testing.assert_close(with_gen(), with_gen())


def test_initial_hold_position_controller():
    hold = torch.tensor([[0.5, -0.2, 0.0, 0.0], [1.0, 2.0, 0.0, 0.0]], dtype=f64)
    ctrl = LinearGaussianController.initial(
        ["x"], num_conditions=2, horizon=T, state_dim=4, joint_position_idx=[0, 1],
        joint_velocity_idx=[2, 3], hold_state=hold, kp=2.0, kd=0.5, variance=3.0,
        deterministic=True,
    )
    x = torch.tensor([[0.5, -0.2, 0.0, 0.0], [0.0, 2.0, 1.0, -1.0]], dtype=f64)
    td = TensorDict(
        {"x": x, "condition": torch.tensor([0, 1]), "step_count": torch.tensor([[0], [3]])},
        batch_size=[2],
    )
    action = ctrl(td)["action"]
    torch.testing.assert_close(action[0], torch.zeros(2, dtype=f64))  # at the hold position
    torch.testing.assert_close(action[1], torch.tensor([2.0 * 1.0 - 0.5, 0.5], dtype=f64))
    torch.testing.assert_close(ctrl.gains.cov, 3.0 * torch.eye(2, dtype=f64).expand(2, T, 2, 2))


def test_from_lqr_and_set_gains():
    F = torch.tensor([[1.0, 0.1, 0.0], [0.0, 1.0, 0.1]], dtype=f64)
    dyn = LinearGaussianDynamics(
        F=F.expand(1, T, 2, 3), f=torch.zeros(1, T, 2, dtype=f64),
        D=torch.zeros(1, T, 2, 2, dtype=f64), x0mu=torch.zeros(1, 2, dtype=f64),
        x0sigma=torch.eye(2, dtype=f64)[None],
    )
    cost = QuadraticCost(
        torch.diag(torch.tensor([1.0, 0.1, 0.1], dtype=f64)).expand(1, T, 3, 3),
        torch.zeros(1, T, 3, dtype=f64), torch.zeros(1, T, dtype=f64),
    )
    ctrl = LinearGaussianController.from_lqr(["x"], dyn, cost, variance=0.5)
    assert ctrl.gains.K.shape == (1, T, 1, 2)
    assert bool((ctrl.gains.K[0, :-2, 0, 0] < 0).all())  # pushes the position back to 0
    new = random_gains()
    other = LinearGaussianController(random_gains(seed=1), [ROBOT, TASK])
    other.set_gains(new)
    torch.testing.assert_close(other.gains.K, new.K)
    torch.testing.assert_close(other.gains.cov, new.cov)
    kept = other.gains  # a snapshot: setting other gains leaves it, and setting it back restores
    other.set_gains(random_gains(seed=2))
    assert not torch.equal(other.gains.K, new.K)
    for name in ("K", "k", "chol", "cov"):
        torch.testing.assert_close(getattr(kept, name), getattr(new, name))
    other.set_gains(kept)
    torch.testing.assert_close(other.gains.k, new.k)
    bad = random_gains()
    bad.K[1, 2, 0, 0] = float("inf")
    with pytest.raises(NumericalError, match="condition=1"):
        other.set_gains(bad)


class TinyEnv(EnvBase):
    """M copies of x' = x + 0.1 [u; 0]: robot state (3), task state (1), and a condition id."""

    def __init__(self) -> None:
        super().__init__(batch_size=torch.Size([M]))
        self.observation_spec = Composite(
            robot=Composite(state=Unbounded((M, dR)), shape=(M,)),
            task=Composite(state=Unbounded((M, dT)), shape=(M,)),
            condition=Categorical(M, shape=(M,), dtype=torch.int64),
            shape=(M,),
        )
        self.action_spec = Unbounded((M, dU))
        self.reward_spec = Unbounded((M, 1))

    def _reset(self, td):
        x = torch.arange(M * dX, dtype=torch.float32).reshape(M, dX) / 10
        return TensorDict(
            {ROBOT: x[:, :dR], TASK: x[:, dR:], "condition": torch.arange(M)}, batch_size=[M]
        )

    def _step(self, td):
        robot = td[ROBOT].clone()
        robot[:, :dU] += 0.1 * td["action"]
        return TensorDict(
            {
                ROBOT: robot, TASK: td[TASK], "condition": td["condition"],
                "reward": -robot.pow(2).sum(-1, keepdim=True),
                "done": torch.zeros(M, 1, dtype=torch.bool),
                "terminated": torch.zeros(M, 1, dtype=torch.bool),
            },
            batch_size=[M],
        )

    def _set_seed(self, seed):
        return seed


def test_policy_of_a_torchrl_rollout():
    env = TransformedEnv(TinyEnv(), StepCounter())
    gains = random_gains()
    ctrl = LinearGaussianController(gains, [ROBOT, TASK], deterministic=True)
    steps = T + 2  # runs past the horizon: the last gains are reused
    traj = env.rollout(steps, policy=ctrl)
    assert traj.shape == (M, steps)
    x = torch.cat([traj[ROBOT], traj[TASK]], -1).double()
    t = traj["step_count"].squeeze(-1).clamp(max=T - 1)
    cond = traj["condition"]
    expected = (gains.K[cond, t] @ x.unsqueeze(-1)).squeeze(-1) + gains.k[cond, t]
    torch.testing.assert_close(traj["action"], expected.float())
    assert traj["step_count"][0, :, 0].tolist() == list(range(steps))
    torch.manual_seed(0)
    sampled = env.rollout(steps, policy=LinearGaussianController(gains, [ROBOT, TASK]))
    assert not torch.allclose(sampled["action"], traj["action"])


@pytest.mark.parametrize("horizon", [30, 3])  # 3: the kernel (radius 8) is wider than the episode
def test_smoothed_noise_is_gpss_filtered_and_renormalised_noise(horizon):
    white = torch.randn(4, horizon, 2, dtype=f64, generator=torch.Generator().manual_seed(0))
    expected = scipy.ndimage.gaussian_filter1d(white.numpy(), 2.0, axis=1, mode="reflect")
    expected /= expected.std(1, keepdims=True)
    smooth = smoothed_noise((4, horizon, 2), 2.0, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(smooth, torch.from_numpy(expected))
    unsmoothed = smoothed_noise((4, horizon, 2), 0.0, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(unsmoothed, white)


def lag_one_correlation(actions: torch.Tensor) -> float:
    """Mean over entries and dims of the correlation of consecutive actions ``[B, T, dU]``."""
    a = actions - actions.mean(1, keepdim=True)
    return float(((a[:, 1:] * a[:, :-1]).sum(1) / a.pow(2).sum(1)).mean())


@pytest.mark.parametrize("sigma", [0.0, 2.0])
def test_rollout_noise_is_smoothed_per_episode(sigma):
    horizon = 40
    gains = LinearGaussianGains.from_covariance(  # zero mean: the actions are the noise
        torch.zeros(M, horizon, dU, dX, dtype=f64),
        torch.zeros(M, horizon, dU, dtype=f64),
        4.0 * torch.eye(dU, dtype=f64).expand(M, horizon, dU, dU),
    )
    ctrl = LinearGaussianController(
        gains, [ROBOT, TASK], noise_smoothing=sigma, generator=torch.Generator().manual_seed(0),
        action_dtype=f64,
    )
    env = TransformedEnv(TinyEnv(), StepCounter())
    first, second = (env.rollout(horizon, policy=ctrl)["action"] for _ in range(2))
    if sigma:
        assert lag_one_correlation(first) > 0.8
        # each episode's noise has exactly the controllers' variance over its steps
        torch.testing.assert_close(first.var(1, unbiased=False), torch.full((M, dU), 4.0, dtype=f64))
    else:
        assert abs(lag_one_correlation(first)) < 0.2
    assert not torch.allclose(first, second)  # drawn afresh for each episode


def test_negative_noise_smoothing_is_refused():
    with pytest.raises(ValueError, match="noise_smoothing"):
        LinearGaussianController(random_gains(), [ROBOT, TASK], noise_smoothing=-1.0)
