"""docs/report.ipynb, the design report as a notebook: committed without outputs, on the pinned
kernel, and executed here (nbclient) -- its cells assert the report's numbers, so a change that
breaks the reproduction fails this test.  ``make report`` renders it to HTML."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOK = ROOT / "docs" / "report.ipynb"
KERNEL = "python3"  # ipykernel (pinned in requirements.txt) on this interpreter


def _nb():  # noqa: ANN202 - nbformat.NotebookNode
    return nbformat.read(NOTEBOOK, as_version=4)


def test_committed_without_outputs_on_the_pinned_kernel() -> None:
    nb = _nb()
    nbformat.validate(nb)
    assert nb.metadata["kernelspec"]["name"] == KERNEL
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert len(code) >= 10
    stale = [i for i, c in enumerate(nb.cells) if c.cell_type == "code" and (c.outputs or c.execution_count)]
    assert not stale, f"cells {stale} carry outputs: commit docs/report.ipynb without them (they would go stale)"


def test_covers_the_report() -> None:
    text = "\n".join(c.source for c in _nb().cells)
    for needle in ("eigenvalues", "transfer_functions", "controllability", "observability", "pid", "poles_from_spec",
                   "lqr_weight_search", "tk.observer", "tk.reduced", "Nyquist", "gang_of_four", "critical_gain"):
        assert needle in text, needle


@pytest.mark.slow
def test_the_notebook_runs(monkeypatch: pytest.MonkeyPatch) -> None:
    from nbclient import NotebookClient

    # the kernel imports this checkout (it also puts the repository first on sys.path itself)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    monkeypatch.delenv("MPLBACKEND", raising=False)  # the kernel's inline backend, figures as PNG outputs
    nb = _nb()
    NotebookClient(nb, kernel_name=KERNEL, timeout=600, resources={"metadata": {"path": str(NOTEBOOK.parent)}}).execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"]
    assert not errors
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.outputs)
    assert "K = [-180.0737  -65.3276  199.8242   40.6161]" in text and "critical gain 3.6150" in text
    images = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if "image/png" in o.get("data", {})]
    assert len(images) >= 5
