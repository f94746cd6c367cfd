"""The notebooks execute top to bottom in quick mode (so they cannot rot)."""

from __future__ import annotations

from pathlib import Path

import pytest

from mi_bivariate.sources import have_shared_data

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"


@pytest.mark.parametrize("name", ["quickstart.ipynb", "evaluation.ipynb"])
def test_notebook_runs(name, tmp_path, monkeypatch, request):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    if name == "quickstart.ipynb":  # its leave-one-out priors' training reductions, made before its cells' clock runs
        request.getfixturevalue("loo_reductions")
    monkeypatch.setenv("MI_BIVARIATE_QUICK", "1")        # the kernel inherits the environment
    # The notebooks' temporary folders (the quickstart's 34 MB export, the quick evaluation) go with the
    # test's: before, every run left them in the system's temporary folder.
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    text = _execute(nbformat, nbclient, name, tmp_path)
    assert any(tmp_path.glob("mi_bivariate_*")), "the notebook's outputs were written outside the test's folder"
    if name == "quickstart.ipynb":  # a shared material is recovered with priors that never saw it
        assert ("priors: leave-one-out" if have_shared_data() else "priors: packaged") in text, text[:2000]
    if name == "evaluation.ipynb":
        # A full run made from the repository's root, as docs/results.md says (out/evaluate), is shown, also
        # when the notebook runs in notebooks/ (Jupyter's working folder). Before, only from the root: from
        # notebooks/ a small evaluation ran instead (minutes) and was shown in its place.
        (run,) = tmp_path.glob("mi_bivariate_eval_*")  # stands in for a full run
        repo = tmp_path / "repo"
        (repo / "notebooks").mkdir(parents=True)
        (repo / "out").mkdir()
        run.rename(repo / "out" / "evaluate")
        monkeypatch.delenv("MI_BIVARIATE_QUICK")
        text = _execute(nbformat, nbclient, name, repo / "notebooks")
        assert "materials in ../out/evaluate" in text, text[:2000]


def _execute(nbformat, nbclient, name: str, folder: Path) -> str:
    """Run a notebook top to bottom in ``folder``; fail on an error output; return its text outputs."""
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    # 300 s a cell: the quickstart's leave-one-out priors find the 73 materials' reductions made (conftest's
    # loo_reductions) and learn from them; before, a cold cache made them inside the cell (> 300 s under load)
    client = nbclient.NotebookClient(nb, timeout=300, kernel_name="python3",
                                     resources={"metadata": {"path": str(folder)}})
    client.execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    return "".join(o.get("text", "") for o in outputs)
