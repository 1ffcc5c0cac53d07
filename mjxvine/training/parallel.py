"""Data-parallel training over all devices with `jax.sharding`.

One 1-D `Mesh` named "env" spans the devices (all of them by default; with
`jax.distributed.initialize()` the devices of every host). The N parallel envs and the
replay rows are split over it along their env axis; the learner (networks, optimiser
states, temperature) is replicated. Each gradient step samples one global batch, which is
constrained to be split over the devices along its batch axis, so XLA computes the
per-device gradients on local samples and all-reduces them: data parallelism with the
same program, the same config and the same results (to float rounding) on 1 or D devices.

Needs `env.num_envs` and `sac.batch_size` divisible by the number of devices.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

AXIS = "env"

# Replay-buffer fields are laid out (rows, N, ...) and split over the env axis, but for
# these: the side ring of truncation frames and the scalar pointers, small and replicated.
_BUFFER_REPLICATED_FIELDS = ("final_depth", "final_owner", "final_ptr", "rows_written")


def make_mesh(num_devices: int = 0) -> Mesh:
  """A 1-D mesh over the first `num_devices` devices (0: all, over every host)."""
  devices = jax.devices()
  if num_devices > len(devices):
    raise ValueError(f"train.devices = {num_devices}: only {len(devices)} device(s) here")
  return Mesh(np.array(devices[:num_devices or len(devices)]), (AXIS,))


def check_divisible(mesh: Mesh, num_envs: int, batch_size: int) -> None:
  d = mesh.devices.size
  for key, value in (("env.num_envs", num_envs), ("sac.batch_size", batch_size)):
    if value % d:
      raise ValueError(f"{key} = {value}: must be a multiple of the {d} devices it is "
                       "split over (or set train.devices)")


def train_state_sharding(ts, mesh: Mesh, seeds: int = 1):
  """NamedShardings for a `mjxvine.training.iteration.TrainState` (or its `jax.eval_shape`): env-state
  leaves split along their env axis, replay rows along their env axis, the rest
  replicated. With `seeds` > 1 every leaf has a leading seeds axis first."""
  lead = (None,) if seeds > 1 else ()
  env_axis = NamedSharding(mesh, P(*lead, AXIS))
  row_env_axis = NamedSharding(mesh, P(*lead, None, AXIS))
  replicated = NamedSharding(mesh, P())
  like = lambda tree, s: jax.tree.map(lambda _: s, tree)
  fields = [f.name for f in dataclasses.fields(ts.buffer) if f.metadata.get("pytree_node", True)]
  buffer = ts.buffer.replace(**{
      f: like(getattr(ts.buffer, f),
              replicated if f in _BUFFER_REPLICATED_FIELDS else row_env_axis)
      for f in fields})
  out = like(ts, replicated)
  return out.replace(env_state=like(ts.env_state, env_axis), buffer=buffer)


def batch_constraint(mesh: Mesh, seeds: int = 1):
  """A function that pins a sampled batch (leading batch axis) to be split over the mesh:
  each device computes the losses of its share, and the gradients are all-reduced. The
  identity on one device. Under the seeds vmap the constraint applies per seed."""
  if mesh.devices.size == 1:
    return lambda batch: batch
  spec = NamedSharding(mesh, P(AXIS))
  return lambda batch: jax.tree.map(
      lambda x: jax.lax.with_sharding_constraint(x, spec), batch)
