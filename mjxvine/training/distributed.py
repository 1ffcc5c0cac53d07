"""A run over several processes (`jax.distributed`): the decisions every process makes
together, and a replicated pytree read on this process. With one process each is a no-op."""

from __future__ import annotations

import jax
import numpy as np


def max_over_processes(value: int) -> int:
  """The largest `value` over all processes: a collective that every process must enter
  (the value itself with one process)."""
  if jax.process_count() == 1:
    return value
  from jax.experimental import multihost_utils
  return int(np.max(multihost_utils.process_allgather(np.int32(value))))


def preempted(step: int) -> bool:
  """Whether JAX's preemption service (a cluster's notice, with `jax.distributed`) asks
  every process to stop at this step (a collective; False with one process)."""
  if jax.process_count() == 1:
    return False
  from jax.experimental import multihost_utils
  try:
    return bool(multihost_utils.reached_preemption_sync_point(step))
  except RuntimeError:  # the preemption service is off
    return False


def local(tree):
  """A replicated (possibly multi-process) pytree as numpy arrays of this process."""
  return jax.tree.map(lambda x: np.asarray(x.addressable_data(0))
                      if isinstance(x, jax.Array) else x, tree)
