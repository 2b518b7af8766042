"""Every docstring example in the library and the benchmarks runs and prints what it says
(TorchRL's style: runnable docs)."""

import doctest
import importlib
import pkgutil
from pathlib import Path

import pytest

import modnet
from modnet import domains

#: walked from modnet.domains too: an editable install maps it from domains/, outside modnet's folder
MODULES = sorted(
    {"modnet.domains"}
    | {
        m.name
        for package in (modnet, domains)
        for m in pkgutil.walk_packages(package.__path__, f"{package.__name__}.")
    }
)
#: the benchmark scripts with examples (importable: pytest puts benchmarks/ on the path)
BENCHMARKS = sorted(
    path.stem
    for path in (Path(__file__).parents[1] / "benchmarks").glob("*.py")
    if ">>> " in path.read_text()
)
#: the public building blocks: each must show how it is called
TEACH_BY_EXAMPLE = {
    "modnet.bank",
    "modnet.modules",
    "modnet.pretrain",
    "modnet.gps.controller",
    "modnet.gps.cost",
    "modnet.gps.dynamics",
    "modnet.gps.errors",
    "modnet.gps.lqr",
}


@pytest.mark.parametrize("name", MODULES + BENCHMARKS)
def test_docstring_examples_run(name):
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert result.failed == 0
    if name in TEACH_BY_EXAMPLE or name in BENCHMARKS:
        assert result.attempted > 0


def test_the_benchmarks_with_examples_are_found():
    assert {"imitation_capacity", "reachable"} <= set(BENCHMARKS)
