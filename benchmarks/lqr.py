"""Benchmark: batched LQR backward pass (torch, all conditions at once) vs a per-condition numpy loop.

Both implement the same KL-augmented Riccati recursion (augmented cost from the previous
controller, Q = C~ + F'VF, Cholesky of Q_uu, K, k, Sigma = Q_uu^-1 and its Cholesky factor,
V = Q_xx + Q_xu K) for M=4 conditions, T=50, dX=20, dU=4. Prints medians and the ratio;
the last line is one JSON object. Both sides run single-threaded (the matrices are tiny;
threads only add noise when other processes share the two cores).

    python benchmarks/lqr.py [--repeats 30]
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

from modnet.gps.controller import LinearGaussianGains  # noqa: E402
from modnet.gps.cost import QuadraticCost  # noqa: E402
from modnet.gps.dynamics import LinearGaussianDynamics  # noqa: E402
from modnet.gps.lqr import lqr_backward  # noqa: E402

M, T, dX, dU = 4, 50, 20, 4
f64 = torch.float64


def problem(seed: int = 0) -> tuple[QuadraticCost, LinearGaussianDynamics, LinearGaussianGains]:
    """A random stable-ish linear system, a PD quadratic cost and a random previous controller."""
    g = torch.Generator().manual_seed(seed)
    dXU = dX + dU
    A = torch.eye(dX, dtype=f64) + 0.05 * torch.randn(M, T, dX, dX, dtype=f64, generator=g)
    B = 0.1 * torch.randn(M, T, dX, dU, dtype=f64, generator=g)
    L = torch.randn(M, T, dXU, dXU, dtype=f64, generator=g) / dXU**0.5
    dynamics = LinearGaussianDynamics(
        F=torch.cat([A, B], -1), f=0.01 * torch.randn(M, T, dX, dtype=f64, generator=g),
        D=1e-3 * torch.eye(dX, dtype=f64).expand(M, T, dX, dX).clone(),
        x0mu=torch.randn(M, dX, dtype=f64, generator=g),
        x0sigma=1e-2 * torch.eye(dX, dtype=f64).expand(M, dX, dX).clone(),
    )
    cost = QuadraticCost(
        C=L @ L.transpose(-1, -2) + 0.1 * torch.eye(dXU, dtype=f64),
        c=torch.randn(M, T, dXU, dtype=f64, generator=g),
        cc=torch.zeros(M, T, dtype=f64),
    )
    S = torch.randn(M, T, dU, dU, dtype=f64, generator=g)
    prev = LinearGaussianGains.from_covariance(
        0.1 * torch.randn(M, T, dU, dX, dtype=f64, generator=g),
        torch.randn(M, T, dU, dtype=f64, generator=g),
        S @ S.transpose(-1, -2) + torch.eye(dU, dtype=f64),
    )
    return cost, dynamics, prev


def numpy_backward(C, c, F, f, K_prev, k_prev, P_prev, eta):
    """Reference: one condition at a time, one step at a time, plain numpy."""
    out_K = np.zeros((M, T, dU, dX))
    out_k = np.zeros((M, T, dU))
    out_chol = np.zeros((M, T, dU, dU))
    for m in range(M):
        V = np.zeros((dX, dX))
        v = np.zeros(dX)
        for t in range(T - 1, -1, -1):
            K, k, P = K_prev[m, t], k_prev[m, t], P_prev[m, t]
            PK = P @ K
            Lam = np.block([[K.T @ PK, -PK.T], [-PK, P]])
            lam = np.concatenate([K.T @ P @ k, -P @ k])
            Q = C[m, t] / eta + Lam
            q = c[m, t] / eta + lam
            if t < T - 1:
                Ft = F[m, t]
                Q = Q + Ft.T @ V @ Ft
                q = q + Ft.T @ (v + V @ f[m, t])
            Q = 0.5 * (Q + Q.T)
            Quu, Qux, Qxx = Q[dX:, dX:], Q[dX:, :dX], Q[:dX, :dX]
            L = np.linalg.cholesky(Quu)
            Linv = np.linalg.inv(L)
            Quu_inv = Linv.T @ Linv
            Kt = -Quu_inv @ Qux
            kt = -Quu_inv @ q[dX:]
            out_K[m, t], out_k[m, t] = Kt, kt
            out_chol[m, t] = np.linalg.cholesky(Quu_inv)
            V = Qxx + Qux.T @ Kt
            V = 0.5 * (V + V.T)
            v = q[:dX] + Qux.T @ kt
    return out_K, out_k, out_chol




def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=30)
    args = parser.parse_args()
    torch.set_num_threads(1)

    cost, dynamics, prev = problem()
    eta = 1.0
    eta_t = torch.full((M,), eta, dtype=f64)
    as_np = lambda t: t.numpy()
    np_args = (
        as_np(cost.C), as_np(cost.c), as_np(dynamics.F), as_np(dynamics.f),
        as_np(prev.K), as_np(prev.k), as_np(prev.precision), eta,
    )
    ours = lqr_backward(cost, dynamics, prev, eta_t)
    ref_K, ref_k, ref_chol = numpy_backward(*np_args)
    max_abs_diff = max(
        float(np.abs(ours.gains.K.numpy() - ref_K).max()),
        float(np.abs(ours.gains.k.numpy() - ref_k).max()),
        float(np.abs(ours.gains.chol.numpy() - ref_chol).max()),
    )
    ours_ms = median_ms(lambda: lqr_backward(cost, dynamics, prev, eta_t), args.repeats)
    numpy_ms = median_ms(lambda: numpy_backward(*np_args), args.repeats)
    result = {
        "benchmark": "lqr_backward",
        "M": M, "T": T, "dX": dX, "dU": dU,
        "repeats": args.repeats,
        "torch_threads": torch.get_num_threads(),
        "batched_torch_median_ms": round(ours_ms, 3),
        "numpy_per_condition_loop_median_ms": round(numpy_ms, 3),
        "speedup_numpy_over_batched": round(numpy_ms / ours_ms, 2),
        "max_abs_diff_K_k_chol": max_abs_diff,
    }
    print(f"batched torch: {ours_ms:.2f} ms, numpy loop: {numpy_ms:.2f} ms (median of {args.repeats})")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
