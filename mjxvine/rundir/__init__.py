"""A training run's directory, and what keeps it consistent through whatever happens to a
run: one writer at a time (`RunLock`), stops on SIGINT / SIGTERM at a chunk boundary
(`StopSignals`), and failed writes reported in one line (`WriteError`, `free_space`).

Under `python -m mjxvine.train` (`atomic.command_main`) a run that has not stopped within
`atomic.stop_grace()` of a signal (`atomic.STOP_GRACE_S` while it is set up or compiles,
`atomic.CHUNK_STOP_GRACE_S` for a chunk and its checkpoint) is ended by the command's
watchdog, keeping its last intact checkpoint.

    RUN_DIR/config.yaml        the resolved config          (`mjxvine.training.loop`)
    RUN_DIR/metrics.jsonl, tb/ one row per member and chunk (`logs.Logger`)
    RUN_DIR/learning_curve.png                              (`logs.plot_learning_curve`)
    RUN_DIR/checkpoints/, best.json                         (`checkpoints`)
    RUN_DIR/lock               held while a process trains there (`RunLock`)

Modules: `checkpoints` (orbax checkpoints, the best and last policy of a run), `logs`
(metrics.jsonl, TensorBoard, the learning curve; logs cut back to the checkpoint a resume
starts from), `settings` (the settings a policy was trained with).

The exit codes of `python -m mjxvine.train` (`EXIT_*`) live here, beside the conditions
they report.
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import fcntl
import json
import os
import shutil
import signal
import socket
import sys
import threading
from pathlib import Path

from mjxvine import atomic
# The run stopped on a signal (a BaseException: no `except Exception` takes it for a
# failure); every command's stop: `atomic.command_main`.
from mjxvine.atomic import Interrupted
from mjxvine.config import Config, ConfigError, changed_keys, config_hash, load_config, to_dict

EXIT_USAGE = 2        # a bad argument or config, or a run directory in use
EXIT_NON_FINITE = 3   # a loss or parameter became NaN / inf
EXIT_WRITE = 4        # a checkpoint or log could not be written (disk full, ...)
# stopped by a signal (every command, `atomic.command_main`); the trainer keeps a checkpoint
# of the chunk it stopped after, or its last one when it had to stop at once
EXIT_SIGINT = 128 + signal.SIGINT    # 130: Ctrl-C
EXIT_SIGTERM = 128 + signal.SIGTERM  # 143: SIGTERM

LOCK_FILE = "lock"


class RunDirBusy(RuntimeError):
  """Another process holds the run directory's lock; the message names it."""


class WriteError(RuntimeError):
  """A checkpoint or log could not be written; the message names the path, what failed
  and the free space."""


class ResumeRefused(ValueError):
  """A resume that would not continue the same run: a changed network, image or replay
  setting, or no intact checkpoint to continue from (exit 2, one line)."""


# ---------------------------------------------------------------------- the run's record
RUN_RECORD = "run.json"  # the config the run started with, apart from the editable config.yaml
# the keys a resume may change: the budget and what runs around the training (evaluations,
# checkpoint cadence, the choice), never the networks, images, replay, envs or members
RESUME_FREE = ("train.total_env_steps", "train.checkpoint_every_chunks",
               "train.eval_every_chunks", "train.eval_starts", "train.video",
               "train.keep_eval_policies", "train.select_worlds", "train.select_candidates",
               "eval.*")


def resume_may_change(key: str) -> bool:
  """Whether a resume may change config key "section.key" (`RESUME_FREE`)."""
  return key in RESUME_FREE or f"{key.split('.')[0]}.*" in RESUME_FREE


# what a run writes: set aside together when it starts afresh in its directory
RUN_OUTPUTS = ("checkpoints", "checkpoints-broken", "best.json", "best_members",
               "eval_policies", "selection.json", "selected.npz", "selected.sac.npz", "eval",
               "metrics.jsonl",
               "tb", "learning_curve.png")


def write_run_record(run_dir: Path, cfg: Config, **facts) -> None:
  """RUN_DIR/run.json: the config a run started with, its hash, and `facts` of the run
  (e.g. conv_tower="native (avx512)")."""
  atomic.write_text(Path(run_dir) / RUN_RECORD, json.dumps(
      {"config_hash": config_hash(cfg), "config": to_dict(cfg), **facts}, indent=1))


def run_record(run_dir: Path) -> dict:
  """RUN_DIR/run.json as a dict ({} when there is none or it is unreadable)."""
  try:
    return json.loads((Path(run_dir) / RUN_RECORD).read_text())
  except (OSError, ValueError):
    return {}


