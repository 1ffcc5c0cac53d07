"""Outputs checked before the work and files written whole or not at all.

`check_output` tells, before a command starts its work, whether it can write where it was
asked to (`OutputError`, one line naming the flag, otherwise); `write_bytes`, `write_text`
and `atomic_path` write a temporary file in the same directory and rename it over the
target once complete (`os.replace`), so that a failure mid-write (a full disk, a signal)
leaves the previous file as it was and no half-written one.

A command stopped by SIGINT / SIGTERM leaves none of its partial files either
(`command_main`): the writes in flight (and, while `track_outputs`, those done and the
directories `check_output` made) are noted, and removed when a signal stops it
(`discard_partial`); it ends within `STOP_GRACE_S` of the signal, even while its main
thread is in compiled code (an XLA compilation, a long rollout) where no Python signal
handler runs, says one line and exits 130 (SIGINT) or 143 (SIGTERM)."""

from __future__ import annotations

import _thread
import atexit
import contextlib
import os
import select
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Iterator, Sequence

# `check_output`'s error and its rule against writing over an input (the commands import
# them from here)
from mjxvine.outputs import OutputError, check_not_input  # noqa: F401


class _Write:
  """One `atomic_path` write: `committing` is set just before the rename, so that a stop
  at any point tells a new file at `path` (the temporary file gone) from an untouched one;
  `replaces`: a file was there before (a stop leaves the new one: the old is gone)."""
  __slots__ = ("path", "tmp", "committing", "replaces")

  def __init__(self, path: Path, tmp: Path):
    self.path, self.tmp, self.committing, self.replaces = path, tmp, False, False


_writes: list[_Write] = []  # in flight, and (while `track_outputs`) done
_made_dirs: list[Path] = []  # made by `check_output` while `track_outputs`
# Set while a command whose outputs form one set runs (`run_command`): the files it wrote
# are removed again when a signal stops it before it ends.
track_outputs = False


def check_output(path: str | Path, flag: str, directory: bool = False, *,
                 inputs: Sequence[tuple] = (), writes: Sequence[str] = (),
                 own: Sequence[str | Path] = ()) -> Path:
  """Checks, before any work, that `path` can be written: a directory (`directory`;
  created if missing) or a file (its directory created if missing; an existing file is
  replaced at the end). Probes with a temporary file, so a read-only or full file system
  and missing permissions are caught too. With `inputs`, first that it writes over none
  of the command's inputs (`check_not_input`; `writes`, `own` as there). Returns the path;
  raises `OutputError`."""
  if inputs:
    check_not_input(path, flag, inputs, writes=writes if directory else None, own=own)
  path = Path(path)
  folder = path if directory else path.parent
  if directory and path.exists() and not path.is_dir():
    raise OutputError(f"{flag} {path}: exists and is not a directory")
  if not directory and path.is_dir():
    raise OutputError(f"{flag} {path}: is a directory; give a file name")
  try:
    missing = [d for d in (folder, *folder.parents) if not d.exists()]
    folder.mkdir(parents=True, exist_ok=True)
    if track_outputs:
      _made_dirs.extend(missing)  # deepest first
    probe = folder / f".write-probe.{os.getpid()}"
    probe.write_bytes(b"")
    probe.unlink()
  except FileExistsError:
    raise OutputError(f"{flag} {path}: a parent of it is a file, not a directory") from None
  except OSError as e:
    reason = e.strerror or type(e).__name__
    raise OutputError(f"{flag} {path}: cannot write in {folder} ({reason})") from None
  return path


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
  """Yields a temporary path beside `path` to write to (with the same suffix, for writers
  that go by it); on success it replaces `path` (if anything was written there), on an
  exception it is removed and `path` is untouched."""
  path = Path(path)
  tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
  write = _Write(path, tmp)
  _writes.append(write)
  try:
    yield tmp
    if tmp.exists():
      # a file it replaces is the user's: a stop keeps the new one rather than none
      write.replaces = path.exists()
      write.committing = True  # before the rename: a stop right after it sees a new file
      try:
        os.replace(tmp, path)
      except BaseException:
        write.committing = False  # nothing was written there
        raise
  finally:
    with contextlib.suppress(FileNotFoundError):
      tmp.unlink()
    if not (write.committing and track_outputs):
      with contextlib.suppress(ValueError):
        _writes.remove(write)


