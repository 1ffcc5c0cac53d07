"""The replay buffer of SAC on the device: a preallocated ring of transitions, each depth
frame stored once (quantised to uint8 / uint16), sampled uniformly; pure functions of
pytrees (`init_buffer`, `insert`, `sample`).

Layout: rows of N transitions, one row per `insert` of the N parallel envs, in a ring
of S = capacity // N rows. Each depth frame is stored once: the next depth of
transition (r, n) is the depth of (r + 1, n), unless the episode ended at r. A terminal
needs no next frame (it is multiplied by 0); a truncation does, so its final frame goes
into a small side ring of K frames (owner-tagged; if it was evicted before the
transition, the sample comes with weight 0). Non-depth observation leaves (the state
vector, or a whole vector observation) are small and stored for obs and next_obs.

Bytes per transition (112x112 depth, state 3, action 2, K = capacity // 64):
  depth 12544 x itemsize + state 2 x 12 + action 8 + reward 4 + flags 2 + final_slot 4
  + side ring (12544 x itemsize + 4) / 64
  uint8: 12,782 B (1e6 transitions: 12.8 GB); uint16: 25,522 B (1e5: 2.6 GB).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import flax.struct
import jax
import jax.numpy as jnp

from mjxvine.depth import dequantize_depth, quantize_depth

Obs = Any


class Transition(NamedTuple):
  """A batch of transitions; every leaf has the leading batch axis B.

  obs / next_obs: observation pytrees (dict {"depth", "state"} or a vector).
  action (B, A) in the action box; reward (B,); terminal (B,) 1.0 where the episode
  ended in a true MDP terminal (collision, success, ...); truncated (B,) 1.0 where it
  ended by the time limit only; weight (B,) or None: per-sample weight of the critic
  loss (0.0 for a transition to learn nothing from: a physics reset, whose successor is
  the restored old state, or a truncation whose final frame the buffer evicted).
  discount (B,) or None: the factor of the bootstrapped value, gamma^k for an n-step
  transition of k steps (`sample` with n_step > 1); None: the learner's gamma.
  """
  obs: Obs
  action: jax.Array
  reward: jax.Array
  terminal: jax.Array
  truncated: jax.Array
  next_obs: Obs
  weight: jax.Array | None = None
  discount: jax.Array | None = None


class ReplayBuffer(flax.struct.PyTreeNode):
  """Preallocated ring buffer of transitions (see the layout note above).

  depth (S, N, H, W, 1) uint, or None for vector observations; rest (S, N, ...) the
  non-depth observation leaves and next_rest their successors; action (S, N, A);
  reward (S, N); terminal, truncated, valid (S, N) bool (valid: the transition's weight
  is nonzero); final_slot (S, N) int32 (-1: none);
  final_depth (K, H, W, 1); final_owner (K,) int32 (r * N + n, -1: free);
  final_ptr () int32; rows_written () int32 (inserts so far).
  """
  depth: jax.Array | None
  rest: Any
  next_rest: Any
  action: jax.Array
  reward: jax.Array
  terminal: jax.Array
  truncated: jax.Array
  valid: jax.Array
  final_slot: jax.Array | None
  final_depth: jax.Array | None
  final_owner: jax.Array | None
  final_ptr: jax.Array
  rows_written: jax.Array
  max_depth: float = flax.struct.field(pytree_node=False, default=5.0)

  @property
  def num_rows(self) -> int:
    return self.action.shape[0]

  @property
  def num_envs(self) -> int:
    return self.action.shape[1]

  @property
  def capacity(self) -> int:
    """Transitions held when full (num_rows * num_envs)."""
    return self.num_rows * self.num_envs


def _split_obs(obs: Obs) -> tuple[jax.Array | None, Any]:
  """obs -> (depth or None, the other leaves)."""
  if isinstance(obs, dict) and "depth" in obs:
    return obs["depth"], {k: v for k, v in obs.items() if k != "depth"}
  return None, obs


def _join_obs(depth: jax.Array | None, rest: Any) -> Obs:
  if depth is None:
    return rest
  return {"depth": depth, **rest}


def init_buffer(obs: Obs, action_size: int, capacity: int, max_depth: float = 5.0,
                depth_dtype=jnp.uint16, final_slots: int | None = None) -> ReplayBuffer:
  """An empty buffer for batches shaped like `obs` (leading axis: the N parallel envs).

  Holds capacity // N rows of N transitions. `final_slots` (K, default
  max(2N, capacity // 64)) is the side ring of truncation frames, K >= N.
  Use `jax.eval_shape(init_buffer, ...)` to size a buffer without allocating it.
  """
  depth, rest = _split_obs(obs)
  n = jax.tree.leaves(obs)[0].shape[0]
  rows = capacity // n
  if rows < 2:
    raise ValueError(f"capacity {capacity} must hold at least 2 rows of {n} envs")
  k = max(2 * n, capacity // 64) if final_slots is None else final_slots
  if k < n:
    raise ValueError(f"final_slots {k} must be >= num_envs {n}")
  rest_buf = jax.tree.map(lambda x: jnp.zeros((rows,) + x.shape, x.dtype), rest)
  kw = dict(depth=None, final_slot=None, final_depth=None, final_owner=None)
  if depth is not None:
    kw = dict(depth=jnp.zeros((rows,) + depth.shape, depth_dtype),
              final_slot=jnp.full((rows, n), -1, jnp.int32),
              final_depth=jnp.zeros((k,) + depth.shape[1:], depth_dtype),
              final_owner=jnp.full((k,), -1, jnp.int32))
  return ReplayBuffer(
      rest=rest_buf, next_rest=jax.tree.map(jnp.copy, rest_buf),
      action=jnp.zeros((rows, n, action_size), jnp.float32),
      reward=jnp.zeros((rows, n), jnp.float32),
      terminal=jnp.zeros((rows, n), bool), truncated=jnp.zeros((rows, n), bool),
      valid=jnp.zeros((rows, n), bool), final_ptr=jnp.zeros((), jnp.int32),
      rows_written=jnp.zeros((), jnp.int32),
      max_depth=float(max_depth), **kw)


def buffer_nbytes(buffer: ReplayBuffer) -> int:
  """Total bytes of the buffer's arrays (works on `jax.eval_shape` results too)."""
  return sum(int(math.prod(x.shape)) * x.dtype.itemsize for x in jax.tree.leaves(buffer))


def insert(buffer: ReplayBuffer, tr: Transition) -> ReplayBuffer:
  """Writes one row: the N transitions of one step of the N envs (leading axis N).

  Consecutive inserts must be consecutive steps of the same envs (env n in slot n),
  as the next depth of a non-final transition is read from the following row.
  `tr.weight` (N,) or None: transitions of weight 0 are stored but sampled with weight 0.
  """
  s, n = buffer.num_rows, buffer.num_envs
  r = buffer.rows_written % s
  terminal = tr.terminal.astype(bool)
  truncated = tr.truncated.astype(bool)
  depth, rest = _split_obs(tr.obs)
  _, next_rest = _split_obs(tr.next_obs)
  setrow = lambda buf, x: buf.at[r].set(x.astype(buf.dtype))
  updates = dict(
      rest=jax.tree.map(setrow, buffer.rest, rest),
      next_rest=jax.tree.map(setrow, buffer.next_rest, next_rest),
      action=setrow(buffer.action, tr.action), reward=setrow(buffer.reward, tr.reward),
      terminal=setrow(buffer.terminal, terminal), truncated=setrow(buffer.truncated, truncated),
      valid=setrow(buffer.valid,
                   jnp.ones_like(terminal) if tr.weight is None else tr.weight > 0),
      rows_written=buffer.rows_written + 1)
  if buffer.depth is not None:
    k = buffer.final_owner.shape[0]
    env = jnp.arange(n)
    need = truncated & ~terminal
    count = jnp.cumsum(need.astype(jnp.int32))
    slot = jnp.where(need, (buffer.final_ptr + count - 1) % k, k)  # k: dropped
    # Free the slots being reused: their previous owner loses its final frame.
    prev = buffer.final_owner.at[slot].get(mode="fill", fill_value=-1)
    pr, pn = prev // n, prev % n
    held = (prev >= 0) & (buffer.final_slot.at[pr, pn].get(mode="fill", fill_value=-1) == slot)
    final_slot = buffer.final_slot.at[jnp.where(held, pr, s), pn].set(-1, mode="drop")
    next_depth, _ = _split_obs(tr.next_obs)
    dtype = buffer.depth.dtype
    updates.update(
        depth=buffer.depth.at[r].set(quantize_depth(depth, buffer.max_depth, dtype)),
        final_depth=buffer.final_depth.at[slot].set(
            quantize_depth(next_depth, buffer.max_depth, dtype), mode="drop"),
        final_owner=buffer.final_owner.at[slot].set(r * n + env, mode="drop"),
        final_slot=final_slot.at[r].set(jnp.where(need, slot, -1)),
        final_ptr=(buffer.final_ptr + count[-1]) % k)
  return buffer.replace(**updates)


def num_sampleable(buffer: ReplayBuffer) -> jax.Array:
  """Transitions `sample` draws from: all written rows but the newest, times N."""
  return (jnp.minimum(buffer.rows_written, buffer.num_rows) - 1).clip(0) * buffer.num_envs


def sample(buffer: ReplayBuffer, key: jax.Array, batch_size: int, n_step: int = 1,
           gamma: float = 0.99) -> Transition:
  """Draws `batch_size` transitions uniformly (with replacement), depth dequantised.

  n_step > 1 (static): each is an n-step transition (`sac.n_step`): reward = sum_k
  gamma^k r_{t+k} over the steps up to the first end of the episode within n,
  next_obs, terminal and truncated those of that last step, and discount (B,) =
  gamma^(steps taken), the factor of the bootstrapped value (n = 1: discount None, the
  learner's gamma). A transition of weight 0 inside the window gives the sample weight 0.
  Needs at least n + 1 inserts (the newest row waits for its successor frames).
  """
  s, n = buffer.num_rows, buffer.num_envs
  k_row, k_env = jax.random.split(key)
  w = buffer.rows_written
  count = jnp.maximum(jnp.minimum(w, s) - n_step, 1)
  oldest = jnp.where(w > s, w % s, 0)
  r = (oldest + jax.random.randint(k_row, (batch_size,), 0, count)) % s
  e = jax.random.randint(k_env, (batch_size,), 0, n)
  get = lambda x: x[r, e]
  reward, weight = get(buffer.reward), get(buffer.valid).astype(jnp.float32)
  last, discount = r, None
  if n_step > 1:
    rows = (r[:, None] + jnp.arange(n_step)) % s  # (B, n)
    window = lambda x: x[rows, e[:, None]]
    done = window(buffer.terminal) | window(buffer.truncated)
    alive = (jnp.cumsum(done, axis=1) - done) == 0  # no end of episode before step k
    steps = jnp.sum(alive, axis=1)  # 1 .. n
    reward = jnp.sum(jnp.where(alive, window(buffer.reward), 0.0)
                     * gamma ** jnp.arange(n_step, dtype=jnp.float32), axis=1)
    weight = jnp.all(jnp.where(alive, window(buffer.valid), True), axis=1).astype(jnp.float32)
    last = (r + steps - 1) % s
    discount = gamma ** steps.astype(jnp.float32)
  at_last = lambda x: x[last, e]
  terminal, truncated = at_last(buffer.terminal), at_last(buffer.truncated)
  depth = next_depth = None
  if buffer.depth is not None:
    need = truncated & ~terminal
    fs = at_last(buffer.final_slot)
    side = buffer.final_depth[jnp.maximum(fs, 0)]
    nd = jnp.where(need[:, None, None, None], side, buffer.depth[(last + 1) % s, e])
    depth = dequantize_depth(get(buffer.depth), buffer.max_depth)
    next_depth = dequantize_depth(nd, buffer.max_depth)
    weight = jnp.where(need & (fs < 0), 0.0, weight)
  return Transition(
      obs=_join_obs(depth, jax.tree.map(get, buffer.rest)),
      action=get(buffer.action), reward=reward,
      terminal=terminal.astype(jnp.float32), truncated=truncated.astype(jnp.float32),
      next_obs=_join_obs(next_depth, jax.tree.map(at_last, buffer.next_rest)), weight=weight,
      discount=discount)
