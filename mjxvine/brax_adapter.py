"""Any brax `Env` behind the batched interface `mjxvine.train` uses.

`VineyardEnv` already offers `reset_batch(rng, n)` and `step_batch(state, action) ->
(state, pre-reset obs)` with auto-reset, a truncation flag and episode returns in `info`.
`BraxAdapter` gives the same to a plain brax environment (e.g.
`brax.envs.get_environment("inverted_pendulum")`), so that the same SAC trainer runs on
brax's own tasks: vector observations go through the MLP torso of `mjxvine.networks`.
"""

from __future__ import annotations

import jax
import jax.numpy as jp
from brax.envs.base import Env, State

from mjxvine.env import RUNNING


class BraxAdapter:
  """Batched auto-resetting wrapper with a time limit of `episode_length` steps.

  A time-out is a truncation (`info["truncation"]` 1, `done` 1); the env's own `done` is a
  terminal. Actions are in [action_low, action_high] (brax envs take [-1, 1])."""

  def __init__(self, env: Env, episode_length: int, action_low: float = -1.0,
               action_high: float = 1.0):
    self.env = env
    self.episode_length = episode_length
    self.action_size = env.action_size
    self.action_low = jp.full((env.action_size,), action_low, jp.float32)
    self.action_high = jp.full((env.action_size,), action_high, jp.float32)

  def _with_info(self, state: State, key: jax.Array) -> State:
    z = jp.zeros((), jp.float32)
    info = dict(state.info, adapter_rng=key, steps=jp.zeros((), jp.int32), episode_return=z,
                last_return=z, last_outcome=jp.int32(RUNNING), truncation=z)
    return state.replace(info=info, done=jp.zeros_like(state.done))

  def _reset(self, key: jax.Array) -> State:
    k_env, k_next = jax.random.split(key)
    return self._with_info(self.env.reset(k_env), k_next)

  def reset_batch(self, rng: jax.Array, num_envs: int) -> State:
    return jax.vmap(self._reset)(jax.random.split(rng, num_envs))

  def _step(self, state: State, action: jax.Array):
    info = state.info
    # `done` of the state we return marks the end of the last episode; the env must not
    # see it (brax envs that keep `done` through `replace` would end at once).
    nxt = self.env.step(state.replace(done=jp.zeros_like(state.done)), action)
    steps = info["steps"] + 1
    terminal = nxt.done > 0
    truncated = (steps >= self.episode_length) & ~terminal
    done = terminal | truncated
    ret = info["episode_return"] + nxt.reward
    k_reset, k_next = jax.random.split(info["adapter_rng"])
    fresh = self._with_info(self.env.reset(k_reset), k_next)
    nxt = nxt.replace(info=dict(
        nxt.info, adapter_rng=k_next, steps=steps, episode_return=ret,
        last_return=jp.where(done, ret, info["last_return"]),
        last_outcome=info["last_outcome"], truncation=truncated.astype(jp.float32)))
    fresh = fresh.replace(info=dict(fresh.info, last_return=nxt.info["last_return"],
                                    truncation=nxt.info["truncation"]))
    out = jax.tree.map(lambda a, b: jp.where(done, a, b), fresh, nxt)
    return out.replace(reward=nxt.reward, done=done.astype(jp.float32)), nxt.obs

  def step_batch(self, state: State, action: jax.Array):
    """(next states, each env's observation before its reset)."""
    return jax.vmap(self._step)(state, action)


class VectorObsEnv(Env):
  """The vineyard task with one flat observation vector, for learners that take vectors
  only (brax's own SAC): the noisy depth image average-pooled to `pool` (h, w) cells and
  scaled to [0, 1] of the camera's range, then [v_prev, w_prev, yaw]. Actions are in
  [-1, 1]^2, mapped affinely onto [0, v_max] x [-w_max, w_max]. The vineyard env does not
  auto-reset here: brax's training wrappers (or `BraxAdapter`) do. `metrics["success"]`
  is 1 at a successful step, so brax's evaluator reports `eval/episode_success`."""

  def __init__(self, cfg, pool: tuple[int, int] = (8, 8)):
    from mjxvine.env import VineyardEnv  # pylint: disable=import-outside-toplevel
    cam = cfg.camera
    if cam.height % pool[0] or cam.width % pool[1]:
      raise ValueError(f"camera {cam.height}x{cam.width} is not a multiple of pool {pool}")
    self.cfg = cfg
    self.pool = pool
    self.inner = VineyardEnv(cfg, auto_reset=False)

  def _flat(self, obs: dict) -> jax.Array:
    h, w = self.pool
    d = obs["depth"][..., 0]
    d = d.reshape(h, d.shape[0] // h, w, d.shape[1] // w).mean(axis=(1, 3))
    return jp.concatenate([d.reshape(-1) / self.cfg.camera.max_depth_m, obs["state"]])

  def reset(self, rng: jax.Array) -> State:
    state = self.inner.reset(rng)
    return state.replace(obs=self._flat(state.obs))

  def step(self, state: State, action: jax.Array) -> State:
    low, high = self.inner.action_low, self.inner.action_high
    physical = low + (jp.clip(action, -1.0, 1.0) + 1.0) * 0.5 * (high - low)
    new = self.inner.step(state, physical)
    # keep metrics that wrappers added (brax's EpisodeWrapper tracks "reward")
    return new.replace(obs=self._flat(new.obs), metrics={**state.metrics, **new.metrics})

  @property
  def observation_size(self) -> int:
    return self.pool[0] * self.pool[1] + 3

  @property
  def action_size(self) -> int:
    return self.inner.action_size

  @property
  def backend(self) -> str:
    return self.inner.backend
