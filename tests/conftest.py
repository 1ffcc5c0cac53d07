"""Shared fixtures: tiny configs and compiled objects built once per session."""

import os

# Keep XLA to what the CI machine has, and quiet.
os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=true")

import pytest  # noqa: E402

from mjxvine.config import load_config  # noqa: E402


@pytest.fixture(scope="session")
def cfg():
  """The default (paper) config."""
  return load_config()
