"""Robots as data: `RobotSpec` and the robot YAML files that describe one (docs/your-robot.md).

A robot file groups its numbers, units in the key names (metres, kg, degrees, pixels):

  name: jackal
  body: {length_m: 0.508, width_m: 0.430, height_m: 0.250, chassis_mass_kg: 16.5}
  wheels: {radius_m: 0.098, mass_kg: 0.477, track_m: 0.376, wheelbase_m: 0.262, track_slip: 1.8}
  camera: {ahead_m: 0.21, height_m: 0.26, pitch_deg: 0.0}

with the optional camera.pitch_deg (default 0), camera.fovx_deg / fovy_deg / width_px /
height_px, velocity.v_max_mps / w_max_radps and the robot's faults, faults.latency_steps /
velocity_lag_s / mount_pitch_deg / mount_roll_deg / mount_height_m (ranges [lo, hi]) /
yaw_walk_deg (`mjxvine.robot_faults`). The built-in robots (`ROBOTS`) are the
files in mjxvine/worlds/data/robots/. A bad file raises `RobotFileError`, one line naming
the file and its fault (`mjxvine.config.robot_spec` turns it into a `ConfigError`).

Every YAML file or value the package reads goes through `load_yaml` / `yaml_text` here: at
most 1 MiB, nested at most 16 deep, no anchors or aliases, scalars as YAML 1.2 reads them;
errors quote values with `short_repr` (one short line). Only yaml and the standard library
are imported: `mjxvine.config` validates with it.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
import reprlib
from pathlib import Path

import yaml

BUILTIN_DIR = Path(__file__).resolve().parent / "worlds" / "data" / "robots"
SUFFIXES = (".yaml", ".yml")


class RobotFileError(ValueError):
  """A robot file (or robot name) is invalid; the message names the file and the fault."""


# Every YAML this package reads (configs, `--set` values, robot files) goes through
# `yaml_text`: a file is at most MAX_YAML_BYTES, nested at most MAX_YAML_DEPTH deep, without
# anchors or aliases (a few hundred bytes of nested aliases expand to gigabytes), and its
# plain scalars mean what YAML 1.2 says (`010` is ten, `1:30` is text, `yes` is text).
MAX_YAML_BYTES = 1 << 20  # 1 MiB: a config or robot file is a few KB
MAX_YAML_DEPTH = 16  # mappings and lists inside each other; a config needs 3


def escaped(text: str) -> str:
  """`text` on one line: control and other unprintable characters (newlines, ANSI escapes)
  escaped as Python writes them; uncut."""
  return text if text.isprintable() else "".join(
      c if c.isprintable() else repr(c)[1:-1] for c in text)


def clean(text: str, limit: int = 200) -> str:
  """`text` for a one-line message: at most `limit` characters ("..." where cut), escaped
  (`escaped`)."""
  head = text[:limit + 1]
  out = escaped(head)
  return out if len(out) <= limit and len(text) <= limit else out[:max(limit - 3, 0)] + "..."


_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxdict, _REPR.maxlist, _REPR.maxtuple = 2, 4, 4, 4
_REPR.maxset = _REPR.maxfrozenset = 4
_REPR.maxstring = _REPR.maxother = _REPR.maxlong = 200


def short_repr(value, limit: int = 60) -> str:
  """`value`'s repr for an error message: its first `limit` characters at most, on one
  line, however big, deep or odd the value (every value an error quotes goes through
  this)."""
  try:
    text = repr(value[:limit + 1]) if isinstance(value, str) else _REPR.repr(value)
  except ValueError:  # an int too long to print (sys.get_int_max_str_digits)
    text = f"<{type(value).__name__}>"
  return clean(text, limit)


class _Loader(yaml.SafeLoader):
  """`yaml.SafeLoader` that refuses anchors, aliases and deep nesting, and resolves plain
  scalars by YAML 1.2's core schema: integers decimal (or 0o / 0x), floats, true / false,
  null; anything else (`1:30`, `yes`, `2024-01-01`, `1_000`) is a string."""

  depth = 0

  def compose_node(self, parent, index):
    event = self.peek_event()
    if isinstance(event, yaml.AliasEvent) or event.anchor is not None:
      raise yaml.composer.ComposerError(
          None, None, "anchors and aliases (&name, *name) are not allowed",
          event.start_mark)
    if self.depth >= MAX_YAML_DEPTH:
      raise yaml.composer.ComposerError(
          None, None, f"nested deeper than {MAX_YAML_DEPTH} levels", event.start_mark)
    self.depth += 1
    try:
      return super().compose_node(parent, index)
    finally:
      self.depth -= 1

  def construct_yaml_int(self, node):
    text = self.construct_scalar(node)
    body = text.lstrip("+-")
    try:  # decimal whatever the leading zeros (YAML 1.1 read 010 as octal 8)
      if body[:2] in ("0o", "0x"):
        value = int(body[2:], 8 if body[1] == "o" else 16)
        return -value if text.startswith("-") else value
      return int(text, 10)
    except ValueError:  # also an int of more digits than Python converts
      raise yaml.constructor.ConstructorError(
          None, None, f"{short_repr(text)} is not an integer", node.start_mark) from None

  def construct_yaml_float(self, node):
    text = self.construct_scalar(node)
    special = {".inf": math.inf, "+.inf": math.inf, "-.inf": -math.inf, ".nan": math.nan}
    if text.lower() in special:
      return special[text.lower()]
    try:  # no sexagesimal (YAML 1.1 read 1:30 as 90)
      return float(text)
    except ValueError:
      raise yaml.constructor.ConstructorError(
          None, None, f"{short_repr(text)} is not a number", node.start_mark) from None


_Loader.yaml_implicit_resolvers = {}
for _tag, _pattern, _first in (
    ("bool", r"true|True|TRUE|false|False|FALSE", "tTfF"),
    ("null", r"~|null|Null|NULL|", ["~", "n", "N", ""]),
    ("int", r"[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+", "-+0123456789"),
    ("float", r"[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?"
     r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN)", "-+0123456789.")):
  _Loader.add_implicit_resolver(f"tag:yaml.org,2002:{_tag}", re.compile(f"^(?:{_pattern})$"),
                                list(_first))
_Loader.add_constructor("tag:yaml.org,2002:int", _Loader.construct_yaml_int)
_Loader.add_constructor("tag:yaml.org,2002:float", _Loader.construct_yaml_float)


def yaml_text(text: str, shown: str, error: type[Exception]):
  """The YAML document `text` (`_Loader`'s rules); `error`, one line naming `shown`, when
  it is not YAML text or breaks a rule."""
  if len(text) > MAX_YAML_BYTES:
    raise error(f"{shown}: longer than {MAX_YAML_BYTES >> 20} MiB of YAML")
  try:
    return yaml.load(text, Loader=_Loader)  # noqa: S506 - a SafeLoader
  except yaml.YAMLError as e:
    mark, problem = getattr(e, "problem_mark", None), getattr(e, "problem", None)
    fault = (f"{problem} at line {mark.line + 1}, column {mark.column + 1}"
             if mark is not None and problem else " ".join(str(e).split()))
    raise error(f"{shown}: not valid YAML ({clean(fault)})") from None


@dataclasses.dataclass(frozen=True)
class RobotSpec:
  """A robot's fixed geometry and masses (docs/design.md, Robots): metres, kg, degrees.

  The optional camera and velocity values (None: the config's) are laid over the config
  by `mjxvine.config.load_config` (`config_values`)."""
  name: str
  length: float        # footprint L (x)
  width: float         # footprint W (y)
  height: float        # H, ground to top
  chassis_mass: float
  wheel_mass: float
  wheel_radius: float
  track: float         # distance between left and right wheel centres
  wheelbase: float     # distance between front and rear axles
  camera_ahead: float  # camera optical centre ahead of the base centre
  camera_height: float  # camera optical centre above the ground
  track_slip: float    # skid-steer expanded-track factor chi: w = (v_r - v_l) / (chi * track)
  camera_pitch_deg: float = 0.0  # about the body's y axis; positive looks down
  camera_fovx_deg: float | None = None
  camera_fovy_deg: float | None = None
  camera_width_px: int | None = None
  camera_height_px: int | None = None
  v_max: float | None = None  # m/s
  w_max: float | None = None  # rad/s
  # the robot's faults (`mjxvine.robot_faults`), the `robot.*` config keys of the same names
  latency_steps: tuple[int, int] | None = None  # control steps, [lo, hi]
  velocity_lag_s: tuple[float, float] | None = None  # s, [lo, hi]
  mount_pitch_deg: tuple[float, float] | None = None  # the error's size, [lo, hi]
  mount_roll_deg: tuple[float, float] | None = None  # the error's size, [lo, hi]
  mount_height_m: tuple[float, float] | None = None  # the error's size, [lo, hi]
  yaw_walk_deg: float | None = None  # per sqrt(s)

  @property
  def mass(self) -> float:
    return self.chassis_mass + 4 * self.wheel_mass


# group -> key -> (RobotSpec field, lo, hi, required); ranges are physical sanity bounds.
SCHEMA = {
    "body": {"length_m": ("length", 0.05, 5.0, True), "width_m": ("width", 0.05, 5.0, True),
             "height_m": ("height", 0.05, 5.0, True),
             "chassis_mass_kg": ("chassis_mass", 0.1, 2000.0, True)},
    "wheels": {"radius_m": ("wheel_radius", 0.05, 5.0, True),
               "mass_kg": ("wheel_mass", 0.1, 2000.0, True),
               "track_m": ("track", 0.05, 5.0, True),
               "wheelbase_m": ("wheelbase", 0.05, 5.0, True),
               "track_slip": ("track_slip", 1.0, 10.0, True)},
    "camera": {"ahead_m": ("camera_ahead", -5.0, 5.0, True),
               "height_m": ("camera_height", 0.05, 5.0, True),
               "pitch_deg": ("camera_pitch_deg", -45.0, 45.0, False),
               "fovx_deg": ("camera_fovx_deg", 1.0, 170.0, False),
               "fovy_deg": ("camera_fovy_deg", 1.0, 170.0, False),
               "width_px": ("camera_width_px", 1, 1024, False),
               "height_px": ("camera_height_px", 1, 1024, False)},
    "velocity": {"v_max_mps": ("v_max", 0.01, 5.0, False),
                 "w_max_radps": ("w_max", 0.01, 10.0, False)},
    # the bounds of the `robot.*` keys (mjxvine.config.RobotConfig)
    "faults": {"latency_steps": ("latency_steps", 0, 5, False),
               "velocity_lag_s": ("velocity_lag_s", 0.0, 2.0, False),
               "mount_pitch_deg": ("mount_pitch_deg", 0.0, 20.0, False),
               "mount_roll_deg": ("mount_roll_deg", 0.0, 20.0, False),
               "mount_height_m": ("mount_height_m", 0.0, 0.3, False),
               "yaw_walk_deg": ("yaw_walk_deg", 0.0, 10.0, False)},
}
RANGES = {"latency_steps", "velocity_lag_s", "mount_pitch_deg", "mount_roll_deg",
          "mount_height_m"}  # RobotSpec fields given as [lo, hi]
# RobotSpec field -> the config key it sets when the file gives it (RobotConfig's rule)
CONFIG_KEYS = {"camera_fovx_deg": "camera.fovx_deg", "camera_fovy_deg": "camera.fovy_deg",
               "camera_width_px": "camera.width", "camera_height_px": "camera.height",
               "v_max": "env.v_max", "w_max": "env.w_max",
               **{spec[0]: f"robot.{spec[0]}" for spec in SCHEMA["faults"].values()}}
UNITS = {"_m": " m", "_kg": " kg", "_deg": " deg", "_px": " px", "_mps": " m/s",
         "_radps": " rad/s", "_s": " s", "_steps": " steps"}
WHOLE = {"_px": "pixels", "_steps": "control steps"}  # integer keys: what they count
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


def _unknown(shown: str, key: str, known) -> RobotFileError:
  key = clean(key, 80)  # a key of the file: shown, but short and on one line
  close = difflib.get_close_matches(key.rsplit(".", 1)[-1], known, n=2, cutoff=0.6)
  hint = f"; did you mean {' or '.join(close)}?" if close else f" (known: {', '.join(known)})"
  return RobotFileError(f"{shown}: unknown key {key}{hint}")


def _number(shown: str, key: str, value, lo, hi):
  """`value` as a float (an int for *_px) in [lo, hi], or the one-line error."""
  if isinstance(value, str):  # YAML 1.1 reads 1e-3 (no dot) as a string
    try:
      value = float(value)
    except ValueError:
      pass
  if isinstance(value, bool) or not isinstance(value, (int, float)):
    raise RobotFileError(f"{shown}: {key} = {short_repr(value)}: expected a number")
  if not math.isfinite(value):
    raise RobotFileError(f"{shown}: {key} = {short_repr(value)}: expected a finite number")
  if isinstance(lo, int):
    if not float(value).is_integer():
      counts = next((w for s, w in WHOLE.items() if key.endswith(s)), "units")
      raise RobotFileError(f"{shown}: {key} = {short_repr(value)}: expected a whole number "
                           f"of {counts}")
    value = int(value)
  else:
    value = float(value)
  if not lo <= value <= hi:
    unit = next((u for s, u in UNITS.items() if key.endswith(s)), "")
    raise RobotFileError(f"{shown}: {key} = {value:g}: must be in [{lo:g}, {hi:g}]{unit}")
  return value


def _range(shown: str, key: str, value, lo, hi) -> tuple:
  """`value` as an increasing pair [min, max] of `_number`s in [lo, hi], or the one-line
  error."""
  if not isinstance(value, (list, tuple)) or len(value) != 2:
    raise RobotFileError(f"{shown}: {key} = {short_repr(value)}: expected a range [min, max] "
                         "of 2 numbers")
  pair = tuple(_number(shown, key, v, lo, hi) for v in value)
  if pair[0] > pair[1]:
    raise RobotFileError(f"{shown}: {key} = [{pair[0]:g}, {pair[1]:g}]: the range must be "
                         "increasing [min, max]")
  return pair


def _check_fit(shown: str, s: RobotSpec) -> None:
  """Cross-field sanity: the wheels under the body, the camera on it, above the axle."""
  checks = (
      (s.height > s.wheel_radius, f"body.height_m = {s.height:g}: must be above "
       f"wheels.radius_m = {s.wheel_radius:g} (the body's top above the axle)"),
      (s.wheel_radius <= s.width, f"wheels.radius_m = {s.wheel_radius:g}: must be at "
       f"most body.width_m = {s.width:g}"),
      (s.track <= s.width, f"wheels.track_m = {s.track:g}: wider than body.width_m = "
       f"{s.width:g} (the wheels must lie within the footprint)"),
      (s.wheelbase + 2 * s.wheel_radius <= s.length, f"wheels.wheelbase_m = "
       f"{s.wheelbase:g}: the wheels (radius {s.wheel_radius:g}) reach beyond "
       f"body.length_m = {s.length:g}; need wheelbase_m + 2 radius_m <= length_m"),
      (s.camera_height > s.wheel_radius, f"camera.height_m = {s.camera_height:g}: must "
       f"be above the wheel axle (wheels.radius_m = {s.wheel_radius:g})"),
      (abs(s.camera_ahead) <= s.length / 2, f"camera.ahead_m = {s.camera_ahead:g}: the "
       f"camera must be on the body, |ahead_m| <= body.length_m / 2 = {s.length / 2:g}"),
  )
  for ok, message in checks:
    if not ok:
      raise RobotFileError(f"{shown}: {message}")


def parse_robot(doc, shown: str) -> RobotSpec:
  """The `RobotSpec` of a robot file's loaded YAML `doc`; `shown` names the file in errors."""
  if not isinstance(doc, dict):
    got = "nothing (an empty file)" if doc is None else f"a {type(doc).__name__}"
    raise RobotFileError(f"{shown}: expected a mapping (name:, body:, wheels:, camera:), "
                         f"got {got}")
  top = ("name", *SCHEMA)
  for key in doc:
    if key not in top:
      raise _unknown(shown, str(key), top)
  name = doc.get("name")
  if name is None:
    raise RobotFileError(f"{shown}: missing key name")
  if not isinstance(name, str) or not NAME.match(name):
    raise RobotFileError(f"{shown}: name = {short_repr(name)}: expected a word of letters, digits, "
                         "'_', '.' or '-' (at most 64 characters)")
  fields = {"name": name}
  for group, keys in SCHEMA.items():
    values = doc.get(group)
    if values is None:
      values = {}
    if not isinstance(values, dict):
      raise RobotFileError(f"{shown}: {group}: expected a mapping of keys "
                           f"({', '.join(keys)}), got a {type(values).__name__}")
    for key in values:
      if key not in keys:
        raise _unknown(shown, f"{group}.{key}", keys)
    for key, (field, lo, hi, required) in keys.items():
      if key in values:
        read = _range if field in RANGES else _number
        fields[field] = read(shown, f"{group}.{key}", values[key], lo, hi)
      elif required:
        raise RobotFileError(f"{shown}: missing key {group}.{key}")
  spec = RobotSpec(**fields)
  _check_fit(shown, spec)
  return spec


def load_yaml(path: Path, shown: str, error: type[Exception], what: str):
  """The YAML document in the file `path` (at most MAX_YAML_BYTES, read by `yaml_text`'s
  rules); `error`, one line naming `shown`, when it cannot be read or is not such YAML text
  (robot files here, config files in `config`)."""
  try:
    with open(path, "rb") as f:
      data = f.read(MAX_YAML_BYTES + 1)
    if len(data) > MAX_YAML_BYTES:
      raise error(f"{shown}: larger than {MAX_YAML_BYTES >> 20} MiB; a {what} is a few KB "
                  "of YAML text")
    text = data.decode("utf-8")
  except UnicodeDecodeError as e:
    raise error(f"{shown}: not a text file (byte {e.start} is not UTF-8); a {what} is "
                "YAML text") from None
  except OSError as e:
    raise error(f"{shown}: cannot be read ({e.strerror})") from None
  return yaml_text(text, shown, error)


def read_robot_file(path: str | Path, shown: str | None = None) -> RobotSpec:
  """The `RobotSpec` of the robot file at `path` (`RobotFileError` if it is bad)."""
  path, shown = Path(path), clean(shown or str(path))
  if not path.is_file():
    raise RobotFileError(f"robot file not found: {shown}")
  doc = load_yaml(path, shown, RobotFileError, "robot file")
  return parse_robot(doc, shown)


ROBOTS = {p.stem: read_robot_file(p) for p in sorted(BUILTIN_DIR.glob("*.yaml"))}


_READ: dict[tuple[str, int], RobotSpec] = {}  # (resolved path, mtime ns) -> its robot


def robot_spec(name_or_path: str | Path) -> RobotSpec:
  """The robot a built-in name (`ROBOTS`) or a robot file path (.yaml / .yml, relative to
  the working directory) names; files are read once per resolved path (again when their
  modification time changes). `RobotFileError` (one line naming the file) if bad."""
  text = str(name_or_path)
  if text in ROBOTS:
    return ROBOTS[text]
  path = Path(text).expanduser()
  if path.suffix.lower() not in SUFFIXES:
    raise RobotFileError(f"unknown robot {short_repr(text)}: a built-in name "
                         f"({', '.join(ROBOTS)}) or a robot file FILE.yaml")
  if not path.is_file():
    raise RobotFileError(f"robot file not found: {clean(text)}")
  resolved = path.resolve()
  key = (str(resolved), resolved.stat().st_mtime_ns)
  if key not in _READ:
    _READ[key] = read_robot_file(resolved, text)
  return _READ[key]


def config_values(robot: RobotSpec) -> dict[str, float | int | tuple]:
  """{"camera.width": 64, "env.v_max": 1.0, "robot.latency_steps": (0, 2), ...}: the config
  keys the robot file sets (its optional camera, velocity and fault values)."""
  return {key: getattr(robot, field) for field, key in CONFIG_KEYS.items()
          if getattr(robot, field) is not None}


__all__ = ["RobotSpec", "RobotFileError", "ROBOTS", "SCHEMA", "robot_spec", "read_robot_file",
           "parse_robot", "config_values", "load_yaml", "yaml_text", "short_repr", "clean",
           "MAX_YAML_BYTES", "MAX_YAML_DEPTH"]
