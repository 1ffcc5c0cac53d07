"""Layers between a single environment and the trainer, as brax's training wrappers.

  * `AutoResetBatch(env, new_start_every)`: N copies of one env under `vmap`, each
    restarted when its episode ends, with a new start every `new_start_every` episodes
    (the paper's pose schedule: 10). It satisfies `mjxvine.episodes.TrainEnv`.
  * `EpisodeWrapper(env, episode_length)`: a plain brax `Env` (e.g.
    `brax.envs.get_environment("inverted_pendulum")`) as a single env of this package: a
    time limit that truncates, episode returns and outcome codes in `info`.
  * `brax_env(env, episode_length)`: both, the trainer's view of a brax env.

A single env here has `reset(rng) -> State`, `step(state, action) -> State` with no reset
(`state.done` marks the end of an episode) and `restart(state, new_start) -> State`: the
next episode after `state`'s, from the same start or (`new_start`) a new one, with random
keys taken from `state.info`. `info["episodes"]` counts finished episodes.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jp
from brax.envs.base import Env, State

from mjxvine.episodes import RUNNING, TIMEOUT

# What a restarted env keeps of the episode that just ended, for the trainer's logs.
EPISODE_FIELDS = ("last_return", "last_outcome", "last_length", "truncation")


class AutoResetBatch:
  """A batch of auto-resetting copies of `env` (attributes not defined here, such as
  `action_low` or `cfg`, are the env's)."""

  def __init__(self, env: Any, new_start_every: int = 1):
    self.env = env
    self.new_start_every = new_start_every

  def __getattr__(self, name: str):
    return getattr(self.env, name)

  def reset_batch(self, rng: jax.Array, num_envs: int) -> State:
    """`num_envs` envs reset with independent keys: a State with a leading env axis."""
    return jax.vmap(self.env.reset)(jax.random.split(rng, num_envs))

  def _restart_if_done(self, state: State) -> State:
    """One env: the next episode's first state if `state` ended one, else `state`. The
    ended step's reward, done, metrics and EPISODE_FIELDS stay visible."""
    episodes = state.info["episodes"] + 1
    fresh = self.env.restart(state, episodes % self.new_start_every == 0)
    kept = {k: state.info[k] for k in EPISODE_FIELDS if k in state.info}
    fresh = fresh.replace(reward=state.reward, done=state.done, metrics=state.metrics,
                          info=dict(fresh.info, episodes=episodes, **kept))
    return jax.tree.map(lambda a, b: jp.where(state.done > 0, a, b), fresh, state)

  def step_batch(self, state: State, action: jax.Array) -> tuple[State, Any]:
    """Steps every env (leading axis) and restarts those that finished. Returns (states,
    the observations before the restarts), for bootstrapping through truncations. The
    restarts (a new depth image each) are computed only when some env finished."""
    state = jax.vmap(self.env.step)(state, action)
    final_obs = state.obs
    state = jax.lax.cond(jp.any(state.done > 0), jax.vmap(self._restart_if_done),
                         lambda s: s, state)
    return state, final_obs


class EpisodeWrapper:
  """A brax `Env` as a single env with a time limit of `episode_length` steps: a time-out
  is a truncation (`info["truncation"]` 1, outcome TIMEOUT); the env's own `done` is a
  terminal (outcome RUNNING: a brax env has no success signal). Actions are passed through
  in the box [action_low, action_high] (brax envs take [-1, 1])."""

  def __init__(self, env: Env, episode_length: int, action_low: float = -1.0,
               action_high: float = 1.0):
    self.env = env
    self.episode_length = episode_length
    self.action_size = env.action_size
    self.action_low = jp.full((env.action_size,), action_low, jp.float32)
    self.action_high = jp.full((env.action_size,), action_high, jp.float32)

  def _start(self, state: State, key: jax.Array, episodes: jax.Array) -> State:
    z = jp.zeros((), jp.float32)
    info = dict(state.info, episode_rng=key, episodes=episodes, steps=jp.zeros((), jp.int32),
                episode_return=z, last_return=z, last_outcome=jp.int32(RUNNING),
                truncation=z)
    return state.replace(info=info, done=jp.zeros_like(state.done))

  def reset(self, rng: jax.Array) -> State:
    k_env, k_next = jax.random.split(rng)
    return self._start(self.env.reset(k_env), k_next, jp.zeros((), jp.int32))

  def restart(self, state: State, new_start: jax.Array) -> State:
    del new_start  # every episode of a brax env starts afresh
    k_env, k_next = jax.random.split(state.info["episode_rng"])
    return self._start(self.env.reset(k_env), k_next, state.info["episodes"])

  def step(self, state: State, action: jax.Array) -> State:
    info = state.info
    # `done` of the state we hold marks the end of the last episode; the env must not see
    # it (brax envs that keep `done` through `replace` would end at once).
    nxt = self.env.step(state.replace(done=jp.zeros_like(state.done)), action)
    steps = info["steps"] + 1
    terminal = nxt.done > 0
    truncated = (steps >= self.episode_length) & ~terminal
    done = terminal | truncated
    ret = info["episode_return"] + nxt.reward
    outcome = jp.where(truncated, TIMEOUT, RUNNING).astype(jp.int32)
    keep = {k: info[k] for k in ("episode_rng", "episodes")}
    return nxt.replace(done=done.astype(jp.float32), info=dict(
        nxt.info, **keep, steps=steps, episode_return=ret,
        last_return=jp.where(done, ret, info["last_return"]),
        last_outcome=jp.where(done, outcome, info["last_outcome"]),
        truncation=truncated.astype(jp.float32)))


def brax_env(env: Env, episode_length: int, action_low: float = -1.0,
             action_high: float = 1.0) -> AutoResetBatch:
  """A plain brax env behind the trainer's interface (`episodes.TrainEnv`): vector
  observations go through the MLP torso of `mjxvine.networks`."""
  return AutoResetBatch(EpisodeWrapper(env, episode_length, action_low, action_high))
