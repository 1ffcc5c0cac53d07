"""SAC learns: a short CPU training run on short straight lanes ends with a deterministic
policy that reaches the end of the row far more often than a random policy and than the
untrained network, from the same random starts (64 episodes each)."""

import functools

import jax
import jax.numpy as jp
import numpy as np

from mjxvine import evaluate
from mjxvine import train as train_mod
from mjxvine.config import load_config
from mjxvine.env import SUCCESS, VineyardEnv

# 4 m straight rows, forward starts only (world yaw near 0, see env.start_directions),
# 40x40 depth, small networks, the reward scale of experiments/fast.yaml.
LEARN = ["world.pool_size=4", "world.train_length_m=4", "camera.width=40", "camera.height=40",
         "env.num_envs=16", "env.max_steps=150", "env.start_yaw_jitter_deg=5",
         "env.start_directions=forward", "sac.batch_size=128", "sac.buffer_size=20000",
         "sac.warmup_steps=1600", "sac.hidden=64", "sac.conv_features=8", "sac.eps_start=0.1",
         "sac.grad_steps_per_iter=4", "sac.learning_rate=0.001", "sac.reward_scale=0.01",
         "sac.alpha=0.002", "train.total_env_steps=3200", "train.iters_per_chunk=25",
         "train.checkpoint_every_chunks=100", "eval.runs_after_train=0"]


def test_sac_beats_random_on_a_short_straight_lane(tmp_path):
  cfg = load_config(None, LEARN)
  env = VineyardEnv(cfg)  # one pool of worlds for training and the check
  train_mod.train(cfg, tmp_path, quiet=True, evaluate_at_end=False, env=env)
  sac, init_fn, _ = train_mod.compiled_trainer(cfg, env=env)
  untrained = init_fn(jax.random.split(jax.random.PRNGKey(cfg.train.seed), 1))
  _, trained = train_mod.Checkpoints(tmp_path, False).restore(untrained)
  assert int(trained.env_steps) == 3200

  def policy(p, state, key):
    mean_action = sac.act_deterministic(p["actor"], state.obs)
    uniform = jax.random.uniform(key, (2,), minval=env.action_low, maxval=env.action_high)
    return jp.where(p["random"], uniform, mean_action)

  outcomes = jax.jit(functools.partial(evaluate.start_outcomes, env, policy, episodes=64))
  success = {}
  for name, learner, rand in (("trained", trained, False), ("untrained", untrained, False),
                              ("random", untrained, True)):
    out = outcomes({"actor": learner.learner.actor_params, "random": rand},
                   jax.random.PRNGKey(7))
    success[name] = float(np.mean(np.asarray(out) == SUCCESS))
  assert success["trained"] >= success["random"] + 0.4, success
  assert success["trained"] >= success["untrained"] + 0.1, success
