"""Training runs end to end on a tiny config: logs, checkpoints, resume (also after a
corrupt checkpoint), non-finite detection. The jitted trainer is compiled once (cached
per process on the config)."""

import json
import shutil
import time

import jax
import jax.numpy as jp
import numpy as np
import pytest

from mjxvine import train as train_mod
from mjxvine.training import loop
from mjxvine.training import programs
from mjxvine import rundir
from mjxvine.training import iteration as trainer
from mjxvine.rundir.checkpoints import Checkpoints
from mjxvine.config import load_config
from mjxvine.networks import describe_conv_impl, learner_conv_impl, resolve_conv_impl

OVERRIDES = ["camera.width=36", "camera.height=36", "env.num_envs=2", "env.max_steps=30",
             "sac.batch_size=16", "sac.buffer_size=512", "sac.warmup_steps=40",
             "sac.hidden=16", "sac.conv_features=4", "train.iters_per_chunk=10",
             "train.checkpoint_every_chunks=1", "world.pool_size=1",
             "world.train_length_m=6", "eval.runs_after_train=0"]


def _cfg(steps, *extra):
  return load_config("experiments/smoke.yaml",
                     OVERRIDES + [f"train.total_env_steps={steps}", *extra])


# The first run also evaluates from 2 + 2 fresh starts every 2 chunks (best checkpoint),
# keeping each evaluated policy.
EVAL = ("train.eval_every_chunks=2", "train.eval_starts=2", "train.keep_eval_policies=true")


WALL_S = {}  # the first run's wall-clock, as its caller measured it


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
  run = tmp_path_factory.mktemp("run")
  t0 = time.perf_counter()
  row = loop.train(_cfg(80, *EVAL), run, quiet=True, evaluate_at_end=False)
  WALL_S["first_run"] = time.perf_counter() - t0
  return run, row


def test_the_profile_by_phase_adds_up_to_the_wall_clock(first_run):
  """run.json and the last row keep the time by phase; the phases, each measured on its
  own, add up to the wall-clock of the call within 5 %."""
  run, row = first_run
  profile = row["profile"]
  assert json.loads((run / "run.json").read_text())["profile"] == profile
  phases = profile["phases_s"]
  for name in ("setup", "collection", "gradient_steps", "fresh_start_evaluations", "logs",
               "checkpoints"):
    assert phases[name] > 0, name
  if not trainer.scan_chunks():  # the host path splits collection from gradient steps
    assert "training_chunks" not in phases
  wall = WALL_S["first_run"]
  assert sum(phases.values()) == pytest.approx(wall, rel=0.05)
  assert profile["wall_s"] == pytest.approx(wall, rel=0.05)


def test_a_fresh_start_evaluation_compiles_its_step_once(caplog):
  # The trainer's params (placed by its mesh) drive it: its env step compiles once, not
  # once for the carry of the reset and again for the carry of a step.
  from mjxvine.evaluation import starts
  cfg = _cfg(80, "train.eval_starts=3")  # a program of its own: compiled here
  _, init, _ = programs.compiled_trainer(cfg)
  ts = init(jax.random.split(jax.random.PRNGKey(0), 1))
  run = programs.start_evaluator(cfg)
  params = programs.starts_params(ts.learner.averaged_actor_params, starts.ACTOR)
  with jax.log_compiles(), caplog.at_level("WARNING"):
    out = run(params, jax.random.PRNGKey(1))
  compiled = [r.getMessage() for r in caplog.records
              if "Finished XLA compilation of jit(step)" in r.getMessage()]
  assert len(compiled) == 1, compiled
  assert out == run(params, jax.random.PRNGKey(1))  # and drives the same


