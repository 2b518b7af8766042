"""PI2's C-step: the temperature meets its KL bound, the update follows the cheaper samples."""

import math

import pytest
import torch

from modnet.gps.controller import LinearGaussianGains
from modnet.gps.errors import NumericalError
from modnet.gps.pi2 import MIN_TEMPERATURE, pi2_update, temperatures


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


def test_covariance_damping_must_be_positive():
    gains = gaussian()
    X, U = torch.zeros(1, 3, 4, 3), torch.zeros(1, 3, 4, 2)
    with pytest.raises(ValueError, match="covariance_damping must be positive"):
        pi2_update(gains, X, U, torch.zeros(1, 3, 4), covariance_damping=0.0)
