"""experiments/sweep.ipynb runs top to bottom (nbclient) on a tiny setting: 2 learning
rates x 2 seeds trained at once, learning curves drawn, the final table printed."""

from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # minutes on 2 cores: `pytest -m slow` (CI runs it)

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

ROOT = Path(__file__).resolve().parent.parent
TINY = """CONFIG = "experiments/smoke.yaml"
OVERRIDES = ["camera.width=36", "camera.height=36", "env.num_envs=2", "env.max_steps=20",
             "sac.batch_size=16", "sac.buffer_size=256", "sac.warmup_steps=20",
             "sac.hidden=16", "sac.conv_features=4", "train.iters_per_chunk=10",
             "world.pool_size=1", "world.train_length_m=6", "train.total_env_steps=80"]
SEEDS = 2
LEARNING_RATES = [1e-3, 3e-3]
RUN_DIR = {run_dir!r}
"""


def test_sweep_notebook_runs_top_to_bottom(tmp_path):
  nb = nbformat.read(ROOT / "experiments" / "sweep.ipynb", as_version=4)
  params = [c for c in nb.cells if "parameters" in c.metadata.get("tags", [])]
  assert len(params) == 1
  params[0].source = TINY.format(run_dir=str(tmp_path / "sweep"))
  nbclient.NotebookClient(nb, timeout=900, kernel_name="python3",
                          resources={"metadata": {"path": str(ROOT)}}).execute()
  outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
  assert any("image/png" in o.get("data", {}) for o in outputs)  # the learning curves
  text = "".join(o.get("text", "") for o in outputs if o.get("output_type") == "stream")
  assert "4 members trained at once" in text
  table = [l for l in text.splitlines() if l.startswith("| 0.00")]
  assert len(table) == 2 and all("| 2 |" in l for l in table)
  rows = (tmp_path / "sweep" / "metrics.jsonl").read_text().splitlines()
  assert len(rows) == 4 * 4  # 4 members x 4 chunks