def test_run_writes_logs_checkpoints_and_curve(first_run):
  run, row = first_run
  rows = [json.loads(l) for l in (run / "metrics.jsonl").read_text().splitlines()]
  assert [r["env_steps"] for r in rows] == [20, 40, 60, 80]
  for key in ("episodes", "return_mean", "success_rate", "actor_loss", "critic_loss", "alpha",
              "sps", "eps", "timeout_rate", "v_mean"):
    assert key in rows[-1]
  assert 0 <= rows[-1]["v_mean"] <= 0.5
  # evaluations at chunks 2 and 4, the best of them kept
  assert ["eval_success_forward" in r for r in rows] == [False, True, False, True]
  for key in ("eval_success_forward", "eval_success_reverse", "eval_mae_m"):
    assert 0 <= rows[-1][key] <= 1.5
  best = json.loads((run / "best.json").read_text())
  assert best["chunk"] in (2, 4) and [int(p.name) for p in
                                      (run / "checkpoints" / "best").iterdir()] == [best["chunk"]]
  scores = [(min(r["eval_success_forward"], r["eval_success_reverse"]), -r["eval_mae_m"])
            for r in rows if "eval_mae_m" in r]
  assert best["chunk"] == 2 * (1 + scores.index(max(scores)))
  assert row["best_eval_mae_m"] == pytest.approx(best["eval_mae_m"])
  assert sorted(p.name for p in (run / "eval_policies").iterdir()) == [
      "env40.npz", "env40.sac.npz", "env80.npz", "env80.sac.npz"]  # each with its agent file
  # learning starts after the warm-up: losses are zero before, real after
  assert rows[0]["critic_loss"] == 0 and rows[-1]["critic_loss"] > 0
  assert rows[-1]["alpha"] == pytest.approx(0.2)
  assert list((run / "tb").glob("events.out.tfevents.*"))
  assert (run / "learning_curve.png").stat().st_size > 5000
  assert sorted(int(p.name) for p in (run / "checkpoints").iterdir() if p.name.isdigit())[-1] == 4
  # config.yaml: the run's config with the conv tower `auto` took here, said in its header
  text = (run / "config.yaml").read_text()
  assert text.startswith(f"# conv tower: {describe_conv_impl()}\n")
  assert load_config(run / "config.yaml") == resolve_conv_impl(_cfg(80, *EVAL))
  assert json.loads((run / "run.json").read_text())["conv_tower"] == describe_conv_impl()


def test_resume_continues_and_survives_a_corrupt_checkpoint(first_run, tmp_path, capsys):
  run, _ = first_run
  copy = tmp_path / "copy"
  shutil.copytree(run, copy)
  # corrupt the newest checkpoint: the resume must fall back to the previous one
  newest = copy / "checkpoints" / "4"
  for f in newest.rglob("*"):
    if f.is_file() and f.stat().st_size > 0 and "ocdbt" not in f.name:
      f.write_bytes(b"garbage")
  row = loop.train(_cfg(120), copy, resume=True, quiet=True, evaluate_at_end=False)
  err = capsys.readouterr().err
  assert "checkpoint 4 is corrupt" in err and "resumed" in err
  rows = [json.loads(l) for l in (copy / "metrics.jsonl").read_text().splitlines()]
  # chunks 1-3 of the first run, then 4-6 from the checkpoint of chunk 3: the row of the
  # first run's chunk 4 (past that checkpoint) is dropped, every chunk appears once
  assert [r["env_steps"] for r in rows] == [20, 40, 60, 80, 100, 120]
  assert [r["chunk"] for r in rows] == [1, 2, 3, 4, 5, 6]
  assert "dropped 1 row(s) of metrics.jsonl" in err
  assert row["env_steps"] == 120
  # TensorBoard is told to purge the stopped run's events from env step 61 on
  starts = [e.step for f in (copy / "tb").glob("events.out.tfevents.*") for e in _events(f)
            if e.HasField("session_log") and e.session_log.status == e.session_log.START]
  assert starts == [61]


def _events(path):
  """The TensorBoard `Event`s of an event file (TFRecord: length, crc, data, crc)."""
  import struct
  from tensorboardX.proto.event_pb2 import Event
  data, at = path.read_bytes(), 0
  while at < len(data):
    (n,) = struct.unpack("<Q", data[at:at + 8])
    yield Event.FromString(data[at + 12:at + 12 + n])
    at += 12 + n + 4


