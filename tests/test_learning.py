"""SAC learns the task in both travel directions: experiments/lanes.yaml as it is (4 m rows,
starts with up to 25 deg of yaw and 0.3 m of lateral offset, 16,000 env steps; about 5
minutes on 2 cores) ends with a best checkpoint whose deterministic policy, in EACH
direction, reaches the end of the row from fresh starts far more often than a random
policy and than driving straight from the same starts."""

import jax
import pytest

from mjxvine import starts
from mjxvine import train as train_mod
from mjxvine.config import load_config

pytestmark = pytest.mark.slow  # minutes on 2 cores: `pytest -m slow` (CI runs it)

MARGIN = 0.25


def test_sac_beats_random_and_straight_in_both_directions(tmp_path):
  cfg = load_config("experiments/lanes.yaml")
  row = train_mod.train(cfg, tmp_path, quiet=True, evaluate_at_end=False)
  assert row["env_steps"] == cfg.train.total_env_steps
  sac, init_fn, _ = train_mod.compiled_trainer(cfg)
  template = init_fn(jax.random.split(jax.random.PRNGKey(cfg.train.seed), 1))
  _, best = train_mod.Checkpoints(tmp_path, False).restore(template, best=True)
  run = train_mod.start_evaluator(cfg)  # the run's own compiled evaluation
  key = jax.random.PRNGKey(11)  # other starts than the ones the best was chosen on
  success = {}
  for name, policy in (("trained", starts.ACTOR), *starts.BASELINES.items()):
    out = run(train_mod.starts_params(best.learner.actor_params, policy), key)
    success[name] = (float(out["success_forward"]), float(out["success_reverse"]))
  for d, direction in enumerate(("forward", "reverse")):
    trained = success["trained"][d]
    assert trained >= success["random"][d] + MARGIN, (direction, success)
    assert trained >= success["straight"][d] + MARGIN, (direction, success)
