"""The privileged reference driver: pure pursuit on the lane centreline, from the true pose
(`mjxvine.env` re-exports it). It is the yardstick's yardstick: it must drive every test
lane."""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jp
import numpy as np
from brax.envs.base import State

from mjxvine.angles import quat_yaw, wrap
from mjxvine.lanes import lane_frame, point_ahead


def pure_pursuit(env: Any, lookahead_m: float = 1.0, speed: float | None = None
                 ) -> Callable[[State, jax.Array], jax.Array]:
  """A pure-pursuit driver of `env` (a `mjxvine.env.VineyardEnv`) aiming `lookahead_m`
  ahead on the lane centerline at `speed` m/s (default env.v_max), using the true pose.

  Returns `policy(state, key) -> action (2,)` [v m/s, w rad/s] of one env (vmap for a
  batch), the signature of learned policies in `mjxvine.evaluate`.
  """
  v_cmd = env.cfg.env.v_max if speed is None else speed
  ahead = int(np.ceil(lookahead_m / env.sample_m))

  def policy(state: State, key: jax.Array) -> jax.Array:
    del key
    pose = state.info["pose"]
    d = state.pipeline_state
    xy, yaw = d.qpos[:2], quat_yaw(d.qpos[3:7])
    line, k, _, _ = env.lanes.lane(pose["world"], pose["lane"])
    i, _, _, _ = lane_frame(line, xy, pose["direction"], k)
    rel = point_ahead(line, i, pose["direction"], ahead, k) - xy
    alpha = wrap(jp.arctan2(rel[1], rel[0]) - yaw)
    dist = jp.maximum(jp.linalg.norm(rel), 0.3)
    w = 2.0 * v_cmd * jp.sin(alpha) / dist
    v = v_cmd * jp.clip(jp.cos(alpha), 0.2, 1.0)
    return jp.clip(jp.array([v, w]), env.action_low, env.action_high)

  return policy


__all__ = ["pure_pursuit"]
