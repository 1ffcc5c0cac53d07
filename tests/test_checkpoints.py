"""Which checkpoint of a run export/evaluate restore (best or last), from relative paths,
and the one-line errors (exit status 2) of a run directory that is not there."""

import shutil
from pathlib import Path

import numpy as np
import orbax.checkpoint as ocp
import pytest

from mjxvine import evaluate, export, policies


def _actor(step: int) -> dict:
  """Tiny actor params whose every value is `step`, so a restore tells its step."""
  full = lambda *shape: np.full(shape, float(step), np.float32)
  return {"tower": {"conv0": {"kernel": full(3, 3, 1, 2), "bias": full(2)}},
          "dense0": {"kernel": full(5, 4), "bias": full(4)},
          "mean": {"kernel": full(4, 2), "bias": full(2)}}


def _save(directory, steps) -> None:
  """CheckpointManager steps as `mjxvine.train.Checkpoints` writes them (item "default")."""
  manager = ocp.CheckpointManager(directory.resolve(),
                                  options=ocp.CheckpointManagerOptions(create=True))
  for step in steps:
    manager.save(step, args=ocp.args.StandardSave(
        {"learner": {"actor_params": _actor(step), "log_alpha": np.float32(0.0)}}))
  manager.wait_until_finished()
  manager.close()


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
  """runs/run: regular steps 3 and 5, best step 4; runs/nobest: step 3 only."""
  root = tmp_path_factory.mktemp("runs")
  _save(root / "run" / "checkpoints", (3, 5))
  _save(root / "run" / "checkpoints" / "best", (4,))
  _save(root / "nobest" / "checkpoints", (3,))
  return root


def _step_of(actor) -> float:
  return float(np.asarray(actor["mean"]["bias"])[0])


def test_checkpoint_item_best_and_last(runs):
  run, ckpts = runs / "run", runs / "run" / "checkpoints"
  assert export.checkpoint_item(run) == ckpts / "best" / "4" / "default"
  assert export.checkpoint_item(run, "last") == ckpts / "5" / "default"
  assert export.checkpoint_item(ckpts) == ckpts / "best" / "4" / "default"
  assert export.checkpoint_item(ckpts, "last") == ckpts / "5" / "default"
  # a step dir, an item dir: used as they are
  assert export.checkpoint_item(ckpts / "3") == ckpts / "3" / "default"
  assert export.checkpoint_item(ckpts / "3" / "default", "last") == ckpts / "3" / "default"
  # without a best/ subtree, best falls back to the last step
  nobest = runs / "nobest" / "checkpoints"
  assert export.checkpoint_item(runs / "nobest") == nobest / "3" / "default"
  with pytest.raises(ValueError, match="which='newest'"):
    export.checkpoint_item(run, "newest")


def test_load_actor_params_picks_the_step(runs):
  actor, item = export.load_actor_params(runs / "run")
  assert _step_of(actor) == 4.0 and item.parent.name == "4"
  actor, _ = export.load_actor_params(runs / "run", which="last")
  assert _step_of(actor) == 5.0
  assert set(actor) == {"tower", "dense0", "mean"}
  assert isinstance(actor["dense0"]["kernel"], np.ndarray)


def test_relative_paths(runs, monkeypatch, tmp_path, capsys):
  monkeypatch.chdir(runs)
  item = export.checkpoint_item("run")
  assert item.is_absolute() and item == runs / "run" / "checkpoints" / "best" / "4" / "default"
  assert _step_of(export.load_actor_params("run", "last")[0]) == 5.0
  # evaluate's loader (through mjxvine.policies), as `evaluate --policy run`
  assert _step_of(policies.load_actor_params("run", env=None)) == 4.0
  assert evaluate.check_policy_file("run", "last") == Path("run")
  # the export CLI: relative run dir and relative output
  out = tmp_path / "policy.npz"
  assert export.main(["--checkpoint", "run", "--which", "last", "--out", str(out)]) == 0
  with np.load(out) as f:
    assert float(f["mean/bias"][0]) == 5.0
  assert "checkpoints/5/default" in capsys.readouterr().err


def test_missing_run_directory_is_one_line_with_status_2(runs, monkeypatch, tmp_path, capsys):
  monkeypatch.chdir(runs)
  assert export.main(["--checkpoint", "runs/nope"]) == 2
  err = capsys.readouterr().err
  assert err == "export error: no such run directory: runs/nope\n"
  assert evaluate.main(["--policy", "runs/nope", "--which", "last", "--out", str(tmp_path)]) == 2
  err = capsys.readouterr().err
  assert "no such run directory: runs/nope" in err and len(err.splitlines()) == 1
  with pytest.raises(evaluate.PolicyError, match="no such run directory"):
    policies.load_actor_params("runs/nope", env=None)
  # a directory without checkpoints says so
  (runs / "empty").mkdir(exist_ok=True)
  assert export.main(["--checkpoint", "empty"]) == 2
  assert "empty: no orbax checkpoint inside" in capsys.readouterr().err
  assert evaluate.main(["--policy", "empty", "--out", str(tmp_path)]) == 2
  assert "no orbax checkpoint" in capsys.readouterr().err


def test_unfinished_steps_are_skipped(runs, tmp_path):
  """orbax writes a step under a temporary name; a step dir without an item is skipped."""
  run = tmp_path / "run"
  shutil.copytree(runs / "nobest", run)
  (run / "checkpoints" / "7.orbax-checkpoint-tmp-1").mkdir()
  (run / "checkpoints" / "9").mkdir()  # no item inside
  assert export.checkpoint_item(run, "last").parent.name == "3"
