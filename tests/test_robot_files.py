"""Robots as YAML files (docs/your-robot.md): the built-in files hold the paper's numbers,
a file with the Husky's numbers builds the Husky's model, the camera pitch, every kind of
bad file is one ConfigError line naming the file, the precedence of the robot file's
camera and velocity values, and the command lines. No JAX compilation."""

import math
from pathlib import Path

import mujoco
import numpy as np
import pytest
import yaml

from mjxvine.config import (ROBOTS, Config, ConfigError, RobotSpec, load_config, replace,
                            robot_spec)
from mjxvine.worlds import build_model, generate_world

ROOT = Path(__file__).resolve().parent.parent
ROBOT_DIR = ROOT / "mjxvine" / "worlds" / "data" / "robots"

# The numbers hard-coded in mjxvine.config before the robot files (docs/design.md, Robots).
EXPECTED = {
    "jackal": RobotSpec("jackal", 0.508, 0.430, 0.250, 16.5, 0.477, 0.098, 0.376, 0.262,
                        0.21, 0.26, 1.8),
    "husky": RobotSpec("husky", 0.990, 0.670, 0.390, 46.0, 2.64, 0.1651, 0.571, 0.512,
                       0.445, 0.40, 3.5),
}
HUSKY = {"name": "husky",
         "body": {"length_m": 0.990, "width_m": 0.670, "height_m": 0.390,
                  "chassis_mass_kg": 46.0},
         "wheels": {"radius_m": 0.1651, "mass_kg": 2.64, "track_m": 0.571,
                    "wheelbase_m": 0.512, "track_slip": 3.5},
         "camera": {"ahead_m": 0.445, "height_m": 0.40, "pitch_deg": 0.0}}
MODEL_FIELDS = ("body_mass", "body_pos", "body_inertia", "geom_size", "geom_pos",
                "geom_friction", "cam_pos", "cam_quat", "cam_fovy", "dof_armature",
                "actuator_gainprm", "actuator_biasprm", "actuator_ctrlrange", "qpos0")


def write(tmp_path, doc, name="robot.yaml") -> Path:
  path = tmp_path / name
  path.write_text(doc if isinstance(doc, str) else yaml.safe_dump(doc))
  return path


def variant(**groups) -> dict:
  """HUSKY with keys of groups replaced (a value None removes the key)."""
  doc = {k: (dict(v) if isinstance(v, dict) else v) for k, v in HUSKY.items()}
  for group, values in groups.items():
    if not isinstance(values, dict):
      doc[group] = values
      continue
    doc.setdefault(group, {})
    for k, v in values.items():
      if v is None:
        doc[group].pop(k, None)
      else:
        doc[group][k] = v
  return doc


@pytest.fixture(scope="module")
def small():
  cfg = replace(Config(), world={"train_rows": 2, "train_length_m": 4.0})
  return cfg, generate_world("train", 0, cfg.world)


def model_of(small, robot: str) -> mujoco.MjModel:
  cfg, world = small
  return build_model(world, replace(cfg, robot={"name": robot}))


def test_builtin_files_hold_the_previous_numbers():
  assert set(ROBOTS) == {"jackal", "husky"}
  for name, spec in EXPECTED.items():
    assert ROBOTS[name] == spec and robot_spec(name) == spec
    assert robot_spec(str(ROBOT_DIR / f"{name}.yaml")) == spec  # as a file, too
    assert spec.camera_pitch_deg == 0.0 and spec.v_max is None and spec.camera_width_px is None
  assert math.isclose(ROBOTS["jackal"].mass, 18.408) and math.isclose(ROBOTS["husky"].mass, 56.56)
  text = (ROBOT_DIR / "jackal.yaml").read_text()
  assert text.startswith("#") and all(f"#   {g}:" in text for g in ("body", "wheels", "camera"))


def test_robot_files_are_package_data():
  import tomllib
  data = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
  assert "data/robots/*.yaml" in data["package-data"]["mjxvine.worlds"]


def test_husky_file_builds_the_husky(tmp_path, small):
  path = write(tmp_path, HUSKY, "my_husky.yml")
  assert robot_spec(str(path)) == ROBOTS["husky"]
  assert robot_spec(str(path)) is robot_spec(str(path.resolve()))  # read once per file
  cfg = load_config(None, [f"robot.name={path}"])
  assert cfg.robot.name == str(path) and cfg.camera == Config().camera and cfg.env == Config().env
  a, b = model_of(small, "husky"), model_of(small, str(path))
  for field in MODEL_FIELDS:
    assert np.array_equal(getattr(a, field), getattr(b, field)), field


def test_pitch_zero_is_the_level_camera(small):
  spec = mujoco.MjSpec()
  spec.worldbody.add_body(name="b").add_camera(name="depth", xyaxes=[0, -1, 0, 0, 0, 1])
  level = spec.compile().cam_quat[0]
  for name in ROBOTS:
    assert np.array_equal(model_of(small, name).cam_quat[0], level)


