"""A model-free C-step: PI2 with a per-step KL bound (Theodorou et al. 2010; Chebotar et al. 2017).

Where the KL-constrained LQR plans on dynamics fitted to the samples, PI2 reweights the
samples themselves. For each condition and step ``t`` it scores every sample by its cost to
go ``S_n,t = sum_{t' >= t} c_n,t'``, weights it ``w_n,t ~ exp(-S_n,t / eta_t)`` with the
temperature ``eta_t`` at which the weights' KL divergence from uniform is ``kl`` (REPS's
bound: the new distribution stays near the one that drew the samples), and moves the
controller's feed-forward term to the weighted mean of the samples' ``u - K x``. The
feedback gains ``K`` stay those of the sampling distribution, and the covariance becomes the
old one times the weighted samples' spread relative to it, damped (the GPS code's
``TrajOptPI2``, whose defaults these are).

Nothing here is fitted across a contact that only some samples make: a sample that moved
the object is weighted by what it achieved, which is what a C-step on contact-rich tasks
needs (RESULTS, "the physics or the learner?").

Examples:
    >>> import torch
    >>> from modnet.gps.controller import LinearGaussianGains
    >>> from modnet.gps.pi2 import pi2_update
    >>> M, N, T = 1, 4, 3
    >>> sampling = LinearGaussianGains.from_covariance(
    ...     torch.zeros(M, T, 1, 2), torch.zeros(M, T, 1), torch.eye(1).expand(M, T, 1, 1))
    >>> U = torch.tensor([-1.0, 0.0, 1.0, 2.0]).reshape(1, N, 1, 1).expand(M, N, T, 1)
    >>> costs = (U[..., 0] - 1.0) ** 2  # the sample that asks for 1 is best
    >>> result = pi2_update(sampling, torch.zeros(M, N, T, 2), U, costs, kl=0.5)
    >>> bool((result.gains.k > 0.5).all()), bool(result.kl.sub(0.5).abs().max() < 1e-6)
    (True, True)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from modnet.gps.controller import LinearGaussianGains
from modnet.gps.linalg import symmetrize

__all__ = ["PI2Result", "pi2_update", "temperatures"]

#: the lowest temperature searched (the GPS code's ``min_temperature``) and the highest
MIN_TEMPERATURE = 1e-3
MAX_TEMPERATURE = 1e16


@dataclass
class PI2Result:
    """A PI2 step: the new ``gains``; per condition and step the temperature ``eta [M, T]`` and
    the weights' KL from uniform ``kl [M, T]``; ``expected_cost [M]``, the reweighted
    samples' cost over the whole horizon (their weights at the first step)."""

    gains: LinearGaussianGains
    eta: torch.Tensor
    kl: torch.Tensor
    expected_cost: torch.Tensor


def _weights(cost_to_go: torch.Tensor, eta: torch.Tensor) -> torch.Tensor:
    """Softmax over samples (dim -2 of ``[..., N, T]``) of ``-cost_to_go / eta``."""
    return torch.softmax(-cost_to_go / eta.unsqueeze(-2), dim=-2)


def _kl_from_uniform(weights: torch.Tensor) -> torch.Tensor:
    n = weights.shape[-2]
    return (weights * (weights.clamp_min(1e-300).log() + math.log(n))).sum(-2)


def temperatures(cost_to_go: torch.Tensor, kl: float, iterations: int = 80) -> torch.Tensor:
    """Per ``[..., T]``, the lowest temperature at which ``softmax(-S / eta)`` over the N
    samples of ``cost_to_go [..., N, T]`` is at most ``kl`` from uniform (the minimiser of
    REPS's dual), searched by bisection in ``log eta`` between ``MIN_TEMPERATURE`` and
    ``MAX_TEMPERATURE``. The KL falls as the temperature rises, from ``log N`` (all weight
    on the best sample) towards 0; where even ``MIN_TEMPERATURE`` keeps it below ``kl``,
    that is the temperature.

    Examples:
        >>> S = torch.tensor([[0.0], [1.0], [2.0]])  # 3 samples, 1 step
        >>> eta = temperatures(S, kl=0.1)
        >>> bool((_kl_from_uniform(_weights(S, eta)) - 0.1).abs().max() < 1e-6)
        True
    """
    S = cost_to_go - cost_to_go.amin(-2, keepdim=True)  # the same weights, no overflow
    low = torch.full(S.shape[:-2] + S.shape[-1:], math.log(MIN_TEMPERATURE), dtype=S.dtype)
    high = torch.full_like(low, math.log(MAX_TEMPERATURE))
    for _ in range(iterations):
        mid = 0.5 * (low + high)
        too_greedy = _kl_from_uniform(_weights(S, mid.exp())) > kl
        low = torch.where(too_greedy, mid, low)
        high = torch.where(too_greedy, high, mid)
    return high.exp()


def pi2_update(
    sampling: LinearGaussianGains,
    X: torch.Tensor,
    U: torch.Tensor,
    costs: torch.Tensor,
    *,
    kl: float = 1.0,
    covariance_damping: float = 2.0,
) -> PI2Result:
    """The PI2 step from samples ``X [M, N, T, dX]``, ``U [M, N, T, dU]`` drawn by the
    linear-Gaussian distribution ``sampling``, with per-step costs ``costs [M, N, T]``.

    ``covariance_damping`` (> 0) sets how fast the exploration shrinks: the new covariance
    is ``sampling.cov`` times ``(tr(cov_old^-1 cov_weighted) / dU) ** (1 / damping)``, so it
    stays positive definite and keeps the shape of the old one.
    """
    if not covariance_damping > 0:
        raise ValueError(f"covariance_damping must be positive, got {covariance_damping}")
    X, U, costs = X.to(torch.float64), U.to(torch.float64), costs.to(torch.float64)
    cost_to_go = costs.flip(-1).cumsum(-1).flip(-1)  # [M, N, T]
    eta = temperatures(cost_to_go, kl)
    S = cost_to_go - cost_to_go.amin(-2, keepdim=True)
    w = _weights(S, eta)  # [M, N, T]
    feed_forward = U - (sampling.K.unsqueeze(1) @ X.unsqueeze(-1)).squeeze(-1)  # [M, N, T, dU]
    k = (w.unsqueeze(-1) * feed_forward).sum(1)  # [M, T, dU]
    spread = feed_forward - k.unsqueeze(1)
    weighted_cov = (w[..., None, None] * spread.unsqueeze(-1) * spread.unsqueeze(-2)).sum(1)
    relative = torch.linalg.solve(sampling.cov, weighted_cov).diagonal(dim1=-2, dim2=-1)
    ratio = (relative.sum(-1) / U.shape[-1]).clamp_min(0)
    cov = symmetrize(ratio.pow(1.0 / covariance_damping)[..., None, None] * sampling.cov)
    gains = LinearGaussianGains.from_covariance(sampling.K, k, cov)
    expected = (w[..., 0] * cost_to_go[..., 0]).sum(-1)
    return PI2Result(gains=gains, eta=eta, kl=_kl_from_uniform(w), expected_cost=expected)
