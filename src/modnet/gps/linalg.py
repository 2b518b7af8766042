"""Small batched linear-algebra helpers shared by the GPS numerics."""

import torch


def symmetrize(a: torch.Tensor) -> torch.Tensor:
    """``(A + A') / 2`` over the last two dims (removes round-off asymmetry of covariances)."""
    return 0.5 * (a + a.transpose(-1, -2))
