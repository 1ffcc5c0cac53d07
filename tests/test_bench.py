"""Smoke test of the benchmarks: `python -m mjxvine.bench all --quick` runs every
sub-command at small sizes and writes one JSON with rows for each. Marked slow: on the
2-core CPU it takes minutes, mostly XLA compilation (CI runs it with `-m slow`)."""

import json

import pytest

from mjxvine import bench


@pytest.mark.slow
def test_bench_all_quick_writes_rows_for_every_subcommand(tmp_path):
  out = tmp_path / "bench.json"
  assert bench.main(["all", "--quick", "--out", str(out)]) == 0
  doc = json.loads(out.read_text())
  assert doc["environment"]["backend"]
  for name in bench.COMMANDS:
    assert doc[name]["benchmark"] == name
    rows = doc[name]["rows"]
    assert rows and all(isinstance(r, dict) and r for r in rows), name
