"""Trained actors as evaluation policies: from a run directory (orbax checkpoint) or an
exported `.npz`, run as the JAX actor's deterministic (mean) action."""

from __future__ import annotations

import json
from pathlib import Path

import jax.numpy as jp
import numpy as np

from mjxvine import networks as nw


def _unflatten(arrays: dict) -> dict:
  tree: dict = {}
  for name, value in arrays.items():
    node = tree
    *parents, leaf = name.split("/")
    for p in parents:
      node = node.setdefault(p, {})
    node[leaf] = jp.asarray(value)
  return tree


def load_actor_params(path: Path, env) -> dict:
  """Actor params from a .npz export or a run directory, checked against `env`'s camera."""
  from mjxvine.evaluate import PolicyError
  from mjxvine.deploy import META_KEY
  if path.suffix == ".npz":
    try:
      with np.load(path, allow_pickle=False) as f:
        meta = json.loads(str(f[META_KEY]))
        arrays = {k: f[k] for k in f.files if k != META_KEY}
    except (OSError, KeyError, ValueError) as e:
      raise PolicyError(f"{path}: not a mjxvine policy file ({e})") from None
    size = tuple(meta.get("image_size", ()))
    want = (env.cfg.camera.height, env.cfg.camera.width)
    if size != want:
      raise PolicyError(f"{path}: trained for {size[0]}x{size[1]} depth images, the "
                        f"evaluation renders {want[0]}x{want[1]} (set camera.height/width)")
    return _unflatten(arrays)
  from mjxvine import export
  try:
    params, _ = export.load_actor_params(path)
  except (FileNotFoundError, KeyError) as e:
    raise PolicyError(str(e)) from None
  return jax_tree(params)


def jax_tree(params):
  import jax
  return jax.tree.map(jp.asarray, params)


def load_actor_policy(path: Path, env):
  """policy(state, key) -> deterministic action, for `mjxvine.evaluate`."""
  from mjxvine.evaluate import PolicyError
  params = load_actor_params(Path(path), env)
  nets = nw.make_networks_from_config(env.cfg)
  try:
    nets.actor.apply({"params": params}, {
        "depth": jp.zeros((1, env.cfg.camera.height, env.cfg.camera.width, 1)),
        "state": jp.zeros((1, 3))})
  except Exception as e:  # noqa: BLE001 - any mismatch of shapes or names
    raise PolicyError(f"{path}: the actor does not fit this config's networks "
                      f"({type(e).__name__}: {str(e).splitlines()[0][:160]})") from None

  def policy(state, key):
    del key
    mean, _ = nets.actor.apply({"params": params}, state.obs)
    return nw.deterministic_action(mean, nets.action_low, nets.action_high)

  return policy
