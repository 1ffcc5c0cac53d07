"""Data parallelism over devices (mjxvine.training.parallel): on 4 host CPU devices, in a fresh
process (the device count is fixed when JAX starts), one chunk trains on 1 and on 4
devices; the envs and the replay are split over the devices, and the first gradient step
agrees to float tolerance."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # minutes on 2 cores: `pytest -m slow` (CI runs it)

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def report():
  env = dict(os.environ, PYTHONPATH=str(ROOT))
  out = subprocess.run([sys.executable, str(ROOT / "tests" / "parallel_check.py")], cwd=ROOT,
                       env=env, capture_output=True, text=True, timeout=900)
  assert out.returncode == 0, out.stderr[-3000:]
  return json.loads(out.stdout.strip().splitlines()[-1])


def test_envs_and_replay_are_split_over_four_devices(report):
  assert report["devices"] == 4
  assert report["env_devices"] == 4
  assert report["depth_split_on_env_axis"]
  assert report["metric_keys_equal"] and report["finite"]


def test_one_and_four_devices_agree_on_the_first_update(report):
  assert report["updates"] == [1, 1]
  l1, l4 = report["critic_loss"]
  # the envs step in different vectorised layouts: float rounding, not different data
  assert l1 > 0 and abs(l1 - l4) <= 1e-3 * abs(l1)
  # the envs are split, not changed: the same observations on 1 and 4 devices, up to
  # the odd ray that grazes an edge (one pixel of 5,184 on some CPUs)
  assert report["state_obs_max_diff"] < 1e-3
  assert report["depth_frac_differ"] < 0.005
  # the same update from the same state and replay, on 1 device and split over 4
  u1, u4 = report["update_critic_loss"]
  assert abs(u1 - u4) <= 1e-5 * abs(u1)
  # Adam's first step is ~lr * sign(gradient) per parameter: all but the parameters with
  # near-zero gradients (whose sign depends on the summation order) agree
  assert report["param_diff_frac"] < 0.01