def test_resume_with_replay_is_exact(tmp_path):
  """With the replay saved, a run of 4 chunks and a run of 2 chunks resumed to 4 end in
  the same learner (the resume loses nothing)."""
  runs = {}
  for name, budgets in (("straight", (80,)), ("resumed", (40, 80))):
    run = tmp_path / name
    for i, steps in enumerate(budgets):
      cfg = load_config("experiments/smoke.yaml",
                        OVERRIDES + [f"train.total_env_steps={steps}", "train.save_replay=true"])
      loop.train(cfg, run, resume=i > 0, quiet=True, evaluate_at_end=False)
    runs[name] = run
  sac, init_fn, _ = programs.compiled_trainer(_cfg(80))
  # the trainer's towers compute as `learner_conv_impl` says (on the CPU the native tower
  # where it builds, else the shifted first conv: test_sac compares both with XLA's)
  assert sac.nets.actor.conv_impl == sac.nets.critic.conv_impl == learner_conv_impl()
  template = init_fn(jax.random.split(jax.random.PRNGKey(0), 1))
  (_, a), (_, b) = (Checkpoints(runs[n], True).restore(template) for n in runs)
  assert int(a.env_steps) == int(b.env_steps) == 80
  for x, y in zip(jax.tree.leaves(a.learner), jax.tree.leaves(b.learner)):
    np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-5, atol=1e-6)


def test_non_finite_parameters_stop_the_run(tmp_path, monkeypatch):
  real = programs.compiled_trainer

  def poisoned(cfg, seeds=1, env=None):
    sac, init_fn, chunk_fn = real(cfg, seeds, env)

    def chunk(ts, *profile):  # (the CPU's host loop takes the run's profile)
      ts, m = chunk_fn(ts, *profile)
      if int(ts.env_steps) >= 40:  # the second chunk goes bad
        ts = ts.replace(learner=ts.learner.replace(
            actor_params=jax.tree.map(lambda x: x * jp.nan, ts.learner.actor_params)))
        m = dict(m, finite=jp.asarray(False))
      return ts, m
    return sac, init_fn, chunk

  monkeypatch.setattr(loop, "compiled_trainer", poisoned)
  with pytest.raises(trainer.NonFiniteError, match="non-finite parameters at env step 40"):
    loop.train(_cfg(80), tmp_path / "nan", quiet=True, evaluate_at_end=False)
  # the checkpoint of the last good chunk is kept
  assert (tmp_path / "nan" / "checkpoints" / "1").is_dir()
  assert not (tmp_path / "nan" / "checkpoints" / "2").exists()


def test_cli_refuses_bad_resume(tmp_path, capsys):
  for path, message in ((tmp_path, "no config.yaml"), (tmp_path / "nope", "no such run")):
    with pytest.raises(SystemExit) as exit_info:
      train_mod.main(["--resume", str(path)])
    assert exit_info.value.code == 2 and message in capsys.readouterr().err


def test_resuming_a_finished_run_says_it_is_complete(first_run, monkeypatch, capsys):
  """A relative run directory; nothing is trained again, the last figures are shown."""
  run, _ = first_run
  monkeypatch.chdir(run.parent)
  assert train_mod.main(["--resume", run.name]) == 0
  err = capsys.readouterr().err
  assert "is complete" in err and "best checkpoint (chunk" in err
  assert len((run / "metrics.jsonl").read_text().splitlines()) == 4
  # what may not change on a resume is refused, naming the key
  assert train_mod.main(["--resume", run.name, "--set", "sac.learning_rate=0.5"]) == 2
  assert "sac.learning_rate" in capsys.readouterr().err


