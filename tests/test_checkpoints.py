"""`mjxvine.rundir.checkpoints`: which checkpoint of a run export/evaluate restore (best or last),
from relative paths, the one-line errors (exit status 2) of a run directory that is not
there, and `Checkpoints` (save, best, restore, a corrupt step) read back as a policy."""

import shutil
from pathlib import Path
from types import SimpleNamespace

import flax.struct
import jax
import jax.numpy as jp
import numpy as np
import orbax.checkpoint as ocp
import pytest

from mjxvine import evaluate, export
from mjxvine.deploy import PolicyError
from mjxvine.evaluation import policies
from mjxvine.rundir import checkpoints as checkpoint
from mjxvine import networks as nw


def _actor(step: int) -> dict:
  """Tiny actor params whose every value is `step`, so a restore tells its step."""
  full = lambda *shape: np.full(shape, float(step), np.float32)
  return {"tower": {"conv0": {"kernel": full(3, 3, 1, 2), "bias": full(2)}},
          "dense0": {"kernel": full(5, 4), "bias": full(4)},
          "mean": {"kernel": full(4, 2), "bias": full(2)}}


def _save(directory, steps) -> None:
  """CheckpointManager steps as `checkpoint.Checkpoints` writes them (item "default")."""
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
  assert checkpoint.checkpoint_item(run) == ckpts / "best" / "4" / "default"
  assert checkpoint.checkpoint_item(run, "last") == ckpts / "5" / "default"
  assert checkpoint.checkpoint_item(ckpts) == ckpts / "best" / "4" / "default"
  assert checkpoint.checkpoint_item(ckpts, "last") == ckpts / "5" / "default"
  # a step dir, an item dir: used as they are
  assert checkpoint.checkpoint_item(ckpts / "3") == ckpts / "3" / "default"
  assert checkpoint.checkpoint_item(ckpts / "3" / "default", "last") == ckpts / "3" / "default"
  # without a best/ subtree, best falls back to the last step
  nobest = runs / "nobest" / "checkpoints"
  assert checkpoint.checkpoint_item(runs / "nobest") == nobest / "3" / "default"
  with pytest.raises(ValueError, match="which='newest'"):
    checkpoint.checkpoint_item(run, "newest")


def test_restore_actor_params_picks_the_step(runs):
  actor, item = checkpoint.restore_actor_params(runs / "run")
  assert _step_of(actor) == 4.0 and item.parent.name == "4"
  actor, _ = checkpoint.restore_actor_params(runs / "run", which="last")
  assert _step_of(actor) == 5.0
  assert set(actor) == {"tower", "dense0", "mean"}
  assert isinstance(actor["dense0"]["kernel"], np.ndarray)


def test_restore_prefers_the_evaluated_actor(tmp_path):
  """A checkpoint with `policy_params` (the evaluated actor, e.g. a Polyak average)
  restores those, not the learning `actor_params`; older ones restore `actor_params`."""
  manager = ocp.CheckpointManager((tmp_path / "checkpoints").resolve(),
                                  options=ocp.CheckpointManagerOptions(create=True))
  manager.save(1, args=ocp.args.StandardSave(
      {"learner": {"actor_params": _actor(1), "policy_params": _actor(7)}}))
  manager.wait_until_finished()
  manager.close()
  assert _step_of(checkpoint.restore_actor_params(tmp_path)[0]) == 7.0


def test_relative_paths(runs, monkeypatch, tmp_path, capsys):
  monkeypatch.chdir(runs)
  item = checkpoint.checkpoint_item("run")
  assert item.is_absolute() and item == runs / "run" / "checkpoints" / "best" / "4" / "default"
  assert _step_of(checkpoint.restore_actor_params("run", "last")[0]) == 5.0
  # evaluate's loader (through mjxvine.evaluation.policies), as `evaluate --policy run`
  assert _step_of(policies.load_actor_params("run", env=None)) == 4.0
  assert policies.check_policy_file("run", "last") == Path("run")
  # the export CLI finds the relative run's checkpoint, and refuses its tiny actor, which
  # is not the one the (default) config builds, in one line naming an array
  out = tmp_path / "policy.npz"
  assert export.main(["--policy", "run", "--which", "last", "--out", str(out)]) == 2
  err = capsys.readouterr().err
  assert "does not fit the config: dense0/bias (4,) (the config's (256,))" in err
  assert len(err.splitlines()) == 1 and not out.exists()


