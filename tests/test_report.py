"""modnet.report: what a run records about the code and the machine that produced it."""

import shutil
import subprocess
from pathlib import Path

import pytest

from modnet.report import KERNEL_VARIABLES, code_version, machine

needs_git = pytest.mark.skipif(shutil.which("git") is None, reason="needs git")


def git(repo: Path, *args: str) -> str:
    done = subprocess.run(
        ["git", "-c", "user.name=modnet", "-c", "user.email=modnet@example.org", *args],
        cwd=repo,
        capture_output=True,
        text=True,
        check=True,
    )
    return done.stdout.strip()


@pytest.fixture
def checkout(tmp_path):
    """A git repository laid out like modnet's: the package under src/modnet, a domain, a config,
    run.py and a document, committed."""
    package = tmp_path / "src" / "modnet"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text("x = 1\n")
    for path in ("domains/arm.xml", "conf/config.yaml", "run.py", "docs/RESULTS.md"):
        (tmp_path / path).parent.mkdir(exist_ok=True)
        (tmp_path / path).write_text("first\n")
    git(tmp_path, "init", "-q")
    git(tmp_path, "add", ".")
    git(tmp_path, "commit", "-q", "-m", "first")
    return tmp_path


@needs_git
def test_a_checkout_reports_its_commit_and_whether_tracked_files_changed(checkout):
    package = checkout / "src" / "modnet"
    assert code_version(package) == {"commit": git(checkout, "rev-parse", "HEAD"), "dirty": False}
    (checkout / "notes.txt").write_text("untracked files do not change the code\n")
    assert code_version(package)["dirty"] is False
    (package / "__init__.py").write_text("x = 2\n")
    assert code_version(package) == {"commit": git(checkout, "rev-parse", "HEAD"), "dirty": True}


@needs_git
@pytest.mark.parametrize("path", ["domains/arm.xml", "conf/config.yaml", "run.py"])
def test_dirty_counts_what_a_run_executes_and_not_the_docs(checkout, path):
    package = checkout / "src" / "modnet"
    (checkout / "docs" / "RESULTS.md").write_text("a result being written up while runs go on\n")
    assert code_version(package)["dirty"] is False
    (checkout / path).write_text("changed\n")
    assert code_version(package)["dirty"] is True


@needs_git
def test_an_installed_copy_has_no_commit_even_inside_another_repository(checkout, tmp_path_factory):
    installed = checkout / ".venv" / "lib" / "site-packages" / "modnet"  # a venv inside a project
    installed.mkdir(parents=True)
    assert code_version(installed) == {"commit": None, "dirty": None}
    alone = tmp_path_factory.mktemp("site-packages") / "modnet"  # no repository at all
    alone.mkdir()
    assert code_version(alone) == {"commit": None, "dirty": None}


def test_the_machine_records_the_variables_that_chose_its_kernels(monkeypatch):
    for name in KERNEL_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    assert machine()["kernel_variables"] == {}
    monkeypatch.setenv("MKL_ENABLE_INSTRUCTIONS", "AVX2")  # read at each call, not at import
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # threads are the run's own setting, not recorded here
    assert machine()["kernel_variables"] == {"MKL_ENABLE_INSTRUCTIONS": "AVX2"}
