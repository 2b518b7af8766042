"""Benchmark: the batched PI2 C-step (torch, every condition and step at once) vs the GPS code's way,
a loop over conditions and steps that minimises REPS's dual for each temperature (scipy); and
PILQR's model cost of each sample (``model_costs``) vs the GPS code's loop over samples and steps.

Both weigh N samples per condition and step by ``exp(-cost_to_go / eta)``, with ``eta`` where
the weights are ``kl`` from uniform, and refit the feed-forward term and the damped covariance
(``modnet.gps.pi2``). Sizes: experiment 2's fine-tuning (M=32 conditions, N=5 samples, T=100
steps, dX=16, dU=3). Prints medians and the ratios, how far each pair agrees, and what PILQR's
step costs against PI2's; the last line is one JSON object. Single-threaded, as the other
benchmarks of the GPS numerics.

    python benchmarks/pi2.py [--conditions 32] [--repeats 5]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from _timing import median_ms  # noqa: E402
from scipy.optimize import minimize  # noqa: E402

from modnet.gps.controller import LinearGaussianGains  # noqa: E402
from modnet.gps.cost import QuadraticCost  # noqa: E402
from modnet.gps.dynamics import LinearGaussianDynamics  # noqa: E402
from modnet.gps.pi2 import MIN_TEMPERATURE, model_costs, pi2_update, pilqr_update, sampling_noise  # noqa: E402

N, T, dX, dU = 5, 100, 16, 3
KL, DAMPING = 1.0, 2.0
#: L-BFGS-B's tolerances, tighter than scipy's defaults
TIGHT = {"ftol": 1e-15, "gtol": 1e-12}
f64 = torch.float64


def problem(M: int, seed: int = 0):
    """Random sampling gains and samples ``X, U``, with costs that favour some samples."""
    g = torch.Generator().manual_seed(seed)
    S = torch.randn(M, T, dU, dU, dtype=f64, generator=g)
    sampling = LinearGaussianGains.from_covariance(
        0.3 * torch.randn(M, T, dU, dX, dtype=f64, generator=g),
        torch.randn(M, T, dU, dtype=f64, generator=g),
        S @ S.transpose(-1, -2) + torch.eye(dU, dtype=f64),
    )
    X = torch.randn(M, N, T, dX, dtype=f64, generator=g)
    noise = torch.randn(M, N, T, dU, 1, dtype=f64, generator=g)
    U = sampling.mean_actions(X) + (sampling.chol.unsqueeze(1) @ noise).squeeze(-1)
    costs = U.pow(2).sum(-1) + 0.1 * X.pow(2).sum(-1)
    return sampling, X, U, costs


def model(M: int, seed: int = 1) -> tuple[LinearGaussianDynamics, QuadraticCost]:
    """Random stable linear dynamics and a convex quadratic cost of ``[x; u]``."""
    g = torch.Generator().manual_seed(seed)
    d = dX + dU
    F = 0.2 * torch.randn(M, T, dX, d, dtype=f64, generator=g) / d**0.5
    F[..., :dX] += torch.eye(dX, dtype=f64)
    zeros = torch.zeros(M, T, dX, dX, dtype=f64)
    x0 = torch.randn(M, dX, dtype=f64, generator=g)
    f = torch.randn(M, T, dX, dtype=f64, generator=g)
    dynamics = LinearGaussianDynamics(F, f, zeros, x0, zeros[:, 0])
    root = torch.randn(M, T, d, d, dtype=f64, generator=g) / d**0.5
    C = root @ root.transpose(-1, -2) + torch.eye(d, dtype=f64)
    c = torch.randn(M, T, d, dtype=f64, generator=g)
    return dynamics, QuadraticCost(C, c, torch.zeros(M, T, dtype=f64))


def model_costs_loop(K, k, chol, F, f, x0, C, c, noise):
    """The GPS code's ``approximated_cost``: each sample, then each step, in numpy."""
    M, N_ = noise.shape[:2]
    out = np.zeros((M, N_, T))
    for m in range(M):
        for i in range(N_):
            x = x0[m]
            for t in range(T):
                tau = np.concatenate([x, K[m, t] @ x + k[m, t] + chol[m, t] @ noise[m, i, t]])
                out[m, i, t] = 0.5 * tau @ C[m, t] @ tau + c[m, t] @ tau
                x = F[m, t] @ tau + f[m, t]
    return out


