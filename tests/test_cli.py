"""Every command line of mjxvine, from one list of their parser builders: each long option
is taken by its whole name only (no prefix matching: `--see 3` is refused, not read as
`--seed 3`), every option says what it does, and the old spellings are gone. Parsing
only: nothing runs."""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
from pathlib import Path
from unittest import mock

import pytest

from mjxvine import choose, evaluate, export, latency, train, view
from mjxvine.bench import __main__ as bench
from mjxvine.worlds import __main__ as worlds

ROOT = Path(__file__).resolve().parent.parent

# module -> (its parser builder, the arguments it requires): every command line
COMMANDS = {
    "mjxvine.train": (train.parser, []),
    "mjxvine.evaluate": (evaluate.parser, ["--policy", "oracle", "--out", "out"]),
    "mjxvine.view": (view.parser, ["--policy", "oracle"]),
    "mjxvine.export": (export.parser, ["--policy", "runs/RUN"]),
    "mjxvine.choose": (choose.parser, ["--policy", "runs/RUN"]),
    "mjxvine.select": (lambda: choose.parser("python -m mjxvine.select"),
                       ["--policy", "runs/RUN"]),
    "mjxvine.latency": (latency.parser, ["--policy", "policy.npz"]),
    "mjxvine.worlds": (worlds.parser, ["--out", "out"]),
    "mjxvine.bench": (bench.parser, []),
}