def write_bytes(path: str | Path, data: bytes) -> Path:
  """Writes `data` to `path` atomically (flushed to disk before the rename)."""
  with atomic_path(path) as tmp:
    with open(tmp, "wb") as f:
      f.write(data)
      f.flush()
      os.fsync(f.fileno())
  return Path(path)


def write_text(path: str | Path, text: str) -> Path:
  """Writes `text` (UTF-8) to `path` atomically."""
  return write_bytes(path, text.encode("utf-8"))


def discard_partial(outputs: bool = True) -> list[Path]:
  """Removes the temporary files of the writes in flight and, with `outputs`, the files
  written (and the directories `check_output` made, if empty) while `track_outputs`: what
  a command stopped before its end leaves. Safe to call from any thread, and twice.
  Returns the outputs removed (not the temporary files)."""
  removed = []
  for write in list(_writes):
    try:
      if write.tmp.exists():  # not renamed yet: the target is as it was
        write.tmp.unlink()
      elif write.committing and outputs and not write.replaces:
        write.path.unlink()
        removed.append(write.path)
    except FileNotFoundError:
      pass
    except OSError:  # a read-only place: nothing more to do there
      pass
  for folder in list(_made_dirs) if outputs else ():
    with contextlib.suppress(OSError):  # not empty: something else is there
      folder.rmdir()
  return removed


# ---------------------------------------------------------------------- a command's stop
STOP_GRACE_S = 3.0  # a command not ended this long after a signal is ended at once
AGAIN_S = 0.5       # ... and this long after a second one
# the trainer's chunks: a first signal lets the chunk, its evaluation and its checkpoint
# end (a stop between chunks keeps all of it); a second one, or this long, ends it at once
CHUNK_STOP_GRACE_S = 120.0


def set_stop_grace(seconds: float) -> float:
  """Sets how long the running command has, after a first signal, to stop by itself;
  returns what it was (`STOP_GRACE_S` outside a command)."""
  if _command is None:
    return STOP_GRACE_S
  previous, _command.grace_s = _command.grace_s, seconds
  return previous


def stop_grace() -> float:
  """How long the running command has, after a first signal, to stop by itself."""
  return STOP_GRACE_S if _command is None else _command.grace_s
SIGNALS = (signal.SIGINT, signal.SIGTERM)
# to the watchdog (no signal has these numbers): raise the signal again soon; stand down
_AGAIN, _CLOSE = 255, 254
RETRY_S = 0.05  # how soon a signal not raised yet (in a JAX callback) is raised again
_CALLBACK_MODULES = ("jax._src.callback", "jax._src.debugging")  # JAX's host callbacks


class Interrupted(BaseException):
  """The command (or run) stopped on a signal; `signum` says which, the message what was
  kept. A BaseException, as KeyboardInterrupt: no `except Exception` takes a signal for a
  failure (a broken checkpoint, a failed write)."""

  def __init__(self, signum: int, message: str):
    super().__init__(message)
    self.signum = signum


