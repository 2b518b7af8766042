"""PI2's C-step: the temperature meets its KL bound, the update follows the cheaper samples;
PILQR's: the model's cost of each sample is exact on a linear world, and PI2 then moves the
LQR's controllers only by the cost the model misses."""

import math

import pytest
import torch

from modnet.gps.controller import LinearGaussianGains, time_filtered
from modnet.gps.cost import QuadraticCost
from modnet.gps.dynamics import LinearGaussianDynamics
from modnet.gps.errors import NumericalError
from modnet.gps.pi2 import (
    MIN_TEMPERATURE,
    model_costs,
    pi2_update,
    pilqr_update,
    policy_log_ratio,
    sampling_noise,
    temperatures,
)


def gaussian(M=1, T=4, dU=2, dX=3, K=None, k=None, variance=1.0) -> LinearGaussianGains:
    K = torch.zeros(M, T, dU, dX, dtype=torch.float64) if K is None else K
    k = torch.zeros(M, T, dU, dtype=torch.float64) if k is None else k
    return LinearGaussianGains.from_covariance(K, k, variance * torch.eye(dU).expand(M, T, dU, dU))


def draw(gains: LinearGaussianGains, X: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """``u ~ N(K x + k, cov)`` at states ``X [M, N, T, dX]``."""
    mean = gains.mean_actions(X)
    noise = torch.randn(mean.shape, generator=generator, dtype=torch.float64)
    return mean + (gains.chol.unsqueeze(1) @ noise.unsqueeze(-1)).squeeze(-1)


@pytest.mark.parametrize("kl", [0.05, 0.5, 1.5])
def test_the_temperature_puts_the_weights_exactly_kl_from_uniform(kl):
    g = torch.Generator().manual_seed(0)
    cost_to_go = 100 * torch.rand(3, 10, 7, generator=g, dtype=torch.float64)  # [M, N, T]
    eta = temperatures(cost_to_go, kl)
    weights = torch.softmax(-(cost_to_go - cost_to_go.amin(1, keepdim=True)) / eta.unsqueeze(1), dim=1)
    divergence = (weights * (weights.log() + math.log(10))).sum(1)
    assert torch.allclose(divergence, torch.full_like(divergence, kl), atol=1e-6)
    # a lower temperature would be greedier than the bound allows, a higher one is not the lowest
    assert bool((eta > MIN_TEMPERATURE).all())


@pytest.mark.parametrize("samples", [1, 2, 3])
def test_a_kl_the_samples_weights_cannot_reach_is_refused_not_met_by_one_sample(samples):
    # the weights of N samples are at most log N from uniform; asked for that, PI2 would put
    # every weight on one sample and collapse the covariance (stop 79's 2-sample fine-tuning)
    cost_to_go = torch.arange(float(samples)).reshape(samples, 1).expand(samples, 4)
    with pytest.raises(ValueError, match=f"weights of {samples} samples"):
        temperatures(cost_to_go, math.log(samples))
    with pytest.raises(ValueError, match="non-negative"):
        temperatures(cost_to_go, -0.1)
    gains = LinearGaussianGains.from_covariance(
        torch.zeros(1, 4, 1, 1), torch.zeros(1, 4, 1), torch.eye(1).expand(1, 4, 1, 1).clone()
    )
    X, U = torch.zeros(1, samples, 4, 1), torch.randn(1, samples, 4, 1)
    with pytest.raises(ValueError, match="out of reach"):
        pi2_update(gains, X, U, cost_to_go.unsqueeze(0), kl=1.0 if samples < 3 else 1.2)


def test_equal_costs_leave_the_weights_uniform_and_the_feed_forward_at_the_samples_mean():
    gains = gaussian(M=2, T=3)
    g = torch.Generator().manual_seed(1)
    X = torch.randn(2, 6, 3, 3, generator=g, dtype=torch.float64)
    U = draw(gains, X, g)
    result = pi2_update(gains, X, U, torch.ones(2, 6, 3))
    assert torch.allclose(result.kl, torch.zeros_like(result.kl), atol=1e-12)
    assert torch.allclose(result.gains.k, U.mean(1))


def test_the_feedback_gains_stay_and_the_feed_forward_is_taken_net_of_them():
    """PI2 moves only ``k``: a sample's feed-forward is ``u - K x`` under the sampling gains."""
    g = torch.Generator().manual_seed(2)
    K = torch.randn(1, 5, 2, 3, generator=g, dtype=torch.float64)
    gains = gaussian(M=1, T=5, K=K)
    X = torch.randn(1, 8, 5, 3, generator=g, dtype=torch.float64)
    U = draw(gains, X, g)
    feed_forward = U - (K.unsqueeze(1) @ X.unsqueeze(-1)).squeeze(-1)
    costs = torch.zeros(1, 8, 5, dtype=torch.float64)
    costs[:, 3, -1] = -50.0  # sample 3 alone is much cheaper, at every step's cost to go
    result = pi2_update(gains, X, U, costs, kl=math.log(8) - 1e-6)  # nearly all weight on it
    assert torch.equal(result.gains.K, K)
    assert torch.allclose(result.gains.k, feed_forward[:, 3], atol=1e-3)


def test_repeated_updates_find_the_cheapest_actions_and_shrink_the_exploration():
    """A bandit at each of T steps: cost ``|u - u*|^2``. Sampling, weighting and refitting
    brings the mean to ``u*`` and narrows the covariance, as PI2 should."""
    M, N, T, dU = 2, 20, 6, 2
    target = torch.tensor([[0.8, -0.5], [-1.2, 0.3]], dtype=torch.float64)[:, None, None]  # [M, 1, 1, dU]
    gains = gaussian(M=M, T=T, dU=dU)
    g = torch.Generator().manual_seed(3)
    X = torch.zeros(M, N, T, 3, dtype=torch.float64)
    for _ in range(40):
        U = draw(gains, X, g)
        gains = pi2_update(gains, X, U, (U - target).pow(2).sum(-1)).gains
    assert (gains.k - target.squeeze(1)).abs().max() < 0.1
    assert float(gains.cov.diagonal(dim1=-2, dim2=-1).max()) < 0.25


def test_a_collapsed_sample_spread_is_a_numerical_error_naming_its_condition():
    gains = gaussian(M=2, T=2)
    X = torch.zeros(2, 4, 2, 3, dtype=torch.float64)
    U = torch.zeros(2, 4, 2, 2, dtype=torch.float64)
    U[0] = torch.randn(4, 2, 2, dtype=torch.float64)  # condition 1's samples all coincide
    with pytest.raises(NumericalError, match="not positive definite") as info:
        pi2_update(gains, X, U, torch.rand(2, 4, 2, dtype=torch.float64))
    assert info.value.condition == 1


def test_the_damping_sets_how_much_of_the_weighted_shrink_the_covariance_takes():
    """``cov_new = cov_old * ratio ** (1 / damping)``: damping 1 takes the whole shrink, 2 its
    square root, and a very large damping keeps the exploration as it was."""
    gains = gaussian(M=1, T=3, variance=2.0)
    g = torch.Generator().manual_seed(5)
    X = torch.zeros(1, 12, 3, 3, dtype=torch.float64)
    U = draw(gains, X, g)
    costs = U.pow(2).sum(-1)  # the samples near 0 weigh most: the weighted spread is narrower

    def scale(damping: float) -> torch.Tensor:
        cov = pi2_update(gains, X, U, costs, covariance_damping=damping).gains.cov
        return cov.diagonal(dim1=-2, dim2=-1) / gains.cov.diagonal(dim1=-2, dim2=-1)

    whole, root, kept = scale(1.0), scale(2.0), scale(1e6)
    assert bool((whole < 0.9).all())
    assert torch.allclose(root, whole.sqrt())
    assert torch.allclose(kept, torch.ones_like(kept), atol=1e-5)


def test_covariance_damping_must_be_positive():
    gains = gaussian()
    X, U = torch.zeros(1, 3, 4, 3), torch.zeros(1, 3, 4, 2)
    with pytest.raises(ValueError, match="covariance_damping must be positive"):
        pi2_update(gains, X, U, torch.zeros(1, 3, 4), covariance_damping=0.0)


def test_a_smoothed_step_is_the_step_filtered_along_time_and_drops_its_chance_part():
    """A bandit at each of T steps whose best action varies slowly along time (``sin``), 10
    draws per condition: each condition's raw step is mostly the chance mean of its few
    samples' noise, which differs from one step and condition to the next (its spread over 64
    conditions). ``step_smoothing`` filters the step, ``k_new - k_old``, along time and adds it
    to the old ``k``, which here alternates from step to step and so must not be filtered
    itself; the smoothed step keeps about a quarter of the chance spread and almost none of its
    change from step to step. The covariance and temperatures are PI2's own either way; a
    negative width is refused."""
    M, N, T, dU = 64, 10, 100, 1
    best = torch.sin(torch.linspace(0, math.pi, T, dtype=torch.float64)).reshape(1, 1, T, 1)
    old = (1.0 + 0.5 * (-1.0) ** torch.arange(T, dtype=torch.float64)).reshape(1, T, 1).expand(M, T, dU)
    gains = gaussian(M=M, T=T, dU=dU, dX=1, k=old)
    X = torch.zeros(M, N, T, 1, dtype=torch.float64)
    U = draw(gains, X, torch.Generator().manual_seed(0))
    costs = (U - old.unsqueeze(1) - best).pow(2).sum(-1)
    raw, smoothed = (pi2_update(gains, X, U, costs, step_smoothing=s) for s in (0.0, 5.0))
    assert torch.allclose(smoothed.gains.k, old + time_filtered(raw.gains.k - old, 5.0))
    k = {"raw": (raw.gains.k - old)[..., 0], "smoothed": (smoothed.gains.k - old)[..., 0]}
    chance = {name: ks - ks.mean(0) for name, ks in k.items()}
    spread = {name: float(c.pow(2).mean().sqrt()) for name, c in chance.items()}
    assert spread["smoothed"] < 0.35 * spread["raw"], spread
    step_to_step = {name: float(c.diff(dim=1).abs().mean()) for name, c in chance.items()}
    assert step_to_step["smoothed"] < 0.05 * step_to_step["raw"], step_to_step
    assert torch.equal(raw.gains.cov, smoothed.gains.cov) and torch.equal(raw.eta, smoothed.eta)
    with pytest.raises(ValueError, match="step_smoothing must be non-negative"):
        pi2_update(gains, X, U, costs, step_smoothing=-1.0)


def test_the_policy_log_ratio_averages_to_the_kl_and_steers_pi2_towards_the_policy():
    """Over samples the controllers drew, the mean log-likelihood ratio is ``KL(q || p)`` of unit
    variances, half the squared gap of the means, whatever the controllers' own spread; added to
    an even cost it moves PI2's feed-forward from the controllers' towards the policy's actions."""
    K = torch.randn(1, 3, 2, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    gains = gaussian(M=1, T=3, K=K, variance=0.5)
    g = torch.Generator().manual_seed(1)
    X = torch.randn(1, 20000, 3, 3, generator=g, dtype=torch.float64)
    U = draw(gains, X, g)
    gap = torch.tensor([0.3, -0.6], dtype=torch.float64)
    policy = gains.mean_actions(X) + gap
    ratio = policy_log_ratio(gains, X, U, policy)
    kl = 0.5 * float(gap @ gap)
    assert torch.allclose(ratio.mean(1), torch.full((1, 3), kl, dtype=torch.float64), rtol=0.05)
    X, U, ratio = X[:, :30], U[:, :30], ratio[:, :30]
    even = torch.zeros(ratio.shape, dtype=torch.float64)
    moved = pi2_update(gains, X, U, even + 5.0 * ratio).gains.k - gains.k
    unmoved = pi2_update(gains, X, U, even).gains.k - gains.k
    assert bool((moved @ gap > 0.5 * float(gap @ gap)).all()), moved  # most of the way to the policy
    assert float((unmoved @ gap).abs().max()) < 0.5 * float(gap @ gap)  # the samples' own mean


class LinearWorld:
    """``x' = A x + B u`` from a fixed ``x0``, cost ``0.5 tau' C tau + c' tau`` per step: a
    world the fitted model describes exactly."""

    def __init__(self, M=2, T=5, dX=3, dU=2, seed=4):
        g = torch.Generator().manual_seed(seed)
        d = dX + dU
        A = torch.eye(dX) + 0.1 * torch.randn(dX, dX, generator=g)
        self.F = torch.cat([A, torch.randn(dX, dU, generator=g)], -1).to(torch.float64).expand(M, T, dX, d)
        self.x0 = torch.randn(M, dX, generator=g, dtype=torch.float64)
        root = torch.randn(d, d, generator=g, dtype=torch.float64)
        self.cost = QuadraticCost(
            (root @ root.T + torch.eye(d)).expand(M, T, d, d).to(torch.float64),
            torch.randn(M, T, d, generator=g, dtype=torch.float64),
            torch.zeros(M, T, dtype=torch.float64),
        )
        self.dynamics = LinearGaussianDynamics(
            self.F,
            torch.zeros(M, T, dX, dtype=torch.float64),
            torch.zeros(M, T, dX, dX, dtype=torch.float64),
            self.x0,
            torch.zeros(M, dX, dX, dtype=torch.float64),
        )

    def run(self, gains: LinearGaussianGains, noise: torch.Tensor):
        """States, actions and the true per-step costs of ``u = K x + k + chol noise``."""
        M, N, T, _ = noise.shape
        x, xs, us = self.x0.unsqueeze(1).expand(M, N, -1), [], []
        for t in range(T):
            u = (gains.K[:, t, None] @ x.unsqueeze(-1)).squeeze(-1) + gains.k[:, t, None]
            u = u + (gains.chol[:, t, None] @ noise[:, :, t].unsqueeze(-1)).squeeze(-1)
            xs.append(x)
            us.append(u)
            x = (self.F[:, t, None] @ torch.cat([x, u], -1).unsqueeze(-1)).squeeze(-1)
        X, U = torch.stack(xs, 2), torch.stack(us, 2)
        return X, U, self.cost(torch.cat([X, U], -1).transpose(0, 1)).transpose(0, 1)


def antithetic_noise(M, N, T, dU, seed=5):
    half = torch.randn(M, N // 2, T, dU, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return torch.cat([half, -half], 1)  # mean exactly zero


def test_the_sampling_noise_and_the_models_cost_of_each_sample_are_exact_on_a_linear_world():
    world = LinearWorld()
    g = torch.Generator().manual_seed(6)
    K = 0.3 * torch.randn(2, 5, 2, 3, generator=g, dtype=torch.float64)
    sampling = gaussian(M=2, T=5, K=K, variance=0.5)
    noise = torch.randn(2, 6, 5, 2, generator=g, dtype=torch.float64)
    X, U, costs = world.run(sampling, noise)
    torch.testing.assert_close(sampling_noise(sampling, X, U), noise)
    torch.testing.assert_close(model_costs(sampling, world.dynamics, world.cost, noise), costs)


def test_where_the_model_explains_every_sample_pilqr_keeps_the_lqrs_step():
    """No residual: the weights are uniform, and the noise replayed through the LQR's new
    controllers averages to their own feed-forward."""
    world, (M, N, T, dU) = LinearWorld(), (2, 8, 5, 2)
    sampling = gaussian(M=M, T=T, variance=0.5)
    X, U, costs = world.run(sampling, antithetic_noise(M, N, T, dU))
    g = torch.Generator().manual_seed(7)
    lqr = gaussian(
        M=M, T=T, K=torch.randn(M, T, dU, 3, generator=g, dtype=torch.float64),
        k=torch.randn(M, T, dU, generator=g, dtype=torch.float64), variance=0.2,
    )
    result = pilqr_update(lqr, sampling, world.dynamics, world.cost, X, U, costs)
    assert float(result.residual_share.max()) < 1e-10
    assert torch.allclose(result.kl, torch.zeros_like(result.kl), atol=1e-10)
    assert torch.equal(result.gains.K, lqr.K)
    torch.testing.assert_close(result.gains.k, lqr.k)


def test_pilqr_moves_the_lqrs_controllers_by_the_cost_the_model_misses():
    """The samples cost ``5 u_0`` more than the model says: PILQR lowers the first action
    against the LQR's step, and leaves the second, which the model prices right, near it."""
    world, (M, N, T, dU) = LinearWorld(), (2, 400, 5, 2)
    sampling = gaussian(M=M, T=T, variance=0.5)
    X, U, costs = world.run(sampling, antithetic_noise(M, N, T, dU))
    missed = 5.0 * U[..., 0]
    result = pilqr_update(sampling, sampling, world.dynamics, world.cost, X, U, costs + missed)
    assert float(result.residual_share.min()) > 0
    step = result.gains.k - sampling.k
    assert bool((step[..., 0] < 0).all()), step
    assert float(step[..., 1].abs().mean()) < 0.2 * float(step[..., 0].abs().mean()), step


def test_a_residual_that_spreads_far_more_than_the_cost_keeps_its_weights_within_the_bound():
    """The model's errors dwarf the cost's spread: at the full cost's temperatures the weights
    would fall on one sample and the covariance collapse; the residual's own bound holds them."""
    world, (M, N, T, dU) = LinearWorld(), (2, 20, 5, 2)
    sampling = gaussian(M=M, T=T, variance=0.5)
    X, U, costs = world.run(sampling, antithetic_noise(M, N, T, dU))
    missed = 1e4 * U[..., 0]
    result = pilqr_update(sampling, sampling, world.dynamics, world.cost, X, U, costs + missed, kl=1.0)
    assert float(result.kl.max()) <= 1.0 + 1e-6
    assert bool((result.gains.cov.diagonal(dim1=-2, dim2=-1) > 1e-3).all())
