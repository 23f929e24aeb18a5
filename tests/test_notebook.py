import pytest
from pathlib import Path

import nbformat
from nbclient import NotebookClient

from explorer.study.search import SearchConfig, SearchRun, search
from conftest import TINY_DATA

NOTEBOOK = Path(__file__).resolve().parents[1] / "notebooks" / "analysis.ipynb"


@pytest.mark.slow
def test_analysis_notebook_runs_on_a_tiny_study(tmp_path, monkeypatch):
    search(SearchConfig(study="nb", space="tiny", data=TINY_DATA, train_size=(32, 32), input_size=(64, 64),
                        train_steps=4, batch_size=8, val_limit=8, supernet_steps=4, finalists=1,
                        finalist_steps=4, tune_steps=1).resolve(),
           SearchRun(n_trials=5, timeout_s=None, reports=tmp_path / "reports"))
    monkeypatch.setenv("EXPLORER_STUDY", "nb")
    monkeypatch.delenv("EXPLORER_REPORTS", raising=False)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = nbformat.read(NOTEBOOK, as_version=4)
    # as Jupyter runs it: from notebooks/, the studies in reports/ beside it
    (tmp_path / "notebooks").mkdir()
    NotebookClient(nb, timeout=300, kernel_name="python3",
                   resources={"metadata": {"path": str(tmp_path / "notebooks")}}).execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    text = "".join(str(o.get("data", {}).get("text/plain", "")) for o in outputs)
    assert "time:uniform:100ms" in text  # the re-scored table