class _Command:
  """The stop of this process's command: the Python handler (main thread), a watchdog
  thread woken by the signal itself (`signal.set_wakeup_fd`: it runs while the main
  thread is in compiled code), and what a stop removes and says."""

  def __init__(self):
    self.keep_outputs, self.grace_s = True, STOP_GRACE_S  # `run_command` sets them
    self.running = False     # main() runs: before, a signal has nothing to stop but imports
    self.signum = 0          # the first SIGINT / SIGTERM
    self.raised = False      # an exception was raised for it: later signals raise nothing
    self.stopping = False    # the main thread is ending: later signals raise nothing
    self.code: int | None = None  # the exit code, once the main thread has one
    self.cleanups: list[Callable[[], str | None]] = []  # `on_stop`
    self.said = False
    self.lock = threading.Lock()
    self.read_fd, self.write_fd = os.pipe()
    os.set_blocking(self.write_fd, False)  # set_wakeup_fd needs it
    self.deferred = False    # a signal waits to be raised (`may_raise`)
    self.redelivered = 0     # signals raised again by the watchdog
    self.previous: dict = {}
    self.previous_fd = -1
    self.previous_hook = sys.unraisablehook

  def install(self) -> None:
    for s in SIGNALS:
      self.previous[s] = signal.signal(s, self.handle)
    self.previous_fd = signal.set_wakeup_fd(self.write_fd, warn_on_full_buffer=False)
    self.previous_hook, sys.unraisablehook = sys.unraisablehook, self.unraisable
    threading.Thread(target=self._watch, name="mjxvine-stop", daemon=True).start()

  def uninstall(self) -> None:
    sys.unraisablehook = self.previous_hook
    signal.set_wakeup_fd(self.previous_fd)
    for s, handler in self.previous.items():
      signal.signal(s, signal.SIG_DFL if handler is None else handler)
    with contextlib.suppress(OSError):
      os.write(self.write_fd, bytes([_CLOSE]))

  def handle(self, signum, frame) -> None:
    self.signum = self.signum or signum
    name = signal.Signals(signum).name
    if not self.running:  # still importing: nothing written, nothing to say but this
      self.say(f"stopped by {name} before the command started")
      os._exit(128 + signum)
    if self.may_raise(frame):
      raise Interrupted(signum, f"stopped by {name}")

  def may_raise(self, frame) -> bool:
    """Whether to raise `Interrupted` now, in `frame` (then counted as raised): once (a
    stop under way, its cleanup and its line, finishes: the watchdog bounds it), and not
    inside a JAX callback, where JAX would take it for the callback's failure (and log
    its traceback): it is raised again once out of there (`defer`)."""
    if self.stopping or self.raised:
      return False
    while frame is not None:
      if frame.f_globals.get("__name__") in _CALLBACK_MODULES:
        self.defer()
        return False
      frame = frame.f_back
    self.raised, self.deferred = True, False
    return True

  def defer(self) -> None:
    """Has the watchdog raise the signal again in `RETRY_S` (`_thread.interrupt_main`)."""
    self.deferred = True
    with contextlib.suppress(OSError):
      os.write(self.write_fd, bytes([_AGAIN]))

  def unraisable(self, info) -> None:
    """`sys.unraisablehook`: an `Interrupted` raised where Python drops exceptions (a gc
    callback such as JAX's, a `__del__`) is raised again instead of a traceback."""
    if isinstance(info.exc_value, Interrupted) and not self.stopping:
      self.raised = False
      self.defer()
    else:
      self.previous_hook(info)

  def _watch(self) -> None:
    deadline = retry = None
    while True:
      times = [t for t in (deadline, retry) if t is not None]
      wait = max(0.0, min(times) - time.monotonic()) if times else None
      ready = select.select([self.read_fd], [], [], wait)[0]
      now = time.monotonic()
      if deadline is not None and now >= deadline:
        self._end_now()
      if retry is not None and now >= retry:
        retry = None
        if self.deferred and not (self.raised or self.stopping):
          self.redelivered += 1  # (its wakeup byte is not a second signal)
          _thread.interrupt_main(self.signum)
      for byte in os.read(self.read_fd, 64) if ready else b"":
        if byte == _CLOSE:
          return
        if byte == _AGAIN:
          retry = now + RETRY_S
        elif byte in SIGNALS and self.redelivered:
          self.redelivered -= 1
        elif byte in SIGNALS:
          self.signum = self.signum or byte
          deadline = now + self.grace_s if deadline is None else min(deadline, now + AGAIN_S)

  def cleanup(self) -> tuple[list[Path], list[str]]:
    """Removes what a stop leaves (`discard_partial`, the `on_stop` callbacks); returns
    (the outputs removed, the callbacks' notes)."""
    removed = discard_partial(outputs=not self.keep_outputs)
    notes = []
    for fn in reversed(list(self.cleanups)):
      try:
        notes.append(fn())
      except Exception:  # noqa: BLE001 - a stop goes on whatever one cleanup does
        pass
    return removed, [n for n in notes if n]

  def stopped(self, message: str, at_once: bool = False) -> int:
    """Cleans up and says `message` in one line (once per process); the exit code."""
    self.stopping = True
    removed, notes = self.cleanup()
    parts = [message + (f": ended at once (no stop point within {self.grace_s:g} s)"
                        if at_once else "")]
    if removed:
      names = ", ".join(str(p) for p in removed[:3])
      parts.append(f"removed its partial outputs ({names}"
                   + (f" and {len(removed) - 3} more)" if len(removed) > 3 else ")"))
    self.say("; ".join(parts + notes))
    return 128 + (self.signum or signal.SIGTERM)

  def say(self, line: str) -> None:
    with self.lock:
      if self.said:
        return
      self.said = True
    if threading.current_thread() is threading.main_thread():
      with contextlib.suppress(OSError, ValueError):  # (a closed stderr)
        print(line, file=sys.stderr, flush=True)
      return
    # the watchdog: the stuck main thread may hold the stream's lock
    _flush(sys.stderr)  # after what the command said before
    with contextlib.suppress(OSError, ValueError):
      os.write(sys.stderr.fileno(), (line + "\n").encode())

  def _end_now(self) -> None:
    """The watchdog's end: the main thread did not end in time."""
    if self.code is None:  # else the command ended and said so; its exit hangs
      name = signal.Signals(self.signum or signal.SIGTERM).name
      self.code = self.stopped(f"stopped by {name}", at_once=True)
    _flush(sys.stdout, sys.stderr)
    self.cleanup()  # again: what the main thread began meanwhile
    os._exit(self.code)


