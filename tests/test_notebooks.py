"""The notebooks execute top to bottom in quick mode (so they cannot rot)."""

from __future__ import annotations

from pathlib import Path

import pytest

from mi_bivariate.sources import have_shared_data

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"


@pytest.mark.parametrize("name", ["quickstart.ipynb", "evaluation.ipynb"])
def test_notebook_runs(name, tmp_path, monkeypatch):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    monkeypatch.setenv("MI_BIVARIATE_QUICK", "1")        # the kernel inherits the environment
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    # 300 s a cell: with a cold cache the quickstart's leave-one-out priors reduce 73 materials first
    client = nbclient.NotebookClient(nb, timeout=300, kernel_name="python3",
                                     resources={"metadata": {"path": str(tmp_path)}})
    client.execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
              if o.get("output_type") == "error"]
    assert not errors
    if name == "quickstart.ipynb":  # a shared material is recovered with priors that never saw it
        text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []))
        assert ("priors: leave-one-out" if have_shared_data() else "priors: packaged") in text, text[:2000]
