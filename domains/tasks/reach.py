"""Reach a white target."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from modnet.specs import TaskDefinition


@dataclass(frozen=True)
class Reach(TaskDefinition):
    @property
    def param_dim(self) -> int:
        return 2

    def sample_params(self, rng: np.random.Generator) -> np.ndarray:
        return self.sample_points(rng, 1, min_separation=0.0).reshape(-1)

    def apply_params(self, data, index, params: np.ndarray) -> None:
        data.mocap_pos[index.mocap("target"), :2] = params


TASKS = {
    "reach": Reach(
        name="reach",
        scene="reach.xml",
        observables=(("ee", "pos"), ("ee", "vel"), ("target", "pos")),
        moved="ee",
        goal="target",
        horizon=50,
        success_distance=0.1,
    )
}
