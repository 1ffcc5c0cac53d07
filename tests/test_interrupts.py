"""What real runs go through: SIGTERM / SIGINT (a checkpoint, then a resume that goes on
from the same chunk, each chunk logged once), a second trainer on a running directory
(refused, naming the holder), a lock left by a killed process (no obstacle), a failed
checkpoint write (one line, exit 4, the previous checkpoint intact, the partial one
removed), and bad inputs (one line, exit 2). The in-process runs share the compiled
trainer of tests/test_train.py (the same compile key)."""

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import pytest

from mjxvine import rundir
from mjxvine import train as train_mod
from mjxvine.training import programs
from mjxvine.config import load_config
from mjxvine.rundir.checkpoints import Checkpoints

ROOT = Path(__file__).resolve().parent.parent
# the compile key of tests/test_train.py's runs (its OVERRIDES): compiled once per session
SETS = ["camera.width=36", "camera.height=36", "env.num_envs=2", "env.max_steps=30",
        "sac.batch_size=16", "sac.buffer_size=512", "sac.warmup_steps=40",
        "sac.hidden=16", "sac.conv_features=4", "train.iters_per_chunk=10",
        "world.pool_size=1", "world.train_length_m=6", "eval.runs_after_train=0"]


def _argv(run, steps, *extra):
  argv = ["--config", str(ROOT / "experiments" / "smoke.yaml"), "--run-dir", str(run),
          "--no-eval"]
  for s in SETS + [f"train.total_env_steps={steps}", *extra]:
    argv += ["--set", s]
  return argv


def _chunks(run):
  return [json.loads(l)["chunk"] for l in (run / "metrics.jsonl").read_text().splitlines()]


def _error_lines(err):
  return [l for l in err.splitlines() if l.strip() and "warp" not in l]


@pytest.mark.slow  # over 20 s on a 2-core CPU: the fast suite stays within 12 minutes
def test_sigterm_checkpoints_and_resume_goes_on_once(tmp_path, capsys):
  """A trainer in a subprocess gets SIGTERM mid-run (checkpoints only every 100 chunks):
  it ends the chunk, writes a checkpoint, exits 143 with the resume command. While it
  trains, a second trainer on its directory is refused in one line naming its pid. The
  resume goes on from the chunk it stopped at, and each chunk is logged once."""
  run = tmp_path / "run"
  env = dict(os.environ, PYTHONPATH=str(ROOT))
  proc = subprocess.Popen(
      [sys.executable, "-m", "mjxvine.train", *_argv(run, 4000, "train.checkpoint_every_chunks=100")],
      cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
  try:
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None:
      if (run / "metrics.jsonl").is_file() and len(_chunks(run)) >= 2:
        break
      time.sleep(0.2)
    assert proc.poll() is None, proc.communicate()[1][-3000:]
    # a second trainer on the running directory: refused, naming the holder
    assert train_mod.main(["--resume", str(run)]) == rundir.EXIT_USAGE
    err = _error_lines(capsys.readouterr().err)
    assert len(err) == 1 and f"process {proc.pid}" in err[0] and "in use" in err[0]
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
  finally:
    if proc.poll() is None:
      proc.kill()
  assert proc.returncode == 143, err[-3000:]
  stopped = _chunks(run)[-1]
  assert f"stopped by SIGTERM after chunk {stopped}" in err
  assert f"resume with: python -m mjxvine.train --resume {run}" in err
  assert "Traceback" not in err
  steps = [int(p.name) for p in (run / "checkpoints").iterdir() if p.name.isdigit()]
  assert steps == [stopped]
  # the resume starts at that chunk and logs each chunk once
  assert train_mod.main(["--resume", str(run),
                         "--set", f"train.total_env_steps={20 * (stopped + 2)}"]) == 0
  assert f"resumed {run} at chunk {stopped}" in capsys.readouterr().err
  assert _chunks(run) == list(range(1, stopped + 3))


def test_signals_stop_at_the_chunk_end_and_a_second_ctrl_c_at_once():
  before = signal.getsignal(signal.SIGINT)  # SIG_IGN where pytest runs in the background
  stops = rundir.StopSignals()
  with stops:
    os.kill(os.getpid(), signal.SIGINT)
    assert stops.requested == signal.SIGINT  # noted: the run stops after its chunk
    with pytest.raises(rundir.Interrupted) as info:
      os.kill(os.getpid(), signal.SIGINT)
    assert info.value.signum == signal.SIGINT
  assert signal.getsignal(signal.SIGINT) is before  # restored
  with rundir.StopSignals(stop_now=lambda: True):  # nothing to finish: stop at once
    with pytest.raises(rundir.Interrupted, match="SIGTERM"):
      os.kill(os.getpid(), signal.SIGTERM)
  assert rundir.exit_code(signal.SIGINT) == 130 and rundir.exit_code(signal.SIGTERM) == 143


def test_a_lock_left_by_a_killed_process_does_not_block(tmp_path, capsys):
  code = ("import sys, time; from mjxvine.rundir import RunLock; "
          f"RunLock({str(tmp_path)!r}).acquire(); print('locked', flush=True); time.sleep(60)")
  proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                          env=dict(os.environ, PYTHONPATH=str(ROOT)))
  try:
    assert proc.stdout.readline().strip() == "locked"
    holder = rundir.lock_holder(tmp_path)
    assert holder["pid"] == proc.pid
    with pytest.raises(rundir.RunDirBusy, match=f"process {proc.pid} on "):
      rundir.RunLock(tmp_path).acquire()
    # a trainer on the locked directory: refused in one line naming the holder, exit 2
    assert train_mod.main(_argv(tmp_path, 40)) == rundir.EXIT_USAGE
    err = _error_lines(capsys.readouterr().err)
    assert len(err) == 1 and f"in use by process {proc.pid} on " in err[0], err
  finally:
    proc.kill()
    proc.wait()
  assert rundir.lock_holder(tmp_path) is None  # the kernel dropped it with the process
  with rundir.RunLock(tmp_path):
    assert rundir.lock_holder(tmp_path)["pid"] == os.getpid()


