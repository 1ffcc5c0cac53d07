"""Outputs that would write over a command's own inputs (`check_not_input`), and the
error of an output that cannot be written (`OutputError`); `mjxvine.atomic.check_output`
applies both before a command starts its work."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence


class OutputError(ValueError):
  """An output path that cannot be written: one line naming the flag, the path and why."""


def check_not_input(path: str | Path, flag: str, inputs: Sequence[tuple],
                    writes: Sequence[str] | None = None, own: Sequence[str | Path] = ()) -> None:
  """Refuses (`OutputError`) an output that would write over what the command reads.
  `inputs`: (path, what) pairs, e.g. (args.world, "the --world file"), those that do not
  exist (a seed, a built-in name) passed over. A file input may be neither the output
  file `path` nor, for an output directory (`writes` given: the names the command writes
  in it, a name ending in "/" a folder of them), one of those files or inside those
  folders. A directory input (a run directory) may not hold the output at all, but for
  the paths `own` (what the command writes there itself, e.g. RUN/policy.npz). Paths
  compare resolved (links followed), so another spelling of an input is refused too."""
  out = Path(path)
  targets = [(out, False)] + ([] if writes is None else
                              [(out / n.rstrip("/"), n.endswith("/")) for n in writes])
  mine = {Path(p).resolve() for p in own}
  for given, what in inputs:
    if given is None or str(given) == "" or not Path(given).exists():
      continue
    source = Path(given).resolve()
    if source.is_dir():
      place = out.resolve()  # an output directory, or the file
      if (place == source or source in place.parents) and place not in mine:
        hint = f" (or {Path(own[0])})" if own else ""
        raise OutputError(f"{flag} {path}: inside {what} {given}, which this command reads; "
                          f"give a path outside it{hint}")
      continue
    for target, folder in targets:
      place = target.resolve()
      if place == source or (folder and place in source.parents) or (
          target.exists() and os.path.samefile(target, source)):
        where = "is" if target == out else f"would write {target.name} over"
        raise OutputError(f"{flag} {path}: {where} {what} {given}, an input of this command; "
                          "give another path")
