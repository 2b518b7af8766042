"""BADMM guided policy search (Levine & Abbeel 2014; the paper's algorithm): its extra pieces.

Next to the C-step's KL trust region, BADMM ties each controller ``p`` to the policy ``pi``
with Lagrange multipliers ``lambda_K [M, T, dU, dX]``, ``lambda_k [M, T, dU]`` on the
action agreement and time-varying weights ``nu_t`` on ``KL(p || pi)``:

* the C-step minimises ``cost - u'(lambda_K x + lambda_k) + nu_t KL(p || pi)`` under the
  trust region (:func:`badmm_cost`, then the usual eta search with ``omega = nu``);
* the S-step regresses the policy onto ``K x + k - nu_t Sigma_t (lambda_K x + lambda_k)``
  with precision ``P_t`` and weight ``nu_t`` (:func:`badmm_targets`);
* the dual step moves the multipliers along the action disagreement and rescales ``nu_t``
  where the per-step KL is unusually small or large (:func:`dual_step`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from modnet.gps.controller import LinearGaussianGains
from modnet.gps.cost import QuadraticCost
from modnet.gps.lqr import gaussian_cost_terms


@dataclass
class BADMMConfig:
    """BADMM options (the authors' modular runs: dual rate 0.2, initial policy weight 0.005)."""

    inner_iterations: int = 4
    dual_rate: float = 0.2
    dual_rate_covar: float = 0.0
    initial_policy_weight: float = 0.005
    kl_lower_std: float = 1.0  # halve nu_t where KL_t < mean - kl_lower_std * std
    kl_upper_std: float = 0.5  # double nu_t where KL_t >= mean + kl_upper_std * std
    min_policy_weight: float = 1e-6
    #: bounds that keep dual ascent from running away when the policy cannot match its
    #: controllers exactly: nu_t at most this, and the S-step target shift
    #: ``|nu_t Sigma_t lambda_k|`` at most ``max_target_shift`` (action units) per step
    max_policy_weight: float = 0.1
    max_target_shift: float = 1.0

    def __post_init__(self) -> None:
        low, start, high = self.min_policy_weight, self.initial_policy_weight, self.max_policy_weight
        if not 0 < low <= start <= high:
            raise ValueError(
                "policy weights must satisfy 0 < min_policy_weight <= initial_policy_weight "
                f"<= max_policy_weight, got {low:g} / {start:g} / {high:g}"
            )


@dataclass
class Multipliers:
    """BADMM's dual variables for M conditions: ``lambda_K``, ``lambda_k`` and ``nu [M, T]``."""

    lambda_K: torch.Tensor
    lambda_k: torch.Tensor
    nu: torch.Tensor

    @classmethod
    def zeros(cls, M: int, T: int, dX: int, dU: int, initial_weight: float) -> Multipliers:
        f64 = torch.float64
        return cls(
            torch.zeros(M, T, dU, dX, dtype=f64),
            torch.zeros(M, T, dU, dtype=f64),
            torch.full((M, T), initial_weight, dtype=f64),
        )


def badmm_cost(cost: QuadraticCost, policy: LinearGaussianGains, duals: Multipliers) -> QuadraticCost:
    """The C-step cost before the trust region: Lagrangian terms and ``nu_t`` times the policy KL."""
    dX = policy.state_dim
    C, c = cost.C.clone(), cost.c.clone()
    C[..., dX:, :dX] -= duals.lambda_K
    C[..., :dX, dX:] -= duals.lambda_K.transpose(-1, -2)
    c[..., dX:] -= duals.lambda_k
    quad, lin = gaussian_cost_terms(policy)
    nu = duals.nu
    return QuadraticCost(C=C + nu[..., None, None] * quad, c=c + nu[..., None] * lin, cc=cost.cc)


def badmm_targets(
    gains: LinearGaussianGains, duals: Multipliers, X: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """S-step targets ``K x + k - nu_t Sigma_t (lambda_K x + lambda_k)`` ``[M, N, T, dU]`` and
    per-sample weights ``nu_t`` ``[M, N, T]`` at the sampled states ``X [M, N, T, dX]``."""
    mean = gains.mean_actions(X)
    pull = (duals.lambda_K[:, None] @ X.unsqueeze(-1)).squeeze(-1) + duals.lambda_k[:, None]
    shift = (gains.cov[:, None] @ pull.unsqueeze(-1)).squeeze(-1) * duals.nu[:, None, :, None]
    weights = duals.nu[:, None].expand(X.shape[:-1])
    return mean - shift, weights


def dual_step(
    duals: Multipliers,
    gains: LinearGaussianGains,
    policy: LinearGaussianGains,
    X: torch.Tensor,
    policy_mean: torch.Tensor,
    kl_per_step: torch.Tensor,
    config: BADMMConfig,
    update_weights: bool,
) -> Multipliers:
    """One dual update from the controllers' and the policy's actions at the samples.

    ``lambda_k -= rate nu_t P_t mean_n(u_traj - u_pol)`` (rescaled so that the S-step target
    shift stays within ``max_target_shift``); ``lambda_K -= rate_covar nu_t P_t (K_traj - K_pol)``;
    when ``update_weights``, ``nu_t`` halves where ``KL_t`` (``[M, T]``, controller to policy) is
    below ``mean - lower std`` and doubles at or above ``mean + upper std`` (within its bounds).
    """
    nu = duals.nu
    P = gains.precision
    gap = (gains.mean_actions(X) - policy_mean).mean(dim=1)  # [M, T, dU]
    lambda_k = duals.lambda_k - config.dual_rate * nu[..., None] * (P @ gap.unsqueeze(-1)).squeeze(-1)
    lambda_K = duals.lambda_K - config.dual_rate_covar * nu[..., None, None] * (P @ (gains.K - policy.K))
    shift = (nu[..., None] * (gains.cov @ lambda_k.unsqueeze(-1)).squeeze(-1)).norm(dim=-1, keepdim=True)
    lambda_k = lambda_k * (config.max_target_shift / shift.clamp_min(1e-12)).clamp(max=1.0)
    if update_weights:
        mean = kl_per_step.mean(dim=1, keepdim=True)
        std = kl_per_step.std(dim=1, keepdim=True)
        factor = torch.ones_like(nu)
        factor = torch.where(kl_per_step < mean - config.kl_lower_std * std, 0.5, factor)
        factor = torch.where(kl_per_step >= mean + config.kl_upper_std * std, 2.0, factor)
        nu = (nu * factor).clamp(config.min_policy_weight, config.max_policy_weight)
    return Multipliers(lambda_K, lambda_k, nu)
