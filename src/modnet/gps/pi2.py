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

PILQR (Chebotar et al. 2017; the GPS code's ``TrajOptPILQR``) combines the two:
:func:`pilqr_update` takes the LQR's new controllers and lets PI2 move their feed-forward by
what the fitted model does not explain, each sample's cost less the cost the linear dynamics
and quadratic cost predict for its noise (:func:`model_costs`). Where the model explains every
sample it leaves the LQR's step; where a contact makes the model wrong, the samples decide.

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

from modnet.gps.controller import LinearGaussianGains, time_filtered
from modnet.gps.cost import QuadraticCost
from modnet.gps.dynamics import LinearGaussianDynamics
from modnet.gps.linalg import symmetrize

__all__ = [
    "PI2Result",
    "model_costs",
    "pi2_update",
    "pilqr_update",
    "policy_log_ratio",
    "sampling_noise",
    "temperatures",
]

#: the lowest temperature searched (the GPS code's ``min_temperature``) and the highest
MIN_TEMPERATURE = 1e-3
MAX_TEMPERATURE = 1e16


@dataclass
class PI2Result:
    """A PI2 step: the new ``gains``; per condition and step the temperature ``eta [M, T]`` and
    the weights' KL from uniform ``kl [M, T]``; ``expected_cost [M]``, the reweighted
    samples' cost over the whole horizon (their weights at the first step). PILQR adds
    ``residual_share [M]``: the share of the samples' cost the fitted model does not explain
    (mean over samples of ``sum_t |residual|``, over that of ``sum_t |cost|``)."""

    gains: LinearGaussianGains
    eta: torch.Tensor
    kl: torch.Tensor
    expected_cost: torch.Tensor
    residual_share: torch.Tensor | None = None


def _cost_to_go(costs: torch.Tensor) -> torch.Tensor:
    """``sum_{t' >= t} c_t'`` along the last dim."""
    return costs.flip(-1).cumsum(-1).flip(-1)


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

    A ``kl`` of ``log N`` or more no temperature meets: every weight would fall on one
    sample, and the covariance fitted to the weighted spread would collapse. It is refused
    (``GPSConfig`` refuses it before any work, in the option's own terms).

    Examples:
        >>> S = torch.tensor([[0.0], [1.0], [2.0]])  # 3 samples, 1 step
        >>> eta = temperatures(S, kl=0.1)
        >>> bool((_kl_from_uniform(_weights(S, eta)) - 0.1).abs().max() < 1e-6)
        True
        >>> temperatures(S, kl=1.2)  # log 3 = 1.0986
        Traceback (most recent call last):
        ...
        ValueError: a KL of 1.2 from uniform is out of reach of the weights of 3 samples ...
    """
    samples = cost_to_go.shape[-2]
    if not kl >= 0:
        raise ValueError(f"kl must be non-negative (0: uniform weights), got {kl}")
    if not kl < math.log(samples):
        raise ValueError(
            f"a KL of {kl:.3g} from uniform is out of reach of the weights of {samples} samples "
            f"(at most log {samples} = {math.log(samples):.3g}): ask for less, or sample more"
        )
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
    eta: torch.Tensor | None = None,
    step_smoothing: float = 0.0,
) -> PI2Result:
    """The PI2 step from samples ``X [M, N, T, dX]``, ``U [M, N, T, dU]`` drawn by the
    linear-Gaussian distribution ``sampling``, with per-step costs ``costs [M, N, T]``.

    ``covariance_damping`` (> 0) sets how fast the exploration shrinks: the new covariance
    is ``sampling.cov`` times ``(tr(cov_old^-1 cov_weighted) / dU) ** (1 / damping)``, so it
    stays positive definite and keeps the shape of the old one. ``eta [M, T]``, when given,
    fixes the temperatures instead of meeting ``kl`` (PILQR's second pass).

    ``step_smoothing`` (>= 0, in time steps) filters the step of the feed-forward, ``k_new -
    sampling.k``, along time with a Gaussian of that standard deviation
    (:func:`~modnet.gps.controller.time_filtered`; truncated at 4 standard deviations, so
    widths below 1/8 of a step change nothing). Each step's weighted mean of a few samples'
    noise moves ``k`` largely by chance, and the networks we fitted to such controllers did not
    follow those changes from one step to the next (RESULTS, "Can a network do what PI2's
    controllers do?"); filtered, the step keeps what neighbouring steps agree on. The
    covariance is PI2's own, the spread around the unfiltered mean. 0 leaves the step as it
    is (the GPS code's).

    Examples:
        >>> M, N, T = 1, 2, 40
        >>> sampling = LinearGaussianGains.from_covariance(
        ...     torch.zeros(M, T, 1, 1), torch.zeros(M, T, 1), torch.eye(1).expand(M, T, 1, 1))
        >>> sign = torch.tensor([1.0, -1.0]).repeat(T // 2)  # the better sample alternates
        >>> U = torch.stack([sign, -sign]).reshape(M, N, T, 1)
        >>> args = (sampling, torch.zeros(M, N, T, 1), U, -(U[..., 0] * sign))
        >>> raw, smoothed = pi2_update(*args, kl=0.3), pi2_update(*args, kl=0.3, step_smoothing=2.0)
        >>> round(float(raw.gains.k.abs().mean()), 2), round(float(smoothed.gains.k.abs().mean()), 2)
        (0.73, 0.02)
        >>> bool(torch.equal(raw.gains.cov, smoothed.gains.cov))
        True
        >>> args = (sampling, torch.zeros(M, N, T, 1), U * sign.reshape(1, 1, T, 1), -(U[..., 0] * sign))
        >>> kept = pi2_update(*args, kl=0.3, step_smoothing=2.0)  # the same sample wins at every step
        >>> bool(kept.gains.k.sub(pi2_update(*args, kl=0.3).gains.k).abs().max() < 1e-12)
        True
    """
    if not covariance_damping > 0:
        raise ValueError(f"covariance_damping must be positive, got {covariance_damping}")
    if not step_smoothing >= 0:
        raise ValueError(f"step_smoothing must be non-negative (0: off), got {step_smoothing}")
    X, U, costs = X.to(torch.float64), U.to(torch.float64), costs.to(torch.float64)
    cost_to_go = _cost_to_go(costs)  # [M, N, T]
    if eta is None:
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
    if step_smoothing > 0:
        old = sampling.k.to(torch.float64)
        k = old + time_filtered(k - old, step_smoothing)
    gains = LinearGaussianGains.from_covariance(sampling.K, k, cov)
    expected = (w[..., 0] * cost_to_go[..., 0]).sum(-1)
    return PI2Result(gains=gains, eta=eta, kl=_kl_from_uniform(w), expected_cost=expected)


def sampling_noise(sampling: LinearGaussianGains, X: torch.Tensor, U: torch.Tensor) -> torch.Tensor:
    """The standard normal draws ``[M, N, T, dU]`` behind actions ``U`` taken in states ``X``
    by the controllers ``sampling``: ``chol^-1 (u - K x - k)``."""
    deviation = U.to(torch.float64) - sampling.mean_actions(X)
    chol = sampling.chol.unsqueeze(1).expand(*deviation.shape[:3], -1, -1)
    return torch.linalg.solve_triangular(chol, deviation.unsqueeze(-1), upper=False).squeeze(-1)


def policy_log_ratio(
    sampling: LinearGaussianGains,
    X: torch.Tensor,
    U: torch.Tensor,
    policy: torch.Tensor,
    *,
    limit: float | None = None,
) -> torch.Tensor:
    """Each sample's ``log q(u|x) - log p(u|x)`` per step, ``[M, N, T]``, for two Gaussians of
    unit variance (torques in N m): ``q`` on the mean actions of the controllers ``sampling``
    that drew the actions ``U`` in the states ``X``, ``p`` on the policy's mean actions there,
    ``policy [M, N, T, dU]``. With ``limit``, the actions and both means are first clipped to
    ``[-limit, limit]``, the torques the arm applies: a gap between two torques beyond the limit
    is no gap in what the arm does. Its mean over the samples estimates ``KL(q || p)``, half the
    squared gap between the two means; one sample's value is that plus the gap's product with
    the sample's own noise, so across the samples of a step it ranks them by how far their
    noise took them towards the policy or away (the noise's size alone cancels).

    Added to PI2's cost with a weight (``GPSConfig.pi2_policy_weight``), it is MDGPS's trust
    region around the policy in a C-step that has no model to put it in: the reweighting
    prefers the samples that stayed near what the network does. In fixed units its spread over
    the samples, like the task cost's, shrinks with the controllers' exploration; in units of
    the controllers' spread (or the policy's, fitted to theirs) it grew a thousandfold as PI2
    narrowed them, and swamped the task cost (RESULTS, "PI2 held near the network").

    Examples:
        >>> import torch
        >>> sampling = LinearGaussianGains.from_covariance(
        ...     torch.zeros(1, 1, 1, 1), torch.zeros(1, 1, 1), torch.eye(1).expand(1, 1, 1, 1))
        >>> U = torch.tensor([-2.0, 0.0, 2.0]).reshape(1, 3, 1, 1)  # the controllers ask for 0
        >>> X, policy = torch.zeros(1, 3, 1, 1), torch.ones(1, 3, 1, 1)
        >>> policy_log_ratio(sampling, X, U, policy)[0, :, 0].tolist()
        [2.5, 0.5, -1.5]
        >>> policy_log_ratio(sampling, X, U, 3.0 * policy, limit=1.0)[0, :, 0].tolist()  # 3 acts as 1
        [1.5, 0.5, -0.5]
    """
    U, controllers, policy = U.to(torch.float64), sampling.mean_actions(X), policy.to(torch.float64)
    if limit is not None:
        U, controllers, policy = (a.clamp(-limit, limit) for a in (U, controllers, policy))
    return 0.5 * ((U - policy).pow(2) - (U - controllers).pow(2)).sum(-1)


def model_costs(
    gains: LinearGaussianGains,
    dynamics: LinearGaussianDynamics,
    cost: QuadraticCost,
    noise: torch.Tensor,
) -> torch.Tensor:
    """What the model predicts each sample cost, ``[M, N, T]``: the controllers ``gains``
    run through the linear ``dynamics`` from the initial mean with each sample's standard
    noise ``noise [M, N, T, dU]`` (``u = K x + k + chol noise``), scored by the quadratic
    ``cost`` (the GPS code's ``approximated_cost``).

    Examples:
        >>> import torch
        >>> from modnet.gps.dynamics import LinearGaussianDynamics
        >>> M, N, T = 1, 2, 3  # x' = x + u from x0 = 1, cost u^2 / 2: the model's cost is exact
        >>> F = torch.ones(M, T, 1, 2).double()
        >>> dynamics = LinearGaussianDynamics(F, torch.zeros(M, T, 1).double(),
        ...     torch.zeros(M, T, 1, 1).double(), torch.ones(M, 1).double(), torch.zeros(M, 1, 1).double())
        >>> cost = QuadraticCost(torch.tensor([[0.0, 0.0], [0.0, 1.0]]).double().expand(M, T, 2, 2),
        ...     torch.zeros(M, T, 2).double(), torch.zeros(M, T).double())
        >>> gains = LinearGaussianGains.from_covariance(
        ...     -0.5 * torch.ones(M, T, 1, 1), torch.zeros(M, T, 1), torch.eye(1).expand(M, T, 1, 1))
        >>> model_costs(gains, dynamics, cost, torch.zeros(M, N, T, 1))[0, 0].tolist()  # u = -x/2
        [0.125, 0.03125, 0.0078125]
    """
    noise = noise.to(torch.float64)
    M, N, T, _ = noise.shape
    x = dynamics.x0mu.unsqueeze(1).expand(M, N, -1)
    taus = []
    for t in range(T):
        u = (
            (gains.K[:, t, None] @ x.unsqueeze(-1)).squeeze(-1)
            + gains.k[:, t, None]
            + (gains.chol[:, t, None] @ noise[:, :, t].unsqueeze(-1)).squeeze(-1)
        )
        tau = torch.cat([x, u], -1)
        taus.append(tau)
        x = (dynamics.F[:, t, None] @ tau.unsqueeze(-1)).squeeze(-1) + dynamics.f[:, t, None]
    return cost(torch.stack(taus, 2).transpose(0, 1)).transpose(0, 1)


def pilqr_update(
    lqr: LinearGaussianGains,
    sampling: LinearGaussianGains,
    dynamics: LinearGaussianDynamics,
    cost: QuadraticCost,
    X: torch.Tensor,
    U: torch.Tensor,
    costs: torch.Tensor,
    *,
    kl: float = 1.0,
    covariance_damping: float = 2.0,
) -> PI2Result:
    """PILQR's step: PI2 on the residual cost, around the LQR's new controllers ``lqr``.

    The samples ``X``, ``U`` (costs ``costs [M, N, T]``) were drawn by ``sampling``; the
    ``dynamics`` and ``cost`` are the model the LQR planned on. Each sample's noise is
    replayed through ``lqr`` (``k' + chol' noise``, the GPS code's ``use_lqr_actions``) and
    weighted by its residual cost to go, the sampled cost less :func:`model_costs` of the
    sampling controllers, at the temperatures that put the weights of the full cost ``kl``
    from uniform (the GPS code's), raised where the residual's weights would be farther than
    ``kl`` from uniform: where the model misses more than the cost spreads, the weights would
    otherwise fall on one sample and the covariance collapse (on push, at iteration 16; the
    GPS code raises the temperature only until the covariance factorises). ``K`` stays the
    LQR's; the covariance is the LQR's, damped by the spread.
    """
    noise = sampling_noise(sampling, X, U)
    costs = costs.to(torch.float64)
    residual = costs - model_costs(sampling, dynamics, cost, noise)
    eta = torch.maximum(temperatures(_cost_to_go(costs), kl), temperatures(_cost_to_go(residual), kl))
    replayed = lqr.mean_actions(X) + (lqr.chol.unsqueeze(1) @ noise.unsqueeze(-1)).squeeze(-1)
    result = pi2_update(lqr, X, replayed, residual, covariance_damping=covariance_damping, eta=eta)
    result.residual_share = residual.abs().sum(-1).mean(-1) / costs.abs().sum(-1).mean(-1)
    return result
