"""The contract between environments and the trainer.

`mjxvine.train` consumes any object that satisfies `TrainEnv`: a batch of auto-resetting
envs (`mjxvine.wrappers.AutoResetBatch` around `mjxvine.env.VineyardEnv`, or around a
brax env through `mjxvine.wrappers.brax_env`). It reads nothing else of the env: no
vineyard names.

After `step_batch`, every env's `state.done` is 1 on the step that ended an episode, and
its `info` holds the ended episode's
  * "truncation": 1.0 where it ended by the time limit or a physics reset (learners
    bootstrap through it), else 0.0;
  * "last_return": its undiscounted, unscaled return;
  * "last_outcome": one of the outcome codes below (int32).
`state.metrics` may hold per-step reward terms as "reward/<term>" (float32), which the
trainer logs as means per env step.
"""

from __future__ import annotations

from typing import Any, Protocol

import jax

# Outcome codes of an episode (info["outcome"], info["last_outcome"], evaluation tables).
# A brax env behind `wrappers.brax_env` uses RUNNING, SUCCESS (never), COLLISION for its
# own terminal and TIMEOUT; the vineyard uses them all.
RUNNING, SUCCESS, COLLISION, REVERSED, LEFT_LANE, TIMEOUT, PHYSICS = range(7)
OUTCOMES = ("running", "success", "collision", "reversed", "left_lane", "timeout", "physics")
REWARD_PREFIX = "reward/"  # state.metrics keys of named reward terms


class TrainEnv(Protocol):
  """A batch of auto-resetting envs, as `mjxvine.train` uses it."""
  action_low: jax.Array   # (A,) float32, the action box
  action_high: jax.Array  # (A,) float32

  @property
  def action_size(self) -> int: ...

  def reset_batch(self, rng: jax.Array, num_envs: int) -> Any:
    """`num_envs` fresh envs: a brax `State` with a leading env axis."""

  def step_batch(self, state: Any, action: jax.Array) -> tuple[Any, Any]:
    """(next states, each env's observation before its auto-reset)."""
