"""Quadratic expansion of a differentiable cost around sampled trajectories.

A world's cost ``cost_fn(x, u) -> scalar`` (torch, differentiable; ``x [dX]``, ``u [dU]``)
is expanded at every visited ``tau = [x; u]`` with ``torch.func`` (value, gradient and
Hessian in one vmapped call), weighted per time step, re-centred at the origin into the
absolute form ``0.5 tau' C tau + c' tau + cc`` and averaged over the N samples.

Examples:
    >>> import torch
    >>> from modnet.gps.cost import expand_cost, time_weights
    >>> def cost_fn(x, u):
    ...     return 0.5 * (x**2).sum(-1) + 0.05 * (u**2).sum(-1)
    >>> X, U = torch.randn(2, 5, 10, 3), torch.randn(2, 5, 10, 1)  # M, N, T
    >>> q = expand_cost(cost_fn, X, U, weights=time_weights(10, "linear", final_multiplier=10.0))
    >>> q.C.shape, q.c.shape, q.cc.shape
    (torch.Size([2, 10, 4, 4]), torch.Size([2, 10, 4]), torch.Size([2, 10]))
    >>> torch.allclose(q.C[0, -1], torch.diag(torch.tensor([1.0, 1, 1, 0.1], dtype=q.C.dtype)) * 10)
    True
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, get_args

import torch
from torch.func import grad_and_value, jacfwd, vmap

from modnet.gps.errors import check_finite

__all__ = [
    "CostDerivatives",
    "QuadraticCost",
    "Ramp",
    "cost_derivatives",
    "expand_cost",
    "recentre",
    "state_spread",
    "time_weights",
    "tracking_cost",
]

Ramp = Literal["constant", "linear", "quadratic", "final_only"]
CostFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def time_weights(
    horizon: int,
    ramp: Ramp = "constant",
    final_multiplier: float = 1.0,
    *,
    dtype: torch.dtype = torch.float64,
) -> torch.Tensor:
    """Per-step cost weights ``[T]``: a ramp in ``(t+1)/T``, then the last step times ``final``.

    ``constant``: 1; ``linear``: (t+1)/T; ``quadratic``: ((t+1)/T)^2; ``final_only``: 1 at T-1.

    Examples:
        >>> time_weights(4, "linear", final_multiplier=10.0)
        tensor([ 0.2500,  0.5000,  0.7500, 10.0000], dtype=torch.float64)
    """
    frac = torch.arange(1, horizon + 1, dtype=dtype) / horizon
    if ramp == "constant":
        weights = torch.ones(horizon, dtype=dtype)
    elif ramp == "linear":
        weights = frac
    elif ramp == "quadratic":
        weights = frac**2
    elif ramp == "final_only":
        weights = torch.zeros(horizon, dtype=dtype)
        weights[-1] = 1.0
    else:
        raise ValueError(f"unknown ramp {ramp!r}; expected {', '.join(get_args(Ramp))}")
    weights[-1] = weights[-1] * final_multiplier
    return weights


@dataclass
class CostDerivatives:
    """Value and derivatives of the cost at each visited (x, u), shapes ``[*B, ...]``."""

    l: torch.Tensor  # [*B]
    lx: torch.Tensor  # [*B, dX]
    lu: torch.Tensor  # [*B, dU]
    lxx: torch.Tensor  # [*B, dX, dX]
    luu: torch.Tensor  # [*B, dU, dU]
    lux: torch.Tensor  # [*B, dU, dX]


@dataclass
class QuadraticCost:
    """Absolute quadratic cost per step: ``0.5 tau' C tau + c' tau + cc`` with ``tau = [x; u]``.

    Shapes: ``C [M, T, dX+dU, dX+dU]``, ``c [M, T, dX+dU]``, ``cc [M, T]``.
    """

    C: torch.Tensor
    c: torch.Tensor
    cc: torch.Tensor

    def __call__(self, tau: torch.Tensor) -> torch.Tensor:
        """Cost of state-actions ``tau [M, T, dX+dU]`` (or with extra leading sample dims)."""
        return 0.5 * torch.einsum("...i,...ij,...j->...", tau, self.C, tau) + (
            (self.c * tau).sum(-1) + self.cc
        )


def cost_derivatives(
    cost_fn: CostFn,
    X: torch.Tensor,
    U: torch.Tensor,
    weights: torch.Tensor | None = None,
) -> CostDerivatives:
    """Value, gradient and Hessian of ``cost_fn`` at every ``(X, U)`` sample, in float64.

    ``X [*B, T, dX]``, ``U [*B, T, dU]``; ``weights [T]`` scales every step's expansion.
    ``cost_fn`` is called on single samples (``x [dX]``, ``u [dU]``) under ``vmap``.
    """
    X = X.to(torch.float64)
    U = U.to(torch.float64)
    dX = X.shape[-1]
    batch = X.shape[:-1]
    tau = torch.cat([X, U], dim=-1).reshape(-1, dX + U.shape[-1])

    def scalar_cost(t: torch.Tensor) -> torch.Tensor:
        return cost_fn(t[:dX], t[dX:]).reshape(())

    def grad_with_aux(t: torch.Tensor) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        g, v = grad_and_value(scalar_cost)(t)
        return g, (g, v)

    hess, (grad, value) = vmap(jacfwd(grad_with_aux, has_aux=True))(tau)
    value = value.reshape(batch)
    grad = grad.reshape(*batch, -1)
    hess = 0.5 * (hess + hess.transpose(-1, -2))
    hess = hess.reshape(*batch, *hess.shape[-2:])
    if weights is not None:
        w = weights.to(torch.float64)
        value = value * w
        grad = grad * w[:, None]
        hess = hess * w[:, None, None]
    check_finite("cost expansion", hess)
    return CostDerivatives(
        l=value,
        lx=grad[..., :dX],
        lu=grad[..., dX:],
        lxx=hess[..., :dX, :dX],
        luu=hess[..., dX:, dX:],
        lux=hess[..., dX:, :dX],
    )


def recentre(derivs: CostDerivatives, X: torch.Tensor, U: torch.Tensor) -> QuadraticCost:
    """Turn expansions around ``tau0 = [X; U]`` into absolute quadratics (same batch shape).

    ``l(tau) ~ l0 + g'(tau-tau0) + 0.5 (tau-tau0)'H(tau-tau0)`` gives ``C = H``,
    ``c = g - H tau0`` and ``cc = l0 - g'tau0 + 0.5 tau0'H tau0``.
    """
    tau0 = torch.cat([X, U], dim=-1).to(torch.float64)
    grad = torch.cat([derivs.lx, derivs.lu], dim=-1)
    hess = torch.cat(
        [
            torch.cat([derivs.lxx, derivs.lux.transpose(-1, -2)], dim=-1),
            torch.cat([derivs.lux, derivs.luu], dim=-1),
        ],
        dim=-2,
    )
    h_tau0 = (hess @ tau0.unsqueeze(-1)).squeeze(-1)
    c = grad - h_tau0
    cc = derivs.l - (grad * tau0).sum(-1) + 0.5 * (h_tau0 * tau0).sum(-1)
    return QuadraticCost(C=hess, c=c, cc=cc)


def expand_cost(
    cost_fn: CostFn,
    X: torch.Tensor,
    U: torch.Tensor,
    weights: torch.Tensor | None = None,
) -> QuadraticCost:
    """Quadratic cost per condition and step, averaged over samples.

    ``X [M, N, T, dX]``, ``U [M, N, T, dU]`` -> ``QuadraticCost`` with ``C [M, T, dXU, dXU]``.
    """
    per_sample = recentre(cost_derivatives(cost_fn, X, U, weights), X, U)
    return QuadraticCost(
        C=per_sample.C.mean(dim=1), c=per_sample.c.mean(dim=1), cc=per_sample.cc.mean(dim=1)
    )


def state_spread(X: torch.Tensor) -> torch.Tensor:
    """Each state entry's standard deviation over samples ``X [..., dX]``, floored at 1e-3.

    Examples:
        >>> state_spread(torch.tensor([[0.0, 1.0], [2.0, 1.0]])).tolist()  # the second never moves
        [1.4142135623730951, 0.001]
    """
    return X.reshape(-1, X.shape[-1]).to(torch.float64).std(0).clamp_min(1e-3)


def tracking_cost(X: torch.Tensor, action_dim: int, action_variance: float, weight: float) -> QuadraticCost:
    """The curvature ``[M, T]`` of a cost for tracking a path: each state entry's deviation over
    its spread over the samples ``X [M, N, T, dX]`` (:func:`state_spread`), squared, plus
    ``weight`` times the ``action_dim`` torques' squares over ``action_variance`` (torques in
    units of the controllers' own spread, as the KL-constrained LQR weighs them). An LQR's
    feedback gains depend on the cost's curvature alone, so its linear terms are zero; a
    smaller ``weight`` gives stiffer gains.

    Examples:
        >>> cost = tracking_cost(torch.randn(2, 3, 4, 5), action_dim=2, action_variance=0.5, weight=0.1)
        >>> cost.C.shape, cost.C[0, 0, -1, -1].item()  # each action entry: 0.1 / 0.5
        (torch.Size([2, 4, 7, 7]), 0.2)
    """
    M, _, T, dX = X.shape
    torques = torch.full((action_dim,), weight / action_variance, dtype=torch.float64)
    C = torch.diag(torch.cat([state_spread(X).pow(-2), torques])).expand(M, T, -1, -1).clone()
    zero = torch.zeros(M, T, dX + action_dim + 1, dtype=torch.float64)
    return QuadraticCost(C, zero[..., 1:], zero[..., 0])