@pytest.mark.parametrize("pitch", [15.0, -10.0])
def test_pitch_turns_the_camera_down(tmp_path, small, pitch):
  path = write(tmp_path, variant(camera={"pitch_deg": pitch}))
  assert robot_spec(str(path)).camera_pitch_deg == pitch
  model, husky = model_of(small, str(path)), model_of(small, "husky")
  assert not np.allclose(model.cam_quat[0], husky.cam_quat[0])
  assert np.array_equal(model.cam_pos, husky.cam_pos)
  axis = np.zeros(3)  # the optical axis (-z of the camera) in the body frame
  mujoco.mju_rotVecQuat(axis, np.array([0.0, 0.0, -1.0]), model.cam_quat[0])
  t = math.radians(pitch)
  np.testing.assert_allclose(axis, [math.cos(t), 0.0, -math.sin(t)], atol=1e-12)
  right = np.zeros(3)  # the image's x axis stays the body's right (-y)
  mujoco.mju_rotVecQuat(right, np.array([1.0, 0.0, 0.0]), model.cam_quat[0])
  np.testing.assert_allclose(right, [0.0, -1.0, 0.0], atol=1e-12)


BAD = [
    ("not a mapping", "- 1\n- 2\n", "expected a mapping"),
    ("empty", "", "empty file"),
    ("not YAML", "body: {length_m: 0.5\n", "not valid YAML"),
    ("unknown top key", variant(wheel={"radius_m": 0.1}), "unknown key wheel; did you mean wheels?"),
    ("unknown key", variant(wheels={"radius": 0.1}), "unknown key wheels.radius; did you mean radius_m?"),
    ("unknown key, no match", variant(camera={"zoom": 2}), "unknown key camera.zoom (known:"),
    ("missing key", variant(wheels={"track_m": None}), "missing key wheels.track_m"),
    ("missing name", {k: v for k, v in HUSKY.items() if k != "name"}, "missing key name"),
    ("bad name", variant(name="my robot"), "name = 'my robot'"),
    ("group not a mapping", variant(body=[1, 2]), "body: expected a mapping"),
    ("not a number", variant(body={"width_m": "wide"}), "body.width_m = 'wide': expected a number"),
    ("a boolean", variant(wheels={"track_slip": True}), "expected a number"),
    ("not finite", variant(body={"height_m": float("nan")}), "expected a finite number"),
    ("infinite", variant(wheels={"mass_kg": float("inf")}), "expected a finite number"),
    ("radius <= 0", variant(wheels={"radius_m": 0.0}), "wheels.radius_m = 0: must be in [0.05, 5] m"),
    ("too heavy", variant(body={"chassis_mass_kg": 5000}), "must be in [0.1, 2000] kg"),
    ("slip below 1", variant(wheels={"track_slip": 0.5}), "wheels.track_slip = 0.5: must be in [1, 10]"),
    ("pitch", variant(camera={"pitch_deg": 60}), "camera.pitch_deg = 60: must be in [-45, 45] deg"),
    ("fov", variant(camera={"fovx_deg": 180}), "camera.fovx_deg = 180: must be in [1, 170] deg"),
    ("px not whole", variant(camera={"width_px": 64.5}), "expected a whole number of pixels"),
    ("px range", variant(camera={"height_px": 2000}), "must be in [1, 1024] px"),
    ("speed", variant(velocity={"v_max_mps": 0}), "velocity.v_max_mps = 0: must be in [0.01, 5] m/s"),
    ("track wider than body", variant(wheels={"track_m": 0.8}), "wider than body.width_m"),
    ("wheels beyond the body", variant(wheels={"wheelbase_m": 0.9}), "reach beyond body.length_m"),
    ("camera below the axle", variant(camera={"height_m": 0.1}), "above the wheel axle"),
    ("camera off the body", variant(camera={"ahead_m": 0.7}), "the camera must be on the body"),
    ("body below the axle", variant(body={"height_m": 0.15}), "must be above wheels.radius_m"),
]


