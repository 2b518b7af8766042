"""KL-constrained LQR (the C-step of guided policy search), batched over M conditions.

Given a quadratic cost, fitted linear-Gaussian dynamics and a previous controller (or a
policy linearisation), find ``p(u|x)`` minimising ``E_p[cost] - omega H(p)`` subject to
``KL(p || prev) <= epsilon``. For a dual variable ``eta`` the solution is the LQR solution
of the augmented cost ``(C + eta Lambda_prev) / (eta + omega)`` (:func:`lqr_backward`);
``eta`` is searched in log space until the KL (:func:`kl_divergence` over the marginals of
:func:`lqr_forward`) matches ``epsilon = kl_step * step_mult * T``
(:func:`solve_kl_constrained_lqr`). :func:`adapt_step_mult` is the step-size rule.

All math is float64. The only Python loops over time are the Riccati recursion and the
forward propagation; every operation inside them is batched over conditions.

Examples:
    >>> import torch
    >>> from modnet.gps.controller import LinearGaussianGains
    >>> from modnet.gps.cost import QuadraticCost
    >>> from modnet.gps.dynamics import LinearGaussianDynamics
    >>> from modnet.gps.lqr import LQRConfig, solve_kl_constrained_lqr
    >>> M, T, dX, dU = 2, 20, 2, 1
    >>> F = torch.tensor([[1.0, 0.1, 0.0], [0.0, 1.0, 0.1]], dtype=torch.float64)
    >>> dyn = LinearGaussianDynamics(
    ...     F=F.expand(M, T, dX, dX + dU), f=torch.zeros(M, T, dX, dtype=torch.float64),
    ...     D=1e-4 * torch.eye(dX, dtype=torch.float64).expand(M, T, dX, dX),
    ...     x0mu=torch.tensor([[1.0, 0.0], [-1.0, 0.0]], dtype=torch.float64),
    ...     x0sigma=1e-2 * torch.eye(dX, dtype=torch.float64).expand(M, dX, dX))
    >>> cost = QuadraticCost(C=torch.diag(torch.tensor([1.0, 0.1, 0.01])).double().expand(M, T, 3, 3),
    ...                      c=torch.zeros(M, T, 3, dtype=torch.float64),
    ...                      cc=torch.zeros(M, T, dtype=torch.float64))
    >>> prev = LinearGaussianGains.from_covariance(
    ...     torch.zeros(M, T, dU, dX), torch.zeros(M, T, dU), torch.ones(M, T, dU, dU))
    >>> result = solve_kl_constrained_lqr(cost, dyn, prev, config=LQRConfig(kl_step=0.2))
    >>> bool(((result.kl - 0.2 * T).abs() < 0.1 * 0.2 * T).all())
    True
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import torch

from modnet.gps.controller import LinearGaussianGains
from modnet.gps.cost import QuadraticCost, tracking_cost
from modnet.gps.dynamics import LinearGaussianDynamics
from modnet.gps.errors import NumericalError, check_finite
from modnet.gps.linalg import symmetrize

__all__ = [
    "BackwardResult",
    "LQRConfig",
    "LQRResult",
    "StateActionMarginals",
    "adapt_step_mult",
    "augmented_cost",
    "expected_cost",
    "gaussian_cost_terms",
    "held_at_centre",
    "kl_divergence",
    "laplace_cost",
    "lqr_backward",
    "lqr_forward",
    "solve_kl_constrained_lqr",
    "tracking_feedback",
]

log = logging.getLogger(__name__)
_f64 = torch.float64


@dataclass
class LQRConfig:
    """Options of the C-step (defaults from the GPS code).

    ``kl_step``: KL budget per time step (times ``step_mult``); ``min_mult``/``max_mult``
    bound the step multiplier; ``min_eta``/``max_eta`` bracket the dual search of at most
    ``max_iterations`` steps, stopped at ``|KL - eps| < kl_tolerance * eps``;
    ``eta_increment`` is the first increment of eta when ``Q_uu`` is not PD (then doubled);
    ``omega`` (float, or ``[M, T]`` per condition and step) joins eta in the denominator of
    the augmented cost: an entropy bonus, or BADMM's policy weights;
    ``min_improvement_ratio``/``max_improvement_ratio`` clip the step-size rule's factor.
    """

    kl_step: float = 0.2
    min_mult: float = 0.01
    max_mult: float = 10.0
    initial_eta: float = 1.0
    min_eta: float = 1e-8
    max_eta: float = 1e16
    max_iterations: int = 50
    kl_tolerance: float = 0.1
    eta_increment: float = 1e-4
    omega: float | torch.Tensor = 0.0
    min_improvement_ratio: float = 0.1
    max_improvement_ratio: float = 5.0


@dataclass
class BackwardResult:
    """Controller from one backward pass, and the eta it was finally computed with
    (larger than the requested one where ``Q_uu`` had to be repaired), ``[M]``."""

    gains: LinearGaussianGains
    eta: torch.Tensor


@dataclass
class StateActionMarginals:
    """Gaussian marginals of ``tau_t = [x_t; u_t]``: ``mu [M, T, dX+dU]``,
    ``sigma [M, T, dX+dU, dX+dU]``."""

    mu: torch.Tensor
    sigma: torch.Tensor


@dataclass
class LQRResult:
    """Outcome of the C-step, per condition ``[M]`` unless noted.

    ``converged``: ``|KL - target| < tol * target``, or KL below target with eta at its
    lower bound (the constraint is inactive there).  ``at_cap``: not converged, with eta's
    bracket collapsed at ``max_eta``: no eta the search allows brings the KL down to its target.
    """

    gains: LinearGaussianGains
    eta: torch.Tensor
    kl: torch.Tensor
    kl_target: torch.Tensor
    expected_cost: torch.Tensor
    marginals: StateActionMarginals
    converged: torch.Tensor
    at_cap: torch.Tensor
    iterations: int


def _as_condition_tensor(value: float | torch.Tensor, M: int) -> torch.Tensor:
    return torch.as_tensor(value, dtype=_f64).expand(M).clone()


# --------------------------------------------------------------------------- pieces
def _check_inputs(
    cost: QuadraticCost,
    dynamics: LinearGaussianDynamics,
    prev: LinearGaussianGains | None,
    **context,
) -> None:
    """NaN/Inf in any input of the backward pass is reported before it can pose as a
    non-PD ``Q_uu``."""
    tensors = {"cost C": cost.C, "cost c": cost.c, "dynamics F": dynamics.F,
               "dynamics f": dynamics.f}
    if prev is not None:
        tensors |= {"previous K": prev.K, "previous k": prev.k, "previous precision": prev.precision}
    for name, tensor in tensors.items():
        check_finite(name, tensor, **context)


def gaussian_cost_terms(gains: LinearGaussianGains) -> tuple[torch.Tensor, torch.Tensor]:
    """Quadratic and linear parts of ``-log p(u|x)`` on ``tau = [x; u]`` (constants dropped):
    ``Lambda = [[K'PK, -K'P], [-PK, P]]`` ``[M,T,D,D]`` and ``lambda = [K'Pk; -Pk]`` ``[M,T,D]``.

    Adding ``nu * (Lambda, lambda)`` to a cost penalises divergence from ``p`` (the previous
    controller here, or a policy linearisation in BADMM).
    """
    K, k, P = gains.K, gains.k, gains.precision
    PK = P @ K  # [M, T, dU, dX]
    Pk = (P @ k.unsqueeze(-1)).squeeze(-1)  # [M, T, dU]
    Lambda = torch.cat(
        [
            torch.cat([K.transpose(-1, -2) @ PK, -PK.transpose(-1, -2)], dim=-1),
            torch.cat([-PK, P], dim=-1),
        ],
        dim=-2,
    )
    lam = torch.cat([(K.transpose(-1, -2) @ Pk.unsqueeze(-1)).squeeze(-1), -Pk], dim=-1)
    return Lambda, lam


def augmented_cost(
    cost: QuadraticCost,
    prev: LinearGaussianGains | None,
    eta: torch.Tensor | None,
    omega: float | torch.Tensor = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``C~ = (C + eta Lambda)/(eta + omega)``, ``c~ = (c + eta lambda)/(eta + omega)`` with
    ``(Lambda, lambda)`` from :func:`gaussian_cost_terms` of ``prev``; ``eta [M]``; ``omega``
    a float or ``[M, T]`` (BADMM: the policy weights ``nu_t``, whose ``nu_t KL(p||pi)`` terms
    the caller has added to the cost). Without ``prev`` the cost is returned unchanged."""
    terms = None if prev is None else gaussian_cost_terms(prev)
    return _augment(cost, terms, eta, omega)


def _augment(
    cost: QuadraticCost,
    terms: tuple[torch.Tensor, torch.Tensor] | None,
    eta: torch.Tensor | None,
    omega: float | torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    C, c = cost.C.to(_f64), cost.c.to(_f64)
    if terms is None or eta is None:
        return C, c
    Lambda, lam = terms
    denom = eta[:, None] + omega  # [M, 1] or [M, T]
    weight = eta[:, None] / denom
    C_aug = C / denom[..., None, None] + weight[..., None, None] * Lambda
    c_aug = c / denom[..., None] + weight[..., None] * lam
    return C_aug, c_aug


def _homogeneous(C: torch.Tensor, c: torch.Tensor, dynamics: LinearGaussianDynamics):
    """Cost and dynamics on ``[1; x; u]``, laid out ``[T, M, ...]`` for per-step views.

    ``Cbar = [[0, c'], [c, C]]`` (so ``0.5 tau_bar' Cbar tau_bar = 0.5 tau'C tau + c'tau``);
    ``Fbar = [[1, 0], [f, F]]`` maps ``[1; x; u]`` to ``[1; x']``.
    """
    M, T, dXU = c.shape
    zero = c.new_zeros(M, T, 1, 1)
    Cbar = torch.cat(
        [torch.cat([zero, c.unsqueeze(-2)], -1), torch.cat([c.unsqueeze(-1), C], -1)], -2
    )
    F, f = dynamics.F.to(_f64), dynamics.f.to(_f64)
    top = torch.zeros(M, T, 1, dXU + 1, dtype=_f64)
    top[..., 0, 0] = 1.0
    Fbar = torch.cat([top, torch.cat([f.unsqueeze(-1), F], -1)], -2)
    as_steps = lambda a: a.transpose(0, 1).contiguous()
    return as_steps(Cbar), as_steps(Fbar), as_steps(Fbar.transpose(-1, -2))


def _riccati(
    C: torch.Tensor, c: torch.Tensor, dynamics: LinearGaussianDynamics
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Backward Riccati recursion for ``C [M,T,D,D]``, ``c [M,T,D]``.

    Runs on homogeneous coordinates ``[1; x; u]`` so that ``Q`` and ``q`` (and ``V``, ``v``)
    travel as one matrix: ``Qbar = Cbar + Fbar' Vbar Fbar``, ``[k | K] = -Q_uu^-1 Qbar_u,(1,x)``,
    ``Vbar = Qbar_(1,x),(1,x) + Qbar_(1,x),u [k | K]``; eight batched ops per step.

    Returns ``K [M,T,dU,dX]``, ``k [M,T,dU]``, ``Q_uu [M,T,dU,dU]``, its Cholesky factor, and
    ``failed [M]`` (``Q_uu`` not PD at some step; that condition's outputs are garbage).
    """
    T = C.shape[1]
    nx = dynamics.state_dim + 1  # homogeneous state [1; x]
    Cbar, Fbar, FbarT = _homogeneous(C, c, dynamics)
    V = None
    solutions, quu, chol_quu, infos = [], [], [], []
    for t in range(T - 1, -1, -1):
        Q = Cbar[t] if V is None else torch.baddbmm(Cbar[t], torch.bmm(FbarT[t], V), Fbar[t])
        Q_uu = Q[:, nx:, nx:]
        L, info = torch.linalg.cholesky_ex(Q_uu)
        solution = torch.cholesky_solve(Q[:, nx:, :nx], L)  # Q_uu^-1 [q_u | Q_ux] = -[k | K]
        V = torch.baddbmm(Q[:, :nx, :nx], Q[:, :nx, nx:], solution, alpha=-1.0)
        V = (V + V.transpose(-1, -2)) * 0.5
        solutions.append(solution)
        quu.append(Q_uu)
        chol_quu.append(L)
        infos.append(info)
    kK = -torch.stack(solutions[::-1], dim=1)
    failed = (torch.stack(infos, dim=1) > 0).any(dim=1)
    Q_uu = torch.stack(quu[::-1], dim=1)
    return kK[..., 1:], kK[..., 0], symmetrize(Q_uu), torch.stack(chol_quu[::-1], dim=1), failed


def lqr_backward(
    cost: QuadraticCost,
    dynamics: LinearGaussianDynamics,
    prev: LinearGaussianGains | None = None,
    eta: float | torch.Tensor | None = None,
    *,
    omega: float | torch.Tensor = 0.0,
    eta_increment: float = 1e-4,
    max_eta: float = 1e16,
    world: str | None = None,
    iteration: int | None = None,
) -> BackwardResult:
    """LQR backward pass on the augmented cost, repairing non-PD ``Q_uu`` by raising eta.

    ``Q_t = C~_t + F_t' V_{t+1} F_t``, ``q_t = c~_t + F_t'(v_{t+1} + V_{t+1} f_t)``;
    ``K = -Q_uu^-1 Q_ux``, ``k = -Q_uu^-1 q_u``, ``Sigma = Q_uu^-1``;
    ``V = Q_xx + Q_xu K``, ``v = q_x + Q_xu k``. Where ``Q_uu`` is not PD for a condition,
    its eta grows by ``eta_increment`` (doubling each retry); at ``max_eta`` (or without a
    ``prev`` to regularise towards) a :class:`NumericalError` names the condition, as it
    does for NaN/Inf inputs.

    Examples:
        >>> import torch
        >>> from modnet.gps.cost import QuadraticCost
        >>> from modnet.gps.dynamics import LinearGaussianDynamics
        >>> eye = lambda n: torch.eye(n, dtype=torch.float64)
        >>> dyn = LinearGaussianDynamics(F=torch.ones(1, 3, 1, 2, dtype=torch.float64),
        ...     f=torch.zeros(1, 3, 1, dtype=torch.float64), D=torch.zeros(1, 3, 1, 1, dtype=torch.float64),
        ...     x0mu=torch.zeros(1, 1, dtype=torch.float64), x0sigma=eye(1)[None])
        >>> cost = QuadraticCost(eye(2).expand(1, 3, 2, 2), torch.zeros(1, 3, 2, dtype=torch.float64),
        ...                      torch.zeros(1, 3, dtype=torch.float64))
        >>> out = lqr_backward(cost, dyn)
        >>> [round(v, 4) for v in out.gains.K[0, :2].flatten().tolist()]  # scalar Riccati
        [-0.6, -0.5]
    """
    _check_inputs(cost, dynamics, prev, world=world, iteration=iteration)
    terms = None if prev is None else gaussian_cost_terms(prev)
    return _backward(
        cost, dynamics, terms, eta, omega=omega, eta_increment=eta_increment, max_eta=max_eta,
        world=world, iteration=iteration,
    )


def _backward(
    cost: QuadraticCost,
    dynamics: LinearGaussianDynamics,
    terms: tuple[torch.Tensor, torch.Tensor] | None,
    eta: float | torch.Tensor | None,
    *,
    omega: float | torch.Tensor,
    eta_increment: float,
    max_eta: float,
    world: str | None,
    iteration: int | None,
) -> BackwardResult:
    """:func:`lqr_backward` on checked inputs, with ``terms = gaussian_cost_terms(prev)``."""
    M = cost.C.shape[0]
    eta_t = None if terms is None else _as_condition_tensor(1.0 if eta is None else eta, M)
    increment = torch.full((M,), float(eta_increment), dtype=_f64)
    while True:
        K, k, Q_uu, L, failed = _riccati(*_augment(cost, terms, eta_t, omega), dynamics)
        if not bool(failed.any()):
            break
        bad = int(failed.nonzero()[0, 0])
        if eta_t is None:
            raise NumericalError(
                "Q_uu is not positive definite (no previous controller to regularise towards)",
                world=world, condition=bad, iteration=iteration,
            )
        eta_t = torch.where(failed, eta_t + increment, eta_t)
        increment = torch.where(failed, 2 * increment, increment)
        if bool((failed & (eta_t >= max_eta)).any()):
            bad = int((failed & (eta_t >= max_eta)).nonzero()[0, 0])
            raise NumericalError(
                f"failed to find a positive-definite Q_uu even for very large eta "
                f"({float(eta_t[bad]):.3g} >= max_eta {max_eta:.3g})",
                world=world, condition=bad, iteration=iteration,
            )
    cov = symmetrize(torch.cholesky_inverse(L))
    chol, info = torch.linalg.cholesky_ex(cov)
    check_finite("LQR K", K, world=world, iteration=iteration)
    check_finite("LQR k", k, world=world, iteration=iteration)
    if bool((info > 0).any()):
        bad = int((info > 0).reshape(M, -1).any(-1).nonzero()[0, 0])
        raise NumericalError(
            "LQR covariance Q_uu^-1 is numerically not positive definite",
            world=world, condition=bad, iteration=iteration,
        )
    gains = LinearGaussianGains(K=K, k=k, cov=cov, chol=chol, precision=Q_uu)
    out_eta = eta_t if eta_t is not None else torch.zeros(M, dtype=_f64)
    return BackwardResult(gains=gains, eta=out_eta)


def lqr_forward(gains: LinearGaussianGains, dynamics: LinearGaussianDynamics) -> StateActionMarginals:
    """Propagate the state-action Gaussian from ``(x0mu, x0sigma)`` through the controller
    and the dynamics: ``mu_u = K mu_x + k``, ``Sigma_uu = K Sigma_x K' + Sigma``,
    ``mu_x' = F mu_tau + f``, ``Sigma_x' = F Sigma_tau F' + D``.

    The loop carries only the state marginal, through the closed-loop map
    ``A = F [I; K]``, ``b = F [0; k] + f``, ``W = F_u Sigma F_u' + D`` (three batched ops per
    step); the state-action marginals are assembled for all steps at once afterwards.
    """
    K, k, cov = gains.K, gains.k, gains.cov
    F, f, D = dynamics.F.to(_f64), dynamics.f.to(_f64), dynamics.D.to(_f64)
    M, T, dU, dX = K.shape
    lift = torch.cat([torch.eye(dX, dtype=_f64).expand(M, T, dX, dX), K], dim=-2)  # [I; K]
    k_pad = torch.cat([k.new_zeros(M, T, dX), k], dim=-1)
    cov_pad = torch.zeros(M, T, dX + dU, dX + dU, dtype=_f64)
    cov_pad[..., dX:, dX:] = cov
    F_u = F[..., dX:]
    as_steps = lambda a: a.transpose(0, 1).contiguous()
    A = as_steps(F @ lift)
    b = as_steps((F @ k_pad.unsqueeze(-1)).squeeze(-1) + f).unsqueeze(-1)
    W = as_steps(F_u @ cov @ F_u.transpose(-1, -2) + D)
    A_T = A.transpose(-1, -2).contiguous()
    mu_x = dynamics.x0mu.to(_f64).unsqueeze(-1)
    sigma_x = dynamics.x0sigma.to(_f64)
    mus, sigmas = [mu_x], [sigma_x]
    for t in range(T - 1):
        mu_x = torch.baddbmm(b[t], A[t], mu_x)
        sigma_x = torch.baddbmm(W[t], torch.bmm(A[t], sigma_x), A_T[t])
        mus.append(mu_x)
        sigmas.append(sigma_x)
    mu_x = torch.stack(mus, dim=1)  # [M, T, dX, 1]
    sigma_x = symmetrize(torch.stack(sigmas, dim=1))
    mu = (lift @ mu_x).squeeze(-1) + k_pad
    sigma = symmetrize(lift @ sigma_x @ lift.transpose(-1, -2) + cov_pad)
    return StateActionMarginals(mu=mu, sigma=sigma)


def expected_cost(marginals: StateActionMarginals, cost: QuadraticCost) -> torch.Tensor:
    """``sum_t cc + 0.5 tr(Sigma C) + 0.5 mu'C mu + mu'c`` per condition ``[M]``."""
    C = cost.C.to(_f64)
    trace = (marginals.sigma * C).sum(dim=(-1, -2))
    return (cost(marginals.mu) + 0.5 * trace).sum(dim=1)


def laplace_cost(
    gains: LinearGaussianGains, dynamics: LinearGaussianDynamics, cost: QuadraticCost
) -> torch.Tensor:
    """Expected cost ``[M]`` of a controller under linear dynamics and a quadratic cost (the
    Laplace estimate used for predicted/actual improvement)."""
    return expected_cost(lqr_forward(gains, dynamics), cost)


def kl_divergence(
    new: LinearGaussianGains,
    prev: LinearGaussianGains,
    marginals: StateActionMarginals,
    per_step: bool = False,
) -> torch.Tensor:
    """``sum_t E_{x ~ new}[KL(new(u|x) || prev(u|x))]``, each step clipped at 0.

    Per step: ``0.5 [tr(P_prev S_new) - dU + log|S_prev| - log|S_new|
    + d(mu_x)' P_prev d(mu_x) + tr(dK' P_prev dK Sigma_x)]`` with
    ``d(x) = dK x + dk``. Returns ``[M]`` (``[M, T]`` with ``per_step``).
    """
    dX, dU = new.state_dim, new.action_dim
    mu_x = marginals.mu[..., :dX].unsqueeze(-1)
    sigma_x = marginals.sigma[..., :dX, :dX]
    P = prev.precision
    dK = new.K - prev.K
    shift = dK @ mu_x + (new.k - prev.k).unsqueeze(-1)
    mean_term = (shift.transpose(-1, -2) @ P @ shift)[..., 0, 0]
    mean_term = mean_term + ((dK.transpose(-1, -2) @ P @ dK) * sigma_x).sum(dim=(-1, -2))
    logdet = lambda chol: 2 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    cov_term = (P * new.cov).sum(dim=(-1, -2)) - dU + logdet(prev.chol) - logdet(new.chol)
    kl = (0.5 * (mean_term + cov_term)).clamp_min(0.0)
    return kl if per_step else kl.sum(dim=1)


# --------------------------------------------------------------------------- C-step
#: eta's search stops when its bracket ``[lo, hi]`` is narrower than this, relative to ``lo``
_COLLAPSED = 1e-3


def solve_kl_constrained_lqr(
    cost: QuadraticCost,
    dynamics: LinearGaussianDynamics,
    prev: LinearGaussianGains,
    *,
    step_mult: float | torch.Tensor = 1.0,
    eta: float | torch.Tensor | None = None,
    config: LQRConfig | None = None,
    world: str | None = None,
    iteration: int | None = None,
) -> LQRResult:
    """Find per-condition eta with ``KL(new || prev) ~= kl_step * step_mult * T``.

    Log-space bracketing in ``[min_eta, max_eta]`` from ``eta`` (warm start, default
    ``config.initial_eta``): KL below target means eta is too large (``hi = eta``,
    ``eta = max(sqrt(lo hi), hi/10)``), above means too small (``lo = eta``,
    ``eta = min(sqrt(lo hi), 10 lo)``). Conditions are searched together; each stops at
    ``|KL - eps| < kl_tolerance eps`` or when its bracket has collapsed.
    ``step_mult`` and ``eta`` may be scalars or ``[M]`` tensors.
    """
    config = config or LQRConfig()
    M, T = cost.C.shape[:2]
    target = config.kl_step * _as_condition_tensor(step_mult, M) * T
    eta_t = _as_condition_tensor(config.initial_eta if eta is None else eta, M)
    eta_t = eta_t.clamp(config.min_eta, config.max_eta)
    lo = torch.full((M,), config.min_eta, dtype=_f64)
    hi = torch.full((M,), config.max_eta, dtype=_f64)
    done = torch.zeros(M, dtype=torch.bool)
    _check_inputs(cost, dynamics, prev, world=world, iteration=iteration)
    terms = gaussian_cost_terms(prev)
    iterations = 0
    for iterations in range(1, config.max_iterations + 1):
        backward = _backward(
            cost, dynamics, terms, eta_t, omega=config.omega, eta_increment=config.eta_increment,
            max_eta=config.max_eta, world=world, iteration=iteration,
        )
        eta_t = backward.eta
        marginals = lqr_forward(backward.gains, dynamics)
        kl = kl_divergence(backward.gains, prev, marginals)
        excess = kl - target
        within = excess.abs() < config.kl_tolerance * target
        collapsed = hi <= lo * (1 + _COLLAPSED)
        done = done | within | collapsed
        if bool(done.all()) or iterations == config.max_iterations:
            break
        kl_too_large = excess > 0  # eta must grow
        lo = torch.where(~done & kl_too_large, eta_t, lo)
        hi = torch.where(~done & ~kl_too_large, eta_t, hi)
        geometric = torch.sqrt(lo * hi)
        proposal = torch.where(
            kl_too_large, torch.minimum(geometric, 10 * lo), torch.maximum(geometric, 0.1 * hi)
        )
        eta_t = torch.where(done, eta_t, proposal)
    # Inactive constraint: KL stays below target all the way down to min_eta.
    inactive = (excess < 0) & (lo <= config.min_eta) & (hi <= lo * (1 + _COLLAPSED))
    converged = (excess.abs() < config.kl_tolerance * target) | inactive
    at_cap = ~converged & (eta_t * (1 + _COLLAPSED) >= config.max_eta)
    if not bool(converged.all()):
        log.warning(
            "KL search did not converge for conditions %s (KL %s, target %s, eta %s)%s",
            (~converged).nonzero().flatten().tolist(), kl.tolist(), target.tolist(),
            eta_t.tolist(), "" if world is None else f" in world {world}",
        )
    check_finite("LQR KL", kl, world=world, iteration=iteration)
    return LQRResult(
        gains=backward.gains,
        eta=eta_t,
        kl=kl,
        kl_target=target,
        expected_cost=expected_cost(marginals, cost),
        marginals=marginals,
        converged=converged,
        at_cap=at_cap,
        iterations=iterations,
    )


def held_at_centre(
    result: LQRResult,
    centre: LinearGaussianGains,
    dynamics: LinearGaussianDynamics,
    cost: QuadraticCost,
    *,
    eta: torch.Tensor,
) -> LQRResult:
    """``result`` with every condition ``at_cap`` keeping ``centre``, the controllers its KL is
    measured from: the limit of the C-step as eta grows, and the one step the bound always
    allows (KL 0). Where the fitted dynamics blow up (a deviation growing 1.4x a step for 90
    steps), the cost they predict outgrows any eta and no step the search tries meets the
    bound; the GPS code takes the capped step anyway, this takes none. Those conditions' eta
    goes back to ``eta [M]`` (the warm start the search began from); marginals, KL and
    expected cost are those of the controllers kept.

    Examples:
        >>> import torch
        >>> from modnet.gps.cost import QuadraticCost
        >>> from modnet.gps.dynamics import LinearGaussianDynamics
        >>> z = lambda *shape: torch.zeros(*shape, dtype=torch.float64)
        >>> eye = torch.eye(2, dtype=torch.float64)
        >>> dyn = LinearGaussianDynamics(F=z(2, 3, 1, 2) + 1, f=z(2, 3, 1), D=z(2, 3, 1, 1),
        ...     x0mu=z(2, 1) + 1, x0sigma=eye[:1, :1].expand(2, 1, 1))
        >>> cost = QuadraticCost(eye.expand(2, 3, 2, 2), z(2, 3, 2), z(2, 3))
        >>> unit = eye[:1, :1].expand(2, 3, 1, 1)
        >>> centre = LinearGaussianGains.from_covariance(z(2, 3, 1, 1), z(2, 3, 1), unit)
        >>> result = solve_kl_constrained_lqr(cost, dyn, centre, config=LQRConfig(kl_step=0.1))
        >>> result.at_cap = torch.tensor([False, True])  # as if condition 1's search had failed
        >>> held = held_at_centre(result, centre, dyn, cost, eta=z(2) + 1)
        >>> torch.equal(held.gains.K[1], centre.K[1]), torch.equal(held.gains.K[0], result.gains.K[0])
        (True, True)
        >>> held.kl[1].item(), held.eta[1].item(), bool(held.kl[0].sub(result.kl[0]).abs() < 1e-12)
        (0.0, 1.0, True)
    """
    cap = result.at_cap

    def pick(name: str) -> torch.Tensor:
        new, kept = getattr(result.gains, name), getattr(centre, name)  # both float64
        return torch.where(cap.reshape(-1, *(1,) * (new.dim() - 1)), kept, new)

    gains = LinearGaussianGains(**{name: pick(name) for name in ("K", "k", "cov", "chol", "precision")})
    marginals = lqr_forward(gains, dynamics)
    return replace(
        result,
        gains=gains,
        eta=torch.where(cap, eta.to(_f64), result.eta),
        kl=kl_divergence(gains, centre, marginals),
        expected_cost=expected_cost(marginals, cost),
        marginals=marginals,
    )


def adapt_step_mult(
    step_mult: float | torch.Tensor,
    predicted_improvement: torch.Tensor,
    actual_improvement: torch.Tensor,
    config: LQRConfig | None = None,
) -> torch.Tensor:
    """Step-size rule: ``r = predicted / (2 max(1e-4, predicted - actual))`` clipped to
    ``[0.1, 5]``; returns ``clip(r * step_mult, min_mult, max_mult)`` per condition.

    Examples:
        >>> import torch
        >>> adapt_step_mult(1.0, torch.tensor([1.0, 1.0, 1.0]), torch.tensor([1.0, 0.5, -3.0]))
        tensor([5.0000, 1.0000, 0.1250], dtype=torch.float64)
    """
    config = config or LQRConfig()
    predicted = torch.as_tensor(predicted_improvement, dtype=_f64)
    actual = torch.as_tensor(actual_improvement, dtype=_f64)
    ratio = predicted / (2 * (predicted - actual).clamp_min(1e-4))
    ratio = ratio.clamp(config.min_improvement_ratio, config.max_improvement_ratio)
    new_mult = ratio * torch.as_tensor(step_mult, dtype=_f64)
    return new_mult.clamp(config.min_mult, config.max_mult)


def tracking_feedback(
    dynamics: LinearGaussianDynamics,
    X: torch.Tensor,
    gains: LinearGaussianGains,
    weight: float,
    *,
    world: str | None = None,
    iteration: int | None = None,
) -> torch.Tensor:
    """Feedback gains ``K [M, T, dU, dX]`` for the controllers ``gains`` that track a path on
    ``dynamics``: the LQR of :func:`~modnet.gps.cost.tracking_cost`, the states scaled by their
    spread over the samples ``X [M, N, T, dX]``, the torques weighted ``weight`` over the
    controllers' mean action variance (smaller: stiffer). Paired with
    :meth:`~modnet.gps.controller.LinearGaussianGains.with_feedback`, the controllers keep their
    path and pull back towards it harder.

    Examples:
        >>> from modnet.gps.controller import LinearGaussianGains
        >>> from modnet.gps.dynamics import LinearGaussianDynamics
        >>> M, T = 1, 20  # x' = x + 0.1 u
        >>> F = torch.tensor([[1.0, 0.1]], dtype=torch.float64).expand(M, T, 1, 2)
        >>> dyn = LinearGaussianDynamics(F, torch.zeros(M, T, 1).double(), torch.zeros(M, T, 1, 1).double(),
        ...     torch.zeros(M, 1).double(), torch.eye(1).double()[None])
        >>> gains = LinearGaussianGains.from_covariance(
        ...     torch.zeros(M, T, 1, 1), torch.zeros(M, T, 1), torch.eye(1).expand(M, T, 1, 1))
        >>> X = torch.randn(M, 8, T, 1)
        >>> soft, stiff = (tracking_feedback(dyn, X, gains, w)[0, 0, 0, 0].item() for w in (1.0, 1e-4))
        >>> stiff < soft < 0  # both pull back; the smaller weight harder
        True
    """
    variance = float(gains.cov.diagonal(dim1=-2, dim2=-1).mean())
    cost = tracking_cost(X, gains.action_dim, variance, weight)
    return lqr_backward(cost, dynamics, world=world, iteration=iteration).gains.K
