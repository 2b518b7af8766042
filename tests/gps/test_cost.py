"""Quadratic cost expansion by autograd: exact on quadratics, finite differences otherwise."""

from __future__ import annotations

import pytest
import torch

from modnet.gps.cost import QuadraticCost, cost_derivatives, expand_cost, recentre, time_weights

f64 = torch.float64
M, N, T, dX, dU = 2, 3, 4, 5, 2


def samples(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return (
        torch.randn(M, N, T, dX, dtype=f64, generator=g),
        torch.randn(M, N, T, dU, dtype=f64, generator=g),
    )


def test_known_quadratic_is_recovered_exactly():
    g = torch.Generator().manual_seed(1)
    L = torch.randn(dX, dX, dtype=f64, generator=g)
    Q = L @ L.T
    R = torch.diag(torch.tensor([0.3, 0.7], dtype=f64))
    cross = torch.randn(dX, dU, dtype=f64, generator=g)
    target = torch.randn(dX, dtype=f64, generator=g)

    def cost_fn(x, u):
        d = x - target
        return 0.5 * d @ Q @ d + 0.5 * u @ R @ u + x @ cross @ u

    X, U = samples()
    q = expand_cost(cost_fn, X.float(), U.float())  # float32 input is accepted
    C = torch.cat([torch.cat([Q, cross], 1), torch.cat([cross.T, R], 1)], 0)
    c = torch.cat([-Q @ target, torch.zeros(dU, dtype=f64)])
    assert q.C.dtype == f64 and q.C.shape == (M, T, dX + dU, dX + dU)
    torch.testing.assert_close(q.C, C.expand(M, T, -1, -1))
    torch.testing.assert_close(q.c, c.expand(M, T, -1))
    torch.testing.assert_close(q.cc, (0.5 * target @ Q @ target).expand(M, T))
    # The absolute quadratic reproduces the cost anywhere.
    tau = torch.randn(M, T, dX + dU, dtype=f64, generator=g)
    direct = torch.stack([torch.stack([cost_fn(tau[m, t, :dX], tau[m, t, dX:])
                                       for t in range(T)]) for m in range(M)])
    torch.testing.assert_close(q(tau), direct)


def nonlinear_cost(x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Two-link end-effector distance, l2 + log form, plus action cost."""
    ee = torch.stack(
        [torch.cos(x[0]) + 0.8 * torch.cos(x[0] + x[1]), torch.sin(x[0]) + 0.8 * torch.sin(x[0] + x[1])]
    )
    d = ee - torch.tensor([0.3, 1.1], dtype=x.dtype)
    dist = (d * torch.tensor([1.0, 2.0], dtype=x.dtype)).pow(2).sum()
    return 0.5 * dist + 0.5 * 0.1 * torch.log(1e-2 + dist) + 0.05 * (u**2).sum() + 0.1 * x[2:].pow(4).sum()


def finite_differences(fn, tau: torch.Tensor, h: float = 1e-4) -> tuple[torch.Tensor, torch.Tensor]:
    D = tau.numel()
    eye = torch.eye(D, dtype=f64) * h
    grad = torch.stack([(fn(tau + e) - fn(tau - e)) / (2 * h) for e in eye])
    hess = torch.stack(
        [
            torch.stack(
                [(fn(tau + a + b) - fn(tau + a - b) - fn(tau - a + b) + fn(tau - a - b)) / (4 * h * h)
                 for b in eye]
            )
            for a in eye
        ]
    )
    return grad, hess


def test_nonlinear_cost_matches_finite_differences():
    X, U = samples(2)
    derivs = cost_derivatives(nonlinear_cost, X, U)
    fn = lambda tau: nonlinear_cost(tau[:dX], tau[dX:])
    for m, n, t in [(0, 0, 0), (1, 2, 3), (0, 1, 2)]:
        tau = torch.cat([X[m, n, t], U[m, n, t]])
        grad, hess = finite_differences(fn, tau)
        torch.testing.assert_close(derivs.l[m, n, t], fn(tau))
        torch.testing.assert_close(torch.cat([derivs.lx[m, n, t], derivs.lu[m, n, t]]), grad,
                                   rtol=1e-6, atol=1e-7)
        torch.testing.assert_close(derivs.lxx[m, n, t], hess[:dX, :dX], rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(derivs.luu[m, n, t], hess[dX:, dX:], rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(derivs.lux[m, n, t], hess[dX:, :dX], rtol=1e-5, atol=1e-5)


def test_recentred_quadratic_is_the_local_taylor_expansion():
    X, U = samples(3)
    derivs = cost_derivatives(nonlinear_cost, X, U)
    per_sample = recentre(derivs, X, U)
    tau0 = torch.cat([X, U], -1)
    torch.testing.assert_close(per_sample(tau0), derivs.l)  # value at the expansion point
    grad = (per_sample.C @ tau0.unsqueeze(-1)).squeeze(-1) + per_sample.c
    torch.testing.assert_close(grad, torch.cat([derivs.lx, derivs.lu], -1))
    # expand_cost is the average over samples of these per-sample quadratics.
    q = expand_cost(nonlinear_cost, X, U)
    torch.testing.assert_close(q.C, per_sample.C.mean(1))
    torch.testing.assert_close(q.c, per_sample.c.mean(1))
    torch.testing.assert_close(q.cc, per_sample.cc.mean(1))
    assert isinstance(q, QuadraticCost)


@pytest.mark.parametrize(
    ("ramp", "expected"),
    [
        ("constant", [1.0, 1.0, 1.0, 10.0]),
        ("linear", [0.25, 0.5, 0.75, 10.0]),
        ("quadratic", [0.0625, 0.25, 0.5625, 10.0]),
        ("final_only", [0.0, 0.0, 0.0, 10.0]),
    ],
)
def test_time_weights_scale_each_step(ramp, expected):
    w = time_weights(T, ramp, final_multiplier=10.0)
    torch.testing.assert_close(w, torch.tensor(expected, dtype=f64))
    X, U = samples(4)
    plain = expand_cost(nonlinear_cost, X, U)
    weighted = expand_cost(nonlinear_cost, X, U, weights=w)
    torch.testing.assert_close(weighted.C, plain.C * w[:, None, None])
    torch.testing.assert_close(weighted.c, plain.c * w[:, None])
    torch.testing.assert_close(weighted.cc, plain.cc * w)


def test_unknown_ramp_is_rejected():
    with pytest.raises(ValueError, match="unknown ramp"):
        time_weights(3, "cubic")  # type: ignore[arg-type]
