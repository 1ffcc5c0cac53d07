"""No config, YAML file or flag can exhaust the machine or mean something other than it says:
YAML read with a size and depth limit and without aliases, its scalars as YAML 1.2 reads
them, errors that quote a short prefix on one line, a run refused before compilation when
it cannot fit in memory, flags range-checked as the keys they stand for, repeated --sweep
values combined, ignored flags refused, and no robot file named by a policy file's
metadata. Nothing here trains or compiles."""

import json
import time
from pathlib import Path

import numpy as np
import pytest

from mjxvine import evaluate, export, latency, train, view
from mjxvine.config import ConfigError, load_config, read_yaml
from mjxvine.robot_files import (MAX_YAML_BYTES, MAX_YAML_DEPTH, RobotFileError,
                                 read_robot_file, short_repr)
from mjxvine.rundir.settings import policy_config
from mjxvine.training import loop
from mjxvine.training.iteration import sweep_members
from mjxvine.worlds.__main__ import main as worlds_main

ROOT = Path(__file__).resolve().parent.parent
POLICY = ROOT / "models" / "jackal.npz"
ROBOT = ROOT / "mjxvine" / "worlds" / "data" / "robots" / "jackal.yaml"

# 9 levels of 9 aliases each: 9^9 (387 million) leaves from 300 bytes, as YAML 1.1 expands it
BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{c}: &{c} [*{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}]\n"
    for p, c in zip("abcdefgh", "bcdefghi"))


def _error(call, *args, error=ConfigError, **kwargs) -> str:
  """The message of the one-line `error` that call(*args) raises."""
  with pytest.raises(error) as e:
    call(*args, **kwargs)
  message = str(e.value)
  assert "\n" not in message and "\x1b" not in message and len(message) < 600, message
  return message


def _exit_2(capsys, main, argv: list[str], *words: str) -> str:
  """main(argv) exits with status 2 (argparse's or its own), saying `words` in one line."""
  try:
    code = main(argv)
  except SystemExit as e:
    code = e.code
  assert code == 2
  err = capsys.readouterr().err
  last = err.strip().splitlines()[-1]  # argparse puts its usage lines first
  for word in words:
    assert word in last, err
  return last


def test_an_alias_bomb_is_refused_fast_wherever_yaml_is_read(tmp_path):
  config = tmp_path / "bomb.yaml"
  config.write_text(BOMB)
  robot = tmp_path / "bomb_robot.yaml"
  robot.write_text(BOMB)
  t = time.time()
  assert "anchors and aliases" in _error(load_config, config)
  assert "anchors and aliases" in _error(load_config, None, [f"robot.name={robot}"])
  assert "anchors and aliases" in _error(read_robot_file, robot, error=RobotFileError)
  assert "anchors and aliases" in _error(load_config, None, ["world.inter_row_m=[&a 2, *a]"])
  assert time.time() - t < 5


