"""Dynamics fit, GMM prior, initial state and policy linearisation."""

from __future__ import annotations

import pytest
import torch

from modnet.gps.dynamics import (
    GMM,
    DynamicsPriorConfig,
    DynamicsPriorGMM,
    LinearGaussianDynamics,
    PolicyPriorGMM,
    conditional_gaussian_fit,
    fit_dynamics,
    fit_policy_linearization,
    policy_linearization_from_jacobian,
)
from modnet.gps.errors import NumericalError

f64 = torch.float64
dX, dU, T = 6, 2, 12


def true_system() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    A = torch.eye(dX, dtype=f64) + 0.1 * torch.randn(dX, dX, dtype=f64, generator=g)
    B = 0.5 * torch.randn(dX, dU, dtype=f64, generator=g)
    drift = 0.1 * torch.randn(dX, dtype=f64, generator=g)
    return A, B, drift


def rollouts(
    M: int, N: int, seed: int, noise: float = 0.01
) -> tuple[torch.Tensor, torch.Tensor]:
    """Noisy linear system under random-feedback exploration: X [M, N, T, dX], U [M, N, T, dU]."""
    A, B, drift = true_system()
    g = torch.Generator().manual_seed(seed)
    X = torch.zeros(M, N, T, dX, dtype=f64)
    U = torch.randn(M, N, T, dU, dtype=f64, generator=g)
    X[:, :, 0] = torch.randn(M, N, dX, dtype=f64, generator=g)
    for t in range(T - 1):
        X[:, :, t + 1] = (
            X[:, :, t] @ A.T + U[:, :, t] @ B.T + drift
            + noise * torch.randn(M, N, dX, dtype=f64, generator=g)
        )
    return X, U


def error_to_truth(F: torch.Tensor) -> torch.Tensor:
    """Frobenius error of [A B] per condition and step (t < T-1) -> mean per condition."""
    A, B, _ = true_system()
    truth = torch.cat([A, B], dim=-1)
    return (F[:, :-1] - truth).flatten(-2).norm(dim=-1).mean(dim=-1)


def test_fit_recovers_linear_system_with_many_samples():
    X, U = rollouts(M=2, N=300, seed=1)
    dyn = fit_dynamics(X.float(), U.float())  # float32 input is accepted
    A, B, drift = true_system()
    assert dyn.F.dtype == f64
    torch.testing.assert_close(dyn.F[:, :-1, :, :dX], A.expand(2, T - 1, dX, dX), atol=0.03, rtol=0)
    torch.testing.assert_close(dyn.F[:, :-1, :, dX:], B.expand(2, T - 1, dX, dU), atol=0.03, rtol=0)
    torch.testing.assert_close(dyn.f[:, :-1], drift.expand(2, T - 1, dX), atol=0.03, rtol=0)
    # Residual covariance is the process noise (0.01^2).
    diag = torch.diagonal(dyn.D[:, :-1], dim1=-2, dim2=-1)
    assert bool(((diag > 0.5e-4) & (diag < 2e-4)).all())
    assert bool((dyn.F[:, -1] == 0).all())
    # Initial state: mean and diagonal variance of x_0.
    torch.testing.assert_close(dyn.x0mu, X[:, :, 0].mean(1))
    torch.testing.assert_close(
        torch.diagonal(dyn.x0sigma, dim1=-2, dim2=-1), X[:, :, 0].var(1, unbiased=False)
    )


def test_gmm_prior_beats_plain_fit_with_few_samples():
    prior = DynamicsPriorGMM(generator=torch.Generator().manual_seed(0))
    X_big, U_big = rollouts(M=1, N=20, seed=2)
    prior.update(X_big, U_big)
    assert prior.gmm.num_clusters == (20 * (T - 1)) // 20  # floor(N (T-1) / min samples)
    X, U = rollouts(M=3, N=5, seed=3)  # 5 samples < dX + dU: the plain fit is underdetermined
    plain = error_to_truth(fit_dynamics(X, U).F)
    with_prior = error_to_truth(fit_dynamics(X, U, prior).F)
    assert bool((with_prior < 0.5 * plain).all()), (with_prior, plain)
    assert bool((with_prior < 0.1).all()), with_prior
    # One prior per condition gives the same kind of fit and informs x0.
    per_condition = fit_dynamics(X, U, [prior, prior, prior])
    torch.testing.assert_close(error_to_truth(per_condition.F), with_prior)


