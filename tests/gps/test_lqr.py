"""KL-constrained LQR: analytic Riccati gains, KL targets, PD repair, NaN reporting."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from modnet.gps.controller import LinearGaussianGains
from modnet.gps.cost import QuadraticCost
from modnet.gps.dynamics import LinearGaussianDynamics
from modnet.gps.errors import NumericalError
from modnet.gps.lqr import (
    LQRConfig,
    StateActionMarginals,
    adapt_step_mult,
    kl_divergence,
    laplace_cost,
    lqr_backward,
    lqr_forward,
    solve_kl_constrained_lqr,
)

f64 = torch.float64
M, T, dX, dU = 3, 15, 4, 2


def double_integrator() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two point masses: x = [p1, p2, v1, v2], u = forces, dt = 0.1, plus a constant drift."""
    dt = 0.1
    A = np.eye(4)
    A[0, 2] = A[1, 3] = dt
    B = np.zeros((4, 2))
    B[2, 0] = B[3, 1] = dt
    B[0, 0] = B[1, 1] = 0.5 * dt**2
    drift = np.array([0.0, 0.0, 0.01, -0.02])
    return A, B, drift


def make_problem(
    x0mu: torch.Tensor | None = None, noise: float = 0.0
) -> tuple[QuadraticCost, LinearGaussianDynamics, dict]:
    A, B, drift = double_integrator()
    Q = np.diag([1.0, 2.0, 0.1, 0.1])
    R = np.diag([0.01, 0.02])
    target = np.array([1.0, -0.5, 0.0, 0.0])
    C = np.zeros((dX + dU, dX + dU))
    C[:dX, :dX], C[dX:, dX:] = Q, R
    c = np.concatenate([-Q @ target, np.zeros(dU)])
    cc = 0.5 * target @ Q @ target
    F = torch.as_tensor(np.hstack([A, B]), dtype=f64)
    if x0mu is None:
        x0mu = torch.randn(M, dX, dtype=f64, generator=torch.Generator().manual_seed(1))
    dynamics = LinearGaussianDynamics(
        F=F.expand(M, T, dX, dX + dU).clone(),
        f=torch.as_tensor(drift, dtype=f64).expand(M, T, dX).clone(),
        D=noise * torch.eye(dX, dtype=f64).expand(M, T, dX, dX).clone(),
        x0mu=x0mu,
        x0sigma=1e-2 * torch.eye(dX, dtype=f64).expand(M, dX, dX).clone(),
    )
    cost = QuadraticCost(
        C=torch.as_tensor(C, dtype=f64).expand(M, T, dX + dU, dX + dU).clone(),
        c=torch.as_tensor(c, dtype=f64).expand(M, T, dX + dU).clone(),
        cc=torch.full((M, T), float(cc), dtype=f64),
    )
    return cost, dynamics, dict(A=A, B=B, drift=drift, Q=Q, R=R, target=target)


def broad_prev(variance: float = 1.0) -> LinearGaussianGains:
    return LinearGaussianGains.from_covariance(
        torch.zeros(M, T, dU, dX, dtype=f64),
        torch.zeros(M, T, dU, dtype=f64),
        variance * torch.eye(dU, dtype=f64).expand(M, T, dU, dU),
    )


def numpy_affine_lqr(A, B, drift, Q, R, target, horizon):
    """Textbook finite-horizon LQR for V_t(x) = 0.5 x'S x + s'x, cost 0.5(x-x*)'Q(x-x*) + 0.5u'Ru."""
    S, s = np.zeros((4, 4)), np.zeros(4)
    Ks, ks = [None] * horizon, [None] * horizon
    for t in reversed(range(horizon)):
        if t == horizon - 1:
            S_next, s_next = np.zeros((4, 4)), np.zeros(4)
        else:
            S_next, s_next = S, s
        H = R + B.T @ S_next @ B
        G = B.T @ S_next @ A
        g = B.T @ (S_next @ drift + s_next)
        K = -np.linalg.solve(H, G)
        k = -np.linalg.solve(H, g)
        S = Q + A.T @ S_next @ A + G.T @ K
        s = -Q @ target + A.T @ (S_next @ drift + s_next) + G.T @ k
        S = 0.5 * (S + S.T)
        Ks[t], ks[t] = K, k
    return np.stack(Ks), np.stack(ks)