@pytest.mark.slow  # over 20 s on a 2-core CPU: the fast suite stays within 12 minutes
def test_exported_policy_evaluates_like_the_checkpoint(first_run, tmp_path):
  """export -> .npz holds the checkpoint's actor; `evaluate --policy x.npz` runs it; a
  policy for another image size is refused in one line."""
  from mjxvine import export
  from mjxvine.deploy import PolicyError
  from mjxvine.evaluation import policies, rollout
  from mjxvine.env import VineyardEnv
  from mjxvine.worlds import generate_world
  run, _ = first_run
  npz = tmp_path / "policy.npz"
  export.main(["--policy", str(run), "--out", str(npz)])
  cfg = load_config(run / "config.yaml", ["world.test_length_m=8", "eval.max_steps=15"])
  world = generate_world("test", 0, cfg.world)
  env = VineyardEnv(cfg, [world])
  from_run = policies.load_actor_params(run, env)
  from_npz = policies.load_actor_params(npz, env)
  for a, b in zip(jax.tree.leaves(from_run), jax.tree.leaves(from_npz)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  # the policy kept at the best evaluation is the best checkpoint's
  best_steps = json.loads((run / "best.json").read_text())["env_steps"]
  kept = policies.load_actor_params(run / "eval_policies" / f"env{best_steps}.npz", env)
  for a, b in zip(jax.tree.leaves(kept), jax.tree.leaves(from_npz)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  doc = rollout.evaluate(cfg, rollout.PolicySource(str(npz)), world,
                         rollout.Protocol(runs=1, noise_factor=1.0, lanes=(1,), directions=("F",)))
  assert doc["overall"]["runs"] == 1 and doc["rows"][0]["outcomes"][0] in (
      "timeout", "collision", "left_lane", "reversed", "success")
  other = VineyardEnv(load_config(run / "config.yaml", ["camera.width=40"]), [world])
  with pytest.raises(PolicyError, match="trained for 36x36"):
    policies.load_policy(str(npz), other)


def _copy(run, tmp_path, name="copy"):
  copy = tmp_path / name
  shutil.copytree(run, copy)
  return copy


def _break(step_dir):
  """Truncates every data file of a checkpoint step to 0 bytes."""
  for f in step_dir.rglob("*"):
    if f.is_file() and f.stat().st_size > 0:
      f.write_bytes(b"")


def test_resume_refuses_an_edited_config_and_changes_nothing(first_run, tmp_path, capsys):
  """config.yaml edited to another network: the resume is refused in one line naming the
  key and both values, before anything is built; the run's files are as they were."""
  copy = _copy(first_run[0], tmp_path)
  (copy / "config.yaml").write_text(
      (copy / "config.yaml").read_text().replace("hidden: 16", "hidden: 24"))
  before = {p: p.read_bytes() for p in copy.rglob("*") if p.is_file() and p.name != "config.yaml"}
  assert train_mod.main(["--resume", str(copy)]) == 2
  err = capsys.readouterr().err
  assert "sac.hidden 16 -> 24" in err and len(err.strip().splitlines()) == 1
  assert {p: p.read_bytes() for p in copy.rglob("*") if p.is_file()
          and p.name != "config.yaml"} == before
  # the library refuses the same way
  with pytest.raises(rundir.ResumeRefused, match="sac.hidden"):
    loop.train(load_config(copy / "config.yaml"), copy, resume=True, quiet=True)


def test_resume_after_broken_checkpoints_takes_the_newest_intact_one(first_run, tmp_path, capsys):
  """The newest steps broken (one file each truncated to 0 bytes): the resume takes the
  next intact one, says so in one line per broken step and moves them aside; with every
  regular step broken it takes the best checkpoint."""
  copy = _copy(first_run[0], tmp_path)
  steps = sorted(int(p.name) for p in (copy / "checkpoints").iterdir() if p.name.isdigit())
  _break(copy / "checkpoints" / str(steps[-1]))
  row = loop.train(_cfg(100, *EVAL), copy, resume=True, quiet=True, evaluate_at_end=False)
  err = capsys.readouterr().err
  assert f"checkpoint {steps[-1]} is corrupt or partial" in err and "moved to" in err
  assert f"resumed {copy} at chunk {steps[-2]}" in err and row["env_steps"] == 100
  assert (copy / "checkpoints-broken" / str(steps[-1])).is_dir()
  # every regular step broken: the best checkpoint
  copy2 = _copy(first_run[0], tmp_path, "copy2")
  for s in steps:
    _break(copy2 / "checkpoints" / str(s))
  best = json.loads((copy2 / "best.json").read_text())["chunk"]
  loop.train(_cfg(100, *EVAL), copy2, resume=True, quiet=True, evaluate_at_end=False)
  err = capsys.readouterr().err
  assert f"resuming from the best checkpoint (chunk {best})" in err
  assert sorted(p.name for p in (copy2 / "checkpoints-broken").iterdir()) == [
      str(s) for s in sorted(steps)]


def test_resume_with_nothing_intact_is_refused_then_restarts_on_request(first_run, tmp_path,
                                                                         capsys):
  copy = _copy(first_run[0], tmp_path)
  for step in list((copy / "checkpoints").rglob("*")):
    if step.is_dir() and step.name.isdigit():
      _break(step)
  assert train_mod.main(["--resume", str(copy)]) == 2
  err = capsys.readouterr().err
  assert "no checkpoint of it can be restored" in err and "--restart" in err
  assert train_mod.main(["--resume", str(copy), "--restart", "--no-eval"]) == 0
  err = capsys.readouterr().err
  assert "starting afresh (--restart)" in err
  previous = [p for p in copy.iterdir() if p.name.startswith("previous-")]
  assert len(previous) == 1 and (previous[0] / "best.json").is_file()
  assert len((previous[0] / "metrics.jsonl").read_text().splitlines()) == 4  # kept whole
  rows = [json.loads(l) for l in (copy / "metrics.jsonl").read_text().splitlines()]
  assert rows[0]["chunk"] == 1 and rows[-1]["env_steps"] == 80
  # the new best checkpoint belongs to the new run (its own best.json), the lock is gone
  assert json.loads((copy / "best.json").read_text())["chunk"] in (2, 4)
  assert not (copy / "lock").exists()


def test_the_same_command_gives_the_same_policy_file(first_run, tmp_path):
  """Two runs of one config and seed on one machine: the same policy file, bit for bit
  (training is deterministic, and the file has no timestamps); it records the tower."""
  from mjxvine.deploy import read_policy_file
  from mjxvine.export import main as export_main
  again = tmp_path / "again"
  loop.train(_cfg(80, *EVAL), again, quiet=True, evaluate_at_end=False)
  files = []
  for run in (first_run[0], again):
    out = tmp_path / f"{run.name}.npz"
    assert export_main(["--policy", str(run), "--out", str(out)]) == 0
    files.append(out.read_bytes())
  assert files[0] == files[1]
  assert (again / "eval_policies" / "env80.npz").read_bytes() == (
      first_run[0] / "eval_policies" / "env80.npz").read_bytes()
  assert read_policy_file(tmp_path / "again.npz")[1]["conv_tower"] == describe_conv_impl()


def test_a_run_continues_from_a_kept_policy_and_its_agent_file(first_run, tmp_path, capsys):
  """--init RUN/eval_policies/env80.npz: the new run starts from that agent (actor,
  critics, targets, temperature); before any update its policy is the loaded one, bit for
  bit; export writes the policy with its agent file; a policy without one is refused."""
  from mjxvine.agent_file import agent_path, read_agent
  from mjxvine.deploy import read_policy_file
  from mjxvine.export import main as export_main
  run, _ = first_run
  kept = run / "eval_policies" / "env80.npz"
  arrays, meta = read_agent(agent_path(kept))
  policy_arrays = read_policy_file(kept)[0]
  for name, value in policy_arrays.items():  # the agent's actor is the kept policy
    np.testing.assert_array_equal(arrays[f"actor/{name}"], value)
  assert {k.split("/")[0] for k in arrays} == {"actor", "critic", "target_critic", "log_alpha"}
  # 20 env steps, all of them warm-up (40): no update, so the policy is the loaded one
  new = tmp_path / "continued"
  row = loop.train(_cfg(20, f"train.init_from={kept}"), new, quiet=False,
                   evaluate_at_end=False)
  assert row["env_steps"] == 20 and "networks and temperature from" in capsys.readouterr().err
  out = tmp_path / "continued.npz"
  assert export_main(["--policy", str(new), "--which", "last", "--out", str(out)]) == 0
  for name, value in policy_arrays.items():
    np.testing.assert_array_equal(read_policy_file(out)[0][name], value)
  again, _ = read_agent(agent_path(out))  # from the orbax checkpoint
  for name in ("critic", "target_critic"):
    for key in (k for k in arrays if k.startswith(name + "/")):
      np.testing.assert_array_equal(again[key], arrays[key])
  np.testing.assert_allclose(again["log_alpha"], arrays["log_alpha"])
  bare = tmp_path / "bare.npz"
  bare.write_bytes(kept.read_bytes())  # a policy file alone
  capsys.readouterr()
  with pytest.raises(SystemExit) as e:
    train_mod.main(["--config", "experiments/smoke.yaml",
                    *sum((["--set", o] for o in OVERRIDES), []),
                    "--init", str(bare), "--out", str(tmp_path / "refused")])
  assert e.value.code == 2 and not (tmp_path / "refused").exists()
  err = capsys.readouterr().err.strip()
  assert len(err.splitlines()) == 1 and "bare.sac.npz" in err and "train.init_from" in err
