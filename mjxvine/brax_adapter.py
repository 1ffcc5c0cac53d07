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
