"""docs/results/default-seeds.md: its table of the default run's seeds is what
`scripts/seed_table.py` prints from the records in docs/results/default-seeds/ (each
NAME-config.yaml, NAME-metrics.jsonl and NAME-record.json), every record there is in it, and the script scores a run as the trainer keeps its best
checkpoint."""

import importlib.util
import json

from test_docs import ROOT

PAGE = ROOT / "docs" / "results" / "default-seeds.md"


def _script():
  spec = importlib.util.spec_from_file_location("seed_table", ROOT / "scripts" / "seed_table.py")
  mod = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(mod)
  return mod


def test_every_table_is_printed_from_its_records():
  mod = _script()
  found = list(mod.marked_tables(PAGE))
  assert found, f"{PAGE.name}: no <!-- seed table: ... --> marker"
  shown = set()
  for _, every, runs, rows in found:
    shown.update(run.name for run in runs)
    want = mod.table(runs, every).splitlines()
    assert rows == want, (f"{PAGE.name}: a table differs from its records; rewrite it with "
                          f"`python scripts/seed_table.py --write {PAGE.relative_to(ROOT)}`")
  records = PAGE.with_suffix("")
  assert shown == {p.name for p in mod.records_in(records)}  # every record shown
  assert len(shown) * len(mod.FILES) == sum(1 for _ in records.iterdir())  # and nothing else


def test_the_best_evaluation_is_the_trainers(tmp_path):
  """The script's best per seed is the weaker direction's success, then the lower MAE,
  over the evaluations it keeps (`--every`)."""
  mod = _script()
  rows = [{"seed": 3, "chunk": 2, "eval_success_forward": 0.9, "eval_success_reverse": 0.5,
           "eval_mae_m": 0.1},
          {"seed": 3, "chunk": 3, "eval_success_forward": 0.6, "eval_success_reverse": 0.7,
           "eval_mae_m": 0.1},
          {"seed": 3, "chunk": 4, "eval_success_forward": 0.6, "eval_success_reverse": 0.6,
           "eval_mae_m": 0.2},
          {"seed": 3, "chunk": 5, "eval_success_forward": None}]
  (tmp_path / "run-metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
  run = tmp_path / "run"
  assert mod.best_per_seed(run)[3]["chunk"] == 3  # 0.6 beats 0.5; then the lower MAE
  assert mod.best_per_seed(run, every=2)[3]["chunk"] == 4  # chunks 2 and 4 only


def test_the_answer_is_the_records():
  """The page's answer, "on all 20 runs and members tried: 94-100 %", is its records'."""
  mod = _script()
  weaker = [mod.weaker(row) for run in mod.records_in(PAGE.with_suffix(""))
            for row in mod.best_per_seed(run).values()]
  text = " ".join(PAGE.read_text().split())
  assert all(w >= mod.TARGET for w in weaker)
  assert (f"on all {len(weaker)} runs and members tried: "
          f"{100 * min(weaker):.0f}-{100 * max(weaker):.0f} %") in text
