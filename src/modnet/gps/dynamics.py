"""Time-varying linear-Gaussian dynamics ``x_{t+1} ~ N(F_t [x_t; u_t] + f_t, D_t)``.

Each step's fit conditions a joint Gaussian over ``y = [x_t, u_t, x_{t+1}]`` estimated from
the N samples, optionally under a normal-inverse-Wishart prior ``(mu0, Phi, m, n0)``; all
time steps and conditions are fitted in one batched call. The prior comes from a Gaussian
mixture fitted by EM on the points of the last few trajectories (:class:`DynamicsPriorGMM`).
The same machinery fits the linearisation ``u ~ N(K_t x_t + k_t, S_t)`` of a neural-network
policy (:func:`fit_policy_linearization`, prior :class:`PolicyPriorGMM`); a policy whose
Jacobian is known can be linearised from it instead (:func:`policy_linearization_from_jacobian`).

Examples:
    >>> import torch
    >>> from modnet.gps.dynamics import DynamicsPriorGMM, fit_dynamics
    >>> g = torch.Generator().manual_seed(0)
    >>> X, U = torch.randn(2, 5, 10, 3, generator=g), torch.randn(2, 5, 10, 1, generator=g)
    >>> prior = DynamicsPriorGMM(generator=g)
    >>> prior.update(X, U)
    >>> dyn = fit_dynamics(X, U, prior)
    >>> [tuple(t.shape) for t in (dyn.F, dyn.f, dyn.D, dyn.x0mu, dyn.x0sigma)]
    [(2, 10, 3, 4), (2, 10, 3), (2, 10, 3, 3), (2, 3), (2, 3, 3)]
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch

from modnet.gps.controller import LinearGaussianGains
from modnet.gps.errors import NumericalError, check_finite
from modnet.gps.linalg import symmetrize

__all__ = [
    "GMM",
    "DynamicsPriorConfig",
    "DynamicsPriorGMM",
    "LinearGaussianDynamics",
    "NIWPrior",
    "PolicyPriorGMM",
    "conditional_gaussian_fit",
    "estimate_initial_state",
    "fit_dynamics",
    "fit_policy_linearization",
    "policy_linearization_from_jacobian",
]

_f64 = torch.float64
_BLOCK_ELEMENTS = 1 << 19  # points x clusters x dims per block in GMM density evaluation


def _eye_like(a: torch.Tensor, n: int) -> torch.Tensor:
    return torch.eye(n, dtype=a.dtype, device=a.device)


@dataclass
class LinearGaussianDynamics:
    """Fitted dynamics of M conditions over T steps (float64).

    ``F [M, T, dX, dX+dU]``, ``f [M, T, dX]``, ``D [M, T, dX, dX]``: step t maps
    ``[x_t; u_t]`` to ``x_{t+1}``; entries at ``t = T-1`` are zero (no successor).
    ``x0mu [M, dX]``, ``x0sigma [M, dX, dX]``: the initial-state Gaussian.
    """

    F: torch.Tensor
    f: torch.Tensor
    D: torch.Tensor
    x0mu: torch.Tensor
    x0sigma: torch.Tensor

    @property
    def state_dim(self) -> int:
        return self.F.shape[-2]

    @property
    def action_dim(self) -> int:
        return self.F.shape[-1] - self.F.shape[-2]

    @property
    def horizon(self) -> int:
        return self.F.shape[1]

    def spectral_radius(self) -> torch.Tensor:
        """``[M, T]``: the largest ``|eigenvalue|`` of each step's state block ``F_x``.

        Above 1 the fit says a deviation grows from that step to the next, whatever the
        actions; an arm under damping stays near 1. A fit far above it (a contact's linear
        fit carried to a condition that never made the contact) makes every controller's
        predicted state covariance explode, and with it the C-step's KL.
        """
        F_x = self.F[..., : self.state_dim].to(torch.float64)
        return torch.linalg.eigvals(F_x).abs().amax(dim=-1)

    def dominant_mode(self, condition: int, step: int) -> int:
        """The state entry that feeds the mode with the largest ``|eigenvalue|`` of ``F_x`` at
        ``(condition, step)``: the largest entry of its left eigenvector, so the entry whose
        value the fit amplifies (the right eigenvector says where the mode shows)."""
        F_x = self.F[condition, step, :, : self.state_dim].to(torch.float64)
        values, vectors = torch.linalg.eig(F_x.T)
        return int(vectors[:, values.abs().argmax()].abs().argmax())


class NIWPrior(NamedTuple):
    """Normal-inverse-Wishart prior over a joint Gaussian: mean ``mu0 [..., D]`` with
    ``m`` pseudo-counts, scatter ``Phi [..., D, D]`` with ``n0`` pseudo-counts."""

    mu0: torch.Tensor
    Phi: torch.Tensor
    m: float
    n0: float


# --------------------------------------------------------------------------- joint fits
def conditional_gaussian_fit(
    Y: torch.Tensor,
    num_inputs: int,
    prior: NIWPrior | None = None,
    ridge: float = 1e-6,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Fit ``y_out | y_in ~ N(W y_in + w, S)`` from samples ``Y [*B, N, D]`` (batched over B).

    The joint covariance is the NIW posterior
    ``(N S_emp + Phi + N m/(N+m) (mean-mu0)(mean-mu0)') / (N + n0)`` (just ``S_emp``
    without a prior), plus ``ridge`` on the input block; conditioning gives
    ``W = Sigma_oi Sigma_ii^-1``, ``w = mean_o - W mean_i``, ``S = Sigma_oo - W Sigma_ii W'``.

    Returns ``W [*B, Dout, Din]``, ``w [*B, Dout]``, ``S [*B, Dout, Dout]``.

    Examples:
        >>> Y = torch.randn(1000, 2, dtype=torch.float64)
        >>> Y[:, 1] = 3 * Y[:, 0] + 1
        >>> W, w, S = conditional_gaussian_fit(Y, num_inputs=1)
        >>> round(W.item(), 4), round(w.item(), 4), abs(S.item()) < 1e-5
        (3.0, 1.0, True)
    """
    Y = Y.to(_f64)
    N = Y.shape[-2]
    mean = Y.mean(dim=-2)
    centred = Y - mean.unsqueeze(-2)
    sigma = centred.transpose(-1, -2) @ centred  # N * empirical covariance (exactly symmetric)
    if prior is None:
        sigma /= N
    else:
        mu0, Phi, m, n0 = prior
        shift = (mean - mu0).unsqueeze(-1)
        sigma += Phi
        sigma += (N * m / (N + m)) * (shift @ shift.transpose(-1, -2))
        sigma /= N + n0
    i = num_inputs
    sigma_in = sigma[..., :i, :i] + ridge * _eye_like(sigma, i)
    sigma_in_out = sigma[..., :i, i:]
    W = torch.linalg.solve_ex(sigma_in, sigma_in_out)[0].transpose(-1, -2)  # NaN in -> NaN out
    w = mean[..., i:] - (W @ mean[..., :i].unsqueeze(-1)).squeeze(-1)
    S = symmetrize(sigma[..., i:, i:] - W @ sigma_in_out)  # Sigma_oo - W Sigma_ii W'
    return W, w, S


