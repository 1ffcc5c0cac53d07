"""What keeps a run directory consistent through whatever happens to a run: one writer at
a time (`RunLock`), logs cut back to the checkpoint a resume starts from
(`truncate_metrics`, `clear_events`), stops on SIGINT / SIGTERM at a chunk boundary
(`StopSignals`), and failed writes reported in one line (`WriteError`, `free_space`).

The exit codes of `python -m mjxvine.train` (`EXIT_*`) live here, beside the conditions
they report.
"""

from __future__ import annotations

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

EXIT_USAGE = 2        # a bad argument or config, or a run directory in use
EXIT_NON_FINITE = 3   # a loss or parameter became NaN / inf
EXIT_WRITE = 4        # a checkpoint or log could not be written (disk full, ...)
EXIT_SIGINT = 128 + signal.SIGINT    # 130: stopped by Ctrl-C, checkpoint written
EXIT_SIGTERM = 128 + signal.SIGTERM  # 143: stopped by SIGTERM, checkpoint written

LOCK_FILE = "lock"


class RunDirBusy(RuntimeError):
  """Another process holds the run directory's lock; the message names it."""


class WriteError(RuntimeError):
  """A checkpoint or log could not be written; the message names the path, what failed
  and the free space."""


class Interrupted(Exception):
  """The run stopped on a signal; `signum` says which, the message what was kept."""

  def __init__(self, signum: int, message: str):
    super().__init__(message)
    self.signum = signum


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
    fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
      fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
      os.close(fd)
      raise RunDirBusy(busy_message(self.path.parent)) from None
    os.ftruncate(fd, 0)
    os.write(fd, (json.dumps({
        "pid": os.getpid(), "host": socket.gethostname(),
        "since": datetime.datetime.now().isoformat(timespec="seconds")}) + "\n").encode())
    self.fd = fd
    return self

  def release(self) -> None:
    if self.fd is not None:
      fcntl.flock(self.fd, fcntl.LOCK_UN)
      os.close(self.fd)
      self.fd = None

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


# ---------------------------------------------------------------------- the logs
def truncate_metrics(path: Path, env_steps: int) -> int:
  """Keeps the rows of metrics.jsonl at `path` up to `env_steps` (those the restored
  checkpoint has seen; 0: none), rewriting the file atomically. Returns the rows dropped."""
  if not path.is_file():
    return 0
  lines = [l for l in path.read_text().splitlines() if l.strip()]
  keep = []
  for line in lines:
    try:
      row = json.loads(line)
    except json.JSONDecodeError:
      continue  # a line cut short by a kill
    if row.get("env_steps", 0) <= env_steps:
      keep.append(line)
  if len(keep) == len(lines):
    return 0
  tmp = path.with_suffix(".jsonl.tmp")
  tmp.write_text("".join(l + "\n" for l in keep))
  os.replace(tmp, path)
  return len(lines) - len(keep)


def clear_events(tb_dir: Path) -> None:
  """Removes the TensorBoard event files of a run that starts afresh in the same dir."""
  for f in Path(tb_dir).glob("events.out.tfevents.*"):
    f.unlink()


# ---------------------------------------------------------------------- signals
class StopSignals:
  """While active, SIGINT and SIGTERM ask the run to stop at the end of the current chunk
  (`requested`: the signal number, or 0); a second SIGINT, or any signal while
  `stop_now()` is true (nothing would be kept by waiting), raises `Interrupted` at once.
  Installs nothing outside the main thread (signal handlers can only live there)."""

  SIGNALS = (signal.SIGINT, signal.SIGTERM)

  def __init__(self, stop_now=lambda: False, say=lambda *a: None):
    self.requested = 0
    self.stop_now, self.say = stop_now, say
    self.previous = {}

  def _handle(self, signum, frame):
    name = signal.Signals(signum).name
    if self.stop_now() or (signum == signal.SIGINT and self.requested == signal.SIGINT):
      raise Interrupted(signum, f"stopped at once by {name}")
    self.requested = self.requested or signum
    self.say(f"\n{name}: stopping after this chunk, with a checkpoint"
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
