"""A trained policy describes itself: the config that a run directory or an exported policy
file was trained with, for every CLI that takes one (`evaluate`, `export`, `view`).

A run directory (or its checkpoints/, a step, an orbax item in it) holds its resolved
config.yaml; an exported `.npz` holds its camera, action box, yaw input and network sizes
in its metadata and arrays. `policy_config` builds the config from that source, then lays
`--config FILE` and `--set` over it: they only override. What the networks were trained
for (`POLICY_KEYS`: image size, depth range, network sizes, action box) may not change;
an override that changes it is one `ConfigError` line naming the key and both values, and
so is a robot file (`--robot FILE.yaml`) that asks for another image size or action box:
the policy's values are kept only by an explicit `--set`.

Only numpy, yaml and the standard library are imported here (jax and orbax only when a
checkpoint is located), so argument checks stay fast.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from mjxvine.rundir.checkpoints import checkpoint_item, run_dir_of
from mjxvine.config import ROBOT_NAMES, Config, ConfigError, load_config, read_yaml, short_repr
from mjxvine.robot_files import config_values
from mjxvine.deploy import read_policy_file

# The keys a trained actor is tied to: its input size and scaling, its layer sizes and
# the action box its outputs are mapped onto.
POLICY_KEYS = ("camera.height", "camera.width", "camera.max_depth_m", "sac.hidden",
               "sac.conv_features", "env.v_min", "env.v_max", "env.w_max")
BUILTIN_POLICIES = ("oracle", "random")


def run_config_file(spec: str | Path, which: str = "best") -> Path | None:
  """The config.yaml of the run that a run dir, its checkpoints/ dir, a step or an item
  dir belongs to; None when there is none (FileNotFoundError when `spec` does not exist)."""
  path = Path(spec)
  item = checkpoint_item(path, which)
  for d in (run_dir_of(item), path):
    if d is not None and (d / "config.yaml").is_file():
      found = d / "config.yaml"
      try:  # as the user named it: relative to the working directory if it was
        return found.relative_to(Path.cwd()) if not path.is_absolute() else found
      except ValueError:
        return found
  return None


def policy_file_settings(path: str | Path) -> dict:
  """The config an exported `.npz` policy carries: its training config (metadata
  "config", in files exported since it was added), with what the policy itself fixes laid
  over it from its metadata and array shapes: {"camera": {...}, "env": {...}, "sac": {...},
  ...} (`PolicyFormatError` if it is not a policy file)."""
  arrays, meta = read_policy_file(path)
  own = meta.get("config") if isinstance(meta.get("config"), dict) else {}
  h, w = (int(v) for v in meta["image_size"])
  low, high = meta["action_low"], meta["action_high"]
  camera = {"height": h, "width": w, "max_depth_m": float(meta["max_depth_m"])}
  camera.update({k: float(meta[k]) for k in ("fovx_deg", "fovy_deg") if k in meta})
  env = {"v_min": float(low[0]), "v_max": float(high[0]), "w_max": float(high[1])}
  env.update({k: meta[k] for k in ("control_dt", "yaw_reference")
              if k in meta})
  sac = {}
  if "dense0/kernel" in arrays and "tower/conv0/kernel" in arrays:
    sac = {"hidden": int(arrays["dense0/kernel"].shape[-1]),
           "conv_features": int(arrays["tower/conv0/kernel"].shape[-1])}
  fixed = {"camera": camera, "env": env, "sac": sac}
  return {**own, **{k: {**(own.get(k) or {}), **v} for k, v in fixed.items()}}


def _robot_named(config_file: str | Path | None, overrides: Sequence[str]) -> bool:
  """Whether the user names the robot: `--set robot.name=...` (`--robot`) or robot.name
  in the `--config` file."""
  if any(o.split("=", 1)[0].strip() == "robot.name" for o in overrides):
    return True
  robot = read_yaml(config_file).get("robot") if config_file else None
  return isinstance(robot, dict) and "name" in robot


def _builtin_robot_only(base: dict, path: Path, named: bool) -> dict:
  """A policy file's recorded config (`policy_file_settings`) with robot.name a built-in
  robot: a robot file there would be read from this machine, any path a file names
  (`config.ROBOT_NAMES` only). Such a name is dropped when the user names the robot
  (`named`), else refused: ConfigError, one line."""
  robot = base.get("robot")
  name = robot.get("name") if isinstance(robot, dict) else None
  if name is None or name in ROBOT_NAMES:
    return base
  if not named:
    raise ConfigError(f"robot.name = {short_repr(name)}: {path}'s metadata names a robot "
                      f"file, and a policy file may name only a built-in robot "
                      f"({', '.join(ROBOT_NAMES)}); give --robot FILE.yaml (or --set "
                      "robot.name=...) to drive it with a robot file of yours")
  return {**base, "robot": {k: v for k, v in robot.items() if k != "name"}}


def _value(cfg: Config, key: str):
  section, name = key.split(".")
  return getattr(getattr(cfg, section), name)


def policy_config(spec: str | Path, config_file: str | Path | None = None,
                  overrides: Sequence[str] = (), which: str = "best") -> tuple[Config, str]:
  """(config, where it came from) for the policy `spec`: a run dir (or a checkpoint in
  it), an exported `.npz`, or oracle/random (defaults). `config_file` and `overrides`
  ("section.key=value") are laid over the policy's own config.

  Raises ConfigError (one line, naming the key) for a bad config or an override of a
  `POLICY_KEYS` value; FileNotFoundError / `PolicyFormatError` for a missing or
  unreadable policy.
  """
  spec = str(spec)
  if spec in BUILTIN_POLICIES:
    return load_config(config_file, overrides), str(config_file or "defaults")
  path = Path(spec)
  if path.suffix == ".npz" or path.is_file():
    base, source = policy_file_settings(path), f"{path}'s metadata"
    base = _builtin_robot_only(base, path, _robot_named(config_file, overrides))
  else:
    found = run_config_file(path, which)
    if found is None:  # an old or hand-made run: the given config, or the defaults
      cfg = load_config(config_file, overrides)
      return cfg, f"{config_file or 'defaults'} ({path} has no config.yaml)"
    base, source = read_yaml(found), str(found)
  own = load_config(None, (), base)
  cfg = load_config(config_file, overrides, base)
  from_robot = config_values(cfg.robot.spec)  # under --set (RobotConfig)
  for key in POLICY_KEYS:
    trained, now = _value(own, key), _value(cfg, key)
    if now != trained and key in from_robot and not any(
        o.split("=", 1)[0].strip() == key for o in overrides):
      raise ConfigError(f"{key} = {now}: the robot file {cfg.robot.name} asks for it, but "
                        f"the policy was trained with {trained} ({source}); its networks "
                        f"fit only that (--set {key}={trained} keeps the policy's)")
    if now != trained:
      raise ConfigError(f"{key} = {now}: the policy was trained with {trained} ({source}); "
                        f"its networks fit only that (drop the override)")
  if config_file or overrides:
    source += " with " + ", ".join(
        ([str(config_file)] if config_file else []) + [f"--set {o}" for o in overrides])
  return cfg, source