def estimate_initial_state(
    X0: torch.Tensor, prior: NIWPrior | None = None, min_variance: float = 1e-6
) -> tuple[torch.Tensor, torch.Tensor]:
    """Initial-state Gaussian from ``X0 [*B, N, dX]``: mean and ``diag(max(var, 1e-6))``.

    With a prior the diagonal empirical covariance ``S`` enters the NIW posterior
    ``(N S + Phi + N m/(N+m) (mean-mu0)(mean-mu0)') / (N + n0)``.
    """
    X0 = X0.to(_f64)
    N = X0.shape[-2]
    x0mu = X0.mean(dim=-2)
    variance = X0.var(dim=-2, unbiased=False).clamp_min(min_variance)
    x0sigma = torch.diag_embed(variance)
    if prior is not None:
        mu0, Phi, m, n0 = prior
        shift = (x0mu - mu0).unsqueeze(-1)
        x0sigma = (N * x0sigma + Phi + (N * m / (N + m)) * (shift @ shift.transpose(-1, -2))) / (
            N + n0
        )
    return x0mu, symmetrize(x0sigma)


def _transition_points(X: torch.Tensor, U: torch.Tensor) -> torch.Tensor:
    """``[x_t, u_t, x_{t+1}]`` for t < T-1: ``X [*B, N, T, dX]`` -> ``[*B, T-1, N, 2dX+dU]``."""
    Y = torch.cat([X[..., :-1, :], U[..., :-1, :], X[..., 1:, :]], dim=-1)
    return Y.transpose(-2, -3)


