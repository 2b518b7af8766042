"""The exploration notebook executes top to bottom on the tiny universe (nbclient)."""

import os
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOK = Path(__file__).resolve().parents[1] / "notebooks" / "explore_module_bank.ipynb"


def execute(tmp_path, bank_dir=None):
    notebook = nbformat.read(NOTEBOOK, as_version=4)
    env = {k: v for k, v in os.environ.items() if k != "MODNET_BANK"}
    if bank_dir is not None:
        env["MODNET_BANK"] = str(bank_dir)
    client = NotebookClient(
        notebook, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    )
    client.execute(env=env)  # the kernel's environment
    return notebook


def outputs(notebook, kind):
    return [
        o
        for cell in notebook.cells
        if cell.cell_type == "code"
        for o in cell.outputs
        if o.output_type == kind
    ]


@pytest.mark.parametrize("source", ["trained here", "saved by run.py"])
def test_notebook_composes_rolls_out_and_compares_with_the_wrong_task(tmp_path, source, request):
    bank_dir = None
    if source == "saved by run.py":
        run_dir, done, _ = request.getfixturevalue("tiny_run")  # the tests' one finished run.py job
        assert done.returncode == 0, done.stderr[-3000:]
        bank_dir = run_dir / "bank"
    notebook = execute(tmp_path, bank_dir)
    assert not outputs(notebook, "error")
    text = "".join(o.get("text", "") for o in outputs(notebook, "stream"))
    assert "trained on: three_link/reach_black" in text  # the manifest listing
    assert "wrong task (reach_red)" in text  # the zero-shot table
    assert str(bank_dir or "bank") in text
    images = [
        o
        for o in outputs(notebook, "execute_result") + outputs(notebook, "display_data")
        if "image/png" in o.get("data", {})
    ]
    assert len(images) >= 3  # distance curves, final positions, bar chart