def test_prior_buffer_and_cluster_rule():
    config = DynamicsPriorConfig(max_trajectories=4, max_clusters=3, min_samples_per_cluster=5)
    prior = DynamicsPriorGMM(config, generator=torch.Generator().manual_seed(0))
    for seed in range(3):
        X, U = rollouts(M=1, N=3, seed=seed)
        prior.update(X, U)
    assert prior.X.shape == (4, T, dX)
    assert prior.gmm.num_clusters == 3
    assert prior.num_clusters(9) == 2  # never fewer than two clusters
    mu0, Phi, m, n0 = prior.eval(torch.randn(7, 4, 2 * dX + dU, dtype=f64))
    assert mu0.shape == (7, 2 * dX + dU) and Phi.shape == (7, 2 * dX + dU, 2 * dX + dU)
    P = 4 * (T - 1)
    assert m == 1.0 and n0 == pytest.approx((P - 2 - (2 * dX + dU)) / P)
    assert bool((torch.linalg.eigvalsh(Phi) > 0).all())
    with pytest.raises(RuntimeError, match="update"):
        DynamicsPriorGMM().eval(torch.zeros(2, 2 * dX + dU))


def test_gmm_em_separates_clusters_and_warm_starts():
    g = torch.Generator().manual_seed(0)
    centres = torch.tensor([[-4.0, 0.0], [4.0, 0.0], [0.0, 6.0]], dtype=f64)
    pts = torch.cat([c + 0.5 * torch.randn(300, 2, dtype=f64, generator=g) for c in centres])
    gmm = GMM(generator=g)
    gmm.fit(pts, 3)
    found = gmm.mu[torch.argsort(gmm.mu[:, 0] + 0.1 * gmm.mu[:, 1])]
    torch.testing.assert_close(found, centres[[0, 2, 1]], atol=0.15, rtol=0)
    torch.testing.assert_close(gmm.log_weights.exp(), torch.full((3,), 1 / 3, dtype=f64), atol=0.02, rtol=0)
    before = gmm.mu.clone()
    gmm.fit(pts, 3)  # warm start from the converged solution: stays put
    torch.testing.assert_close(gmm.mu, before, atol=1e-6, rtol=0)
    # Moments under one-hot weights are that cluster's mean and covariance.
    mu0, Phi = gmm.moments(torch.eye(3, dtype=f64)[1])
    torch.testing.assert_close(mu0, gmm.mu[1])
    torch.testing.assert_close(Phi, gmm.sigma[1])


def test_batched_fit_equals_per_step_fit():
    X, U = rollouts(M=2, N=8, seed=4)
    prior = DynamicsPriorGMM(generator=torch.Generator().manual_seed(0))
    prior.update(X, U)
    dyn = fit_dynamics(X, U, prior)
    for m in range(2):
        for t in (0, T - 2):
            Y = torch.cat([X[m, :, t], U[m, :, t], X[m, :, t + 1]], dim=-1)
            F, f, D = conditional_gaussian_fit(Y, dX + dU, prior.eval(Y))
            torch.testing.assert_close(dyn.F[m, t], F)
            torch.testing.assert_close(dyn.f[m, t], f)
            torch.testing.assert_close(dyn.D[m, t], D)


def test_nan_in_samples_names_world_condition_iteration():
    X, U = rollouts(M=3, N=10, seed=5)
    X[1, 4, 6, 2] = float("nan")
    with pytest.raises(NumericalError) as info:
        fit_dynamics(X, U, world="4link-push", iteration=11)
    message = str(info.value)
    assert "world=4link-push" in message and "condition=1" in message
    assert "iteration=11" in message
    assert info.value.condition == 1


def test_policy_linearisation_recovers_linear_policy():
    g = torch.Generator().manual_seed(6)
    M, N = 2, 40
    X = torch.randn(M, N, T, dX, dtype=f64, generator=g)
    K_true = torch.randn(dU, dX, dtype=f64, generator=g)
    k_true = torch.randn(dU, dtype=f64, generator=g)
    mean = X @ K_true.T + k_true + 0.01 * torch.randn(M, N, T, dU, dtype=f64, generator=g)
    policy_cov = 0.3 * torch.eye(dU, dtype=f64).expand(M, N, T, dU, dU)
    prior = PolicyPriorGMM(generator=g)
    prior.update(X, mean)
    lin = fit_policy_linearization(X, mean, policy_cov, prior)
    assert lin.K.shape == (M, T, dU, dX)
    torch.testing.assert_close(lin.K, K_true.expand(M, T, dU, dX), atol=0.02, rtol=0)
    torch.testing.assert_close(lin.k, k_true.expand(M, T, dU), atol=0.02, rtol=0)
    torch.testing.assert_close(
        lin.cov, 0.3 * torch.eye(dU, dtype=f64).expand(M, T, dU, dU), atol=1e-3, rtol=0
    )


