"""The trainer is not vineyard-specific: through `wrappers.brax_env` it trains a brax `Env` with
vector observations (a small point-mass task here; brax's own envs work the same way but
take ~40 s to compile on 2 CPU cores)."""

import json

import jax
import jax.numpy as jp
import numpy as np
import pytest
from brax.envs.base import Env, State

from mjxvine.training import loop
from mjxvine.wrappers import brax_env
from mjxvine.config import load_config
from mjxvine.episodes import TIMEOUT


class PointToTarget(Env):
  """x in R, action a in [-1, 1] moves x by 0.2 a; reward -|x - 1|; x0 ~ U(-1, 1)."""

  def reset(self, rng):
    x = jax.random.uniform(rng, (1,), minval=-1.0, maxval=1.0)
    return State(pipeline_state=x, obs=x, reward=jp.zeros(()), done=jp.zeros(()),
                 metrics={}, info={})

  def step(self, state, action):
    x = state.pipeline_state + 0.2 * jp.clip(action, -1.0, 1.0)
    return state.replace(pipeline_state=x, obs=x, reward=-jp.abs(x[0] - 1.0))

  @property
  def observation_size(self):
    return 1

  @property
  def action_size(self):
    return 1

  @property
  def backend(self):
    return "jax"


def test_brax_env_truncates_and_resets():
  env = brax_env(PointToTarget(), episode_length=3)
  s = env.reset_batch(jax.random.PRNGKey(0), 2)
  step = jax.jit(env.step_batch)
  x0 = np.asarray(s.obs)
  for t in range(3):
    s, final = step(s, jp.ones((2, 1)))
  assert np.all(s.done == 1) and np.all(s.info["truncation"] == 1)
  np.testing.assert_allclose(final, np.minimum(x0 + 0.6, x0 + 0.6), atol=1e-6)
  assert not np.allclose(s.obs, final)  # reset to a new start
  assert np.all(s.info["steps"] == 0) and np.all(s.info["last_return"] < 0)
  assert np.all(s.info["last_outcome"] == TIMEOUT) and np.all(s.info["episodes"] == 1)
  s, _ = step(s, jp.ones((2, 1)))
  assert np.all(s.done == 0) and np.all(s.info["steps"] == 1)


@pytest.mark.slow  # over 20 s on a 2-core CPU: the fast suite stays within 12 minutes
def test_sac_trainer_learns_a_brax_env(tmp_path):
  cfg = load_config(None, [
      "env.num_envs=8", "sac.batch_size=64", "sac.buffer_size=20000", "sac.warmup_steps=400",
      "sac.hidden=64", "sac.eps_start=0.0", "sac.grad_steps_per_iter=2",
      "sac.learning_rate=0.001", "train.iters_per_chunk=50", "train.total_env_steps=6000",
      "train.checkpoint_every_chunks=100"])
  env = brax_env(PointToTarget(), episode_length=20)
  loop.train(cfg, tmp_path, quiet=True, env=env)
  rows = [json.loads(l) for l in (tmp_path / "metrics.jsonl").read_text().splitlines()]
  first, last = rows[0]["return_mean"], rows[-1]["return_mean"]
  # random actions: about -20 per 20-step episode; reaching x = 1 and staying: about -3
  assert first < -10 and last > -7, (first, last)
