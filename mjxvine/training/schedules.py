"""Schedules over a run's budget of env steps (docs/design.md, SAC hyper-parameters):
exploration (`epsilon`, `explore_action`) and the target critics' rate (`target_rate`),
each a pure function of the env steps taken, summed over all envs."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from mjxvine.config import SACConfig

# The paper's epsilon: x 0.992 per episode, over a budget counted as 1500 episodes.
EPS_DECAY, EPS_BUDGET_EPISODES = 0.992, 1500.0
TAU_LATE_FROM = 0.25  # `sac.tau_late` applies from this fraction of the budget: eps's floor


def explore_action(key: jax.Array, policy_action: jax.Array, eps: jax.Array, low: jax.Array,
                   high: jax.Array, warmup: jax.Array | bool) -> jax.Array:
  """Warm-up / epsilon-greedy exploration on top of the SAC sample.

  policy_action (N, A); eps () or (N,) probability; low, high (A,); warmup: bool scalar
  or (N,). Where warming up, or with probability eps, the action is uniform in the box
  with each dimension drawn independently; otherwise policy_action.
  """
  k_uniform, k_coin = jax.random.split(key)
  rand = jax.random.uniform(k_uniform, policy_action.shape, policy_action.dtype, low, high)
  coin = jax.random.uniform(k_coin, policy_action.shape[:-1])
  explore = jnp.logical_or(warmup, coin < eps)
  return jnp.where(explore[..., None], rand, policy_action)


def epsilon(cfg: SACConfig, env_steps: jax.Array, total_env_steps: int) -> jax.Array:
  """Exploration probability () after `env_steps` env steps summed over all envs.

  The budget `total_env_steps` counts as `EPS_BUDGET_EPISODES` episodes, and epsilon is
  `cfg.eps_start` multiplied by `EPS_DECAY` per such episode, floored at `cfg.eps_min`:
  it reaches the floor at the same fraction of the budget whatever the number of envs
  (the paper's 0.992 per episode over 1500 episodes: at 25 %).
  """
  episodes = EPS_BUDGET_EPISODES * jnp.asarray(env_steps, jnp.float32) / total_env_steps
  return jnp.maximum(cfg.eps_start * jnp.power(EPS_DECAY, episodes), cfg.eps_min)


def target_rate(cfg: SACConfig, env_steps: jax.Array, total_env_steps) -> jax.Array | float:
  """The target critics' Polyak rate after `env_steps` env steps summed over all envs:
  `cfg.tau`, then `cfg.tau_late` from `TAU_LATE_FROM` x `total_env_steps` on. With
  tau_late 0 it is the Python float cfg.tau, so that runs without the switch compile as
  before."""
  if not cfg.tau_late:
    return cfg.tau
  late = jnp.asarray(env_steps, jnp.float32) >= TAU_LATE_FROM * total_env_steps
  return jnp.where(late, jnp.float32(cfg.tau_late), jnp.float32(cfg.tau))