def test_with_fewer_samples_than_state_dimensions_only_the_jacobian_recovers_the_policy():
    """Fine-tuning's first linearisation sees 5 samples per step in a 16-dimensional state
    (three_link/drawer_horizontal). Where the policy's slope changes from step to step (a
    network along a trajectory), the prior pooled over steps cannot supply it and regression
    has too few samples to find it; the network's own derivative gives it exactly. Off the
    line, cov holds the curvature."""
    g = torch.Generator().manual_seed(0)
    M, N, T_, dX_ = 2, 5, 4, 16
    X = torch.randn(M, N, T_, dX_, dtype=f64, generator=g)
    K_true = torch.randn(T_, dU, dX_, dtype=f64, generator=g)  # one slope per step
    k_true = torch.randn(dU, dtype=f64, generator=g)
    mean = torch.einsum("tux,mntx->mntu", K_true, X) + k_true
    prior = PolicyPriorGMM(generator=g)
    prior.update(X, mean)
    regressed = fit_policy_linearization(X, mean, None, prior)
    exact = policy_linearization_from_jacobian(X, mean, K_true.expand(M, N, T_, dU, dX_))
    torch.testing.assert_close(exact.K, K_true.expand(M, T_, dU, dX_))
    torch.testing.assert_close(exact.k, k_true.expand(M, T_, dU))
    assert exact.cov.abs().max() < 1e-5  # a linear policy: the line misses nothing
    assert (regressed.K - K_true).abs().max() > 0.5  # 5 points cannot pin 16 slopes

    # a curved policy u = tanh(K x): K is the mean slope, the spread it misses goes to cov
    curved = torch.tanh(X @ K_true[0].T)
    slope = (1 - curved.pow(2)).unsqueeze(-1) * K_true[0]  # [M, N, T, dU, dX]
    lin = policy_linearization_from_jacobian(X, curved, slope)
    torch.testing.assert_close(lin.K, slope.mean(dim=1))
    torch.testing.assert_close(lin.mean_actions(X).mean(dim=1), curved.mean(dim=1))
    missed = curved - lin.mean_actions(X)
    torch.testing.assert_close(
        torch.diagonal(lin.cov, dim1=-2, dim2=-1), missed.pow(2).mean(dim=1) + 1e-6, rtol=1e-6, atol=1e-9
    )


def test_nan_reaching_the_prior_is_reported_with_context():
    X, U = rollouts(M=2, N=4, seed=7)
    U[1, 0, 3, 0] = float("inf")
    with pytest.raises(NumericalError, match="condition=1") as info:
        DynamicsPriorGMM().update(X, U, world="w", iteration=2)
    assert info.value.world == "w" and info.value.iteration == 2


def test_ridge_bounds_the_gain_along_a_direction_the_samples_barely_excite():
    """Two state parts that move together (like joint and end-effector velocities): the data fix
    only their sum's effect.  A tiny ridge lets noise set the gain along their difference, which
    the LQR then trusts as real; ``gps.dynamics_ridge`` shrinks it towards zero."""
    g = torch.Generator().manual_seed(0)
    N, T = 5, 30
    U = torch.randn(1, N, T, 1, dtype=f64, generator=g)
    X = torch.zeros(1, N, T, 2, dtype=f64)
    X[:, :, 0] = torch.randn(1, N, 1, dtype=f64, generator=g)  # v = w
    for t in range(T - 1):  # both parts follow v + w; they differ only by 1e-4 of noise
        shared = 0.45 * X[:, :, t].sum(-1, keepdim=True) + 0.5 * U[:, :, t]
        X[:, :, t + 1] = shared + 1e-4 * torch.randn(1, N, 2, dtype=f64, generator=g)

    def largest_mode(ridge: float) -> float:
        F = fit_dynamics(X, U, ridge=ridge).F[0, :-1, :, :2]  # [T-1, 2, 2]: d x' / d (v, w)
        return float(torch.linalg.eigvals(F).abs().max())

    assert largest_mode(1e-9) > 1.5  # noise sets the gain along v - w: an unstable mode from nothing
    assert largest_mode(1e-3) == pytest.approx(0.9, abs=0.01)  # the true system's only mode
    on_manifold = fit_dynamics(X, U, ridge=1e-3).F[0, :-1, :, :2].sum(-1)  # gain of v + w together
    torch.testing.assert_close(on_manifold, torch.full_like(on_manifold, 0.9), atol=0.01, rtol=0)


def test_spectral_radius_and_the_state_entry_that_feeds_the_growing_mode():
    """F_x = [[0.9, 3], [0, 2]]: the mode with eigenvalue 2 shows in both entries but is fed
    by entry 1 alone (the left eigenvector), which is the entry to blame."""
    F = torch.zeros(2, 3, 2, 3, dtype=torch.float64)
    F[..., 0, 0] = 0.9
    F[0, 1, :, :2] = torch.tensor([[0.9, 3.0], [0.0, 2.0]], dtype=torch.float64)
    zeros = torch.zeros(2, 3, 2, dtype=torch.float64)
    dynamics = LinearGaussianDynamics(
        F=F, f=zeros, D=torch.zeros(2, 3, 2, 2, dtype=torch.float64), x0mu=zeros[:, 0], x0sigma=F[:, 0, :, :2]
    )
    radius = dynamics.spectral_radius()
    assert radius.shape == (2, 3)
    assert radius[0].tolist() == pytest.approx([0.9, 2.0, 0.9])
    assert radius[1].tolist() == pytest.approx([0.9] * 3)
    assert dynamics.dominant_mode(0, 1) == 1
