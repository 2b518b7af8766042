"""Time-varying linear-Gaussian controllers ``u ~ N(K_t x + k_t, Sigma_t)`` for M conditions.

:class:`LinearGaussianGains` holds the numbers (float64, batched over conditions and
time); :class:`LinearGaussianController` is the TensorDictModule that acts with them in a
TorchRL rollout: it concatenates the state keys into ``x``, picks the gains of each batch
entry's ``"condition"`` and ``"step_count"`` (clamped to T-1) and writes ``"action"``.

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from modnet.gps.controller import LinearGaussianController
    >>> ctrl = LinearGaussianController.initial(
    ...     [("robot", "state")], num_conditions=2, horizon=5, state_dim=4,
    ...     joint_position_idx=[0, 1], joint_velocity_idx=[2, 3], variance=1.0)
    >>> td = TensorDict({("robot", "state"): torch.ones(3, 4),
    ...                  "condition": torch.tensor([0, 1, 1]),
    ...                  "step_count": torch.tensor([[0], [4], [9]])}, batch_size=[3])
    >>> ctrl(td)["action"].shape
    torch.Size([3, 2])
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import torch
from tensordict.nn import InteractionType, TensorDictModule
from tensordict.nn.probabilistic import interaction_type
from tensordict.utils import NestedKey
from torch import nn

from modnet.gps.errors import NumericalError, check_finite
from modnet.gps.linalg import symmetrize

if TYPE_CHECKING:
    from modnet.gps.cost import QuadraticCost
    from modnet.gps.dynamics import LinearGaussianDynamics

__all__ = ["LinearGaussianController", "LinearGaussianGains", "smoothed_noise", "time_filtered"]


def smoothed_noise(
    shape: Sequence[int],
    sigma: float,
    *,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
) -> torch.Tensor:
    """Standard normal noise ``[B, T, dU]``, Gaussian-filtered along time, then renormalised.

    The GPS code's exploration noise (``generate_noise`` with ``smooth_noise``): each
    episode's white noise is filtered along its T steps with a Gaussian kernel of standard
    deviation ``sigma`` steps (truncated at 4 sigma, edges mirrored as in
    ``scipy.ndimage.gaussian_filter``), then divided by its own standard deviation over time,
    so every action dimension keeps unit variance while neighbouring steps push the same way.
    ``sigma = 0`` gives white noise.

    Examples:
        >>> g = torch.Generator().manual_seed(0)
        >>> noise = smoothed_noise((2, 100, 3), 2.0, generator=g)
        >>> noise.shape, bool(noise.var(1, unbiased=False).allclose(torch.tensor(1.0, dtype=noise.dtype)))
        (torch.Size([2, 100, 3]), True)
        >>> lag1 = (noise[:, 1:] * noise[:, :-1]).mean()
        >>> bool(lag1 > 0.8)  # white noise: about 0
        True
    """
    B, T, dU = shape
    noise = torch.randn(B, T, dU, generator=generator, dtype=dtype)
    if sigma <= 0 or T < 2:
        return noise
    filtered = time_filtered(noise, sigma)
    return filtered / filtered.std(1, unbiased=False, keepdim=True).clamp_min(1e-12)


def time_filtered(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """``x [B, T, D]`` filtered along time (dim 1) with a Gaussian kernel of standard deviation
    ``sigma > 0`` steps, truncated at 4 sigma, edges mirrored as in ``scipy.ndimage.gaussian_filter``.

    Examples:
        >>> x = (torch.arange(40.0) % 2).reshape(1, 40, 1)  # 0 1 0 1 ...: a change every step
        >>> round(float(time_filtered(x, 2.0)[0, 20, 0]), 4)  # filtered out: the mean is left
        0.5
    """
    T = x.shape[1]
    radius = int(4.0 * sigma + 0.5)
    offsets = torch.arange(-radius, radius + 1, dtype=x.dtype)
    kernel = torch.exp(-0.5 * (offsets / sigma) ** 2)
    kernel = kernel / kernel.sum()
    # "reflect" edges (d c b a | a b c d | d c b a): index i -> its mirror, period 2T
    index = torch.arange(-radius, T + radius) % (2 * T)
    index = torch.where(index >= T, 2 * T - 1 - index, index)
    windows = x[:, index].unfold(1, 2 * radius + 1, 1)  # [B, T, D, 2r+1]
    return windows @ kernel


@dataclass
class LinearGaussianGains:
    """Gains of M time-varying linear-Gaussian controllers (float64).

    Shapes: ``K [M, T, dU, dX]``, ``k [M, T, dU]``, ``cov``/``chol``/``precision``
    ``[M, T, dU, dU]`` with ``cov = chol chol'`` and ``precision = cov^-1``.

    Examples:
        >>> g = LinearGaussianGains.from_covariance(
        ...     torch.zeros(1, 3, 2, 4), torch.zeros(1, 3, 2), 4.0 * torch.eye(2).expand(1, 3, 2, 2))
        >>> g.chol[0, 0].diagonal().tolist(), g.precision[0, 0].diagonal().tolist()
        ([2.0, 2.0], [0.25, 0.25])
    """

    K: torch.Tensor
    k: torch.Tensor
    cov: torch.Tensor
    chol: torch.Tensor
    precision: torch.Tensor

    @classmethod
    def from_covariance(
        cls, K: torch.Tensor, k: torch.Tensor, cov: torch.Tensor
    ) -> LinearGaussianGains:
        """Gains from a covariance; its Cholesky factor and inverse are computed here."""
        cov = symmetrize(cov.to(torch.float64))
        chol, info = torch.linalg.cholesky_ex(cov)
        if bool((info > 0).any()):
            bad = int((info > 0).reshape(cov.shape[0], -1).any(-1).nonzero()[0, 0])
            raise NumericalError("controller covariance is not positive definite", condition=bad)
        return cls(
            K=K.to(torch.float64),
            k=k.to(torch.float64),
            cov=cov,
            chol=chol,
            precision=torch.cholesky_inverse(chol),
        )

    @property
    def num_conditions(self) -> int:
        return self.K.shape[0]

    @property
    def horizon(self) -> int:
        return self.K.shape[1]

    @property
    def action_dim(self) -> int:
        return self.K.shape[2]

    @property
    def state_dim(self) -> int:
        return self.K.shape[3]

    def mean_actions(self, X: torch.Tensor) -> torch.Tensor:
        """``K_t x + k_t`` for trajectories ``X [M, N, T, dX]`` -> ``[M, N, T, dU]``."""
        X = X.to(torch.float64)
        return torch.einsum("mtux,mntx->mntu", self.K, X) + self.k[:, None]

    def with_feedback(self, K: torch.Tensor, path: torch.Tensor) -> LinearGaussianGains:
        """These gains with the feedback ``K [M, T, dU, dX]`` instead, the feed-forward moved so
        that the mean action along ``path [M, T, dX]`` stays (``k' = k + (K_old - K) x_t``): the
        same controllers on that path, other ones off it. The covariance stays.

        Examples:
            >>> old = LinearGaussianGains.from_covariance(
            ...     torch.ones(1, 2, 1, 2), torch.zeros(1, 2, 1), torch.eye(1).expand(1, 2, 1, 1))
            >>> path = torch.tensor([[[1.0, 2.0], [3.0, 4.0]]])
            >>> new = old.with_feedback(torch.zeros(1, 2, 1, 2), path)
            >>> new.mean_actions(path[:, None]).flatten().tolist()  # old: 1 + 2, 3 + 4
            [3.0, 7.0]
        """
        K = K.to(torch.float64)
        k = self.k + ((self.K - K) @ path.to(torch.float64).unsqueeze(-1)).squeeze(-1)
        return replace(self, K=K, k=k)


class _LinearGaussianPolicy(nn.Module):
    """``(*state parts, condition, step_count) -> action``; the gains live in buffers."""

    def __init__(
        self,
        gains: LinearGaussianGains,
        deterministic: bool | None,
        generator: torch.Generator | None,
        action_dtype: torch.dtype | None,
        noise_smoothing: float = 0.0,
    ) -> None:
        super().__init__()
        self.register_buffer("K", gains.K.clone())
        self.register_buffer("k", gains.k.clone())
        self.register_buffer("chol", gains.chol.clone())
        self.deterministic = deterministic
        self.generator = generator
        self.action_dtype = action_dtype
        self.noise_smoothing = noise_smoothing
        self.episode_noise: torch.Tensor | None = None  # [B, T, dU], drawn at each episode's t = 0

    def use_mean(self) -> bool:
        """Explicit flag first; otherwise act on the mean unless the interaction type is RANDOM."""
        if self.deterministic is not None:
            return self.deterministic
        current = interaction_type()
        return current is not None and current != InteractionType.RANDOM

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        *state_parts, condition, step_count = inputs
        x = torch.cat([part.to(self.K.dtype) for part in state_parts], dim=-1)
        batch_shape = x.shape[:-1]
        x = x.reshape(-1, x.shape[-1])
        cond = condition.reshape(-1).long()
        t = step_count.reshape(-1).long().clamp(0, self.K.shape[1] - 1)
        action = (self.K[cond, t] @ x.unsqueeze(-1)).squeeze(-1) + self.k[cond, t]
        if not self.use_mean():
            noise = self.noise(t, action)
            action = action + (self.chol[cond, t] @ noise.unsqueeze(-1)).squeeze(-1)
        out_dtype = self.action_dtype or state_parts[0].dtype
        return action.reshape(*batch_shape, -1).to(out_dtype)

    def noise(self, t: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Unit noise ``[B, dU]`` for the batch entries at steps ``t``: white, or read from each
        episode's smoothed sequence, drawn when the entry is at its first step."""
        if self.noise_smoothing <= 0:
            return torch.randn(
                action.shape, generator=self.generator, dtype=action.dtype, device=action.device
            )
        B, (T, dU) = action.shape[0], self.k.shape[1:]
        if self.episode_noise is None or self.episode_noise.shape[0] != B:
            self.episode_noise = smoothed_noise((B, T, dU), self.noise_smoothing, generator=self.generator)
        else:
            fresh = (t == 0).nonzero().squeeze(-1)
            if fresh.numel():
                self.episode_noise[fresh] = smoothed_noise(
                    (fresh.numel(), T, dU), self.noise_smoothing, generator=self.generator
                )
        return self.episode_noise[torch.arange(B), t].to(action)


class LinearGaussianController(TensorDictModule):
    """TorchRL policy acting with M time-varying linear-Gaussian controllers of one world.

    Reads ``state_keys`` (concatenated in that order into ``x``), ``condition_key`` (int64
    ``[*B]``) and ``step_key`` (int64 ``[*B, 1]``); writes ``action_key`` =
    ``K[c, t] x + k[c, t] + chol[c, t] @ noise`` with ``t`` clamped to ``T - 1``.

    Noise: ``torch.randn`` with ``generator`` (global RNG when None, so reproducible under
    ``torch.manual_seed``). The mean is returned when ``deterministic=True``, or when
    ``deterministic`` is None and the exploration type is set to anything but RANDOM
    (e.g. ``set_exploration_type(ExplorationType.DETERMINISTIC)``); unset means sample.
    The action has ``action_dtype`` (default: the dtype of the first state part).
    With ``noise_smoothing > 0`` the noise is the GPS code's smoothed exploration noise
    (:func:`smoothed_noise`): each batch entry draws a whole episode's sequence when its
    ``step_key`` is 0 and reads step t from it, so the entries must keep their batch
    positions through an episode, as in a batched rollout.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from modnet.gps.controller import LinearGaussianController, LinearGaussianGains
        >>> gains = LinearGaussianGains.from_covariance(
        ...     K=torch.ones(1, 2, 1, 2), k=torch.tensor([[[0.0], [10.0]]]),
        ...     cov=torch.eye(1).expand(1, 2, 1, 1))
        >>> ctrl = LinearGaussianController(gains, ["x"], deterministic=True)
        >>> td = TensorDict({"x": torch.tensor([[1.0, 2.0]]), "condition": torch.tensor([0]),
        ...                  "step_count": torch.tensor([[5]])}, batch_size=[1])
        >>> ctrl(td)["action"]
        tensor([[13.]])
    """

    def __init__(
        self,
        gains: LinearGaussianGains,
        state_keys: Sequence[NestedKey],
        *,
        condition_key: NestedKey = "condition",
        step_key: NestedKey = "step_count",
        action_key: NestedKey = "action",
        deterministic: bool | None = None,
        generator: torch.Generator | None = None,
        action_dtype: torch.dtype | None = None,
        noise_smoothing: float = 0.0,
    ) -> None:
        if noise_smoothing < 0:
            raise ValueError(f"noise_smoothing must be non-negative, got {noise_smoothing}")
        policy = _LinearGaussianPolicy(gains, deterministic, generator, action_dtype, noise_smoothing)
        super().__init__(
            policy, in_keys=[*state_keys, condition_key, step_key], out_keys=[action_key]
        )
        self.state_keys = list(state_keys)

    # ---- gains -------------------------------------------------------------------------
    @property
    def gains(self) -> LinearGaussianGains:
        """A snapshot of the current gains (cov and precision recomputed from the Cholesky
        factor): its tensors are copies, so a later :meth:`set_gains` leaves it as it was and
        ``kept = ctrl.gains; ...; ctrl.set_gains(kept)`` restores them."""
        policy = self.module
        chol = policy.chol.detach().clone()
        return LinearGaussianGains(
            K=policy.K.detach().clone(), k=policy.k.detach().clone(), cov=chol @ chol.transpose(-1, -2),
            chol=chol, precision=torch.cholesky_inverse(chol),
        )

    def set_gains(self, gains: LinearGaussianGains) -> None:
        """Replace the gains in place (a collector holding this module sees the new ones)."""
        policy = self.module
        if gains.K.shape != policy.K.shape:
            raise ValueError(f"gains K shape {tuple(gains.K.shape)} != {tuple(policy.K.shape)}")
        check_finite("controller K", gains.K)
        check_finite("controller k", gains.k)
        check_finite("controller chol", gains.chol)
        policy.K.copy_(gains.K)
        policy.k.copy_(gains.k)
        policy.chol.copy_(gains.chol)

    @property
    def deterministic(self) -> bool | None:
        return self.module.deterministic

    @deterministic.setter
    def deterministic(self, value: bool | None) -> None:
        self.module.deterministic = value

    # ---- constructors ------------------------------------------------------------------
    @classmethod
    def initial(
        cls,
        state_keys: Sequence[NestedKey],
        *,
        num_conditions: int,
        horizon: int,
        state_dim: int,
        joint_position_idx: Sequence[int] | torch.Tensor,
        joint_velocity_idx: Sequence[int] | torch.Tensor,
        hold_state: torch.Tensor | None = None,
        kp: float = 1.0,
        kd: float = 0.1,
        variance: float = 10.0,
        **kwargs,
    ) -> LinearGaussianController:
        """Hold-position PD controller ``u_j = -kp (q_j - q*_j) - kd qdot_j`` plus noise.

        Joint j is actuated by action j; ``q*`` is taken from ``hold_state [M, dX]`` (e.g.
        each condition's initial state; zeros when None). Covariance is ``variance * I``.
        Extra keyword arguments go to the constructor.
        """
        pos = torch.as_tensor(joint_position_idx, dtype=torch.long)
        vel = torch.as_tensor(joint_velocity_idx, dtype=torch.long)
        if pos.shape != vel.shape:
            raise ValueError("joint_position_idx and joint_velocity_idx must have equal length")
        action_dim = pos.numel()
        gain = torch.zeros(action_dim, state_dim, dtype=torch.float64)
        joints = torch.arange(action_dim)
        gain[joints, pos] = -kp
        gain[joints, vel] = -kd
        K = gain.expand(num_conditions, horizon, action_dim, state_dim)
        if hold_state is None:
            hold_state = torch.zeros(num_conditions, state_dim, dtype=torch.float64)
        target = hold_state.to(torch.float64)[:, pos]  # [M, dU]
        k = (kp * target)[:, None, :].expand(num_conditions, horizon, action_dim)
        cov = variance * torch.eye(action_dim, dtype=torch.float64)
        gains = LinearGaussianGains.from_covariance(
            K, k, cov.expand(num_conditions, horizon, action_dim, action_dim)
        )
        return cls(gains, state_keys, **kwargs)

    @classmethod
    def from_lqr(
        cls,
        state_keys: Sequence[NestedKey],
        dynamics: LinearGaussianDynamics,
        cost: QuadraticCost,
        *,
        variance: float = 10.0,
        **kwargs,
    ) -> LinearGaussianController:
        """Unconstrained finite-horizon LQR gains for known linear dynamics and a quadratic cost
        (e.g. a hold-position cost), with covariance ``variance * I``."""
        from modnet.gps.lqr import lqr_backward

        solved = lqr_backward(cost, dynamics)
        M, T, dU, _ = solved.gains.K.shape
        cov = variance * torch.eye(dU, dtype=torch.float64).expand(M, T, dU, dU)
        gains = LinearGaussianGains.from_covariance(solved.gains.K, solved.gains.k, cov)
        return cls(gains, state_keys, **kwargs)