def record_fact(run_dir: Path, **facts) -> None:
  """Adds `facts` to RUN_DIR/run.json (e.g. profile={...}, where the wall-clock went);
  the recorded config stays as it was."""
  record = run_record(run_dir)
  if record:
    atomic.write_text(Path(run_dir) / RUN_RECORD, json.dumps({**record, **facts}, indent=1))


def original_config(run_dir: Path) -> Config | None:
  """The config a run started with (RUN_DIR/run.json; None for a run without one, from
  before the record). ResumeRefused when the record is unreadable or was edited."""
  path = Path(run_dir) / RUN_RECORD
  if not path.is_file():
    return None
  try:
    record = json.loads(path.read_text())
    cfg = load_config(None, base=record["config"])
  except (OSError, ValueError, KeyError, TypeError, ConfigError) as e:
    raise ResumeRefused(f"{path}: unreadable ({type(e).__name__}: {e}); it records the "
                        "config the run started with") from None
  if config_hash(cfg) != record.get("config_hash"):
    raise ResumeRefused(f"{path} was edited (its config no longer has its recorded hash); "
                        "it records the config the run started with")
  return cfg


def refuse_changes(run_dir: Path, cfg: Config, base: Config, normalize=lambda c: c) -> None:
  """ResumeRefused, naming the keys and their values, when a resume would change more
  than `RESUME_FREE` (network, image, replay, ... settings: another run). Both configs
  are compared after `normalize` (e.g. `sac.resolve_conv_impl`: a run recorded with
  `train.conv_impl: auto` resumes as the tower auto takes)."""
  original, cfg = normalize(original_config(run_dir) or base), normalize(cfg)
  changed = [k for k in changed_keys(original, cfg) if not resume_may_change(k)]
  if changed:
    value = lambda c, k: getattr(getattr(c, k.split(".")[0]), k.split(".")[1])
    what = ", ".join(f"{k} {value(original, k)!r} -> {value(cfg, k)!r}" for k in changed)
    raise ResumeRefused(f"--resume {run_dir}: the run started with other settings ({what}); "
                        "a resume may change only its budget and what runs around the "
                        "training (train.total_env_steps, the evaluations, the choice, "
                        "eval.*): restore config.yaml, or train a new run")


def set_aside(run_dir: Path) -> Path | None:
  """Moves what a run wrote (`RUN_OUTPUTS`: checkpoints, scores, policies, logs) to
  RUN_DIR/previous-<time>/, for a run that starts afresh in its directory: nothing is
  lost, and no old best checkpoint sits beside the new networks. Returns that directory
  (None: nothing to move)."""
  run_dir = Path(run_dir)
  present = [run_dir / n for n in RUN_OUTPUTS if (run_dir / n).exists()]
  if not present:
    return None
  target = run_dir / f"previous-{datetime.datetime.now():%Y%m%d-%H%M%S}"
  target.mkdir()
  for p in present:
    shutil.move(str(p), str(target / p.name))
  return target


def free_space(path: Path) -> str:
  """The free space (e.g. "12.3 MiB") on the disk of `path` or of its nearest existing
  parent; "unknown" when even that fails."""
  path = Path(path).resolve()
  while not path.exists() and path != path.parent:
    path = path.parent
  try:
    free = shutil.disk_usage(path).free
  except OSError:
    return "unknown"
  for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
    if free < 1024 or unit == "TiB":
      return f"{free:.0f} {unit}" if unit == "B" else f"{free:.1f} {unit}"
    free /= 1024
  return "unknown"


def write_failure(path: Path, what: str, error: BaseException) -> WriteError:
  """A `WriteError` for `error` raised while writing `what` at `path`: the root cause's
  first line (an OSError's strerror, or orbax / tensorstore's message) and the free space."""
  cause = _root_cause(error)
  if isinstance(cause, OSError) and cause.strerror:
    reason = f"{cause.strerror} [{errno.errorcode.get(cause.errno, cause.errno)}]"
  else:
    reason = (str(cause).strip().splitlines() or [type(cause).__name__])[-1][:200]
  return WriteError(f"cannot write {what} to {path}: {reason}; {free_space(path)} free there")


def _root_cause(error: BaseException) -> BaseException:
  """The innermost OSError of an exception chain, else its innermost exception."""
  seen, chain = set(), []
  while error is not None and id(error) not in seen:
    seen.add(id(error))
    chain.append(error)
    error = error.__cause__ or error.__context__
  return next((e for e in reversed(chain) if isinstance(e, OSError)), chain[-1])


