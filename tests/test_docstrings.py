"""Every docstring example in the library runs and prints what it says (TorchRL's style: runnable docs)."""

import doctest
import importlib
import pkgutil

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


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name):
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert result.failed == 0
    if name in TEACH_BY_EXAMPLE:
        assert result.attempted > 0
