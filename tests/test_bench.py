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


def test_env_against_a_config_is_a_usage_error_when_bad(tmp_path, capsys):
  """`bench env --against` takes a valid config file, and not with `--block`."""
  bad = tmp_path / "bad.yaml"
  bad.write_text("sensor:\n  preset: d999\n")
  for argv in (["env", "--against", str(tmp_path / "none.yaml")], ["env", "--against", str(bad)],
               ["env", "--against", "experiments/jackal.yaml", "--block", "2x10"]):
    with pytest.raises(SystemExit) as e:
      main(argv)
    assert e.value.code == 2, argv
  err = capsys.readouterr().err
  assert "config file not found" in err and "sensor.preset" in err
  assert "not allowed with argument" in err


@pytest.mark.slow  # two env steps to compile
def test_env_against_times_both_configs_in_turn(tmp_path):
  """A tiny `bench env --against`: a row per config, named by its hash, the second (the
  --config's) with its time over the first's."""
  from mjxvine.config import config_hash, load_config
  base = tmp_path / "base.yaml"
  base.write_text("camera:\n  width: 8\n  height: 6\n")
  out = tmp_path / "against.json"
  assert main(["env", "--set", "camera.width=8", "--set", "camera.height=6", "--set",
               "sensor.preset=d435", "--sizes", "2", "--steps", "2", "--rounds", "3",
               "--against", str(base), "--out", str(out)]) == 0
  doc = json.loads(out.read_text())
  first, second = doc["rows"]
  assert first["config"] == doc["against"] == config_hash(load_config(str(base)))
  assert second["config"] == doc["config_hash"] != first["config"]
  assert first["ratio"] == 1.0 and second["ratio"] > 0
  assert doc["ratio"] == {"2": second["ratio"]}


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