def test_huge_kl_budget_gives_analytic_riccati_gains():
    cost, dynamics, sys = make_problem()
    result = solve_kl_constrained_lqr(cost, dynamics, broad_prev(), config=LQRConfig(kl_step=1e6))
    assert bool((result.eta < 1e-6).all()), result.eta
    assert bool(result.converged.all())
    K_ref, k_ref = numpy_affine_lqr(sys["A"], sys["B"], sys["drift"], sys["Q"], sys["R"], sys["target"], T)
    for m in range(M):
        np.testing.assert_allclose(result.gains.K[m].numpy(), K_ref, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(result.gains.k[m].numpy(), k_ref, rtol=1e-5, atol=1e-6)
    # Unconstrained backward pass (no previous controller) gives the same gains.
    plain = lqr_backward(cost, dynamics)
    np.testing.assert_allclose(plain.gains.K[0].numpy(), K_ref, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("kl_step", [0.05, 0.5])
def test_small_kl_budget_is_met_within_tolerance(kl_step):
    cost, dynamics, _ = make_problem(noise=1e-3)
    prev = broad_prev()
    step_mult = torch.tensor([1.0, 0.5, 2.0], dtype=f64)
    result = solve_kl_constrained_lqr(
        cost, dynamics, prev, step_mult=step_mult, config=LQRConfig(kl_step=kl_step)
    )
    target = kl_step * step_mult * T
    torch.testing.assert_close(result.kl_target, target)
    assert bool(((result.kl - target).abs() < 0.1 * target).all()), (result.kl, target)
    assert bool(result.converged.all()) and not bool(result.at_cap.any())
    # The KL reported is the KL of the returned controller.
    again = kl_divergence(result.gains, prev, lqr_forward(result.gains, dynamics))
    torch.testing.assert_close(again, result.kl)
    # A bigger budget buys a lower expected cost than the previous controller's.
    assert bool((result.expected_cost < laplace_cost(prev, dynamics, cost)).all())
    # Warm start from the found eta converges at once.
    warm = solve_kl_constrained_lqr(
        cost, dynamics, prev, step_mult=step_mult, eta=result.eta, config=LQRConfig(kl_step=kl_step)
    )
    assert warm.iterations == 1


@pytest.mark.parametrize("max_eta", [1e-3, 7.3e-3])
def test_a_kl_target_no_allowed_eta_meets_ends_at_the_cap(max_eta):
    """The search for eta stops once its bracket has collapsed against ``max_eta``, which it
    reaches from below in geometric steps: eta then ends within the collapse tolerance of
    the cap, not on it, and the result still says that it is at the cap."""
    cost, dynamics, _ = make_problem(noise=1e-3)
    config = LQRConfig(kl_step=1e-9, initial_eta=1e-5, max_eta=max_eta)
    result = solve_kl_constrained_lqr(cost, dynamics, broad_prev(), config=config)
    assert bool((result.kl > result.kl_target).all()) and not bool(result.converged.any())
    assert bool(result.at_cap.all()), (result.eta, max_eta)
    assert bool((result.eta > 0.99 * max_eta).all())
    roomy = solve_kl_constrained_lqr(cost, dynamics, broad_prev(), config=LQRConfig(kl_step=0.5))
    assert not bool(roomy.at_cap.any())


def test_kl_closed_form_matches_distribution_kl_and_monte_carlo():
    g = torch.Generator().manual_seed(3)

    def random_gains() -> LinearGaussianGains:
        A = torch.randn(1, 1, dU, dU, dtype=f64, generator=g)
        return LinearGaussianGains.from_covariance(
            torch.randn(1, 1, dU, dX, dtype=f64, generator=g),
            torch.randn(1, 1, dU, dtype=f64, generator=g),
            A @ A.transpose(-1, -2) + 0.5 * torch.eye(dU, dtype=f64),
        )

    new, prev = random_gains(), random_gains()
    mu_x = torch.randn(dX, dtype=f64, generator=g)
    L = 0.3 * torch.randn(dX, dX, dtype=f64, generator=g)
    sigma_x = L @ L.T
    sigma = torch.zeros(1, 1, dX + dU, dX + dU, dtype=f64)
    sigma[..., :dX, :dX] = sigma_x
    mu = torch.cat([mu_x, torch.zeros(dU, dtype=f64)]).reshape(1, 1, -1)
    kl = kl_divergence(new, prev, StateActionMarginals(mu, sigma), per_step=True)[0, 0]

    xs = torch.distributions.MultivariateNormal(mu_x, sigma_x).sample((20000,))

    def conditional(gains: LinearGaussianGains) -> torch.distributions.MultivariateNormal:
        mean = xs @ gains.K[0, 0].T + gains.k[0, 0]
        return torch.distributions.MultivariateNormal(mean, gains.cov[0, 0])

    mc = torch.distributions.kl_divergence(conditional(new), conditional(prev)).mean()
    assert abs(float(kl) - float(mc)) < 0.03 * float(mc)


def test_non_pd_quu_is_repaired_by_raising_eta():
    cost, dynamics, _ = make_problem()
    dynamics.F[..., dX:] = 0.0  # actions do not move the state: Q_uu = C_uu/eta + P
    cost.C[..., dX:, dX:] = -0.5 * torch.eye(dU, dtype=f64)  # negative control cost
    prev = broad_prev(variance=1.0)  # P = I, so Q_uu is PD iff eta > 0.5
    out = lqr_backward(cost, dynamics, prev, eta=1e-3)
    assert bool((out.eta > 0.5).all()) and bool((out.eta < 1.1).all()), out.eta
    assert bool((torch.linalg.eigvalsh(out.gains.precision) > 0).all())
    assert bool((torch.linalg.eigvalsh(out.gains.cov) > 0).all())
    # The dual search copes with the repair, too.
    result = solve_kl_constrained_lqr(cost, dynamics, prev, eta=1e-3)
    assert bool((result.eta > 0.5).all())
    # Without a previous controller nothing can repair it.
    with pytest.raises(NumericalError, match="not positive definite"):
        lqr_backward(cost, dynamics)


def test_unrepairable_quu_raises_numerical_error():
    cost, dynamics, _ = make_problem()
    dynamics.F[..., dX:] = 0.0
    cost.C[1, :, dX:, dX:] = -1e30 * torch.eye(dU, dtype=f64)  # beyond any eta <= 1e16
    with pytest.raises(NumericalError, match="very large eta") as info:
        lqr_backward(cost, dynamics, broad_prev(), eta=1.0, world="w", iteration=7)
    assert info.value.condition == 1 and info.value.iteration == 7


def test_planted_nan_names_world_condition_iteration():
    cost, dynamics, _ = make_problem()
    cost.c[2, 5, 0] = float("nan")
    with pytest.raises(NumericalError) as info:
        solve_kl_constrained_lqr(cost, dynamics, broad_prev(), world="3link-reach", iteration=4)
    message = str(info.value)
    assert "world=3link-reach" in message
    assert "condition=2" in message
    assert "iteration=4" in message


def test_step_mult_rule():
    config = LQRConfig()
    # Prediction came true: grow (capped at 5x); over-optimistic: shrink (floored at 0.1x).
    new = adapt_step_mult(
        torch.tensor([1.0, 1.0, 1.0, 8.0]),
        torch.tensor([1.0, 1.0, 1.0, 1.0]),
        torch.tensor([1.0, 0.5, -10.0, 1.0]),
        config,
    )
    torch.testing.assert_close(new, torch.tensor([5.0, 1.0, 0.1, 10.0], dtype=f64))
    assert float(adapt_step_mult(0.05, torch.tensor(1.0), torch.tensor(-10.0))) == 0.01


def test_omega_per_step_matches_scalar_and_enters_the_denominator():
    cost, dynamics, _ = make_problem(noise=1e-3)
    prev = broad_prev()
    eta = torch.full((M,), 0.7, dtype=f64)
    scalar = lqr_backward(cost, dynamics, prev, eta, omega=0.3)
    per_step = lqr_backward(cost, dynamics, prev, eta, omega=torch.full((M, T), 0.3, dtype=f64))
    torch.testing.assert_close(per_step.gains.K, scalar.gains.K)
    # (C + eta Lambda) / (eta + omega) at the last step: Q_uu is exactly that block.
    expected = (cost.C[:, -1, dX:, dX:] + 0.7 * prev.precision[:, -1]) / 1.0
    torch.testing.assert_close(scalar.gains.precision[:, -1], expected)
