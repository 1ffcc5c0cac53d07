"""Evaluation policies, policy(state, key) -> action (2,) [v m/s, w rad/s] for one env
(the rollouts vmap it): the privileged oracle, uniform random actions, and trained actors.

A trained actor runs as the one closure of its deterministic (mean) action
(`actor_policy`; the trainer's closing evaluation, `mjxvine.evaluate` and `mjxvine.bench`
use it), with params from a run directory (`mjxvine.rundir.checkpoints`) or an exported
`.npz` (read by `deploy.read_policy_file`, the robot's loader with its format checks).
Every failure is a `deploy.PolicyError` (`deploy.PolicyFormatError` is a subclass).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jp

from mjxvine.deploy import NumpyPolicy, PolicyError, PolicyFormatError, read_policy_file
from mjxvine.formatting import first_line
from mjxvine.networks import SACNetworks, act_deterministic, make_networks_from_config
from mjxvine.rundir.checkpoints import checkpoint_item, restore_actor_params, unflatten_params

Policy = Callable  # policy(state, key) -> action (2,), one env (vmapped by the rollout)


def random_policy(env) -> Policy:
  """Uniform random actions in `env`'s (a `VineyardEnv`) action box."""
  def policy(state, key):
    del state
    return jax.random.uniform(key, (2,), minval=env.action_low, maxval=env.action_high)
  return policy


def load_policy(spec: str, env, which: str = "best",
                member: int | None = None) -> tuple[Policy, str]:
  """`oracle`, `random`, a run directory / checkpoint, or an exported `.npz` actor, for
  `env` (a `VineyardEnv`): (policy, its name).
  which: the checkpoint of a run directory, "best" or "last" (`checkpoint_item`);
  member: of a `--num-seeds` / sweep run, which one (None: the one checkpoints/best follows)."""
  if spec == "oracle":
    from mjxvine.env import pure_pursuit  # (the env's imports are heavy: only when needed)
    return pure_pursuit(env), "oracle (pure pursuit, privileged pose)"
  if spec == "random":
    return random_policy(env), "random"
  path = check_policy_file(spec, which)
  return load_actor_policy(path, env, which, member), str(path)


def check_policy_file(spec: str, which: str = "best") -> Path:
  """The path of a policy given as a run dir or .npz, checked before anything is built:
  it exists, an .npz reads as a policy file, a run dir holds a checkpoint (`which`)."""
  path = Path(spec)
  if not path.exists():
    what = "policy not found" if path.suffix == ".npz" else "no such run directory"
    raise PolicyError(f"{what}: {spec} (give oracle, random, a run dir or a .npz)")
  if path.is_file() and path.suffix != ".npz":
    raise PolicyError(f"{spec}: a file, but not an .npz policy file (give oracle, random, a "
                      "run directory or an .npz written by python -m mjxvine.export; an "
                      ".onnx graph runs with onnxruntime, not here)")
  if path.suffix == ".npz":
    try:  # the robot's loader checks the arrays against the metadata, as a robot would
      NumpyPolicy(*read_policy_file(path))
    except PolicyFormatError as e:
      raise PolicyFormatError(e if str(path) in str(e) else f"{path}: {e}") from None
  else:
    try:
      checkpoint_item(path, which)
    except FileNotFoundError as e:
      raise PolicyError(str(e)) from None
  return path


def actor_policy(nets: SACNetworks, actor_params, *, brax: bool = False,
                 mirror: tuple | None = None):
  """The actor's deterministic action (the squashed mean, in the action box) as a policy.

  nets: the networks the params belong to (`sac.SAC.nets`, `make_networks_from_config`).
  actor_params: the actor's flax "params" dict of one member (no seeds axis).
  Returns policy(state, key) -> action (..., A) for an env State (its `.obs`, batched or
  not); the key is unused. brax=True: brax's `Policy` instead, (obs, key) -> (action, {}),
  for `brax.training.acting.Evaluator`. mirror: (mirror_obs, mirror_action) for the
  mirror-averaged action (`sac.mirror_average`, `networks.act_deterministic`).
  """
  def policy(state, key):
    del key
    action = act_deterministic(nets, actor_params, state if brax else state.obs, mirror)
    return (action, {}) if brax else action

  return policy


def load_actor_params(path: Path, env, which: str = "best", member: int | None = None) -> dict:
  """Actor params from a .npz export or a run directory, checked against `env`'s camera.

  which: the checkpoint of a run directory, "best" or "last" (`checkpoint_item`);
  member: of a run that trained several, which one (None: the one checkpoints/best
  follows, `checkpoints.best_member`). Raises `PolicyError` (`PolicyFormatError` for an
  unreadable .npz).
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
    return jax.tree.map(jp.asarray, unflatten_params(arrays))
  try:
    params, _ = restore_actor_params(path, which, member)
  except (FileNotFoundError, KeyError, ValueError) as e:
    raise PolicyError(e.args[0] if e.args else str(e)) from None
  return jax.tree.map(jp.asarray, params)


def averaging_mirror(cfg) -> tuple | None:
  """`actor_policy`'s mirror for `cfg`: the vineyard's (mirror_obs, mirror_action) when
  `sac.mirror_average` is set, else None."""
  if not cfg.sac.mirror_average:
    return None
  from mjxvine.env import VineyardEnv  # (the env's imports are heavy: only when needed)
  return VineyardEnv.mirror_obs, VineyardEnv.mirror_action


def load_actor_policy(path: Path, env, which: str = "best", member: int | None = None):
  """`actor_policy` of the actor at `path` (see `load_actor_params`), for `env`'s config
  (build it with `rundir.settings.policy_config`), mirror-averaged when its
  `sac.mirror_average` is set; PolicyError when the params do not fit that config's
  networks."""
  params = load_actor_params(Path(path), env, which, member)
  nets = make_networks_from_config(env.cfg)
  try:
    nets.actor.apply({"params": params}, {
        "depth": jp.zeros((1, env.cfg.camera.height, env.cfg.camera.width, 1)),
        "state": jp.zeros((1, 3))})
  except Exception as e:  # noqa: BLE001 - any mismatch of shapes or names
    raise PolicyError(f"{path}: the actor does not fit the networks of camera "
                      f"{env.cfg.camera.height}x{env.cfg.camera.width}, sac.hidden "
                      f"{env.cfg.sac.hidden}, sac.conv_features {env.cfg.sac.conv_features} "
                      f"(a run without config.yaml needs --config; {type(e).__name__}: "
                      f"{first_line(e)})") from None
  return actor_policy(nets, params, mirror=averaging_mirror(env.cfg))