_command: _Command | None = None  # this process's command (`run_command`), if any


def _flush(*streams) -> None:
  """Flushes `streams` within 0.5 s (a stream's lock may be held by a stuck thread)."""
  def flush():
    for s in streams:
      with contextlib.suppress(Exception):
        s.flush()
  t = threading.Thread(target=flush, daemon=True)
  t.start()
  t.join(0.5)


def guard_command() -> None:
  """Installs the stop of a command now, before its imports (which take seconds), when
  this process is `python -m mjxvine.<command>`: a signal then ends it at once, in one
  line, instead of a traceback (SIGINT) or no exit code (SIGTERM). `import mjxvine`
  calls it; `run_command` takes the stop over."""
  global _command
  argv = getattr(sys, "orig_argv", [])
  module = argv[argv.index("-m") + 1] if "-m" in argv[1:-1] else ""
  if (_command is None and sys.argv[:1] == ["-m"] and module.split(".")[0] == "mjxvine"
      and threading.current_thread() is threading.main_thread()):
    _command = _Command()
    _command.install()
    atexit.register(_end_at_exit)  # first registered: it runs after every other one


def _end_at_exit() -> None:
  """The last exit handler of a command: ends the process with its exit code, without
  the interpreter's teardown of its modules (a second or so after a JAX program), where
  Python no longer handles signals (a SIGTERM there would end it without the code)."""
  if _command is None or _command.code is None:
    return
  if "logging" in sys.modules:  # its own exit handler, registered before this one
    sys.modules["logging"].shutdown()
  for stream in (sys.stdout, sys.stderr):
    with contextlib.suppress(Exception):
      stream.flush()
  os._exit(_command.code)