def _eval_priors(
    prior: _TrajectoryGMMPrior | Sequence[_TrajectoryGMMPrior], points: torch.Tensor
) -> NIWPrior:
    """Evaluate one shared prior on ``points [M, ..., N, D]``, or one prior per condition."""
    if not isinstance(prior, Sequence):
        return prior.eval(points)
    if len(prior) != points.shape[0]:
        raise ValueError(f"got {len(prior)} priors for {points.shape[0]} conditions")
    return _stack_priors([p.eval(pts) for p, pts in zip(prior, points, strict=True)])


def _stack_priors(parts: Sequence[NIWPrior]) -> NIWPrior:
    """Stack per-condition priors; pseudo-counts become broadcastable tensors if they differ."""
    mu0 = torch.stack([p.mu0 for p in parts])
    Phi = torch.stack([p.Phi for p in parts])
    if len({p.m for p in parts}) == 1 and len({p.n0 for p in parts}) == 1:
        return NIWPrior(mu0, Phi, parts[0].m, parts[0].n0)
    shape = (-1,) + (1,) * (Phi.dim() - 1)
    m = torch.tensor([p.m for p in parts], dtype=_f64).reshape(shape)
    n0 = torch.tensor([p.n0 for p in parts], dtype=_f64).reshape(shape)
    return NIWPrior(mu0, Phi, m, n0)  # type: ignore[arg-type]


def fit_dynamics(
    X: torch.Tensor,
    U: torch.Tensor,
    prior: DynamicsPriorGMM | Sequence[DynamicsPriorGMM] | None = None,
    *,
    ridge: float = 1e-6,
    world: str | None = None,
    iteration: int | None = None,
) -> LinearGaussianDynamics:
    """Fit per-step linear-Gaussian dynamics to ``X [M, N, T, dX]``, ``U [M, N, T, dU]``.

    ``prior``: one GMM prior shared by all conditions, one per condition, or None (plain
    fit: empirical covariance plus ``ridge``). Per-condition priors also inform the
    initial-state estimate; a shared one does not (its buffer mixes conditions).
    Raises :class:`NumericalError` when the fit produces NaN/Inf.
    """
    X = X.to(_f64)
    U = U.to(_f64)
    dX, dU = X.shape[-1], U.shape[-1]
    points = _transition_points(X, U)  # [M, T-1, N, D]
    niw = None if prior is None else _eval_priors(prior, points)
    F, f, D = conditional_gaussian_fit(points, dX + dU, niw, ridge)
    pad = lambda a: torch.cat([a, torch.zeros_like(a[:, :1])], dim=1)
    x0_prior = None
    if isinstance(prior, Sequence):
        x0_prior = _stack_priors([p.initial_state() for p in prior])
    x0mu, x0sigma = estimate_initial_state(X[:, :, 0], x0_prior)
    dynamics = LinearGaussianDynamics(F=pad(F), f=pad(f), D=pad(D), x0mu=x0mu, x0sigma=x0sigma)
    for name in ("F", "f", "D", "x0mu", "x0sigma"):
        check_finite(f"dynamics {name}", getattr(dynamics, name), world=world, iteration=iteration)
    return dynamics


