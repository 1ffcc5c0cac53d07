"""Trained actors as evaluation policies: from a run directory (orbax checkpoint) or an
exported `.npz`, run as the JAX actor's deterministic (mean) action."""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jp

from mjxvine import networks as nw
from mjxvine.deploy import PolicyError, read_policy_file


def _unflatten(arrays: dict) -> dict:
  tree: dict = {}
  for name, value in arrays.items():
    node = tree
    *parents, leaf = name.split("/")
    for p in parents:
      node = node.setdefault(p, {})
    node[leaf] = jp.asarray(value)
  return tree


def load_actor_params(path: Path, env, which: str = "best") -> dict:
  """Actor params from a .npz export or a run directory, checked against `env`'s camera.

  which: the checkpoint of a run directory, "best" or "last" (`export.checkpoint_item`).
  Raises `PolicyError` (`PolicyFormatError` for an unreadable .npz).
  """
  path = Path(path)
  if path.suffix == ".npz":
    arrays, meta = read_policy_file(path)  # the format checks of the robot's loader
    size = tuple(meta.get("image_size", ()))
    want = (env.cfg.camera.height, env.cfg.camera.width)
    if size != want:
      got = "x".join(str(v) for v in size) or "unknown"
      raise PolicyError(f"{path}: trained for {got} depth images, the "
                        f"evaluation renders {want[0]}x{want[1]} (set camera.height/width)")
    return _unflatten(arrays)
  from mjxvine import export
  try:
    params, _ = export.load_actor_params(path, which)
  except (FileNotFoundError, KeyError) as e:
    raise PolicyError(e.args[0] if e.args else str(e)) from None
  return jax_tree(params)


def jax_tree(params):
  import jax
  return jax.tree.map(jp.asarray, params)


def load_actor_policy(path: Path, env, which: str = "best"):
  """policy(state, key) -> deterministic action, for `mjxvine.evaluate`."""
  params = load_actor_params(Path(path), env, which)
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
