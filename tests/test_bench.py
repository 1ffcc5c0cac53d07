"""The benchmarks' command line (`mjxvine.bench.__main__`): every sub-command parses its
flags, bad values are usage errors; and a smoke run: `python -m mjxvine.bench all
--quick` runs every sub-command at small sizes and writes one JSON with rows for each.
The smoke run is marked slow: on the 2-core CPU it takes minutes, mostly XLA compilation
(CI runs it with `-m slow`)."""

import json

import pytest

from mjxvine.bench.__main__ import COMMANDS, main
from mjxvine.bench.brax_envs import brax_summary


@pytest.mark.parametrize("name", [*COMMANDS, "all"])
def test_every_subcommand_has_help(name, capsys):
  with pytest.raises(SystemExit) as e:
    main([name, "--help"])
  assert e.value.code == 0
  assert "--out" in capsys.readouterr().out


@pytest.mark.parametrize("argv", [["depth", "--sizes", "112"], ["depth", "--batches", "1,0"],
                                  ["physics", "--steps", "x"], ["brax", "--pool", "8x"]])
def test_bad_values_are_usage_errors(argv, capsys):
  with pytest.raises(SystemExit) as e:
    main(argv)
  assert e.value.code == 2
  assert "expected" in capsys.readouterr().err


def test_brax_summary_ratios():
  rows = [dict(learner="brax.sac", env_steps=100, train_s=10.0, success=0.2),
          dict(learner="brax.sac", env_steps=200, train_s=20.0, success=0.6),
          dict(learner="mjxvine.sac", env_steps=100, train_s=5.0, success=0.7)]
  s = brax_summary(rows, 0.5)
  assert s["brax.sac"] == dict(env_steps=200, train_s=20.0)
  assert s["wall_clock_ratio"] == 4.0 and s["env_steps_ratio"] == 2.0
  assert brax_summary(rows, 0.9) == {"brax.sac": None, "mjxvine.sac": None}


@pytest.mark.slow
def test_bench_all_quick_writes_rows_for_every_subcommand(tmp_path):
  out = tmp_path / "bench.json"
  assert main(["all", "--quick", "--out", str(out)]) == 0
  doc = json.loads(out.read_text())
  assert doc["environment"]["backend"]
  for name in COMMANDS:
    assert doc[name]["benchmark"] == name
    rows = doc[name]["rows"]
    assert rows and all(isinstance(r, dict) and r for r in rows), name
