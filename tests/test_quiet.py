"""`import mjxvine` drops three known messages of dependencies, and only those."""

import io
import logging
import subprocess
import sys
import warnings

from mjxvine import _quiet


def test_warp_lines_are_dropped_at_import():
  code = "import mjxvine, mujoco.mjx; print('ready')"
  out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120)
  assert out.returncode == 0, out.stderr
  assert "Failed to import" not in out.stdout + out.stderr
  assert out.stdout.splitlines()[-1] == "ready"


def test_drop_lines_keeps_other_output():
  target = io.StringIO()
  stream = _quiet._DropLines(target, _quiet._WARP_LINE)
  print("Failed to import warp:", ModuleNotFoundError("No module named 'warp'"), file=stream)
  print("Failed to import mujoco_warp: No module named 'warp'", file=stream)
  print("Failed to import warp: CUDA driver too old", file=stream)  # a real problem: kept
  print("other", "output", file=stream)
  stream.write("no newline")
  stream.flush()
  assert target.getvalue() == "Failed to import warp: CUDA driver too old\nother output\nno newline"


def test_absl_filter_drops_only_the_checkpoint_metadata_message():
  from absl import logging as absl_logging  # noqa: F401 - creates the "absl" logger
  import mjxvine  # noqa: F401 - installs the filter

  logger = logging.getLogger("absl")
  assert any(isinstance(f, _quiet._AbslFilter) for f in logger.filters)
  record = lambda msg, *args: logging.LogRecord("absl", logging.WARNING, __file__, 1, msg,
                                                args, None)
  assert not logger.filter(record("Metadata file does not exist: %s",
                                  "/runs/a/checkpoints/4/default/_CHECKPOINT_METADATA"))
  assert logger.filter(record("Metadata file does not exist: %s", "/runs/a/_METADATA"))
  assert logger.filter(record("Failed to read Metadata file: %s", "x/_CHECKPOINT_METADATA"))


def test_orbax_sharding_warning_is_filtered_by_message_and_module():
  # pytest restores the warning filters after collection, which imported mjxvine: again
  _quiet.install()

  def warn(module):
    with warnings.catch_warnings(record=True) as caught:
      warnings.warn_explicit("Sharding info not provided when restoring. Populating...",
                             UserWarning, "f.py", 1, module=module)
    return len(caught)

  assert warn("orbax.checkpoint._src.serialization.jax_array_handlers") == 0
  assert warn("somewhere.else") == 1
