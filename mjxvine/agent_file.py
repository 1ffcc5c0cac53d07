"""The agent file: what training can continue from, beside a policy file.

A policy file (`models/jackal.npz`) holds the actor alone. Beside it, its agent file
`<name>.sac.npz` holds what SAC needs to go on learning: the actor (the evaluated one, the
policy file's), both critics, their targets and the temperature (log alpha), with the
policy's metadata; no replay and no optimiser state. A run writes one beside every policy
it keeps for the choice (RUN/eval_policies/env<steps>.sac.npz), the choice copies the
chosen one to RUN/selected.sac.npz, and `python -m mjxvine.export` copies it beside the
policy file it writes. `train --init` reads it (`mjxvine.training.warm_start`).
"""

from __future__ import annotations

import json
import types
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from mjxvine import atomic
from mjxvine.deploy.export import flatten_params, write_npz
from mjxvine.deploy.numpy_policy import META_KEY

AGENT_SUFFIX = ".sac.npz"
FORMAT = "mjxvine-sac-agent-1"
# the LearnerState fields an agent file holds (the actor: the evaluated, averaged one)
PARTS = {"actor": "averaged_actor_params", "critic": "critic_params",
         "target_critic": "target_critic_params"}


def agent_path(path: str | Path) -> Path:
  """The agent file of a policy file (`x.npz` -> `x.sac.npz`); an agent file is its own."""
  path = Path(path)
  if path.name.endswith(AGENT_SUFFIX):
    return path
  return path.with_name(path.name[:-len(".npz")] + AGENT_SUFFIX if path.suffix == ".npz"
                        else path.name + AGENT_SUFFIX)


def agent_arrays(learner: Any) -> dict[str, np.ndarray]:
  """The arrays of one member's `sac.LearnerState`: "actor/...", "critic/...",
  "target_critic/..." (flax paths) and "log_alpha"."""
  out = {}
  for prefix, field in PARTS.items():
    out.update(flatten_params(getattr(learner, field), prefix + "/"))
  out["log_alpha"] = np.asarray(learner.log_alpha, np.float32)
  return out


def write_agent(path: str | Path, arrays: dict[str, np.ndarray], meta: dict) -> Path:
  """Writes an agent file: `arrays` (`agent_arrays`) and the policy's metadata `meta`."""
  path = Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  with atomic.atomic_path(path) as tmp:
    write_npz(tmp, {**arrays, META_KEY: np.array(json.dumps({**meta, "format": FORMAT}))})
  return path


def read_agent(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
  """(arrays, meta) of an agent file; ValueError in one line when it is not one."""
  path = Path(path)
  try:
    with np.load(path, allow_pickle=False) as z:
      arrays = {k: np.asarray(z[k]) for k in z.files}
    meta = json.loads(str(arrays.pop(META_KEY)))
  except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as e:
    raise ValueError(f"{path}: not a readable agent file ({type(e).__name__}: "
                     f"{str(e).splitlines()[0] if str(e) else 'damaged'})") from None
  if not isinstance(meta, dict) or meta.get("format") != FORMAT:
    raise ValueError(f"{path}: not an agent file (no format {FORMAT!r} in its metadata)")
  bad = [k for k, v in arrays.items() if v.dtype.kind != "f" or not np.all(np.isfinite(v))]
  if bad:
    raise ValueError(f"{path}: array {bad[0]} is not a finite floating-point array")
  return arrays, meta


def checkpoint_agent(item: Path, member: int | None = None) -> dict[str, np.ndarray]:
  """`agent_arrays` of an orbax checkpoint item of a run: of a run of several members, of
  `member` (None: the one checkpoints/best follows). ValueError for a checkpoint without
  a learner's networks, or a member it does not have."""
  import jax
  from mjxvine.rundir.checkpoints import best_member, restore_tree, run_dir_of
  learner = restore_tree(item).get("learner")
  fields = [*PARTS.values(), "log_alpha"]
  if not isinstance(learner, dict) or any(f not in learner for f in fields):
    raise ValueError(f"{item}: no learner networks and temperature to continue from")
  if np.ndim(learner["log_alpha"]):  # members stacked on a leading axis
    count = len(learner["log_alpha"])
    k = best_member(run_dir_of(item)) if member is None else member
    if not 0 <= k < count:
      raise ValueError(f"member {k}: this run trained {count} members (0 to {count - 1})")
    learner = jax.tree.map(lambda x: np.asarray(x)[k], {f: learner[f] for f in fields})
  return agent_arrays(types.SimpleNamespace(**{f: learner[f] for f in fields}))
