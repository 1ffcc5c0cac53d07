"""Batches worlds of the same structure into one `mjx.Model` with per-world fields.

As in MuJoCo Playground's domain randomisation: the fields that differ between the worlds
(plant geom positions, sizes and orientations, heightfield data, ...) get a leading batch
axis, the rest are shared, and `in_axes` says which is which, so that
`jax.vmap(mjx.step, in_axes=(in_axes, 0))(batched_model, data)` steps N vineyards at once.
"""

from __future__ import annotations

from typing import Sequence

import jax
import jax.numpy as jp
import mujoco
import numpy as np
from mujoco import mjx


def batch_models(models: Sequence[mujoco.MjModel],
                 like: mjx.Model | None = None) -> tuple[mjx.Model, mjx.Model]:
  """Returns (batched mjx.Model, in_axes) for MjModels of identical structure.

  A leaf that differs between the models is stacked along a new axis 0 (in_axes 0);
  a leaf equal in all of them is kept once (in_axes None). `like`: the in_axes of
  another batch of the same worlds (the env's models with plants); a leaf stacked there
  is stacked here too, so that XLA computes with it as it does there (a leaf kept once is
  a constant, which XLA may fold, rounding differently in the last bit).
  """
  if not models:
    raise ValueError("batch_models needs at least one model")
  # This process's own device: mjx puts on jax.devices()[0] by default, which under
  # jax.distributed is process 0's device (not addressable from the others).
  device = jax.local_devices()[0]
  puts = _unify_static([mjx.put_model(m, device=device) for m in models])
  flat = [jax.tree_util.tree_flatten(p) for p in puts]
  treedef = flat[0][1]
  for i, (_, td) in enumerate(flat[1:], 1):
    if td != treedef:
      raise ValueError(f"model {i} has another structure than model 0 (plant slots, robot?)")
  stack = ([a == 0 for a in jax.tree.leaves(like, is_leaf=lambda x: x is None)]
           if like is not None else [False] * len(flat[0][0]))
  if len(stack) != len(flat[0][0]):
    raise ValueError("like: the in_axes of another model structure")
  leaves, axes = [], []
  for group, stacked in zip(zip(*(f[0] for f in flat)), stack):
    shapes = {np.shape(x) for x in group}
    if len(shapes) != 1:
      raise ValueError(f"models differ in an array's shape {shapes}: not batchable")
    first = np.asarray(group[0])
    if not stacked and all(np.array_equal(first, np.asarray(x)) for x in group[1:]):
      leaves.append(group[0])
      axes.append(None)
    else:
      leaves.append(jp.stack([jp.asarray(x) for x in group]))
      axes.append(0)
  return treedef.unflatten(leaves), treedef.unflatten(axes)


# Static (numpy, non-traced) MJX fields that may differ between worlds, and how to unify
# them: a per-geom bounding radius that sizes heightfield collision grids takes the max.
_UNIFY_STATIC = {"geom_rbound_hfield": lambda xs: np.max(np.stack(xs), axis=0)}


def mjx_backend_fields(model: mjx.Model):
  """The backend's own fields of an `mjx.Model` (`mjx.Model._impl`): the one private
  attribute of MJX that this package reads, here alone. Raises a RuntimeError naming the
  installed MJX when it is gone or lacks a field `_unify_static` unifies (a test checks
  it on every MJX release the suite runs with)."""
  impl = getattr(model, "_impl", None)
  missing = [n for n in _UNIFY_STATIC if not hasattr(impl, n)]
  if impl is None or not hasattr(impl, "replace") or missing:
    from importlib import metadata
    raise RuntimeError(
        f"mujoco-mjx {metadata.version('mujoco-mjx')}: mjx.Model's backend fields (_impl) "
        f"{'are gone' if impl is None else 'lack ' + ', '.join(missing)}; "
        "mjxvine.worlds.batch needs updating for this MJX")
  return impl


def _unify_static(puts: list[mjx.Model]) -> list[mjx.Model]:
  impls = [mjx_backend_fields(p) for p in puts]
  changes = {name: unify([np.asarray(getattr(i, name)) for i in impls])
             for name, unify in _UNIFY_STATIC.items()}
  return [p.replace(_impl=impl.replace(**changes)) for p, impl in zip(puts, impls)]


def take_world(model: mjx.Model, in_axes: mjx.Model, index) -> mjx.Model:
  """The single-world mjx.Model number `index` of a batched model."""
  return jax.tree.map(lambda x, a: x if a is None else x[index], model, in_axes,
                      is_leaf=lambda x: x is None)
