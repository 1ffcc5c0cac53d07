"""Shared fixtures: tiny configs and compiled objects built once per session.

XLA's compiled programs are kept on disk (JAX's persistent compilation cache, in
.pytest_cache/): tests and their subprocesses that compile the same program compile it
once, and a second local run of the suite compiles little. The slow tests (marked
`slow`: the learning run, 4 devices, the notebook) run with `pytest -m slow`."""

import os
import textwrap
from pathlib import Path

# Keep XLA to what the CI machine has, and quiet.
os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=true")
# Before jax is imported: subprocesses (notebook kernel, 4-device check) inherit it.
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR",
                      str(Path(__file__).resolve().parent.parent / ".pytest_cache" / "xla"))

import ast  # noqa: E402
import gc  # noqa: E402

import pytest  # noqa: E402

# The start of a subprocess script that must run with numpy alone (the robot's side):
# importing jax, flax, mujoco, brax, optax or orbax raises; BLOCKED names them.
NUMPY_ONLY_PRELUDE = textwrap.dedent("""
  import sys
  BLOCKED = ("jax", "jaxlib", "flax", "mujoco", "brax", "optax", "orbax")
  class Block:
    def find_spec(self, name, path=None, target=None):
      if name.split(".")[0] in BLOCKED:
        raise ImportError(f"blocked import of {name}")
      return None
  sys.meta_path.insert(0, Block())
""")

from mjxvine.config import load_config  # noqa: E402


@pytest.fixture(scope="session")
def cfg():
  """The default (paper) config."""
  return load_config()


def parse_source(text: str, **kw) -> ast.Module:
  """`ast.parse` with the garbage collector paused: CPython 3.11 raises "AST constructor
  recursion depth mismatch" when a finalizer (asyncio's, orbax's, left by earlier tests)
  runs Python code while the tree's objects are built."""
  enabled = gc.isenabled()
  gc.disable()
  try:
    return ast.parse(text, **kw)
  finally:
    if enabled:
      gc.enable()

