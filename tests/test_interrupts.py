"""What real runs go through: SIGTERM / SIGINT (a checkpoint, then a resume that goes on
from the same chunk, each chunk logged once), a second trainer on a running directory
(refused, naming the holder), a lock left by a killed process (no obstacle), a failed
checkpoint write (one line, exit 4, the previous checkpoint intact, the partial one
removed), and bad inputs (one line, exit 2). Every command stopped by SIGINT / SIGTERM
at any moment (`atomic.command_main`): the trainer while it compiles, `worlds` mid-set, a
main thread stuck in compiled code, a Ctrl-C inside a JAX callback: exit 130 / 143 within
5 s in one line, nothing partial left; `choose` refuses a run in use and keeps the earlier
choice until the new one is ready. The in-process runs share the compiled trainer of
tests/test_train.py (the same compile key)."""

import errno
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import jax
import pytest

from mjxvine import atomic, rundir
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
  argv = ["--config", str(ROOT / "experiments" / "smoke.yaml"), "--out", str(run),
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
    train_mod.main(["--config", str(path), "--out", str(tmp_path / "r"), *extra])
  err = _error_lines(capsys.readouterr().err)
  assert info.value.code == 2 and len(err) == 1 and message in err[0], err


def test_run_dir_that_is_a_file_is_one_line(tmp_path, capsys):
  afile = tmp_path / "file"
  afile.write_text("x")
  with pytest.raises(SystemExit) as info:
    train_mod.main(["--config", str(ROOT / "experiments" / "smoke.yaml"), "--out",
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


# ---------------------------------------------------------------------- every command's stop
def _run_and_signal(cmd, sig, ready, timeout=240):
  """Runs `cmd`, sends `sig` once `ready(stderr so far)` holds; (exit code, seconds from
  the signal to the exit, stdout, stderr)."""
  proc = subprocess.Popen(cmd, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)),
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
  err, out = [], []
  readers = [threading.Thread(target=lambda s=s, into=into: into.extend(s), daemon=True)
             for s, into in ((proc.stderr, err), (proc.stdout, out))]
  for r in readers:
    r.start()
  try:
    deadline = time.time() + timeout
    while not ready("".join(err)) and proc.poll() is None and time.time() < deadline:
      time.sleep(0.02)
    assert proc.poll() is None, "".join(err)[-3000:]
    sent = time.time()
    proc.send_signal(sig)
    proc.wait(timeout=30)
    took = time.time() - sent
  finally:
    if proc.poll() is None:
      proc.kill()
  for r in readers:
    r.join(10)
  return proc.returncode, took, "".join(out), "".join(err)


def _partial_files(folder: Path) -> list[Path]:
  """Temporary files of atomic writes, orbax's temporary steps, a lock file."""
  return [p for p in folder.rglob("*")
          if ".tmp" in p.name or "orbax-checkpoint-tmp" in p.name or p.name == "lock"]


def test_sigterm_while_the_first_chunk_compiles_ends_at_once(tmp_path):
  """SIGTERM while the first chunk compiles (which never reached the flag checked between
  chunks, and in XLA's compiler no Python handler runs): exit 143 within 5 s, one line
  saying how to resume, no partial file, no lock, no checkpoint yet."""
  run = tmp_path / "run"
  code, took, _, err = _run_and_signal(
      [sys.executable, "-m", "mjxvine.train", *_argv(run, 4000)], signal.SIGTERM,
      lambda err: "compiling the training iteration" in err and time.sleep(0.3) is None)
  assert code == 143 and took < 5, (code, took, err[-3000:])
  assert "Traceback" not in err
  last = _error_lines(err)[-1]
  assert "SIGTERM" in last and f"resume with: python -m mjxvine.train --resume {run}" in last
  assert not _partial_files(run), _partial_files(run)
  assert not [p for p in (run / "checkpoints").iterdir() if p.name.isdigit()]
  assert rundir.lock_holder(run) is None


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_during_worlds_leaves_nothing_of_the_set(tmp_path, sig):
  """`worlds --out` stopped after world.xml is written, while the depth image is made:
  none of the set stays (nor the directory it made; another file there stays), one line,
  exit 130 / 143, no traceback."""
  out = tmp_path / "out"
  if sig == signal.SIGTERM:  # a directory that holds something else already
    out.mkdir()
    (out / "notes.txt").write_text("mine")
  code, took, _, err = _run_and_signal(
      [sys.executable, "-m", "mjxvine.worlds", "--out", str(out), "--depth-at", "2,0,0"],
      sig, lambda err: (out / "world.xml").exists())
  assert code == 128 + sig and took < 5, (code, took, err)
  assert "Traceback" not in err and len(_error_lines(err)) == 1, err
  assert _error_lines(err)[0].startswith(f"stopped by {signal.Signals(sig).name}")
  if sig == signal.SIGTERM:
    assert [p.name for p in out.iterdir()] == ["notes.txt"]
  else:
    assert not out.exists()


_STUCK = """
import ctypes, signal, sys
from pathlib import Path
from mjxvine import atomic

def main():
  out = atomic.check_output(sys.argv[1], "--out", directory=True)
  atomic.write_text(out / "first.json", "{}")  # the first file of an unfinished set
  # as a main thread in compiled code (an XLA compilation): no Python handler runs there
  signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
  print("in compiled code", file=sys.stderr, flush=True)
  ctypes.CDLL(None).sleep(60)
  return 0

atomic.command_main(main)
"""


def test_a_command_stuck_in_compiled_code_ends_within_the_grace(tmp_path):
  """The watchdog: a main thread that no signal handler reaches is ended within
  `atomic.STOP_GRACE_S` of SIGTERM, its outputs removed, in one line, exit 143."""
  out = tmp_path / "out"
  code, took, _, err = _run_and_signal(
      [sys.executable, "-c", _STUCK, str(out)], signal.SIGTERM,
      lambda err: "in compiled code" in err)
  assert code == 143 and took < 5, (code, took, err)
  assert _error_lines(err)[-1].startswith("stopped by SIGTERM: ended at once"), err
  assert "first.json" in err and not out.exists()


_CALLBACK = """
import sys, time
import jax, jax.numpy as jnp
from mjxvine import atomic

def slow(x):
  print("in the callback", file=sys.stderr, flush=True)
  time.sleep(1)

def main():
  try:  # as code that takes any failure of a rollout for its own
    jax.jit(lambda x: (jax.debug.callback(slow, x), x + 1)[1])(jnp.ones(2)).block_until_ready()
  except Exception as e:
    print(f"rollout failed: {type(e).__name__}", file=sys.stderr)
  return 0

atomic.command_main(main)
"""


def test_a_ctrl_c_in_a_jax_callback_is_not_swallowed():
  """A Ctrl-C that lands in a JAX callback (where JAX would turn the exception into its
  own error, which the command takes for a failed rollout, and go on to exit 0) is raised
  once the jitted call has returned: exit 130, one line."""
  code, took, _, err = _run_and_signal([sys.executable, "-c", _CALLBACK], signal.SIGINT,
                                       lambda err: "in the callback" in err)
  assert code == 130 and took < 5, (code, took, err)
  assert _error_lines(err)[-1] == "stopped by SIGINT", err
  assert "Traceback" not in err and "rollout failed" not in err, err


def test_choose_refuses_a_run_in_use(tmp_path, capsys):
  from mjxvine import choose
  (tmp_path / "config.yaml").write_text((ROOT / "experiments" / "smoke.yaml").read_text())
  with rundir.RunLock(tmp_path):
    assert choose.main(["--policy", str(tmp_path)]) == rundir.EXIT_USAGE
  err = _error_lines(capsys.readouterr().err)
  assert len(err) == 1 and f"in use by process {os.getpid()}" in err[0], err


def test_choose_keeps_the_earlier_choice_until_the_new_one_is_ready(tmp_path, monkeypatch):
  """The earlier selected.npz stays while a new choice scores its candidates (a choice
  stopped there keeps it); the new one replaces it whole at the end."""
  from mjxvine import choose
  from mjxvine.evaluation import choice
  run = tmp_path
  (run / "config.yaml").write_text((ROOT / "experiments" / "smoke.yaml").read_text())
  (run / "metrics.jsonl").write_text(json.dumps(
      {"env_steps": 40, "member": 0, "eval_success_forward": 1.0,
       "eval_success_reverse": 1.0, "eval_mae_m": 0.1}) + "\n")
  (run / "eval_policies").mkdir()
  (run / "eval_policies" / "env40.npz").write_bytes(b"new")
  (run / "selected.npz").write_bytes(b"earlier")
  scores = {"worlds": {"100": {"success": 1, "episodes": 1, "mae_m_rows": 0.1,
                               "rows_status": "full", "failed": []}},
            "noise": {}, "success": 1, "episodes": 1, "mae_m": 0.1, "wall_s": 0.0}
  sets = ["--set", "train.select_worlds=1", "--set", "world.test_length_m=8"]

  def stopped(*a, **k):
    assert (run / "selected.npz").read_bytes() == b"earlier"
    raise rundir.Interrupted(signal.SIGTERM, "stopped by SIGTERM")

  monkeypatch.setattr(choice, "score_policy", stopped)
  with pytest.raises(rundir.Interrupted):
    choose.main(["--policy", str(run), *sets])
  assert (run / "selected.npz").read_bytes() == b"earlier"
  monkeypatch.setattr(choice, "score_policy", lambda *a, **k: scores)
  assert choose.main(["--policy", str(run), *sets]) == 0
  assert (run / "selected.npz").read_bytes() == b"new" and not _partial_files(run)


def test_a_stopped_command_removes_its_set_and_nothing_else(tmp_path, capsys):
  """In process (`atomic.run_command`): a signal while a file is written removes the
  files of the set written so far and the directory made for them; the file being
  written when it came stays as it was."""
  (tmp_path / "earlier.json").write_text("old")
  before = signal.getsignal(signal.SIGTERM)

  def main():
    out = atomic.check_output(tmp_path / "out" / "set", "--out", directory=True)
    atomic.write_text(out / "a.json", "new")
    with atomic.atomic_path(tmp_path / "earlier.json") as tmp:
      tmp.write_text("half")
      os.kill(os.getpid(), signal.SIGTERM)
      time.sleep(5)  # (the handler raises here)
    return 0

  assert atomic.run_command(main) == 143
  assert [p.name for p in tmp_path.iterdir()] == ["earlier.json"]
  assert (tmp_path / "earlier.json").read_text() == "old"
  err = _error_lines(capsys.readouterr().err)
  assert err == [f"stopped by SIGTERM; removed its partial outputs ({tmp_path}/out/set/a.json)"]
  assert signal.getsignal(signal.SIGTERM) is before  # restored


def test_a_stop_removes_new_files_and_keeps_replaced_ones(tmp_path, monkeypatch):
  """What a stopped command removes (`discard_partial`): the files it created, never one it
  replaced (the user's earlier file is gone either way: the new content stays); a failed
  rename leaves the original alone; the next command starts with nothing of the last."""
  old, new = tmp_path / "old.json", tmp_path / "new.json"
  old.write_text("earlier")
  monkeypatch.setattr(atomic, "track_outputs", True)
  atomic.write_text(old, "replaced")
  atomic.write_text(new, "created")
  assert atomic.discard_partial() == [new]
  assert old.read_text() == "replaced" and not new.exists()
  atomic._writes.clear()
  keep = tmp_path / "keep.json"
  keep.write_text("original")
  monkeypatch.setattr(atomic.os, "replace", lambda a, b: (_ for _ in ()).throw(OSError("no")))
  with pytest.raises(OSError):
    atomic.write_text(keep, "never")
  monkeypatch.undo()
  monkeypatch.setattr(atomic, "track_outputs", True)
  assert atomic.discard_partial() == [] and keep.read_text() == "original"
  assert atomic.run_command(lambda: 0) == 0 and not atomic._writes


def test_a_training_chunk_gets_longer_to_stop_than_a_compilation():
  """The watchdog's grace after a first signal: `STOP_GRACE_S` while a command is set up or
  compiles, `CHUNK_STOP_GRACE_S` while the trainer runs a chunk and its checkpoint."""
  seen = []
  def main():
    seen.append(atomic.stop_grace())
    previous = atomic.set_stop_grace(atomic.CHUNK_STOP_GRACE_S)
    seen.extend([previous, atomic.stop_grace()])
    return 0
  assert atomic.run_command(main) == 0
  assert seen == [atomic.STOP_GRACE_S, atomic.STOP_GRACE_S, atomic.CHUNK_STOP_GRACE_S]
  assert atomic.CHUNK_STOP_GRACE_S > 10 * atomic.STOP_GRACE_S


def test_a_run_of_the_earlier_release_is_refused_on_resume_before_any_restore(tmp_path):
  """A run whose checkpoints hold 0.2.0's learner state is refused in one line, before
  anything is restored or moved aside."""
  from mjxvine.training import loop
  step = tmp_path / "checkpoints" / "40" / "default"
  step.mkdir(parents=True)
  (step / "_METADATA").write_text('{"tree_metadata": {"learner": {"policy_params": {}}}}')
  with pytest.raises(rundir.ResumeRefused, match="0.2.0") as e:
    loop._restore(tmp_path, None, None, False, True, print)
  assert "\n" not in str(e.value) and step.is_dir()
