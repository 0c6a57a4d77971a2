"""notebooks/quickstart.ipynb runs top to bottom on CPU (nbclient)."""

import os
import pathlib

import nbclient
import nbformat
import pytest

NOTEBOOK = (pathlib.Path(__file__).resolve().parents[1] / "notebooks"
            / "quickstart.ipynb")
QUICKSTART_TEST_STEPS = 60


# jupyter_client and zmq warn about their own deprecations at import and
# shutdown; they are not ours to fix.
@pytest.mark.filterwarnings("ignore::DeprecationWarning")
@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_quickstart_runs(tmp_path, monkeypatch):
  nb = nbformat.read(NOTEBOOK, as_version=4)
  # Outputs are stripped in git: a committed output would hide a stale run.
  assert all(not c.get("outputs") for c in nb.cells
             if c.cell_type == "code"), "strip the notebook's outputs"
  monkeypatch.setenv("JAX_PLATFORMS", "cpu")
  # Every cell runs; 60 steps instead of the notebook's 300 keep the test
  # to its compiles (the cells' logic is the same at any length).
  monkeypatch.setenv("QUICKSTART_STEPS", str(QUICKSTART_TEST_STEPS))
  client = nbclient.NotebookClient(
      nb, timeout=600, kernel_name="python3",
      resources={"metadata": {"path": str(tmp_path)}})
  client.execute()
  text = "\n".join(o.get("text", "") for c in nb.cells
                   if c.cell_type == "code" for o in c.outputs)
  assert "vanilla: test PSNR" in text and "guided: test PSNR" in text, text
  images = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs
            if "image/png" in o.get("data", {})]
  assert len(images) >= 4, "renders, mask, histogram and curve are drawn"
  assert os.path.exists(NOTEBOOK)