def run_command(main: Callable[[], int | None], keep_outputs: bool = False,
                grace_s: float = STOP_GRACE_S, restore: bool = True) -> int:
  """Runs a command's `main()` and returns its exit code; SIGINT / SIGTERM stop it.

  A signal raises `Interrupted` in the main thread (a command may handle it itself, as
  the trainer does, `mjxvine.rundir.StopSignals`), once; whatever the main thread does,
  the command ends within `grace_s` (a watchdog thread ends it while the main thread is
  in compiled code), after a second signal within `AGAIN_S`. A stopped command removes
  its temporary files and, unless `keep_outputs` (the trainer's and the choice's files
  are what a resume continues), the files it wrote (`discard_partial`); says one line on
  stderr; exits 130 (SIGINT) or 143 (SIGTERM). A signal that `main` swallowed (e.g.
  raised in a JAX callback, which JAX turns into its own error) still exits so.
  `restore`: put the previous handlers back at the end. In the main thread, one command
  at a time; else `main()` as it is."""
  global _command, track_outputs
  if threading.current_thread() is not threading.main_thread() or (
      _command is not None and _command.running):
    return main() or 0
  if _command is None:
    _command = _Command()
    _command.install()
  command = _command
  command.keep_outputs, command.grace_s = keep_outputs, grace_s
  _writes.clear()  # an earlier command's files are not this one's to remove
  _made_dirs.clear()
  track_outputs = not keep_outputs
  try:
    command.running = True
    code = main() or 0
    command.stopping = True
    if command.signum and code != 128 + command.signum:  # swallowed, or late
      code = command.stopped(f"stopped by {signal.Signals(command.signum).name}")
    elif command.signum:  # the command said how it stopped
      command.said = True
      command.cleanup()
  except Interrupted as e:
    command.signum = command.signum or e.signum
    code = command.stopped(str(e))
  except BaseException:  # noqa: BLE001 - after a signal, whatever it turned into
    if not command.signum:  # (SystemExit: argparse's errors, --help)
      raise
    code = command.stopped(f"stopped by {signal.Signals(command.signum).name}")
  finally:
    command.stopping = True
    track_outputs = False
    _writes.clear()
    _made_dirs.clear()
    if restore:
      command.uninstall()
      _command = None
  command.code = code
  return code


def command_main(main: Callable[[], int | None], keep_outputs: bool = False) -> None:
  """Exits with `run_command(main)`'s code, for `if __name__ == "__main__"`. A stopped
  command ends at once (`os._exit`, its streams flushed): the interpreter's teardown
  can crash while XLA threads still compile; the handlers stay until then."""
  code = run_command(main, keep_outputs=keep_outputs, restore=False)
  if _command is not None and _command.signum:
    _flush(sys.stdout, sys.stderr)
    os._exit(code)
  sys.exit(code)


@contextlib.contextmanager
def on_stop(cleanup: Callable[[], str | None]):
  """While the block runs, `cleanup()` is part of a stop by a signal: run (and the note
  it returns said) by the command before it ends, maybe from the watchdog thread while
  the main thread is in compiled code, or here when the block ends by `Interrupted`. It
  may run in another thread, and twice."""
  command = _command
  if command is not None:
    command.cleanups.append(cleanup)
  try:
    yield
  except Interrupted:
    with contextlib.suppress(Exception):
      cleanup()
    raise
  finally:
    if command is not None:
      with contextlib.suppress(ValueError):
        command.cleanups.remove(cleanup)


def command_signal() -> int:
  """The signal this process's command received (0: none yet, or no command runs)."""
  return _command.signum if _command is not None else 0


def note_signal(signum: int, raise_now: bool, frame=None) -> bool:
  """For a handler that stands in for the command's for a while (`rundir.StopSignals`):
  notes `signum` for the command's exit code. With `raise_now`, whether the handler may
  raise `Interrupted` now in `frame` (`_Command.may_raise`: else it runs again later,
  out of a JAX callback)."""
  command = _command
  if command is None:
    return raise_now
  command.signum = command.signum or signum
  return raise_now and command.may_raise(frame)
