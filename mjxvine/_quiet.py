"""Drops three known, harmless messages of dependencies, and nothing else.

- mujoco-mjx prints "Failed to import warp: No module named 'warp'" and the same line for
  mujoco_warp to stdout (a `print` in mujoco/mjx/warp/__init__.py, run when `mujoco.mjx`
  is imported) whenever the optional NVIDIA Warp backend is not installed. Those two lines
  are dropped while that module is imported; any other output (or another reason, e.g. an
  installed Warp that fails to load) still shows.
- orbax logs through absl (python logger "absl") "Metadata file does not exist:
  .../_CHECKPOINT_METADATA" when one item directory of a CheckpointManager step is
  restored on its own, which is what `mjxvine.export` does: the step-level metadata is
  one directory up. Only that message about that file is filtered.
- orbax warns (UserWarning) "Sharding info not provided when restoring. Populating
  sharding info from sharding file..." when a jax.Array is restored without a sharding.

`install()` runs once, from `import mjxvine`, before mujoco.mjx, absl or orbax are
imported; it imports none of them (hooks act when they are imported), so the numpy-only
`mjxvine.deploy` stays numpy-only.
"""

from __future__ import annotations

import contextlib
import importlib.abc
import io
import logging
import re
import sys
import warnings

# Lines that mujoco/mjx/warp/__init__.py prints when Warp is simply not installed.
_WARP_LINE = re.compile(r"Failed to import (mujoco_)?warp: No module named '(warp|warp\.\w+)'")
_ABSL_MESSAGE = "Metadata file does not exist: %s"
_ORBAX_WARNING = r"Sharding info not provided when restoring"


class _DropLines(io.TextIOBase):
  """A text stream forwarding whole lines to `target`, except lines matching `pattern`."""

  def __init__(self, target, pattern: re.Pattern):
    self.target, self.pattern, self.pending = target, pattern, ""

  def writable(self) -> bool:
    return True

  def write(self, text: str) -> int:
    # print() writes its arguments and the newline separately: buffer up to a newline.
    self.pending += text
    *lines, self.pending = self.pending.split("\n")
    for line in lines:
      if not self.pattern.fullmatch(line):
        self.target.write(line + "\n")
    return len(text)

  def flush(self) -> None:
    if self.pending and not self.pattern.fullmatch(self.pending):
      self.target.write(self.pending)
    self.pending = ""
    self.target.flush()


@contextlib.contextmanager
def _quiet_warp_import():
  stream = _DropLines(sys.stdout, _WARP_LINE)
  try:
    with contextlib.redirect_stdout(stream):
      yield
  finally:
    stream.flush()


class _AbslFilter(logging.Filter):
  """Rejects orbax's "Metadata file does not exist: .../_CHECKPOINT_METADATA" record."""

  def filter(self, record: logging.LogRecord) -> bool:
    return not (record.msg == _ABSL_MESSAGE and record.args and
                str(record.args[0]).endswith("_CHECKPOINT_METADATA"))


def _filter_absl() -> None:
  # absl must create its logger itself (it sets its logger class first): only attach the
  # filter once absl.logging is imported.
  logger = logging.getLogger("absl")
  if not any(isinstance(f, _AbslFilter) for f in logger.filters):
    logger.addFilter(_AbslFilter())


class _Loader(importlib.abc.Loader):
  """Runs `loader.exec_module` inside `around()`, then `after()`."""

  def __init__(self, loader, around=None, after=None):
    self.loader, self.around, self.after = loader, around, after

  def create_module(self, spec):
    return self.loader.create_module(spec)

  def exec_module(self, module) -> None:
    # the module keeps its own loader (resources, reloads)
    module.__loader__ = self.loader
    if module.__spec__ is not None:
      module.__spec__.loader = self.loader
    with self.around() if self.around else contextlib.nullcontext():
      self.loader.exec_module(module)
    if self.after:
      self.after()


# module name -> (context manager around its import, callback after it)
_HOOKS = {"mujoco.mjx.warp": (_quiet_warp_import, None), "absl.logging": (None, _filter_absl)}


class _Finder(importlib.abc.MetaPathFinder):
  """Finds the modules of `_HOOKS` with the other finders and wraps their loader."""

  def find_spec(self, name, path, target=None):
    if name not in _HOOKS:
      return None
    for finder in sys.meta_path:
      if finder is self or not hasattr(finder, "find_spec"):
        continue
      spec = finder.find_spec(name, path, target)
      if spec is not None:
        break
    else:
      return None
    if spec.loader is not None and hasattr(spec.loader, "exec_module"):
      spec.loader = _Loader(spec.loader, *_HOOKS[name])
    return spec


def install() -> None:
  """Installs the filters (idempotent)."""
  warnings.filterwarnings("ignore", message=_ORBAX_WARNING, category=UserWarning,
                          module=r"orbax\.checkpoint\.")
  if "absl.logging" in sys.modules:
    _filter_absl()
  if not any(isinstance(f, _Finder) for f in sys.meta_path):
    sys.meta_path.insert(0, _Finder())
