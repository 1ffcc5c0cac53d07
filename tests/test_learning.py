"""SAC learns the task in both travel directions: a short CPU training run of
experiments/lanes.yaml (4 m rows, starts with up to 25 deg of yaw and 0.3 m of lateral
offset) ends with a deterministic policy that, in EACH direction, reaches the end of the
row from fresh starts far more often than a random policy and than driving straight."""

import jax
import jax.numpy as jp

from mjxvine import starts
from mjxvine import train as train_mod
from mjxvine.config import load_config

BUDGET = ["train.total_env_steps=6400", "train.eval_every_chunks=0"]
MARGIN = 0.3


def test_sac_beats_random_and_straight_in_both_directions(tmp_path):
  cfg = load_config("experiments/lanes.yaml", BUDGET)
  row = train_mod.train(cfg, tmp_path, quiet=True, evaluate_at_end=False)
  assert row["env_steps"] == 6400
  sac, init_fn, _ = train_mod.compiled_trainer(cfg)
  template = init_fn(jax.random.split(jax.random.PRNGKey(cfg.train.seed), 1))
  _, last = train_mod.Checkpoints(tmp_path, False).restore(template)
  env = train_mod._default_env(train_mod._compile_key(cfg))

  def act(p, obs, key):
    batch = obs["state"].shape[0]
    trained = sac.act_deterministic(p["actor"], obs)
    uniform = jax.random.uniform(key, (batch, 2), minval=env.action_low,
                                 maxval=env.action_high)
    straight = jp.broadcast_to(jp.array([cfg.env.v_max, 0.0]), (batch, 2))
    return jp.where(p["random"], uniform, jp.where(p["straight"], straight, trained))

  run = starts.make_start_eval(env, act, starts=48)
  success = {}
  for name, rand, straight in (("trained", False, False), ("random", True, False),
                               ("straight", False, True)):
    out = run({"actor": last.learner.actor_params, "random": rand, "straight": straight},
              jax.random.PRNGKey(11))
    success[name] = (float(out["success_forward"]), float(out["success_reverse"]))
  for d, direction in enumerate(("forward", "reverse")):
    trained = success["trained"][d]
    assert trained >= success["random"][d] + MARGIN, (direction, success)
    assert trained >= success["straight"][d] + MARGIN, (direction, success)
