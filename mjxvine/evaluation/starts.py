"""Deterministic evaluation from fresh random starts of the training pool, forward and
reverse counted apart: the quick check that a training run runs during and after learning.

The paper's protocol (`rollout.run_protocol`) drives the test world from each lane's start;
this drives `starts` episodes per travel direction from the env's own random starts
(random pool world, lane, point along it, lateral and yaw jitter), with the policy's
deterministic action, and reports per direction the success rate and the mean absolute
lateral offset (m) from the lane centreline while driving.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jp
import numpy as np

from mjxvine.env import RUNNING, SUCCESS, TIMEOUT, VineyardEnv, lane_frame

CHECK_EVERY = 10  # steps between host checks whether every episode has ended
# The policies `with_baselines` drives: the actor's deterministic action, the constant
# drive-straight action [v_max, 0], and uniform random actions.
ACTOR, STRAIGHT, RANDOM = 0, 1, 2
BASELINES = {"straight": STRAIGHT, "random": RANDOM}
# The start points' range (fractions of the row length from the lane's start) of every
# evaluation (training draws from the same range, `env.START_ALONG`): one yardstick.
EVAL_START_ALONG = (0.0, 0.6)


def with_baselines(act_deterministic: Callable, low: jax.Array, high: jax.Array) -> Callable:
  """act(p, obs, key) for `make_start_eval` with p = {"actor": actor params, "policy":
  ACTOR | STRAIGHT | RANDOM (int32)}: one compiled evaluation serves the trained policy and
  the two baselines it must beat, from the same starts."""
  def act(p, obs, key):
    batch = obs["state"].shape[0]
    actor = act_deterministic(p["actor"], obs)
    straight = jp.broadcast_to(jp.stack([high[0], jp.zeros_like(high[1])]), (batch, 2))
    uniform = jax.random.uniform(key, (batch, 2), minval=low, maxval=high)
    return jp.select([p["policy"] == STRAIGHT, p["policy"] == RANDOM],
                     [straight, uniform], actor)
  return act


def make_start_eval(env: VineyardEnv, act: Callable, starts: int, members: int = 1):
  """Returns `run(actor_params, key) -> dict of numpy arrays` (a leading members axis when
  `members` > 1, params stacked the same way; every member drives the same starts).

  act(actor_params, obs, key) -> actions (B, 2): the batched policy (the trainer's is the
  actor's deterministic action and ignores the key; baselines may draw from it).
  The dict: success_forward, success_reverse (fractions of `starts` episodes each),
  mae_m (mean |lateral offset| over the steps driven, both directions), timeout (fraction
  of episodes that timed out), v_mean (m/s, mean commanded speed while driving).
  """
  n = 2 * starts
  directions = jp.concatenate([jp.ones(starts), -jp.ones(starts)])

  def reset(key):
    state = jax.vmap(lambda k, d: env.reset(k, d, EVAL_START_ALONG))(
        jax.random.split(key, n), directions)
    z = jp.zeros(n, jp.float32)
    return state, jp.full(n, RUNNING, jp.int32), z, z, z

  def lateral(state):
    pose = state.info["pose"]
    line, k, _, _ = env.lanes.lane(pose["world"], pose["lane"])
    return lane_frame(line, state.pipeline_state.qpos[:2], pose["direction"], k)[2]

  def step(params, carry, key):
    state, outcome, err, speed, steps = carry
    action = act(params, state.obs, key)
    driving = (outcome == RUNNING).astype(jp.float32)
    err = err + driving * jp.abs(jax.vmap(lateral)(state))
    speed = speed + driving * action[:, 0]
    steps = steps + driving
    # no auto-reset: an ended episode stays ended (and its env stops costing a reset)
    state = jax.vmap(env.step)(state, action)
    first = (outcome == RUNNING) & (state.done > 0)
    outcome = jp.where(first, state.info["outcome"], outcome)
    return state, outcome, err, speed, steps

  def summary(carry):
    _, outcome, err, speed, steps = carry
    ok = outcome == SUCCESS
    return {"success_forward": jp.mean(ok[:starts]), "success_reverse": jp.mean(ok[starts:]),
            "mae_m": jp.sum(err) / jp.maximum(jp.sum(steps), 1.0),
            "timeout": jp.mean(outcome == TIMEOUT),
            "v_mean": jp.sum(speed) / jp.maximum(jp.sum(steps), 1.0)}

  if members > 1:
    reset_fn = jax.jit(lambda key: jax.vmap(lambda _: reset(key))(jp.arange(members)))
    step_fn = jax.jit(jax.vmap(step, (0, 0, None)), donate_argnums=1)
    summary_fn = jax.jit(jax.vmap(summary))
  else:
    reset_fn, step_fn, summary_fn = jax.jit(reset), jax.jit(step, donate_argnums=1), \
        jax.jit(summary)

  def run(actor_params, key) -> dict:
    if jax.device_count() == 1:
      # Params placed by the trainer's mesh would give the step's outputs another
      # placement than the reset's, and the step would compile twice (once per placement).
      actor_params = jax.device_get(actor_params)
    key, k_reset = jax.random.split(key)
    carry = reset_fn(k_reset)
    for t in range(env.cfg.env.max_steps):
      carry = step_fn(actor_params, carry, jax.random.fold_in(key, t))
      if (t + 1) % CHECK_EVERY == 0 and not np.any(np.asarray(carry[1]) == RUNNING):
        break
    return {k: np.asarray(v) for k, v in jax.device_get(summary_fn(carry)).items()}

  return run