@pytest.mark.parametrize("doc, message", [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_bad_files_are_one_line(tmp_path, doc, message):
  path = write(tmp_path, doc)
  with pytest.raises(ConfigError) as e:
    robot_spec(str(path))
  text = str(e.value)
  assert text.startswith(f"{path}: ") and "\n" not in text and message in text, text
  with pytest.raises(ConfigError) as e:  # in a config: robot.name, then the file
    load_config(None, [f"robot.name={path}"])
  assert str(e.value).startswith(f"robot.name: {path}: ") and "\n" not in str(e.value)


def test_bad_names_and_missing_files(tmp_path):
  for name, message in (("tank", "unknown robot 'tank'"), ("robot.json", "unknown robot"),
                        (str(tmp_path / "gone.yaml"), "robot file not found")):
    with pytest.raises(ConfigError, match=f"^{message}") as e:
      robot_spec(name)
    assert name in str(e.value) and "\n" not in str(e.value)
  bad = tmp_path / "bin.yaml"
  bad.write_bytes(b"\xff\xfe\x00")
  with pytest.raises(ConfigError, match="not a text file"):
    robot_spec(str(bad))


def test_precedence(tmp_path):
  """defaults < config YAML < robot file < --set, for the optional values."""
  robot = write(tmp_path, variant(camera={"fovx_deg": 70.0, "width_px": 64, "height_px": 48},
                                  velocity={"v_max_mps": 0.8, "w_max_radps": 1.5}))
  assert load_config(None, [f"robot.name={robot}"]).camera.fovy_deg == 46.8  # not in the file
  config = write(tmp_path, f"robot: {{name: {robot}}}\ncamera: {{width: 41, fovy_deg: 50.0}}\n"
                 "env: {v_max: 0.3}\n", "config.yaml")
  cfg = load_config(config)
  assert (cfg.camera.width, cfg.camera.height, cfg.camera.fovx_deg) == (64, 48, 70.0)
  assert cfg.camera.fovy_deg == 50.0  # the config's: the file does not give it
  assert (cfg.env.v_max, cfg.env.w_max) == (0.8, 1.5)
  cfg = load_config(config, ["camera.width=33", "env.v_max=0.4"])
  assert (cfg.camera.width, cfg.camera.height, cfg.env.v_max) == (33, 48, 0.4)
  # --set robot.name beats the config's robot, and brings its own values
  cfg = load_config(config, ["robot.name=husky"])
  assert (cfg.robot.name, cfg.camera.width, cfg.env.v_max) == ("husky", 41, 0.3)


def test_a_policy_keeps_its_image_size(tmp_path):
  """A robot file asking for another image size than a trained policy's is one line;
  `--set` of the policy's value keeps it."""
  from mjxvine.rundir.settings import policy_config
  robot = write(tmp_path, variant(camera={"width_px": 64, "height_px": 64, "fovx_deg": 70.0}))
  policy = ROOT / "models" / "jackal.npz"
  with pytest.raises(ConfigError) as e:
    policy_config(policy, None, [f"robot.name={robot}"])
  text = str(e.value)
  assert "\n" not in text and text.startswith("camera.")
  assert f"the robot file {robot} asks for it" in text and "trained with 41" in text
  cfg, _ = policy_config(policy, None, [f"robot.name={robot}", "camera.height=41",
                                        "camera.width=41"])
  assert (cfg.camera.width, cfg.camera.fovx_deg) == (41, 70.0)  # the fov is not the networks'


@pytest.mark.parametrize("module", ["worlds", "evaluate"])
def test_command_lines_take_a_file(tmp_path, capsys, module):
  """`--robot BAD.yaml` is exit 2 and one line on stderr; `--robot FILE.yaml` works."""
  from mjxvine import evaluate
  from mjxvine.worlds.__main__ import main as worlds_main
  main = worlds_main if module == "worlds" else evaluate.main
  bad = write(tmp_path, variant(wheels={"radius_m": -1}), "bad.yaml")
  args = ["--out", str(tmp_path / "out")] + (["--policy", "oracle"] if module == "evaluate" else [])
  try:
    code = main(["--robot", str(bad), *args])
  except SystemExit as e:
    code = e.code
  err = capsys.readouterr().err.strip()
  assert code == 2 and "\n" not in err and str(bad) in err and "wheels.radius_m" in err, err
  if module == "worlds":
    good = write(tmp_path, HUSKY, "good.yaml")
    assert worlds_main(["--robot", str(good), "--out", str(tmp_path / "good")]) == 0
    assert "(" + str(good) + ")" in capsys.readouterr().out


def test_the_guide_shows_the_example_file():
  """docs/your-robot.md's robot file is examples/my_robot.yaml, and that is a valid robot."""
  import re
  text = (ROOT / "docs" / "your-robot.md").read_text()
  block = re.search(r"<!-- skip: a robot file.*?-->\n```yaml\n(.*?)```", text, re.S).group(1)
  example = ROOT / "examples" / "my_robot.yaml"
  assert yaml.safe_load(block) == yaml.safe_load(example.read_text())
  robot = robot_spec(str(example))
  assert robot.name == "my_robot" and robot.camera_pitch_deg == 5.0
  cfg = load_config(ROOT / "experiments" / "smoke.yaml", [f"robot.name={example}"])
  assert (cfg.camera.fovx_deg, cfg.camera.fovy_deg) == (70.0, 55.0)