def fit_policy_linearization(
    X: torch.Tensor,
    policy_mean: torch.Tensor,
    policy_cov: torch.Tensor | None = None,
    prior: PolicyPriorGMM | Sequence[PolicyPriorGMM] | None = None,
    *,
    ridge: float = 1e-6,
    world: str | None = None,
    iteration: int | None = None,
) -> LinearGaussianGains:
    """Linearise a policy around samples: ``pi(x_t) ~ N(pol_K_t x_t + pol_k_t, pol_S_t)``.

    ``X [M, N, T, dX]`` states, ``policy_mean [M, N, T, dU]`` the policy's mean actions on
    them, ``policy_cov [M, N, T, dU, dU]`` its covariance (averaged over samples and added to
    the fitted conditional covariance). Returns gains with ``K [M, T, dU, dX]``.
    """
    X = X.to(_f64)
    policy_mean = policy_mean.to(_f64)
    dX, dU = X.shape[-1], policy_mean.shape[-1]
    points = torch.cat([X, policy_mean], dim=-1).transpose(-2, -3)  # [M, T, N, dX+dU]
    niw = None if prior is None else _eval_priors(prior, points)
    K, k, S = conditional_gaussian_fit(points, dX, niw, ridge)
    if policy_cov is not None:
        S = S + policy_cov.to(_f64).mean(dim=1)
    S = S + ridge * _eye_like(S, dU)
    for name, value in (("K", K), ("k", k), ("S", S)):
        check_finite(f"policy linearisation {name}", value, world=world, iteration=iteration)
    return LinearGaussianGains.from_covariance(K, k, S)


def policy_linearization_from_jacobian(
    X: torch.Tensor,
    policy_mean: torch.Tensor,
    jacobian: torch.Tensor,
    policy_cov: torch.Tensor | None = None,
    *,
    ridge: float = 1e-6,
    world: str | None = None,
    iteration: int | None = None,
) -> LinearGaussianGains:
    """Linearise a policy from its Jacobian at the samples, instead of by regression.

    ``X [M, N, T, dX]`` states, ``policy_mean [M, N, T, dU]`` the policy's mean actions there,
    ``jacobian [M, N, T, dU, dX]`` their derivative with respect to the state. ``K_t`` is the
    Jacobian averaged over the N samples of step t, and ``k_t`` puts the line through the mean
    sample: ``k_t = mean(pi(x)) - K_t mean(x)``. The covariance is the policy's own
    (``policy_cov [M, N, T, dU, dU]``, averaged) plus the spread of what this line misses at
    the samples (the policy's curvature across them). :func:`fit_policy_linearization` must
    infer ``K_t`` from N noisy samples in dX dimensions and leans on its prior for it; here
    it is the network's own slope, so the controllers start from what the network does.
    Returns gains with ``K [M, T, dU, dX]``.

    Examples:
        >>> X = torch.randn(2, 4, 3, 5, dtype=torch.float64)
        >>> K = torch.randn(2, 1, 3, 2, 5, dtype=torch.float64)  # a linear policy, per (m, t)
        >>> mean = (K @ X.unsqueeze(-1)).squeeze(-1) + 1.0
        >>> gains = policy_linearization_from_jacobian(X, mean, K.expand(2, 4, 3, 2, 5))
        >>> torch.allclose(gains.K, K[:, 0]), torch.allclose(gains.k, torch.ones_like(gains.k))
        (True, True)
    """
    X, policy_mean, jacobian = X.to(_f64), policy_mean.to(_f64), jacobian.to(_f64)
    dU = policy_mean.shape[-1]
    K = jacobian.mean(dim=1)  # [M, T, dU, dX]
    x_bar, u_bar = X.mean(dim=1), policy_mean.mean(dim=1)
    k = u_bar - (K @ x_bar.unsqueeze(-1)).squeeze(-1)
    missed = policy_mean - (K.unsqueeze(1) @ X.unsqueeze(-1)).squeeze(-1) - k.unsqueeze(1)  # [M, N, T, dU]
    S = (missed.unsqueeze(-1) * missed.unsqueeze(-2)).mean(dim=1)
    if policy_cov is not None:
        S = S + policy_cov.to(_f64).mean(dim=1)
    S = symmetrize(S) + ridge * _eye_like(S, dU)
    for name, value in (("K", K), ("k", k), ("S", S)):
        check_finite(f"policy linearisation {name}", value, world=world, iteration=iteration)
    return LinearGaussianGains.from_covariance(K, k, S)


