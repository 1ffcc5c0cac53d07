"""The shipped policy, models/jackal.npz: it loads and acts with numpy alone, its metadata
is the config that trained it (experiments/jackal.yaml), and on the JAX evaluator it
drives test world 0's lane 1 forward (straight) and lane 4 in reverse (curved) to the end
of the row."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import NUMPY_ONLY_PRELUDE

from mjxvine.config import config_hash, load_config, to_dict
from mjxvine.deploy import NumpyPolicy
from mjxvine.episodes import OUTCOMES, SUCCESS
from mjxvine.evaluation.metrics import summarize
from mjxvine.evaluation.rollout import PolicySource, rollout_cases
from mjxvine.rundir.settings import policy_config
from mjxvine.worlds import load_test_world

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "jackal.npz"
CONFIG = ROOT / "experiments" / "jackal.yaml"

_NUMPY_ONLY = NUMPY_ONLY_PRELUDE + textwrap.dedent("""
  import numpy as np
  from mjxvine.deploy import NumpyPolicy
  policy = NumpyPolicy.load(sys.argv[1])
  h, w = policy.meta["image_size"]
  depth = np.full((h, w), 3.0, np.float32)
  depth[:, : w // 3] = 1.0  # a row close on the left
  v, w = policy(depth, np.zeros(3, np.float32))
  assert not [m for m in sys.modules if m.split(".")[0] in BLOCKED]
  print(v, w)
""")


def test_loads_and_acts_with_numpy_alone():
  env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get(
      "PYTHONPATH", "")]), OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
  out = subprocess.run([sys.executable, "-c", _NUMPY_ONLY, str(MODEL)], capture_output=True,
                       text=True, env=env, timeout=120)
  assert out.returncode == 0, out.stderr
  v, w = (float(x) for x in out.stdout.split())
  meta = NumpyPolicy.load(MODEL).meta
  assert meta["action_low"][0] <= v <= meta["action_high"][0]
  assert meta["action_low"][1] <= w <= meta["action_high"][1]


def test_metadata_is_the_config_that_trained_it():
  """The file's config, read as `evaluate` reads it, is the config file's, the conv tower
  aside: the config leaves it to the backend (`auto`), and the file records the tower that
  ran (`native` on an x86-64 CPU) and its kernel's instruction set. Its hash is that of
  what it records, and its run's record ends at the config's env-step budget."""
  meta = NumpyPolicy.load(MODEL).meta
  cfg = load_config(str(CONFIG))
  assert cfg.train.conv_impl == "auto"
  assert meta["config"]["train"]["conv_impl"] == "native"
  assert meta["conv_tower"].startswith("native (")
  file_cfg, _ = policy_config(MODEL, overrides=["train.conv_impl=auto"])
  assert to_dict(file_cfg) == to_dict(cfg)
  record = ROOT / "docs" / "results" / "shipped-agent" / "metrics.jsonl"  # its run's record
  assert json.loads(record.read_text().splitlines()[-1])["env_steps"] == cfg.train.total_env_steps
  assert meta["env_steps"] == json.loads(
      (record.parent / "selection.json").read_text())["selected"]
  assert meta["config_hash"] == config_hash(meta["config"])
  assert meta["image_size"] == [cfg.camera.height, cfg.camera.width]
  assert meta["max_depth_m"] == cfg.camera.max_depth_m


def test_the_evaluator_acts_as_the_robot():
  """On random views, the JAX policy that `evaluate` loads gives the numpy policy's
  actions, mirror-averaged or not as the file says (`sac.mirror_average`), and
  `--set sac.mirror_average=true` makes it exactly symmetric: a mirrored view gets the
  mirrored action."""
  import jax.numpy as jp

  from mjxvine.env import VineyardEnv
  from mjxvine.evaluation import policies

  numpy_policy = NumpyPolicy.load(MODEL)
  cfg, _ = policy_config(MODEL)
  assert cfg.sac.mirror_average == numpy_policy.mirror_average
  env = VineyardEnv(cfg, [load_test_world(cfg.world)])
  rng = np.random.default_rng(0)
  h, w = numpy_policy.meta["image_size"]
  depth = rng.uniform(0.5, cfg.camera.max_depth_m, (4, h, w, 1)).astype(np.float32)
  state = rng.uniform([0.0, -1.0, -0.5], [0.5, 1.0, 0.5], (4, 3)).astype(np.float32)
  obs = {"depth": jp.asarray(depth), "state": jp.asarray(state)}
  act = lambda policy, o: np.asarray(policy(SimpleNamespace(obs=o), None))  # a State's .obs
  np.testing.assert_allclose(act(policies.load_actor_policy(MODEL, env), obs),
                             numpy_policy.action(depth, state), atol=1e-4)
  sym_cfg, _ = policy_config(MODEL, overrides=["sac.mirror_average=true"])
  sym = policies.load_actor_policy(MODEL, VineyardEnv(sym_cfg, env.worlds))
  got = act(sym, obs)
  np.testing.assert_allclose(act(sym, VineyardEnv.mirror_obs(obs)), got * [1.0, -1.0],
                             atol=1e-5)


@pytest.mark.slow  # a minute on 2 cores: it compiles the evaluator at the policy's image size
def test_drives_a_straight_and_a_curved_lane_to_the_end():
  cfg, _ = policy_config(MODEL)
  world = load_test_world(cfg.world)
  assert world.lanes[0].shape == "straight" and world.lanes[3].shape == "curved"
  noise = cfg.eval.noise_factor
  raw, _ = rollout_cases(cfg, PolicySource(str(MODEL)), [world],
                         [(0, 1, "F", noise), (0, 4, "R", noise)])
  assert [OUTCOMES[int(o)] for o in raw["outcome"]] == [OUTCOMES[SUCCESS]] * 2
  doc = summarize(cfg, world, [(0, 1, "F", noise), (0, 4, "R", noise)], [0, 1], raw)
  assert doc["overall"]["mae_m_rows"] < 0.15  # near the centre line, not along a row
