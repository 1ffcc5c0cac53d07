"""Bad input to the command lines, as a careless user gives it: each is one line on stderr
naming the flag or file, what was wrong and what is expected, and exit 2 (4 for a write
that fails), before any work; no traceback, nothing written half, no previous file lost."""

import errno
from pathlib import Path

import numpy as np
import pytest

from mjxvine.export import main as export_main
from mjxvine.train import main as train_main
from mjxvine.worlds.__main__ import main as worlds_main

ROOT = Path(__file__).resolve().parent.parent
POLICY = ROOT / "models" / "jackal.npz"


def _one_line(capsys, *words) -> str:
  err = capsys.readouterr().err.strip()
  assert len(err.splitlines()) == 1 and "Traceback" not in err, err
  for word in words:
    assert word in err, err
  return err


@pytest.mark.parametrize("out, words", [
    ("{tmp}", ("--out", "is a directory")),
    ("/proc/no/policy.onnx", ("--out /proc/no/policy.onnx", "cannot write")),
    ("{tmp}/file.txt/policy.onnx", ("--out", "is a file, not a directory")),
])
def test_export_refuses_an_output_it_cannot_write(tmp_path, capsys, out, words):
  (tmp_path / "file.txt").write_text("x")
  code = export_main(["--policy", str(POLICY), "--format", "onnx",
                      "--out", out.format(tmp=tmp_path)])
  assert code == 2
  _one_line(capsys, *words)


def test_export_keeps_the_previous_file_when_the_disk_is_full(tmp_path, capsys, monkeypatch):
  out = tmp_path / "policy.onnx"
  out.write_bytes(b"the previous policy")
  import onnx

  def full_disk(model, path, *a, **k):
    Path(path).write_bytes(b"half a gra")
    raise OSError(errno.ENOSPC, "No space left on device")

  monkeypatch.setattr(onnx, "save", full_disk)
  assert export_main(["--policy", str(POLICY), "--format", "onnx", "--out", str(out)]) == 4
  _one_line(capsys, "could not write", "No space left on device", "unchanged")
  assert out.read_bytes() == b"the previous policy"
  assert [p.name for p in tmp_path.iterdir()] == ["policy.onnx"]  # no temporary left


@pytest.mark.parametrize("make, words", [
    (lambda p: p.with_suffix(".onnx").write_bytes(b"\x08\x07onnx"), ("not an .npz policy file",)),
    (lambda p: p.with_suffix(".txt").write_text("hello"), ("not an .npz policy file",)),
])
def test_export_names_a_file_that_is_not_a_policy(tmp_path, capsys, make, words):
  make(tmp_path / "x")
  path = next(tmp_path.iterdir())
  assert export_main(["--policy", str(path), "--format", "onnx"]) == 2
  _one_line(capsys, str(path), *words)


def test_worlds_refuses_an_output_and_seeds_it_cannot_use(tmp_path, capsys):
  assert worlds_main(["--out", "/proc/mjxvine-world"]) == 2
  _one_line(capsys, "--out /proc/mjxvine-world", "cannot write")
  for seed in ("-5", "99999999999"):
    assert worlds_main(["--out", str(tmp_path / "w"), "--world", seed]) == 2
    _one_line(capsys, f"--world {seed}", "0 to 4294967295")
  assert not (tmp_path / "w" / "world.xml").exists()


def test_train_refuses_a_binary_config_and_an_unwritable_run_dir(tmp_path, capsys):
  config = tmp_path / "config.yaml"
  config.write_bytes(bytes(range(256)) * 4)
  with pytest.raises(SystemExit) as exit_info:
    train_main(["--config", str(config), "--out", str(tmp_path / "run")])
  assert exit_info.value.code == 2
  _one_line(capsys, str(config), "not a text file")
  with pytest.raises(SystemExit) as exit_info:
    train_main(["--config", "experiments/smoke.yaml", "--out", "/proc/mjxvine-run"])
  assert exit_info.value.code == 2
  err = capsys.readouterr().err
  assert "--out /proc/mjxvine-run: cannot write" in err and "Traceback" not in err


def test_a_world_file_that_is_not_one_is_named(tmp_path):
  from mjxvine.worlds import WorldFileError, make_world
  from mjxvine.config import WorldConfig
  bad = tmp_path / "world.json"
  bad.write_text('{"kind": "test"}')
  with pytest.raises(WorldFileError, match=f"{bad}: not a world file.*missing .*lanes"):
    make_world(str(bad), WorldConfig())
  bad.write_text("{not json")
  with pytest.raises(WorldFileError, match=f"{bad}: not a world file \\(not JSON"):
    make_world(str(bad), WorldConfig())
  with pytest.raises(ValueError, match="--world -5: a seed is a whole number from 0 to"):
    make_world("-5", WorldConfig())
  with pytest.raises(FileNotFoundError, match="--world nope.json: world file not found"):
    make_world("nope.json", WorldConfig())


@pytest.mark.parametrize("argv, words", [
    (["--policy", "oracle", "--out", "{file}"], ("--out {file}", "not a directory")),
    (["--policy", "oracle", "--out", "/proc/mjxvine-eval"], ("--out /proc/mjxvine-eval",
                                                             "cannot write")),
    (["--policy", "{onnx}", "--out", "{tmp}/e"], ("{onnx}", "not an .npz policy file")),
    (["--policy", "{missing}", "--out", "{tmp}/e"], ("{missing}", "lacks arrays: dense0/bias")),
    (["--policy", "oracle", "--world", "-5", "--out", "{tmp}/e"], ("--world -5", "0 to")),
    (["--policy", "oracle", "--world", "99999999999", "--out", "{tmp}/e"],
     ("--world 99999999999", "0 to 4294967295")),
    (["--policy", "oracle", "--world", "{badjson}", "--out", "{tmp}/e"],
     ("{badjson}", "not a world file")),
    (["--policy", "oracle", "--world", "{nolanes}", "--out", "{tmp}/e"],
     ("{nolanes}", "missing", "lanes")),
])
def test_evaluate_refuses_bad_input_before_the_first_rollout(tmp_path, capsys, argv, words):
  import json
  from mjxvine.evaluate import main as evaluate_main
  from mjxvine.worlds.store import TEST_WORLD_FILE
  names = {"tmp": tmp_path, "file": tmp_path / "file.txt", "onnx": tmp_path / "p.onnx",
           "missing": tmp_path / "missing.npz", "badjson": tmp_path / "bad.json",
           "nolanes": tmp_path / "nolanes.json"}
  names["file"].write_text("x")
  names["onnx"].write_bytes(b"\x08\x07")
  with np.load(POLICY) as f:
    np.savez(names["missing"], **{k: f[k] for k in f.files if k != "dense0/bias"})
  names["badjson"].write_text('{"kind": ')
  doc = json.loads(TEST_WORLD_FILE.read_text())
  names["nolanes"].write_text(json.dumps({k: v for k, v in doc.items() if k != "lanes"}))
  argv = [a.format(**names) for a in argv]
  assert evaluate_main(argv) == 2
  _one_line(capsys, *(w.format(**names) for w in words))
  assert not (tmp_path / "e" / "results.json").exists()


def test_an_error_is_said_in_its_first_line_whole():
  from mjxvine.formatting import first_line
  assert first_line(ValueError("")) == "ValueError"
  assert first_line(RuntimeError("\n  shapes differ: (64,) vs (48,)\n  at dense0")) == (
      "shapes differ: (64,) vs (48,)")
  long = first_line(ValueError("word " * 200))
  assert long.endswith(" ...") and len(long) <= 404 and "wor ..." not in long

