"""Reach one of four coloured blocks (red, green, yellow, black) at random places.

Every colour task observes all four blocks in the same order, so a task module must
learn which block matters: the paper's first experiment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from modnet.specs import TaskDefinition

COLORS = ("red", "green", "yellow", "black")


@dataclass(frozen=True)
class ReachColor(TaskDefinition):
    @property
    def param_dim(self) -> int:
        return 2 * len(COLORS)

    def sample_params(self, rng: np.random.Generator) -> np.ndarray:
        return self.sample_points(rng, len(COLORS), min_separation=0.25).reshape(-1)

    def apply_params(self, data, index, params: np.ndarray) -> None:
        for color, xy in zip(COLORS, params.reshape(-1, 2), strict=True):
            data.mocap_pos[index.mocap(color), :2] = xy


def make(color: str) -> ReachColor:
    return ReachColor(
        name=f"reach_{color}",
        scene="reach_color.xml",
        observables=(("ee", "pos"), ("ee", "vel")) + tuple((c, "pos") for c in COLORS),
        moved="ee",
        goal=color,
        horizon=50,
        success_distance=0.1,
    )


TASKS = {task.name: task for task in map(make, COLORS)}
