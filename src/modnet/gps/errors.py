"""Numerical failures of the GPS core, with enough context to find the culprit.

Examples:
    >>> import torch
    >>> from modnet.gps.errors import NumericalError, check_finite
    >>> check_finite("F", torch.zeros(2, 3))  # fine: returns the tensor
    tensor([[0., 0., 0.],
            [0., 0., 0.]])
    >>> try:
    ...     check_finite("F", torch.tensor([[0.0, float("nan")]]), world="3link-reach", iteration=4)
    ... except NumericalError as err:
    ...     print(err)
    F contains 1 NaN and 0 Inf value(s) [world=3link-reach, condition=0, iteration=4]
"""

from __future__ import annotations

import torch

__all__ = ["NumericalError", "check_finite", "location_suffix"]


def location_suffix(
    *, world: str | None = None, condition: int | None = None, iteration: int | None = None
) -> str:
    """``" [world=..., condition=..., iteration=...]"`` for the fields given, empty for none: how a
    numerical message, raised or only warned, says where it happened.

    >>> location_suffix(world="three_link/reach_red", iteration=2)
    ' [world=three_link/reach_red, iteration=2]'
    """
    context = ", ".join(
        f"{name}={value}"
        for name, value in (("world", world), ("condition", condition), ("iteration", iteration))
        if value is not None
    )
    return f" [{context}]" if context else ""


class NumericalError(RuntimeError):
    """A NaN/Inf or an unrepairable matrix in the GPS numerics.

    ``world``, ``condition`` and ``iteration`` say where it happened; those that are
    given are appended to the message so a log line alone locates the failure.
    """

    def __init__(
        self,
        message: str,
        *,
        world: str | None = None,
        condition: int | None = None,
        iteration: int | None = None,
    ) -> None:
        self.world = world
        self.condition = condition
        self.iteration = iteration
        self.reason = message
        super().__init__(message + location_suffix(world=world, condition=condition, iteration=iteration))

    def with_context(
        self,
        *,
        world: str | None = None,
        condition: int | None = None,
        iteration: int | None = None,
    ) -> NumericalError:
        """A copy with missing context filled in (existing fields win)."""
        return NumericalError(
            self.reason,
            world=self.world if self.world is not None else world,
            condition=self.condition if self.condition is not None else condition,
            iteration=self.iteration if self.iteration is not None else iteration,
        )


def check_finite(
    name: str,
    tensor: torch.Tensor,
    *,
    world: str | None = None,
    condition: int | None = None,
    iteration: int | None = None,
    per_condition: bool = True,
) -> torch.Tensor:
    """Return ``tensor`` unchanged, or raise :class:`NumericalError` if it holds NaN/Inf.

    When ``condition`` is not given and ``per_condition`` says the leading dimension is
    the condition (M), the first condition holding a bad value is reported.
    """
    finite = torch.isfinite(tensor)
    if bool(finite.all()):
        return tensor
    num_nan = int(torch.isnan(tensor).sum())
    num_inf = int(torch.isinf(tensor).sum())
    if condition is None and per_condition and tensor.dim() >= 1:
        bad = (~finite).reshape(tensor.shape[0], -1).any(dim=1)
        condition = int(bad.nonzero()[0, 0])
    raise NumericalError(
        f"{name} contains {num_nan} NaN and {num_inf} Inf value(s)",
        world=world,
        condition=condition,
        iteration=iteration,
    )