def test_missing_run_directory_is_one_line_with_status_2(runs, monkeypatch, tmp_path, capsys):
  monkeypatch.chdir(runs)
  assert export.main(["--policy", "runs/nope"]) == 2
  err = capsys.readouterr().err
  assert err == "export error: no such run directory: runs/nope\n"
  assert evaluate.main(["--policy", "runs/nope", "--which", "last", "--out", str(tmp_path)]) == 2
  err = capsys.readouterr().err
  assert "no such run directory: runs/nope" in err and len(err.splitlines()) == 1
  with pytest.raises(PolicyError, match="no such run directory"):
    policies.load_actor_params("runs/nope", env=None)
  # a directory without checkpoints says so
  (runs / "empty").mkdir(exist_ok=True)
  assert export.main(["--policy", "empty"]) == 2
  assert "empty: no orbax checkpoint inside" in capsys.readouterr().err
  assert evaluate.main(["--policy", "empty", "--out", str(tmp_path)]) == 2
  assert "no orbax checkpoint" in capsys.readouterr().err


def test_unfinished_steps_are_skipped(runs, tmp_path):
  """orbax writes a step under a temporary name; a step dir without an item is skipped."""
  run = tmp_path / "run"
  shutil.copytree(runs / "nobest", run)
  (run / "checkpoints" / "7.orbax-checkpoint-tmp-1").mkdir()
  (run / "checkpoints" / "9").mkdir()  # no item inside
  assert checkpoint.checkpoint_item(run, "last").parent.name == "3"


# ----------------------------------------------------------------------------------------
# `Checkpoints` (the trainer's writer) read back by the policy loaders, without training.

class _State(flax.struct.PyTreeNode):
  """The parts of a TrainState that `Checkpoints` treats apart."""
  learner: dict
  buffer: jax.Array    # stored only with save_replay
  env_steps: jax.Array
  empty: jax.Array     # zero-size (as in MJX data): never stored, taken from the template


@pytest.fixture(scope="module")
def tiny_actor():
  """(networks, actor params, observation with a batch of 1) of a tiny depth actor."""
  nets = nw.make_networks([0.0, -1.0], [0.5, 1.0], hidden=8, conv_features=2)
  obs = {"depth": jp.full((1, 36, 36, 1), 2.0), "state": jp.zeros((1, 3))}
  return nets, nw.init_params(nets, jax.random.PRNGKey(0), obs)[0], obs


def _state(actor_params, step: int) -> _State:
  return _State(learner={"actor_params": jax.tree.map(lambda x: x * step, actor_params),
                         "log_alpha": jp.float32(step)},
                buffer=jp.full(4, float(step)), env_steps=jp.int32(step), empty=jp.zeros(0))


def test_checkpoints_save_restore_and_load_the_policy(tiny_actor, tmp_path, capsys):
  nets, actor, obs = tiny_actor
  ckpt = checkpoint.Checkpoints(tmp_path, save_replay=False)
  assert ckpt.best_scores() is None and ckpt.restore(_state(actor, 0)) is None
  for step in (1, 2, 3):
    ckpt.save(step, _state(actor, step))
  ckpt.save_best(2, _state(actor, 2), {"eval_mae_m": 0.1})
  assert ckpt.best_scores() == {"chunk": 2, "eval_mae_m": 0.1}
  template = _state(actor, 0)
  for best, want in ((False, 3), (True, 2)):
    step, ts = ckpt.restore(template, best=best)
    assert step == want and int(ts.env_steps) == want and float(ts.learner["log_alpha"]) == want
    assert float(ts.buffer[0]) == 0.0 and ts.empty.shape == (0,)  # the template's
  # the loaders of export/evaluate read the same files: best, then last
  for which, want in (("best", 2), ("last", 3)):
    params, item = checkpoint.restore_actor_params(tmp_path, which)
    assert item == checkpoint.checkpoint_item(tmp_path, which) and item.parent.name == str(want)
    policy = policies.actor_policy(nets, jax.tree.map(jp.asarray, params))
    scaled = jax.tree.map(lambda x: x * want, actor)
    expected = nw.deterministic_action(nets.actor.apply({"params": scaled}, obs)[0],
                                       nets.action_low, nets.action_high)
    np.testing.assert_allclose(policy(SimpleNamespace(obs=obs), None), expected, atol=1e-6)
  # the same closure as brax's Policy: (obs, key) -> (action, extras)
  action, extras = policies.actor_policy(nets, actor, brax=True)(obs, None)
  assert action.shape == (1, 2) and extras == {}
  # a corrupt newest step: restore falls back to the previous one and says so
  for f in (tmp_path / "checkpoints" / "3").rglob("*"):
    if f.is_file() and f.stat().st_size > 0 and "ocdbt" not in f.name:
      f.write_bytes(b"garbage")
  step, _ = checkpoint.Checkpoints(tmp_path, save_replay=False).restore(template)
  err = capsys.readouterr().err
  assert step == 2 and "checkpoint 3 is corrupt or partial" in err
  # ... moved aside, where nothing reads it but a person: "last" is step 2 now
  broken = tmp_path / "checkpoints-broken" / "3"
  assert f"moved to {broken}" in err and not (tmp_path / "checkpoints" / "3").exists()
  assert checkpoint.checkpoint_item(tmp_path, "last").parent.name == "2"
  # ... and the policy loaders name the broken step in one line
  with pytest.raises(ValueError, match="3/default: not a readable orbax checkpoint"):
    checkpoint.restore_actor_params(broken)
  with pytest.raises(PolicyError, match="not a readable orbax checkpoint"):
    policies.load_actor_params(broken, env=None)
  assert export.main(["--policy", str(broken)]) == 2
  err = capsys.readouterr().err
  assert "not a readable orbax checkpoint" in err and len(err.splitlines()) == 1