@pytest.mark.slow  # over 20 s on a 2-core CPU: the fast suite stays within 12 minutes
def test_a_failed_checkpoint_write_is_one_line_and_keeps_the_previous(tmp_path, monkeypatch,
                                                                      capsys):
  import orbax.checkpoint as ocp
  real = ocp.CheckpointManager.save

  def full_disk(self, step, *a, **k):
    if step >= 2:
      (Path(self.directory) / f"{step}.orbax-checkpoint-tmp-1").mkdir()  # a partial write
      raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    return real(self, step, *a, **k)

  run = tmp_path / "run"
  monkeypatch.setattr(ocp.CheckpointManager, "save", full_disk)
  assert train_mod.main(_argv(run, 60, "train.checkpoint_every_chunks=1")) == rundir.EXIT_WRITE
  err = _error_lines(capsys.readouterr().err)
  assert "Traceback" not in "\n".join(err) and sum("error" in l for l in err) == 1, err
  err = err[-1:]
  assert "cannot write checkpoint 2" in err[0] and str(run / "checkpoints") in err[0]
  assert "No space left on device [ENOSPC]" in err[0] and " free there" in err[0]
  assert not list((run / "checkpoints").glob("*.orbax-checkpoint-tmp*"))  # cleaned up
  monkeypatch.setattr(ocp.CheckpointManager, "save", real)
  # the previous checkpoint restores; a partial one left by a kill is removed on resume
  sac, init_fn, _ = programs.compiled_trainer(load_config(run / "config.yaml"))
  step, ts = Checkpoints(run, False).restore(init_fn(jax.random.split(jax.random.PRNGKey(0), 1)))
  assert step == 1 and int(ts.env_steps) == 20
  (run / "checkpoints" / "2.orbax-checkpoint-tmp-7").mkdir()
  assert train_mod.main(["--resume", str(run)]) == 0
  assert "removed 1 partial checkpoint(s)" in capsys.readouterr().err
  assert not list((run / "checkpoints").glob("*tmp*")) and _chunks(run) == [1, 2, 3]


@pytest.mark.parametrize("content, extra, message", [
    ("- a\n- b\n", ["--set", "env.num_envs=2"], "expected a mapping of sections"),
    ("", [], "empty (write {} to train the defaults)"),
    ("# only a comment\n", [], "empty"),
])
def test_bad_config_files_are_one_line(tmp_path, capsys, content, extra, message):
  path = tmp_path / "c.yaml"
  path.write_text(content)
  with pytest.raises(SystemExit) as info:
    train_mod.main(["--config", str(path), "--run-dir", str(tmp_path / "r"), *extra])
  err = _error_lines(capsys.readouterr().err)
  assert info.value.code == 2 and len(err) == 1 and message in err[0], err


def test_run_dir_that_is_a_file_is_one_line(tmp_path, capsys):
  afile = tmp_path / "file"
  afile.write_text("x")
  with pytest.raises(SystemExit) as info:
    train_mod.main(["--config", str(ROOT / "experiments" / "smoke.yaml"), "--run-dir",
                    str(afile)])
  err = _error_lines(capsys.readouterr().err)
  assert info.value.code == 2 and "not a directory" in err[-1]
  assert sum("error" in l for l in err) == 1  # argparse's usage line, then one error


def test_distributed_flags_are_checked(capsys):
  with pytest.raises(SystemExit) as info:
    train_mod.main(["--num-processes", "2"])
  assert info.value.code == 2 and "go with --distributed" in capsys.readouterr().err
  with pytest.raises(SystemExit) as info:
    train_mod.main(["--distributed", "--coordinator", "localhost:1", "--num-processes", "2",
                    "--process-id", "2"])
  assert info.value.code == 2 and "not in 0..1" in capsys.readouterr().err