# --------------------------------------------------------------------------- GMM prior
class GMM:
    """Full-covariance Gaussian mixture fitted by EM in float64, warm-started between fits.

    Examples:
        >>> g = torch.Generator().manual_seed(0)
        >>> pts = torch.cat([torch.randn(200, 2, generator=g) - 5, torch.randn(200, 2, generator=g) + 5])
        >>> gmm = GMM(generator=g)
        >>> gmm.fit(pts, num_clusters=2)
        >>> sorted(round(v) for v in gmm.mu[:, 0].tolist())
        [-5, 5]
    """

    def __init__(
        self,
        covariance_reg: float = 1e-6,
        max_iterations: int = 100,
        tolerance: float = 1e-5,
        generator: torch.Generator | None = None,
    ) -> None:
        self.covariance_reg = covariance_reg
        self.max_iterations = max_iterations
        self.tolerance = tolerance
        self.generator = generator
        self.mu: torch.Tensor | None = None  # [K, D]
        self.sigma: torch.Tensor | None = None  # [K, D, D]
        self.log_weights: torch.Tensor | None = None  # [K]
        self.num_points = 0
        self._inv_chol: torch.Tensor | None = None  # L_k^-1 with sigma_k = L_k L_k'
        self._half_logdet: torch.Tensor | None = None  # log |L_k|

    @property
    def num_clusters(self) -> int:
        return 0 if self.mu is None else self.mu.shape[0]

    def _initialise(self, points: torch.Tensor, num_clusters: int) -> None:
        """Means at distinct random points, every covariance the data covariance."""
        P, D = points.shape
        pick = torch.randperm(P, generator=self.generator)[:num_clusters]
        centred = points - points.mean(0)
        data_cov = centred.T @ centred / P + self.covariance_reg * _eye_like(points, D)
        self.mu = points[pick].clone()
        self._set_covariances(data_cov.expand(num_clusters, D, D).clone())
        self.log_weights = torch.full((num_clusters,), -math.log(num_clusters), dtype=_f64)

    def _set_covariances(self, sigma: torch.Tensor) -> None:
        """Store ``sigma [K, D, D]`` and its factorisation; a covariance that rounding made
        indefinite gets jitter (10x the regulariser, growing tenfold) until it factorises."""
        sigma = symmetrize(sigma)
        D = sigma.shape[-1]
        eye = _eye_like(sigma, D)
        chol, info = torch.linalg.cholesky_ex(sigma)
        scale = torch.diagonal(sigma, dim1=-2, dim2=-1).mean(-1).clamp_min(1.0)
        jitter = 10 * self.covariance_reg
        while bool((info > 0).any()):
            if jitter > 1e-2:
                raise NumericalError("GMM covariance is not positive definite even with jitter")
            failed = (info > 0)[:, None, None]
            sigma = torch.where(failed, sigma + (jitter * scale)[:, None, None] * eye, sigma)
            chol, info = torch.linalg.cholesky_ex(sigma)
            jitter *= 10
        self.sigma = sigma
        self._inv_chol = torch.linalg.solve_triangular(chol, eye, upper=False)
        self._half_logdet = torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)

    def log_densities(self, points: torch.Tensor) -> torch.Tensor:
        """``log N(points | mu_k, sigma_k)``: ``[*B, D]`` -> ``[*B, K]``.

        ``z_pk = L_k^-1 x_p - L_k^-1 mu_k`` for all clusters is one GEMM per block of points
        (blocks keep the ``[points, K, D]`` intermediate cache-sized).
        """
        assert self.mu is not None and self._inv_chol is not None
        K, D = self.mu.shape
        flat = points.reshape(-1, D).to(_f64)
        whiten = self._inv_chol.reshape(K * D, D).T  # [D, K*D]
        whitened_mu = (self._inv_chol @ self.mu.unsqueeze(-1)).reshape(K * D)
        block = max(1, _BLOCK_ELEMENTS // (K * D))
        mahalanobis = torch.cat(
            [
                (chunk @ whiten - whitened_mu).square_().reshape(-1, K, D).sum(-1)
                for chunk in flat.split(block)
            ]
        )
        log_dens = -0.5 * mahalanobis - self._half_logdet - 0.5 * D * math.log(2 * math.pi)
        return log_dens.reshape(*points.shape[:-1], K)

    def log_responsibilities(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Posterior cluster log-probabilities ``[*B, K]`` and per-point log-likelihood."""
        assert self.log_weights is not None
        joint = self.log_densities(points) + self.log_weights
        log_lik = torch.logsumexp(joint, dim=-1)
        return joint - log_lik.unsqueeze(-1), log_lik

    def fit(self, points: torch.Tensor, num_clusters: int) -> None:
        """EM on ``points [P, D]``; reuses the previous solution when K is unchanged."""
        points = points.to(_f64)
        P, D = points.shape
        if self.num_clusters != num_clusters or self.mu is None or self.mu.shape[1] != D:
            self._initialise(points, num_clusters)
        self.num_points = P
        reg = self.covariance_reg * _eye_like(points, D)
        # M-step through second moments of globally centred points: one GEMM per iteration.
        centre = points.mean(0)
        centred = points - centre
        outer = (centred[:, :, None] * centred[:, None, :]).reshape(P, D * D)
        previous = -math.inf
        for _ in range(self.max_iterations):
            log_resp, log_lik = self.log_responsibilities(points)
            total = float(log_lik.sum())
            if abs(total - previous) < self.tolerance * abs(total):
                break
            previous = total
            resp = log_resp.exp()  # [P, K]
            counts = resp.sum(0).clamp_min(1e-10)
            self.log_weights = torch.log(counts / counts.sum())
            mean = resp.T @ centred / counts[:, None]  # [K, D]
            second = (resp.T @ outer).reshape(-1, D, D) / counts[:, None, None]
            self.mu = mean + centre
            self._set_covariances(second - mean[:, :, None] * mean[:, None, :] + reg)
        check_finite("GMM means", self.mu, per_condition=False)

    def moments(self, weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and covariance of the mixture re-weighted by ``weights [*B, K]``:
        ``mu0 = sum w_k mu_k``, ``Phi = sum w_k (Sigma_k + (mu_k - mu0)(mu_k - mu0)')``."""
        assert self.mu is not None and self.sigma is not None
        centre = self.mu.mean(0)
        offsets = self.mu - centre  # keeps the second moments well conditioned
        second = self.sigma + offsets[:, :, None] * offsets[:, None, :]
        shift = weights @ offsets  # [*B, D]
        mu0 = shift + centre
        Phi = torch.einsum("...k,kde->...de", weights, second) - shift[..., :, None] * shift[
            ..., None, :
        ]
        return mu0, symmetrize(Phi)

    def inference(self, points: torch.Tensor) -> NIWPrior:
        """NIW prior for the set ``points [*B, N, D]``: mixture moments under the averaged
        responsibilities, ``m = 1``, ``n0 = (P - 2 - D) / P`` (P = points in the fit; floored
        at 0 so that a tiny buffer cannot make the posterior's ``N + n0`` non-positive)."""
        log_resp, _ = self.log_responsibilities(points)
        weights = torch.logsumexp(log_resp, dim=-2).sub(math.log(points.shape[-2])).exp()
        mu0, Phi = self.moments(weights)
        D = points.shape[-1]
        P = self.num_points
        return NIWPrior(mu0, Phi, 1.0, max(0.0, (P - 2 - D) / P))


@dataclass
class DynamicsPriorConfig:
    """Options of the GMM priors (defaults from the GPS code; MuJoCo examples used
    ``max_clusters=20, min_samples_per_cluster=40``).

    ``max_trajectories`` is the buffer of one prior (the latest ones); a prior shared by
    several conditions should be given trajectories interleaved across conditions so that
    the buffer spans all of them (the trainer passes them sample-major).
    """

    max_clusters: int = 50
    min_samples_per_cluster: int = 20
    max_trajectories: int = 20
    strength: float = 1.0
    max_em_iterations: int = 100
    covariance_reg: float = 1e-6
    em_tolerance: float = 1e-5


class _TrajectoryGMMPrior:
    """A GMM prior over per-step points built from a buffer of the latest trajectories."""

    def __init__(
        self, config: DynamicsPriorConfig | None = None, generator: torch.Generator | None = None
    ) -> None:
        self.config = config or DynamicsPriorConfig()
        self.gmm = GMM(
            self.config.covariance_reg,
            self.config.max_em_iterations,
            self.config.em_tolerance,
            generator,
        )
        self.X: torch.Tensor | None = None  # [n_traj, T, dX]
        self.U: torch.Tensor | None = None  # [n_traj, T, dU]

    def _points(self, X: torch.Tensor, U: torch.Tensor) -> torch.Tensor:
        """Per-step points of trajectories ``[n, T, .]`` -> ``[n * steps, D]``."""
        raise NotImplementedError

    def num_clusters(self, num_points: int) -> int:
        """``max(2, min(max_clusters, floor(points / min_samples_per_cluster)))``."""
        c = self.config
        return max(2, min(c.max_clusters, num_points // c.min_samples_per_cluster))

    def update(
        self,
        X: torch.Tensor,
        U: torch.Tensor,
        *,
        world: str | None = None,
        iteration: int | None = None,
    ) -> None:
        """Add trajectories ``X [M, N, T, dX]``, ``U [M, N, T, dU]`` (leading dims are
        flattened), keep the latest ``max_trajectories`` and refit the GMM. NaN/Inf in the
        new trajectories raise :class:`NumericalError` naming their condition."""
        check_finite("prior trajectories X", X, world=world, iteration=iteration)
        check_finite("prior trajectories U", U, world=world, iteration=iteration)
        X = X.to(_f64).reshape(-1, *X.shape[-2:])
        U = U.to(_f64).reshape(-1, *U.shape[-2:])
        if self.X is not None:
            X = torch.cat([self.X, X])
            U = torch.cat([self.U, U])
        keep = self.config.max_trajectories
        self.X, self.U = X[-keep:], U[-keep:]
        points = self._points(self.X, self.U)
        self.gmm.fit(points, self.num_clusters(points.shape[0]))

    def eval(self, points: torch.Tensor) -> NIWPrior:
        """Prior ``(mu0, Phi, m, n0)`` for point sets ``[*B, N, D]``, scaled by ``strength``
        (``m, n0 *= strength``; ``Phi *= m``)."""
        if self.gmm.mu is None:
            raise RuntimeError("prior has no data yet: call update(X, U) first")
        mu0, Phi, m, n0 = self.gmm.inference(points.to(_f64))
        m = m * self.config.strength
        n0 = n0 * self.config.strength
        return NIWPrior(mu0, Phi * m, m, n0)

    def initial_state(self) -> NIWPrior:
        """Prior on ``x_0`` from the buffer: its mean and ``diag(var)`` with one pseudo-count
        (times ``strength``)."""
        if self.X is None:
            raise RuntimeError("prior has no data yet: call update(X, U) first")
        x0 = self.X[:, 0]
        strength = self.config.strength
        Phi = torch.diag_embed(x0.var(0, unbiased=False).clamp_min(1e-6)) * strength
        return NIWPrior(x0.mean(0), Phi, strength, strength)


class DynamicsPriorGMM(_TrajectoryGMMPrior):
    """GMM prior over transitions ``[x_t, u_t, x_{t+1}]`` (for :func:`fit_dynamics`)."""

    def _points(self, X: torch.Tensor, U: torch.Tensor) -> torch.Tensor:
        return _transition_points(X, U).reshape(-1, 2 * X.shape[-1] + U.shape[-1])


class PolicyPriorGMM(_TrajectoryGMMPrior):
    """GMM prior over state-policy-action pairs ``[x_t, pi(x_t)]`` (for
    :func:`fit_policy_linearization`; pass the policy's mean actions as ``U``)."""

    def _points(self, X: torch.Tensor, U: torch.Tensor) -> torch.Tensor:
        return torch.cat([X, U], dim=-1).reshape(-1, X.shape[-1] + U.shape[-1])