def _subcommands(p: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
  return {name: sub for a in p._actions if isinstance(a, argparse._SubParsersAction)
          for name, sub in a.choices.items()}


def _cases():
  """(name, builder, the arguments before an option, the parser that holds the option):
  each command, and each sub-command of one that has them (bench)."""
  out = []
  for module, (build, required) in COMMANDS.items():
    p = build()
    out.append((module, build, required, p))
    for name, sub in _subcommands(p).items():
      out.append((f"{module} {name}", build, [*required, name], sub))
  return out


CASES = _cases()


def _parse(build, argv: list[str]) -> int | argparse.Namespace:
  """The namespace of `argv`, or the exit status argparse gave it (its messages hidden)."""
  with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
    try:
      return build().parse_args(argv)
    except SystemExit as e:
      return e.code


def _value(action: argparse.Action) -> list[str]:
  """A value the option accepts (none for a flag)."""
  if action.nargs == 0:
    return []
  if action.choices:
    return [str(next(iter(action.choices)))]
  for text in ("1", "64x64", "experiments/smoke.yaml"):
    try:
      (action.type or str)(text)
      return [text]
    except (ValueError, TypeError, argparse.ArgumentTypeError):
      pass
  raise AssertionError(f"{action.option_strings}: no sample value")


def test_every_command_line_is_listed():
  """The list holds every module of the package that runs as `python -m`, and each one's
  `main` parses with the parser its builder makes."""
  found = {}  # command -> the module with its `main`
  for path in (ROOT / "mjxvine").rglob("*.py"):
    if 'if __name__ == "__main__":' in path.read_text():
      module = ".".join(path.relative_to(ROOT).with_suffix("").parts)
      found[module.removesuffix(".__main__")] = module
  assert set(found) == set(COMMANDS)

  class Parsed(Exception):
    pass

  def stop(self, args=None, namespace=None):
    raise Parsed(self)

  for module, (build, required) in COMMANDS.items():
    mod = importlib.import_module(found[module])
    with mock.patch.object(argparse.ArgumentParser, "parse_args", stop):
      with pytest.raises(Parsed) as e:
        mod.main(required)
    used = e.value.args[0]
    assert used.prog == build().prog
    assert sorted(used._option_string_actions) == sorted(build()._option_string_actions)


@pytest.mark.parametrize("name, build, required, p", CASES, ids=[c[0] for c in CASES])
def test_options_are_taken_by_their_whole_name_only(name, build, required, p):
  """Each long option parses by its name, and each shorter prefix that is not an option
  itself is a usage error (exit 2)."""
  options = set(p._option_string_actions)
  checked = 0
  for action in p._actions:
    for flag in (f for f in action.option_strings if f.startswith("--") and len(f) > 3):
      value = _value(action)
      if not isinstance(action, argparse._HelpAction):
        parsed = _parse(build, [*required, flag, *value])
        assert isinstance(parsed, argparse.Namespace), f"{name} {flag}: exit {parsed}"
      for end in range(3, len(flag)):
        prefix = flag[:end]
        if prefix not in options:
          assert _parse(build, [*required, prefix, *value]) == 2, f"{name}: {prefix} taken"
          checked += 1
  assert checked  # --help at least


@pytest.mark.parametrize("name, build, required, p", CASES, ids=[c[0] for c in CASES])
def test_every_option_has_help(name, build, required, p):
  for action in p._actions:
    if action.option_strings and action.help != argparse.SUPPRESS:
      assert action.help and action.help.strip(), f"{name} {action.option_strings}: no help"
    if isinstance(action, argparse._SubParsersAction):
      for choice in action._choices_actions:
        assert choice.help and choice.help.strip(), f"{name} {choice.dest}: no help"


def test_train_seeds():
  """`train --seed N` is train.seed (as --set train.seed=N), `--num-seeds K` the number of
  members; an abbreviation is refused."""
  p = train.parser()
  args = p.parse_args(["--seed", "3", "--num-seeds", "2"])
  assert (args.seed, args.num_seeds) == (3, 2)
  assert _parse(train.parser, ["--see", "3"]) == 2
  assert _parse(train.parser, ["--seeds", "3"]) == 2  # the old name of --num-seeds


def test_train_seed_and_out_make_the_config(tmp_path, capsys):
  p = train.parser()
  out = tmp_path / "run"
  args = p.parse_args(["--config", "experiments/smoke.yaml", "--seed", "3", "--num-seeds",
                       "2", "--out", str(out)])
  cfg, run_dir = train.new_config(p, args)
  assert (cfg.train.seed, cfg.train.num_seeds, run_dir) == (3, 2, out)
  args = p.parse_args(["--config", "experiments/smoke.yaml", "--seed", "3", "--set",
                       "train.seed=5", "--out", str(out)])
  assert train.new_config(p, args)[0].train.seed == 5  # --set has the last word
  (tmp_path / "old").mkdir()
  (tmp_path / "old" / "config.yaml").write_text((ROOT / "experiments" / "smoke.yaml")
                                                .read_text())
  for extra in (["--seed", "1"], ["--num-seeds", "2"], ["--out", str(out)]):
    args = p.parse_args(["--resume", str(tmp_path / "old"), *extra])
    with pytest.raises(SystemExit) as e:
      train.resumed_config(p, args)
    assert e.value.code == 2
  assert "give no --out" in capsys.readouterr().err


@pytest.mark.parametrize("module, argv", [
    ("mjxvine.train", ["--run-dir", "runs/x"]),
    ("mjxvine.export", ["--checkpoint", "runs/RUN"]),
    ("mjxvine.choose", ["runs/RUN"]),
    ("mjxvine.latency", ["policy.npz"]),
    ("mjxvine.worlds", ["--out", "out", "--seed", "3"]),
    ("mjxvine.worlds", ["--out", "out", "--from", "block.geojson"]),
])
def test_old_spellings_are_refused(module, argv):
  assert _parse(COMMANDS[module][0], argv) == 2


def test_the_policy_a_command_reads_is_policy():
  for module in ("mjxvine.evaluate", "mjxvine.view", "mjxvine.export", "mjxvine.choose",
                 "mjxvine.latency", "mjxvine.worlds"):
    assert "--policy" in COMMANDS[module][0]()._option_string_actions, module


def test_which_says_what_best_is():
  for build in (evaluate.parser, view.parser, export.parser):
    text = build()._option_string_actions["--which"].help
    assert "selected.npz" in text and "checkpoints/best" in text


def test_worlds_takes_a_seed_or_a_file_as_world():
  p = worlds.parser()
  assert p.parse_args(["--out", "o"]).world == "0"
  assert p.parse_args(["--out", "o", "--world", "examples/vineyard-block.geojson"]).world \
      == "examples/vineyard-block.geojson"


def test_view_drives_the_robot_it_is_given(monkeypatch):
  """`view --robot` sets robot.name, as `evaluate --robot` does (the env and policy are
  stand-ins here: nothing is built or compiled)."""
  import mjxvine.env
  import mjxvine.evaluation.policies
  made = {}
  monkeypatch.setattr(mjxvine.env, "VineyardEnv",
                      lambda cfg, worlds, noise_factor: made.setdefault("cfg", cfg))
  monkeypatch.setattr(mjxvine.evaluation.policies, "load_policy",
                      lambda *a: (None, "oracle"))
  view.load(view.parser().parse_args(["--policy", "oracle", "--robot", "husky"]))
  assert made["cfg"].robot.name == "husky"


def test_choose_errors_are_one_line(tmp_path, capsys):
  assert choose.main(["--policy", str(tmp_path)]) == 2
  assert capsys.readouterr().err == f"error: --policy {tmp_path}: no config.yaml (not a " \
                                    "run directory)\n"


def test_latency_threads_on_a_policy_file(capsys):
  """`latency --threads 1` with an .npz works on a plain install (threadpoolctl is a
  dependency)."""
  assert latency.main(["--policy", str(ROOT / "models" / "jackal.npz"), "--threads", "1",
                       "--calls", "2"]) == 0
  assert '"median_ms"' in capsys.readouterr().out


def test_bench_says_what_it_will_run(monkeypatch):
  import jax
  assert set(bench.CPU_MINUTES) == set(bench.COMMANDS)
  monkeypatch.setattr(jax, "default_backend", lambda: "cpu")
  line = bench.plan_line("all")
  assert line.startswith(f"bench all on cpu: {len(bench.COMMANDS)} benchmarks") and \
      "hours" in line and "--quick" in line
  assert "minutes" in bench.plan_line("all", quick=True)
  for name in bench.COMMANDS:
    assert bench.plan_line(name).startswith(f"bench {name} on cpu: ")
  monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
  assert bench.plan_line("depth") is None and "no time estimate" in bench.plan_line("all")


def test_bench_update_conv_impls():
  p = _subcommands(bench.parser())["update"]
  assert p._option_string_actions["--conv-impl"].choices == ("xla", "shift", "native")