# ---------------------------------------------------------------------- the lock
class RunLock:
  """An exclusive `fcntl.flock` on RUN_DIR/lock, held while a process trains in RUN_DIR.

  The kernel drops the lock when its process dies (kill -9 included), so a lock left by
  a killed run never blocks the next resume. The file holds the holder's pid, host and
  start time, for the message of the process that is refused (`RunDirBusy`)."""

  def __init__(self, run_dir: Path):
    self.path = Path(run_dir) / LOCK_FILE
    self.fd: int | None = None

  def acquire(self) -> "RunLock":
    while True:
      fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
      try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
      except BlockingIOError:
        os.close(fd)
        raise RunDirBusy(busy_message(self.path.parent)) from None
      # `release` removes the file: a lock taken on a file removed meanwhile is no lock
      try:
        if os.stat(self.path).st_ino == os.fstat(fd).st_ino:
          break
      except FileNotFoundError:
        pass
      os.close(fd)
    os.ftruncate(fd, 0)
    os.write(fd, (json.dumps({
        "pid": os.getpid(), "host": socket.gethostname(),
        "since": datetime.datetime.now().isoformat(timespec="seconds")}) + "\n").encode())
    self.fd = fd
    return self

  def release(self) -> None:
    """Removes the lock file (while still holding it: a run that ended leaves none) and
    unlocks."""
    if self.fd is not None:
      self.drop_file()  # only our own file: another process may hold a new one there
      fcntl.flock(self.fd, fcntl.LOCK_UN)
      os.close(self.fd)
      self.fd = None

  def drop_file(self) -> None:
    """Removes the lock file if it is still this lock's, keeping the lock: for a process
    about to end at once (the kernel unlocks), which leaves no stale file."""
    with contextlib.suppress(OSError):
      if self.fd is not None and os.stat(self.path).st_ino == os.fstat(self.fd).st_ino:
        self.path.unlink()

  def __enter__(self):
    return self.acquire()

  def __exit__(self, *exc):
    self.release()


def lock_holder(run_dir: Path) -> dict | None:
  """{"pid", "host", "since"} of the process that holds RUN_DIR's lock, or None when no
  process does (no lock file, or one left by a process that has ended)."""
  path = Path(run_dir) / LOCK_FILE
  if not path.is_file():
    return None
  fd = os.open(path, os.O_RDONLY)
  try:
    try:
      fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
      try:
        return json.loads(path.read_text() or "{}")
      except json.JSONDecodeError:
        return {}
    fcntl.flock(fd, fcntl.LOCK_UN)
    return None
  finally:
    os.close(fd)


def busy_message(run_dir: Path) -> str:
  holder = lock_holder(run_dir) or {}
  who = (f"process {holder.get('pid', '?')} on {holder.get('host', '?')} (since "
         f"{holder.get('since', '?')})")
  return f"{run_dir} is in use by {who}: wait for it to end, or stop it first"


# ---------------------------------------------------------------------- signals
class StopSignals:
  """While active, SIGINT and SIGTERM ask the run to stop at the end of the current chunk
  (`requested`: the signal number, or 0); a second SIGINT, or any signal while
  `stop_now()` is true (nothing would be kept by waiting), raises `Interrupted` at once
  (once per command, and not inside a JAX callback: `atomic.note_signal`). Installs
  nothing outside the main thread (signal handlers can only live there)."""

  SIGNALS = (signal.SIGINT, signal.SIGTERM)

  def __init__(self, stop_now=lambda: False, say=lambda *a: None):
    self.requested = 0
    self.stop_now, self.say = stop_now, say
    self.previous = {}

  def _handle(self, signum, frame):
    name = signal.Signals(signum).name
    at_once = self.stop_now() or (signum == signal.SIGINT and self.requested == signal.SIGINT)
    # (noted for the command's exit code; a stop under way finishes, bounded by its watchdog)
    if atomic.note_signal(signum, at_once, frame):
      raise Interrupted(signum, f"stopped at once by {name}")
    if at_once:
      return
    self.requested = self.requested or signum
    late = (f" if within {atomic.stop_grace():g} s (else at once, keeping the last one)"
            if atomic.command_signal() else "")
    self.say(f"\n{name}: stopping after this chunk, with a checkpoint{late}"
             + (" (Ctrl-C again to stop at once)" if signum == signal.SIGINT else ""))

  def __enter__(self):
    if threading.current_thread() is threading.main_thread():
      for s in self.SIGNALS:
        self.previous[s] = signal.signal(s, self._handle)
    return self

  def __exit__(self, *exc):
    for s, handler in self.previous.items():
      # None: a handler installed outside Python (JAX's preemption notifier), which
      # Python cannot reinstall
      signal.signal(s, signal.SIG_DFL if handler is None else handler)
    self.previous = {}


def exit_code(signum: int) -> int:
  """The shell's convention: 128 + the signal number (130 for SIGINT, 143 for SIGTERM)."""
  return 128 + int(signum)


def eprint(*args) -> None:
  print(*args, file=sys.stderr, flush=True)