def test_size_and_depth_limits(tmp_path):
  big = tmp_path / "big.yaml"
  big.write_text("# padding\n" * (MAX_YAML_BYTES // 10 + 1) + "{}\n")
  assert "larger than 1 MiB" in _error(read_yaml, big)
  deep = tmp_path / "deep.yaml"
  deep.write_text("world: " + "[" * (MAX_YAML_DEPTH + 5) + "]" * (MAX_YAML_DEPTH + 5) + "\n")
  assert f"nested deeper than {MAX_YAML_DEPTH} levels" in _error(read_yaml, deep)
  shallow = tmp_path / "shallow.yaml"  # what a config needs passes
  shallow.write_text("world: {inter_row_m: [1.6, 2.0]}\n")
  assert load_config(shallow).world.inter_row_m == (1.6, 2.0)


def test_errors_quote_a_short_prefix_on_one_line(tmp_path):
  huge = tmp_path / "huge.yaml"
  huge.write_text("world: {train_rows: [" + ", ".join(["12345"] * 20_000) + "]}\n")
  assert "world.train_rows = [12345, 12345, 12345, 12345, ...]" in _error(load_config, huge)
  # control characters (a newline, an ANSI colour) are escaped, long values cut
  message = _error(load_config, None, ["robot.name=\x1b[31mred\nline" + "x" * 10_000])
  assert "\\x1b[31mred\\nline" in message
  message = _error(load_config, None, ["world.no\nsuch=1"])
  assert "world.no\\nsuch: unknown key" in message
  assert short_repr("y" * 10**6, 60) == "'" + "y" * 56 + "..."
  assert len(short_repr({"k": [list(range(10**4))] * 10**3})) <= 60
  robot = tmp_path / "r.yaml"
  robot.write_text(ROBOT.read_text().replace("height_m: 0.26", 'height_m: "\\e[2J' + "9" * 5000
                                             + '"'))  # YAML's escape of ESC
  message = _error(read_robot_file, robot, error=RobotFileError)
  assert "camera.height_m = '\\x1b[2J999" in message


def test_scalars_read_as_yaml_1_2(tmp_path):
  """Decimal integers whatever their leading zeros; no sexagesimal numbers, no yes/no."""
  assert load_config(None, ["train.seed=010"]).train.seed == 10
  assert load_config(None, ["train.seed=0o10"]).train.seed == 8  # octal said as such
  config = tmp_path / "c.yaml"
  config.write_text("train: {seed: 010}\neval: {noise_factor: 1e1}\n")
  cfg = load_config(config)
  assert (cfg.train.seed, cfg.eval.noise_factor) == (10, 10.0)
  assert "expected a number" in _error(load_config, None, ["eval.noise_factor=1:30"])
  config.write_text("eval: {noise_factor: 1:30}\n")
  assert "eval.noise_factor = '1:30': expected a number" in _error(load_config, config)
  assert "expected true or false" in _error(load_config, None, ["train.video=yes"])
  robot = tmp_path / "r.yaml"
  robot.write_text(ROBOT.read_text() + "\n" + "velocity: {v_max_mps: 0:30}\n")
  assert "velocity.v_max_mps = '0:30': expected a number" in _error(
      read_robot_file, robot, error=RobotFileError)
  robot.write_text(ROBOT.read_text().replace("pitch_deg: 0.0", "pitch_deg: 010"))
  assert read_robot_file(robot).camera_pitch_deg == 10.0


def test_a_run_that_cannot_fit_is_refused_before_compilation(tmp_path, capsys, monkeypatch):
  """2^20 envs and a 2^26 replay: refused in one line naming the keys, before the run
  directory is made; the shipped CPU config fits a 4 GiB machine."""
  config = tmp_path / "huge.yaml"
  config.write_text("env: {num_envs: 1048576}\nsac: {buffer_size: 67108864}\n")
  out = tmp_path / "run"
  t = time.time()
  line = _exit_2(capsys, train.main, ["--config", str(config), "--out", str(out)],
                 "config error: the run needs about", "sac.buffer_size 67108864",
                 "env.num_envs 1048576", "train.num_seeds")
  assert time.time() - t < 20 and not out.exists(), line
  monkeypatch.setattr(loop, "available_memory", lambda: (4 << 30, "a 4 GiB machine"))
  loop.check_memory(load_config("cpu.yaml"))
  assert "a 4 GiB machine is 4,096 MiB" in _error(
      loop.check_memory, load_config("cpu.yaml", ["train.num_seeds=64"]))
  monkeypatch.setenv("MJXVINE_MEMORY_CHECK", "0")
  loop.check_memory(load_config("cpu.yaml", ["train.num_seeds=64"]))


def test_the_estimate_is_the_replay_the_run_allocates():
  cfg = load_config("smoke.yaml")
  parts = loop.memory_estimate(cfg, 3)
  # smoke: 4096 transitions of a 40 x 40 uint16 frame, their side ring, actions, flags
  assert 3 * 4096 * 40 * 40 * 2 < parts["replay"] < 3 * 4096 * 40 * 40 * 2 * 1.1


@pytest.mark.parametrize("main, argv, words", [
    (evaluate.main, ["--policy", "oracle", "--out", "{tmp}", "--runs", "1000000"],
     ("--runs", "eval.runs = 1000000: must be in [1, 1000]")),
    (evaluate.main, ["--policy", "oracle", "--out", "{tmp}", "--noise", "inf"],
     ("--noise", "expected a finite number")),
    (evaluate.main, ["--policy", "oracle", "--out", "{tmp}", "--noise", "nan"],
     ("--noise", "expected a finite number")),
    (evaluate.main, ["--policy", "oracle", "--out", "{tmp}", "--noise", "101"],
     ("--noise", "must be in [0.0, 100.0]")),
    (evaluate.main, ["--policy", "oracle", "--out", "{tmp}", "--member", "-1"],
     ("--member", "must be in [0, 1023]")),
    (evaluate.main, ["--policy", str(POLICY), "--out", "{tmp}", "--member", "99"],
     ("--member 99: a policy file holds one policy",)),
    (evaluate.main, ["--policy", "random", "--out", "{tmp}", "--member", "1"],
     ("--member 1: the random policy has no members",)),
    (view.main, ["--policy", "oracle", "--noise", "inf"], ("--noise", "finite")),
    (view.main, ["--policy", str(POLICY), "--member", "2"], ("--member", "policy file")),
    (train.main, ["--num-seeds", "0"], ("--num-seeds", "must be in [1, 1024]")),
    (train.main, ["--num-seeds", "-2"], ("--num-seeds", "must be in [1, 1024]")),
    (train.main, ["--seed", "-1"], ("--seed", "train.seed = -1")),
    (latency.main, ["--policy", str(POLICY), "--calls", "0"], ("--calls", "[1, 1000000]")),
    (latency.main, ["--policy", str(POLICY), "--calls", "10000000000"], ("--calls", "[1, ")),
    (latency.main, ["--policy", str(POLICY), "--threads", "0"], ("--threads", "[1, 256]")),
    (latency.main, ["--policy", str(POLICY), "--threads", "100000"], ("--threads", "[1, 256]")),
    (worlds_main, ["--out", "{tmp}", "--depth-at", "1e300,0,0"],
     ("--depth-at: (1e+300, 0) is off the world's terrain",)),
    (worlds_main, ["--out", "{tmp}", "--depth-at", "2,0,nan"], ("expected X,Y,YAW",)),
    (worlds_main, ["--out", "{tmp}", "--depth-at", "2,0,1e300"], ("expected X,Y,YAW",)),
    (export.main, ["--policy", str(POLICY), "--format", "onnx", "--config", "cpu.yaml",
                   "--out", "{tmp}/p.onnx"], ("--config/--set",)),
    (export.main, ["--policy", str(POLICY), "--format", "onnx", "--set", "sac.hidden=8",
                   "--out", "{tmp}/p.onnx"], ("--config/--set",)),
    (export.main, ["--policy", str(POLICY), "--format", "onnx", "--member", "1",
                   "--out", "{tmp}/p.onnx"], ("--member 1",)),
    (export.main, ["--policy", str(POLICY), "--format", "onnx", "--which", "last",
                   "--out", "{tmp}/p.onnx"], ("--which last",)),
])
def test_flags_are_range_checked_and_ignored_ones_refused(tmp_path, capsys, monkeypatch, main,
                                                          argv, words):
  monkeypatch.setenv("DISPLAY", ":0")  # view checks its flags before it opens a window
  _exit_2(capsys, main, [a.format(tmp=tmp_path) for a in argv], *words)
  assert not (tmp_path / "p.onnx").exists() and not (tmp_path / "results.json").exists()


def test_flags_take_what_their_keys_take():
  p = evaluate.parser()
  args = p.parse_args(["--policy", "oracle", "--out", "x", "--runs", "010", "--noise", "0"])
  assert (args.runs, args.noise) == (10, 0.0)
  args = train.parser().parse_args(["--num-seeds", "1024", "--seed", "7"])
  assert (args.num_seeds, args.seed) == (1024, 7)


def test_repeated_sweeps_of_a_key_combine_and_keys_make_a_grid(tmp_path):
  def members(*flags):
    p = train.parser()
    args = p.parse_args(["--config", "smoke.yaml", "--out", str(tmp_path / "run"), *flags])
    return sweep_members(train.new_config(p, args)[0])

  assert len(members("--sweep", "sac.alpha=0.1", "--sweep", "sac.alpha=0.2")) == 2
  assert len(members("--sweep", "sac.alpha=0.1,0.2", "--sweep", "sac.alpha=0.2,0.3")) == 3
  grid = members("--sweep", "sac.learning_rate=1e-4,1e-3", "--sweep", "sac.alpha=0.1",
                 "--sweep", "sac.alpha=0.2", "--num-seeds", "2")
  assert len(grid) == 8
  assert {(m["sac.learning_rate"], m["sac.alpha"]) for m in grid} == {
      (lr, a) for lr in (1e-4, 1e-3) for a in (0.1, 0.2)}
  assert "at most 1024 train at once" in _error(load_config, None, [
      "train.num_seeds=2", "train.sweep=sac.alpha=" + ",".join(
          str(0.001 * (i + 1)) for i in range(513))])


def _policy_naming(tmp_path: Path, name: str) -> Path:
  """models/jackal.npz with its recorded config's robot.name set to `name`."""
  with np.load(POLICY) as f:
    arrays = {k: f[k] for k in f.files}
  meta = json.loads(str(arrays["__meta__"]))
  meta["config"]["robot"]["name"] = name
  arrays["__meta__"] = np.array(json.dumps(meta))
  path = tmp_path / f"named-{Path(name).stem}.npz"
  np.savez(path, **arrays)
  return path


def test_a_policy_file_names_only_a_built_in_robot(tmp_path, capsys):
  local = tmp_path / "secret.yaml"  # a robot file on this machine, never to be read
  local.write_text(ROBOT.read_text().replace("name: jackal", "name: secret"))
  policy = _policy_naming(tmp_path, str(local))
  message = _error(policy_config, policy)
  assert "a policy file may name only a built-in robot (husky, jackal)" in message
  assert "--robot FILE.yaml" in message
  # the user naming a robot, a file too, is their choice
  assert policy_config(policy, None, ["robot.name=husky"])[0].robot.name == "husky"
  assert policy_config(policy, None, [f"robot.name={local}"])[0].robot.spec.name == "secret"
  assert policy_config(_policy_naming(tmp_path, "husky"))[0].robot.name == "husky"
  line = _exit_2(capsys, evaluate.main, ["--policy", str(policy), "--out", str(tmp_path / "e")],
                 "config error: robot.name")
  assert "name: secret" not in line


def test_an_accelerator_is_judged_by_its_own_memory(monkeypatch):
  """On a GPU the figure is its allocator's limit less what is in use (JAX's
  memory_stats), not the host's; without statistics there is no check."""
  class Device:
    platform, device_kind = "gpu", "Test GPU"
    stats = {"bytes_limit": 2 << 30, "bytes_in_use": 1 << 30}

    def memory_stats(self):
      return self.stats

  monkeypatch.setattr(loop.jax, "local_devices", lambda: [Device()])
  assert loop.available_memory() == (1 << 30, "the Test GPU's memory")
  loop.check_memory(load_config("smoke.yaml"))
  assert "the Test GPU's memory is 1,024 MiB" in _error(loop.check_memory,
                                                       load_config("paper.yaml"))
  Device.stats = None
  assert loop.available_memory() is None
  loop.check_memory(load_config("paper.yaml"))
