"""Outputs checked before the work and files written whole or not at all.

`check_output` tells, before a command starts its work, whether it can write where it was
asked to (`OutputError`, one line naming the flag, otherwise); `write_bytes`, `write_text`
and `atomic_path` write a temporary file in the same directory and rename it over the
target once complete (`os.replace`), so that a failure mid-write (a full disk, a signal)
leaves the previous file as it was and no half-written one."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Iterator


class OutputError(ValueError):
  """An output path that cannot be written: one line naming the flag, the path and why."""


def check_output(path: str | Path, flag: str, directory: bool = False) -> Path:
  """Checks, before any work, that `path` can be written: a directory (`directory`;
  created if missing) or a file (its directory created if missing; an existing file is
  replaced at the end). Probes with a temporary file, so a read-only or full file system
  and missing permissions are caught too. Returns the path; raises `OutputError`."""
  path = Path(path)
  folder = path if directory else path.parent
  if directory and path.exists() and not path.is_dir():
    raise OutputError(f"{flag} {path}: exists and is not a directory")
  if not directory and path.is_dir():
    raise OutputError(f"{flag} {path}: is a directory; give a file name")
  try:
    folder.mkdir(parents=True, exist_ok=True)
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
  try:
    yield tmp
    if tmp.exists():
      os.replace(tmp, path)
  finally:
    with contextlib.suppress(FileNotFoundError):
      tmp.unlink()


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
