"""Universes: the robot x task grids of the paper's experiments, and which world each holds out.

A universe is data: its robots, its tasks, whether task modules see images, and the world
its experiment holds out.  Every (robot, task) pair is a world; all but the held-out one
are trained, then the held-out world's robot and task modules are composed zero-shot.
That is only possible when the held-out robot and the held-out task each appear in some
training world (the paper's condition), which :meth:`Universe.split` checks.

The Hydra group ``conf/universe/`` selects a universe by name and sets its training budget;
the facts live here only.

Examples:
    >>> universe = get_universe("tiny")
    >>> [world_name(w) for w in universe.worlds]
    ['three_link/reach_red', 'three_link/reach_black', 'four_link/reach_red', 'four_link/reach_black']
    >>> universe.split("four_link/reach_black").training
    (('three_link', 'reach_red'), ('three_link', 'reach_black'), ('four_link', 'reach_red'))
    >>> get_universe("tiny").split("five_link/reach_red")
    Traceback (most recent call last):
    ...
    modnet.universes.UniverseError: held-out world 'five_link/reach_red' is not in universe 'tiny' ...

From a shell (the worlds of a universe, comma-separated for a Hydra sweep)::

    python -m modnet.universes list
    python -m modnet.universes list-worlds color_reach_state
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from modnet.worlds import robot_spec, task_spec

__all__ = ["UNIVERSES", "Split", "Universe", "UniverseError", "get_universe", "parse_world", "world_name"]

World = tuple[str, str]  # (robot, task)


class UniverseError(ValueError):
    """A universe or held-out world that cannot be used: says what is missing and the valid choices."""


def world_name(world: World) -> str:
    """``("four_link", "reach_black")`` -> ``"four_link/reach_black"`` (how runs and results name worlds)."""
    return "/".join(world)


def parse_world(name: str) -> World:
    """``"four_link/reach_black"`` -> ``("four_link", "reach_black")``; :class:`UniverseError` if not."""
    parts = name.split("/") if isinstance(name, str) else []
    if len(parts) != 2 or not all(parts):
        raise UniverseError(f"a world is written ROBOT/TASK (e.g. four_link/reach_black), got {name!r}")
    return parts[0], parts[1]


@dataclass(frozen=True)
class Split:
    """A universe's worlds split into the training worlds and the one held out."""

    holdout: World
    training: tuple[World, ...]


@dataclass(frozen=True)
class Universe:
    """A robot x task grid, the world its experiment holds out, and whether policies see pixels."""

    name: str
    robots: tuple[str, ...]
    tasks: tuple[str, ...]
    holdout: str
    pixels: bool = False
    description: str = ""

    def __post_init__(self) -> None:
        for robot in self.robots:
            robot_spec(robot)  # ValueError naming the valid robots
        for task in self.tasks:
            task_spec(task)

    @property
    def worlds(self) -> tuple[World, ...]:
        """Every (robot, task) pair, robot-major."""
        return tuple((robot, task) for robot in self.robots for task in self.tasks)

    def split(self, holdout: str | None = None) -> Split:
        """Hold out ``holdout`` (``ROBOT/TASK``; the universe's own when None) and train on the rest.

        Raises :class:`UniverseError` when the world is not in the grid or when no training
        world covers its robot or its task (its modules could then never be trained).
        """
        name = self.holdout if holdout is None else holdout
        world = parse_world(name)
        if world not in self.worlds:
            robot, task = world
            missing = []
            if robot not in self.robots:
                missing.append(f"robot {robot!r}")
            if task not in self.tasks:
                missing.append(f"task {task!r}")
            raise UniverseError(
                f"held-out world {name!r} is not in universe {self.name!r} ({' and '.join(missing)} not in "
                f"its grid); robots: {', '.join(self.robots)}; tasks: {', '.join(self.tasks)}"
            )
        training = tuple(w for w in self.worlds if w != world)
        uncovered = [
            f"{factor} {value!r}"
            for factor, index, value in (("robot", 0, world[0]), ("task", 1, world[1]))
            if not any(w[index] == value for w in training)
        ]
        if uncovered:
            raise UniverseError(
                f"cannot hold out {name!r} in universe {self.name!r}: no training world covers its "
                f"{' or its '.join(uncovered)}, so its module would never be trained (a universe needs "
                "at least two robots and two tasks)"
            )
        return Split(world, training)


UNIVERSES: dict[str, Universe] = {
    u.name: u
    for u in (
        Universe(
            "color_reach_state",
            robots=("three_link", "three_link_short", "four_link"),
            tasks=("reach_red", "reach_green", "reach_yellow", "reach_black"),
            holdout="four_link/reach_black",
            description="the paper's colour-reaching grid from states (section V-A)",
        ),
        Universe(
            "color_reach",
            robots=("three_link", "three_link_short", "four_link"),
            tasks=("reach_red", "reach_green", "reach_yellow", "reach_black"),
            holdout="four_link/reach_black",
            pixels=True,
            description="the paper's colour-reaching grid from 64x80 images (section V-A, Table I)",
        ),
        Universe(
            "manipulation",
            robots=("three_link", "four_link", "five_link"),
            tasks=("drawer_horizontal", "drawer_vertical", "push"),
            holdout="three_link/drawer_horizontal",
            description="drawers and block pushing from states (section V-B, fine-tuning figure)",
        ),
        Universe(
            "visual_manipulation",
            robots=("three_link", "three_link_short", "four_link"),
            tasks=("reach", "push", "peg"),
            holdout="four_link/push",
            pixels=True,
            description="visually distinct manipulation from images (section V-C, Table II)",
        ),
        Universe(
            "tiny",
            robots=("three_link", "four_link"),
            tasks=("reach_red", "reach_black"),
            holdout="four_link/reach_black",
            description="2 x 2 colour reaching, for tests and quick looks",
        ),
    )
}


def get_universe(name: str) -> Universe:
    """The universe called ``name``; :class:`UniverseError` naming the valid ones."""
    if name not in UNIVERSES:
        raise UniverseError(f"unknown universe {name!r}; valid universes: {', '.join(UNIVERSES)}")
    return UNIVERSES[name]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m modnet.universes", description=__doc__.split("\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    commands.add_parser("list", help="every universe, its grid and its held-out world")
    worlds = commands.add_parser("list-worlds", help="a universe's worlds, comma-separated (a Hydra sweep)")
    worlds.add_argument("universe")
    args = parser.parse_args(argv)
    if args.command == "list":
        for u in UNIVERSES.values():
            print(
                f"{u.name}: {', '.join(u.robots)} x {', '.join(u.tasks)}; holds out {u.holdout}"
                f"{' (pixels)' if u.pixels else ''}; {u.description}"
            )
        return
    try:
        universe = get_universe(args.universe)
    except UniverseError as err:
        parser.error(str(err))
    print(",".join(world_name(w) for w in universe.worlds))


if __name__ == "__main__":
    main()