def test_a_member_of_a_seeds_run(tmp_path):
  """A --num-seeds run saves stacked params: one member is picked, by default the one
  checkpoints/best follows (best.json may name it), and a member it lacks is one line."""
  stacked = jax.tree.map(lambda *x: np.stack(x), _actor(10), _actor(11), _actor(12))
  manager = ocp.CheckpointManager((tmp_path / "checkpoints").resolve(),
                                  options=ocp.CheckpointManagerOptions(create=True))
  manager.save(1, args=ocp.args.StandardSave({"learner": {"actor_params": stacked}}))
  manager.wait_until_finished()
  manager.close()
  assert checkpoint.num_members(stacked) == 3 and checkpoint.num_members(_actor(1)) is None
  assert _step_of(checkpoint.restore_actor_params(tmp_path)[0]) == 10.0  # member 0
  assert _step_of(checkpoint.restore_actor_params(tmp_path, member=2)[0]) == 12.0
  (tmp_path / "best.json").write_text('{"chunk": 1, "member": 1}')
  assert _step_of(checkpoint.restore_actor_params(tmp_path)[0]) == 11.0
  assert checkpoint.restore_actor_params(tmp_path)[0]["mean"]["kernel"].shape == (4, 2)
  with pytest.raises(ValueError, match="member 3: this run trained 3 members"):
    checkpoint.restore_actor_params(tmp_path, member=3)
  with pytest.raises(ValueError, match="member 1: this run trained one member"):
    checkpoint.select_member(_actor(1), 1)


def test_each_member_keeps_its_own_best_policy(tmp_path, tiny_actor):
  """A --num-seeds run writes each member's best actor (by its own evaluations) as a policy
  file; a worse evaluation keeps the file, and the files load with numpy alone."""
  from mjxvine.config import load_config
  from mjxvine.deploy import NumpyPolicy
  from mjxvine.training.hooks import MemberBest

  _, actor, obs = tiny_actor
  cfg = load_config(None, ["camera.width=36", "camera.height=36", "sac.hidden=8",
                           "sac.conv_features=2"])
  stacked = jax.tree.map(lambda x: jp.stack([x, 2 * x]), actor)
  row = lambda f, r, mae: {"eval_success_forward": f, "eval_success_reverse": r,
                           "eval_mae_m": mae}
  best = MemberBest(tmp_path, cfg)
  best.update(1, 100, [row(0.5, 0.5, 0.2), row(0.0, 1.0, 0.1)], stacked)
  best.update(2, 200, [row(0.5, 0.5, 0.1), row(0.0, 0.5, 0.1)], jax.tree.map(
      lambda x: 3 * x, stacked))  # member 0 better (lower MAE), member 1 worse
  scores = MemberBest(tmp_path, cfg).scores  # read back, as a resumed run does
  assert {k: v["chunk"] for k, v in scores.items()} == {"0": 2, "1": 1}
  for k, scale in ((0, 3.0), (1, 2.0)):
    policy = NumpyPolicy.load(tmp_path / "best_members" / f"member{k}.npz")
    assert policy.meta["member"] == k
    with np.load(tmp_path / "best_members" / f"member{k}.npz") as arrays:
      np.testing.assert_allclose(arrays["mean/kernel"],
                                 scale * np.asarray(actor["mean"]["kernel"]), rtol=1e-6)
    action = policy.action(np.asarray(obs["depth"][0, ..., 0]), np.zeros(3))
    assert action.shape == (2,) and np.all(np.isfinite(action))
