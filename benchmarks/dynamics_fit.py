"""Benchmark: dynamics fit batched over time steps vs a per-time-step Python loop of the same fit.

M=4 conditions, T=50, dX=20, dU=4, N in {5, 10, 20} samples per condition, with and without
the GMM prior (its evaluation is part of the fit). Also times the GMM prior's EM fit on a full
buffer (20 trajectories), cold and warm-started. Prints medians and ratios; the last line is
one JSON object. Single-threaded (small matrices; threads only add noise on two shared cores).

    python benchmarks/dynamics_fit.py [--repeats 20]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import torch  # noqa: E402
from _timing import median_ms  # noqa: E402

from modnet.gps.dynamics import (  # noqa: E402
    DynamicsPriorGMM,
    conditional_gaussian_fit,
    fit_dynamics,
)

M, T, dX, dU = 4, 50, 20, 4
f64 = torch.float64


def rollouts(N: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A stable random linear system (spectral radius 0.98) driven by random actions, with
    process noise: ``X [M, N, T, dX]``, ``U [M, N, T, dU]``."""
    system = torch.Generator().manual_seed(0)
    A = torch.eye(dX, dtype=f64) + 0.05 * torch.randn(dX, dX, dtype=f64, generator=system)
    A = 0.98 * A / torch.linalg.eigvals(A).abs().max()
    B = 0.1 * torch.randn(dX, dU, dtype=f64, generator=system)
    g = torch.Generator().manual_seed(seed)
    X = torch.zeros(M, N, T, dX, dtype=f64)
    U = torch.randn(M, N, T, dU, dtype=f64, generator=g)
    X[:, :, 0] = torch.randn(M, N, dX, dtype=f64, generator=g)
    for t in range(T - 1):
        noise = 0.01 * torch.randn(M, N, dX, dtype=f64, generator=g)
        X[:, :, t + 1] = X[:, :, t] @ A.T + U[:, :, t] @ B.T + noise
    return X, U


def per_step_fit(X: torch.Tensor, U: torch.Tensor, prior: DynamicsPriorGMM | None):
    """Reference: the same conditional Gaussian fit, one time step at a time."""
    Fs, fs, Ds = [], [], []
    for t in range(T - 1):
        Y = torch.cat([X[:, :, t], U[:, :, t], X[:, :, t + 1]], dim=-1)  # [M, N, D]
        niw = None if prior is None else prior.eval(Y)
        F, f, D = conditional_gaussian_fit(Y, dX + dU, niw)
        Fs.append(F)
        fs.append(f)
        Ds.append(D)
    return torch.stack(Fs, 1), torch.stack(fs, 1), torch.stack(Ds, 1)




def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    torch.set_num_threads(1)

    buffer_X, buffer_U = rollouts(5, seed=100)  # 4 x 5 = 20 trajectories fill the buffer
    prior = DynamicsPriorGMM(generator=torch.Generator().manual_seed(0))
    cold = []
    for seed in range(max(3, args.repeats // 4)):
        fresh = DynamicsPriorGMM(generator=torch.Generator().manual_seed(seed))
        start = time.perf_counter()
        fresh.update(buffer_X, buffer_U)
        cold.append((time.perf_counter() - start) * 1e3)
    prior.update(buffer_X, buffer_U)
    warm = []
    for _ in range(max(3, args.repeats // 4)):
        start = time.perf_counter()
        prior.gmm.fit(prior._points(prior.X, prior.U), prior.gmm.num_clusters)
        warm.append((time.perf_counter() - start) * 1e3)

    rows = {}
    for N in (5, 10, 20):
        X, U = rollouts(N, seed=N)
        for label, p in (("plain", None), ("prior", prior)):
            batched = fit_dynamics(X, U, p)
            F, f, D = per_step_fit(X, U, p)
            diff = float((batched.F[:, :-1] - F).abs().max())
            batched_ms = median_ms(lambda X=X, U=U, p=p: fit_dynamics(X, U, p), args.repeats)
            loop_ms = median_ms(lambda X=X, U=U, p=p: per_step_fit(X, U, p), args.repeats)
            rows[f"N{N}_{label}"] = {
                "batched_median_ms": round(batched_ms, 3),
                "per_step_loop_median_ms": round(loop_ms, 3),
                "speedup": round(loop_ms / batched_ms, 2),
                "max_abs_diff_F": diff,
            }
            print(f"N={N:2d} {label:5s}: batched {batched_ms:7.2f} ms, loop {loop_ms:7.2f} ms, "
                  f"x{loop_ms / batched_ms:.1f}")
    result = {
        "benchmark": "dynamics_fit",
        "M": M, "T": T, "dX": dX, "dU": dU,
        "repeats": args.repeats,
        "torch_threads": torch.get_num_threads(),
        "fits": rows,
        "median_speedup": round(statistics.median(r["speedup"] for r in rows.values()), 2),
        "gmm_prior": {
            "points": int(prior.gmm.num_points),
            "clusters": prior.gmm.num_clusters,
            "cold_fit_median_ms": round(statistics.median(cold), 1),
            "warm_refit_median_ms": round(statistics.median(warm), 1),
        },
    }
    print(f"GMM prior fit: cold {result['gmm_prior']['cold_fit_median_ms']} ms, "
          f"warm {result['gmm_prior']['warm_refit_median_ms']} ms")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
