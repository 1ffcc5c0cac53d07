"""experiments/sweep.ipynb runs top to bottom (nbclient) as it is shipped, its own
parameters cell unchanged, in an empty folder (its CONFIG, `experiments/default.yaml`, is
then the packaged copy): every member trained at once, the learning curves drawn, the
final table printed with one row per learning rate."""

import math
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # minutes on 2 cores: `pytest -m slow` (CI runs it)

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

ROOT = Path(__file__).resolve().parent.parent


def test_sweep_notebook_runs_as_shipped(tmp_path):
  from mjxvine.config import load_config
  nb = nbformat.read(ROOT / "experiments" / "sweep.ipynb", as_version=4)
  params = [c for c in nb.cells if "parameters" in c.metadata.get("tags", [])]
  assert len(params) == 1
  p = {}
  exec(params[0].source, p)  # the values the notebook runs with, to check its output
  nbclient.NotebookClient(nb, timeout=900, kernel_name="python3",
                          resources={"metadata": {"path": str(tmp_path)}}).execute()
  outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
  assert any("image/png" in o.get("data", {}) for o in outputs)  # the learning curves
  text = "".join(o.get("text", "") for o in outputs if o.get("output_type") == "stream")
  members = p["SEEDS"] * len(p["LEARNING_RATES"])
  assert f"{members} members trained at once" in text
  for lr in p["LEARNING_RATES"]:
    assert any(l.startswith(f"| {lr:g} | {p['SEEDS']} |") for l in text.splitlines()), lr
  cfg = load_config(p["CONFIG"], p["OVERRIDES"])
  chunks = math.ceil(cfg.train.total_env_steps / (cfg.env.num_envs * cfg.train.iters_per_chunk))
  rows = (tmp_path / p["RUN_DIR"] / "metrics.jsonl").read_text().splitlines()
  assert len(rows) == members * chunks
