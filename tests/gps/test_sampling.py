"""Sampling for GPS: what the samples record of the actions, and what the dynamics fit makes of it."""

from __future__ import annotations

import torch

from modnet.gps.controller import LinearGaussianController, LinearGaussianGains
from modnet.gps.dynamics import fit_dynamics
from modnet.gps.sampling import STATE_KEYS, WorldSampler
from modnet.specs import TORQUE_LIMIT


def noise_controller(sampler: WorldSampler, std: float) -> LinearGaussianController:
    """Zero-mean Gaussian torques of standard deviation ``std`` on every joint."""
    M, T = sampler.num_conditions, sampler.horizon
    dU, dX = sampler.world.robot.action_dim, sampler.world.state_dim
    cov = std**2 * torch.eye(dU, dtype=torch.float64).expand(M, T, dU, dU)
    gains = LinearGaussianGains.from_covariance(torch.zeros(M, T, dU, dX), torch.zeros(M, T, dU), cov)
    return LinearGaussianController(gains, STATE_KEYS, generator=torch.Generator().manual_seed(0))


def fitted_torque_gain(std: float) -> tuple[float, torch.Tensor]:
    """Mean |dx'/du| of the dynamics fitted to torques of spread ``std``, and the samples' actions."""
    sampler = WorldSampler("three_link", "reach", samples_per_condition=40, horizon=8)
    samples = sampler.sample(noise_controller(sampler, std))
    dynamics = fit_dynamics(samples.X, samples.U)
    B = dynamics.F[:, :-1, :, sampler.world.state_dim :]  # [M, T-1, dX, dU]
    return float(B.abs().mean()), samples.U


def test_the_dynamics_are_fitted_to_the_torques_asked_for_so_torque_beyond_the_limit_does_nothing():
    """The samples keep the actions as commanded (the env clips them, as MuJoCo's ctrlrange did
    in the original GPS code), so a fit over saturating torques finds that asking for more moves
    the arm less per newton-metre asked: the LQR then predicts what clipping will let happen.
    Fitted to the clipped torques instead, the model gave the full gain to torque the arm
    lacks, and the controllers planned with up to 25 Nm of it (2 Nm arms)."""
    gentle, gentle_actions = fitted_torque_gain(std=0.5)
    saturating, asked = fitted_torque_gain(std=6.0)
    assert gentle_actions.abs().max() < TORQUE_LIMIT  # all within the arm's reach: the true gain
    assert asked.abs().max() > 3 * TORQUE_LIMIT  # recorded as asked, not as applied
    # a clipped N(0, 36) torque tracks the asked one with slope P(|u| < 2) ~ 0.26
    assert saturating < 0.5 * gentle, (saturating, gentle)
