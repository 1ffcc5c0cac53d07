"""Training that starts from a trained agent: `train.init_from` (`train --init`).

A run with `train.init_from` (a policy file with its agent file beside it, or the agent
file: `mjxvine.agent_file`) starts its networks from it (`warm_start`), every array
checked against the config's networks first (one line naming the first that differs).
Its warm-up then drives with the loaded actor instead of uniform random actions
(`training.iteration.collect_step`), so the replay fills with the agent's own driving
before the first update.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from mjxvine.agent_file import PARTS, agent_path, read_agent
from mjxvine.config import ConfigError
from mjxvine.rundir.checkpoints import unflatten_params


def resolve(spec: str) -> Path:
  """The agent file of `train.init_from`: itself, or the one beside a policy file;
  ConfigError in one line where there is none."""
  path = agent_path(spec)
  if not path.is_file():
    beside = "" if path == Path(spec) else f" (the agent file beside {spec})"
    raise ConfigError(f"train.init_from = {spec!r}: no {path}{beside}; a policy file alone "
                      "holds no critics to continue from")
  return path


def _shapes(tree: Any, prefix: str) -> dict[str, tuple]:
  """{"prefix/a/b": shape} of a params tree (arrays or `jax.ShapeDtypeStruct`s)."""
  import jax
  out = {}
  for key_path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
    names = [str(getattr(k, "key", getattr(k, "name", k))) for k in key_path]
    out["/".join([prefix, *names])] = tuple(leaf.shape)
  return out


def network_shapes(cfg) -> dict[str, tuple]:
  """The agent-file array shapes of `cfg`'s networks, from their abstract initialisation
  (nothing is computed)."""
  import jax
  import jax.numpy as jp
  from mjxvine import networks as nw
  nets = nw.make_networks_from_config(cfg)
  obs = {"depth": jax.ShapeDtypeStruct((1, cfg.camera.height, cfg.camera.width, 1), jp.float32),
         "state": jax.ShapeDtypeStruct((1, 3), jp.float32)}
  if cfg.sac.privileged_critics:  # the critics' lane-state input (`LaneTable.lane_state`)
    obs["lane"] = jax.ShapeDtypeStruct((1, 3), jp.float32)
  actor, critic = jax.eval_shape(lambda k, o: nw.init_params(nets, k, o),
                                 jax.random.PRNGKey(0), obs)
  return {**_shapes(actor, "actor"), **_shapes(critic, "critic"),
          **_shapes(critic, "target_critic"), "log_alpha": ()}


def load_agent(spec: str, shapes: dict[str, tuple]) -> dict[str, np.ndarray]:
  """The arrays of the agent file of `spec` (`resolve`), checked against `shapes`
  (`network_shapes`): ConfigError, one line, for a file that is no agent file or does
  not fit the networks (an array missing or extra, another shape)."""
  path = resolve(spec)
  try:
    arrays, _ = read_agent(path)
  except ValueError as e:
    raise ConfigError(f"train.init_from: {e}") from None
  for name in sorted(set(shapes) | set(arrays)):
    want = shapes.get(name)
    got = arrays[name].shape if name in arrays else None
    if want != got:
      what = ("is missing" if got is None else "is not in these networks" if want is None
              else f"has shape {list(got)}, the config's networks {list(want)}")
      raise ConfigError(f"train.init_from: {path}'s {name} {what} (sac.hidden, "
                        "sac.conv_features and camera.height/width must be the agent's)")
  return arrays


def warm_start(learner: Any, spec: str, say=lambda *a: None) -> Any:
  """`learner` (a `sac.LearnerState` of one member, or several stacked) with its networks
  and temperature from the agent file of `spec` (`load_agent`): the actor, its average
  and the anchor (`sac.anchor_weight`) all become the file's actor, in every member. `say` tells where they came from."""
  import jax
  import jax.numpy as jp
  one = jax.tree.map(lambda x: x[0], learner) if _stacked(learner) else learner
  shapes = {**{k: v for prefix, field in PARTS.items()
               for k, v in _shapes(getattr(one, field), prefix).items()}, "log_alpha": ()}
  arrays = load_agent(spec, shapes)

  def put(old, new):  # the file's values in every member, where the old arrays live
    new = jp.broadcast_to(jp.asarray(new, old.dtype), old.shape)
    return jax.device_put(new, old.sharding)

  parts = {}
  for prefix, field in PARTS.items():
    tree = unflatten_params({k[len(prefix) + 1:]: v for k, v in arrays.items()
                             if k.startswith(prefix + "/")})
    # the file's arrays, checked against these trees' shapes: the same dicts of dicts
    parts[field] = jax.tree.map(put, getattr(learner, field), tree)
  # its own buffers: the trainer donates these trees to the compiled step
  parts["actor_params"] = jax.tree.map(jp.copy, parts["averaged_actor_params"])
  if learner.anchor_actor_params is not None:  # sac.anchor_weight: pulled towards the file's
    parts["anchor_actor_params"] = jax.tree.map(jp.copy, parts["averaged_actor_params"])
  say(f"networks and temperature from {resolve(spec)}")
  return learner.replace(log_alpha=put(learner.log_alpha, arrays["log_alpha"]), **parts)


def _stacked(learner: Any) -> bool:
  return np.ndim(learner.log_alpha) > 0
