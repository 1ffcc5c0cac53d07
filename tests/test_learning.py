"""SAC learns the task in both travel directions: the default run (experiments/default.yaml
as it is: 4 m rows, starts with up to 15 deg of yaw and 0.2 m of lateral offset, 16,000
env steps; about 3.5 minutes on 2 cores, without its closing test-world evaluation) ends
with a best checkpoint whose deterministic policy, in EACH direction, reaches the end of
the row clearly more often than driving straight and than random actions, from 128 fresh
starts per direction that are harder than the training ones (up to 25 deg and 0.3 m:
driving straight solves under half of them, so the policy must steer from the image).

Why harder starts: from the training starts driving straight solves 70-85 %, which
leaves too little room for a clear margin, and which side of it a run lands on changed
with the last bits of its arithmetic (another CPU, another fusion of the same step)."""

import jax
import pytest

from mjxvine.evaluation import starts
from mjxvine.training import loop
from mjxvine.training import programs
from mjxvine.rundir.checkpoints import Checkpoints
from mjxvine.config import load_config, replace

pytestmark = pytest.mark.slow  # minutes on 2 cores: `pytest -m slow` (CI runs it)

MARGIN_STRAIGHT = 0.2  # driving straight solves about 45-50 % of these starts
MARGIN_RANDOM = 0.4
HARD_STARTS = {"start_yaw_jitter_deg": 25.0, "start_lateral_jitter_m": 0.3}


def test_sac_beats_random_and_straight_in_both_directions(tmp_path):
  cfg = load_config("experiments/default.yaml")
  row = loop.train(cfg, tmp_path, quiet=True, evaluate_at_end=False)
  assert row["env_steps"] == cfg.train.total_env_steps
  sac, init_fn, _ = programs.compiled_trainer(cfg)
  template = init_fn(jax.random.split(jax.random.PRNGKey(cfg.train.seed), 1))
  _, best = Checkpoints(tmp_path, False).restore(template, best=True)
  run = programs.start_evaluator(replace(cfg, env=HARD_STARTS, train={"eval_starts": 128}))
  key = jax.random.PRNGKey(11)
  success = {}
  for name, policy in (("trained", starts.ACTOR), *starts.BASELINES.items()):
    out = run(programs.starts_params(best.learner.averaged_actor_params, policy), key)
    success[name] = (float(out["success_forward"]), float(out["success_reverse"]))
  for d, direction in enumerate(("forward", "reverse")):
    trained = success["trained"][d]
    assert trained >= success["random"][d] + MARGIN_RANDOM, (direction, success)
    assert trained >= success["straight"][d] + MARGIN_STRAIGHT, (direction, success)
    assert trained >= 0.7, (direction, success)