def dual(eta: np.ndarray, kl: float, cost_to_go: np.ndarray) -> tuple[float, np.ndarray]:
    """REPS's dual of one step's temperature (the GPS code's ``kl_dual``) and its derivative,
    ``kl - KL(weights || uniform)``: zero where the weights meet the bound."""
    shifted = -(cost_to_go - cost_to_go.min()) / eta[0]
    log_mean = np.log(np.mean(np.exp(shifted)))
    w = np.exp(shifted - shifted.max())
    w /= w.sum()
    divergence = float(np.sum(w * np.log(np.maximum(w, 1e-300) * len(w))))
    return float(eta[0] * kl - cost_to_go.min() + eta[0] * log_mean), np.array([kl - divergence])


def reference(K, cov_old, X, U, costs):
    """One condition and step at a time: the temperature by minimising the dual, then the
    weighted mean and the damped covariance."""
    M = U.shape[0]
    k, cov, eta = np.zeros((M, T, dU)), np.zeros((M, T, dU, dU)), np.zeros((M, T))
    cost_to_go = np.flip(np.cumsum(np.flip(costs, -1), -1), -1)
    for m in range(M):
        for t in range(T):
            S = cost_to_go[m, :, t]
            bounds = [(MIN_TEMPERATURE, None)]
            res = minimize(dual, [10.0], args=(KL, S), jac=True, bounds=bounds, options=TIGHT)
            eta[m, t] = res.x[0]
            w = np.exp(-(S - S.min()) / eta[m, t])
            w /= w.sum()
            ff = U[m, :, t] - X[m, :, t] @ K[m, t].T
            k[m, t] = w @ ff
            d = ff - k[m, t]
            weighted = (w[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0)
            ratio = np.trace(np.linalg.solve(cov_old[m, t], weighted)) / dU
            cov[m, t] = ratio ** (1 / DAMPING) * cov_old[m, t]
    return k, cov, eta


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--conditions", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(1)

    sampling, X, U, costs = problem(args.conditions)
    run = lambda: pi2_update(sampling, X, U, costs, kl=KL, covariance_damping=DAMPING)  # noqa: E731
    as_np = tuple(t.numpy() for t in (sampling.K, sampling.cov, X, U, costs))
    ours = run()
    ref_k, ref_cov, ref_eta = reference(*as_np)
    ours_ms = median_ms(run, args.repeats)
    reference_ms = median_ms(lambda: reference(*as_np), args.repeats)

    dynamics, cost = model(args.conditions)
    noise = sampling_noise(sampling, X, U)
    modelled = model_costs(sampling, dynamics, cost, noise)
    loop_args = (sampling.K, sampling.k, sampling.chol, dynamics.F, dynamics.f, dynamics.x0mu)
    loop_args = tuple(t.numpy() for t in (*loop_args, cost.C, cost.c, noise))
    ref_modelled = model_costs_loop(*loop_args)
    scale = np.abs(ref_modelled).max()
    model_ms = median_ms(lambda: model_costs(sampling, dynamics, cost, noise), args.repeats)
    model_loop_ms = median_ms(lambda: model_costs_loop(*loop_args), args.repeats)
    pilqr = lambda: pilqr_update(sampling, sampling, dynamics, cost, X, U, costs, kl=KL)  # noqa: E731
    pilqr_ms = median_ms(pilqr, args.repeats)
    result = {
        "benchmark": "pi2_update",
        "M": args.conditions, "N": N, "T": T, "dX": dX, "dU": dU, "kl": KL,
        "repeats": args.repeats,
        "torch_threads": torch.get_num_threads(),
        "batched_torch_median_ms": round(ours_ms, 3),
        "scipy_dual_loop_median_ms": round(reference_ms, 3),
        "speedup_loop_over_batched": round(reference_ms / ours_ms, 2),
        "max_abs_diff_k": float(np.abs(ours.gains.k.numpy() - ref_k).max()),
        "max_rel_diff_cov": float((np.abs(ours.gains.cov.numpy() - ref_cov) / np.abs(ref_cov).max()).max()),
        "max_rel_diff_eta": float((np.abs(ours.eta.numpy() - ref_eta) / ref_eta).max()),
        "max_kl_from_bound": float((ours.kl - KL).abs().max()),
        "model_costs_batched_median_ms": round(model_ms, 3),
        "model_costs_loop_median_ms": round(model_loop_ms, 3),
        "speedup_model_costs_loop_over_batched": round(model_loop_ms / model_ms, 2),
        "max_rel_diff_model_costs": float(np.abs(modelled.numpy() - ref_modelled).max() / scale),
        "pilqr_median_ms": round(pilqr_ms, 3),
        "pilqr_over_pi2": round(pilqr_ms / ours_ms, 2),
    }
    print(f"batched torch: {ours_ms:.2f} ms, scipy loop: {reference_ms:.2f} ms (median of {args.repeats})")
    print(f"model costs: batched {model_ms:.2f} ms, loop {model_loop_ms:.2f} ms; PILQR {pilqr_ms:.2f} ms")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
