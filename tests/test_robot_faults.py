"""The robot's faults (`mjxvine.robot_faults`, docs/your-robot.md): the latency delays the
wheels by exactly k control steps, the lag answers a step as 1 - exp(-t / tau), the mount
errors turn and raise the camera as a camera mounted so would be, the IMU yaw walks with
its std per sqrt(s); the env wires them in (one small env compiled for the module), with
every factor at zero it computes exactly what it computed without them, and a robot file
sets them."""

import math
import types

import jax
import jax.numpy as jp
import mujoco
import numpy as np
import pytest
import yaml
from mujoco import mjx

from mjxvine import depth as depth_cam, robot_faults
from mjxvine.angles import quat_yaw, wrap
from mjxvine.config import ConfigError, load_config, replace
from mjxvine.robot_files import BUILTIN_DIR
from mjxvine.worlds import build_model, generate_world, wheel_speeds

N = 4
TAU_S = 0.25
FAULTS = ["robot.latency_steps=[2, 2]", f"robot.velocity_lag_s=[{TAU_S}, {TAU_S}]",
          "robot.mount_pitch_deg=[3.0, 3.0]", "robot.mount_roll_deg=[2.0, 2.0]",
          "robot.mount_height_m=[0.03, 0.03]",
          "robot.yaw_walk_deg=5.0"]
TINY = ["camera.width=16", "camera.height=12", "env.max_steps=20", "world.pool_size=1"]


def faults_config(*overrides):
  return load_config("experiments/smoke.yaml", [*TINY, *overrides])


def run_commands(cfg, faults, commands):
  """The wheels' [v, w] of each command (T, 2) stepped through `robot_faults.step`."""
  def one(f, c):
    wheels, f = robot_faults.step(cfg, f, c, jax.random.PRNGKey(0))
    return f, wheels
  return np.asarray(jax.jit(lambda f, cs: jax.lax.scan(one, f, cs)[1])(faults, commands))


# ------------------------------------------------------------------ the stages, one by one
def test_latency_delays_the_wheels_by_exactly_k_steps():
  cfg = faults_config("robot.latency_steps=[0, 3]")
  commands = jax.random.uniform(jax.random.PRNGKey(1), (12, 2), minval=-1.0, maxval=1.0)
  f = robot_faults.draw(cfg.robot, jax.random.PRNGKey(2))
  assert f.pending.shape == (3, 2) and not np.any(f.pending)
  for k in range(4):
    wheels = run_commands(cfg, f._replace(latency_steps=jp.int32(k)), commands)
    shifted = np.concatenate([np.zeros((k, 2)), np.asarray(commands)[:12 - k]])
    np.testing.assert_array_equal(wheels, shifted)  # at rest until the first command lands


def test_lag_answers_a_step_as_one_minus_exp():
  cfg = faults_config(f"robot.velocity_lag_s=[{TAU_S}, {TAU_S}]", "robot.latency_steps=[0, 2]")
  f = robot_faults.draw(cfg.robot, jax.random.PRNGKey(3))
  assert float(f.lag_s) == pytest.approx(TAU_S)
  step = jp.array([0.5, -0.8])
  n = np.arange(1, 21)
  dt = cfg.env.control_dt
  for k in (0, 2):  # the lag acts on the delayed command
    wheels = run_commands(cfg, f._replace(latency_steps=jp.int32(k)), jp.tile(step, (20, 1)))
    rise = np.where(n > k, 1 - np.exp(-np.maximum(n - k, 0) * dt / TAU_S), 0.0)
    np.testing.assert_allclose(wheels, rise[:, None] * np.asarray(step), atol=1e-6)
  # tau drawn 0 (a range [0, x]): no lag
  wheels = run_commands(cfg, f._replace(lag_s=jp.float32(0), latency_steps=jp.int32(0)),
                        jp.tile(step, (3, 1)))
  np.testing.assert_array_equal(wheels, np.tile(step, (3, 1)))


def test_yaw_walk_std_per_sqrt_second():
  cfg = faults_config("robot.yaw_walk_deg=2.0")
  steps, walks = 10, 4000
  sigma = math.radians(2.0) * math.sqrt(cfg.env.control_dt)  # rad per control step

  def walk(key):
    f = robot_faults.draw(cfg.robot, key)
    def one(f, k):
      _, f = robot_faults.step(cfg, f, jp.zeros(2), k)
      return f, f.yaw_drift
    return jax.lax.scan(one, f, jax.random.split(key, steps))[1]

  drift = np.asarray(jax.jit(jax.vmap(walk))(jax.random.split(jax.random.PRNGKey(4), walks)))
  increments = np.diff(np.concatenate([np.zeros((walks, 1)), drift], 1), axis=1)
  count = increments.size  # the std's relative sampling error is 1 / sqrt(2 count): 0.35 %
  assert abs(increments.std() / sigma - 1) < 4 / math.sqrt(2 * count)
  assert abs(increments.mean()) < 4 * sigma / math.sqrt(count)
  # a random walk: the drift after n steps has std sigma sqrt(n)
  assert abs(drift[:, -1].std() / (sigma * math.sqrt(steps)) - 1) < 4 / math.sqrt(2 * walks)
  # the yaw input: the true one plus the drift; without a walk the true one itself
  f = robot_faults.draw(cfg.robot, jax.random.PRNGKey(0))._replace(yaw_drift=jp.float32(0.1))
  assert float(robot_faults.imu_yaw(cfg.robot, jp.float32(0.2), f)) == pytest.approx(0.3)
  yaw = jp.float32(0.2)
  assert robot_faults.imu_yaw(replace(cfg, robot={"yaw_walk_deg": 0.0}).robot, yaw, f) is yaw


def test_draws_cover_their_ranges():
  cfg = faults_config("robot.latency_steps=[1, 3]", "robot.velocity_lag_s=[0.1, 0.3]",
                      "robot.mount_pitch_deg=[0, 4.0]", "robot.mount_roll_deg=[0, 2.0]",
                      "robot.mount_height_m=[0, 0.05]")
  f = jax.jit(jax.vmap(lambda k: robot_faults.draw(cfg.robot, k)))(
      jax.random.split(jax.random.PRNGKey(5), 3000))
  assert f.latency_steps.dtype == jp.int32
  np.testing.assert_allclose(np.bincount(np.asarray(f.latency_steps), minlength=4)[1:] / 3000,
                             [1 / 3] * 3, atol=0.04)
  assert np.asarray(f.latency_steps).min() == 1  # (bincount checks the max)
  lag = np.asarray(f.lag_s)
  assert lag.min() >= 0.1 and lag.max() <= 0.3 and abs(lag.mean() - 0.2) < 0.01
  half = np.array([math.radians(4.0), math.radians(2.0), 0.05])
  mount = np.asarray(f.mount)
  assert np.all(np.abs(mount) <= half + 1e-7)
  np.testing.assert_allclose(mount.std(0), half / math.sqrt(3), rtol=0.05)  # uniform in +-
  assert not np.any(f.yaw_drift) and not np.any(f.setpoint) and not np.any(f.pending)
  # a range [a, a] fixes the factor (the evaluation's high end)
  fixed = robot_faults.draw(faults_config(*FAULTS).robot, jax.random.PRNGKey(6))
  assert int(fixed.latency_steps) == 2 and float(fixed.lag_s) == pytest.approx(TAU_S)
  # a size range [a, a] fixes the mount error's size; its sign stays random
  sizes = jax.jit(jax.vmap(lambda k: robot_faults.draw(faults_config(*FAULTS).robot, k).mount))(
      jax.random.split(jax.random.PRNGKey(7), 400))
  np.testing.assert_allclose(np.abs(np.asarray(sizes)),
                             np.broadcast_to([math.radians(3.0), math.radians(2.0), 0.03],
                                             (400, 3)), rtol=1e-6)
  assert 0.4 < float(np.mean(np.asarray(sizes) > 0)) < 0.6


# ------------------------------------------------------------------ the camera mount
@pytest.fixture(scope="module")
def camera_scene(tmp_path_factory):
  """(render(data) -> image, level model and data, model of a camera pitched 4 deg down,
  cfg): the Jackal in a small generated world, as a robot file with a pitched camera."""
  cfg = load_config("experiments/smoke.yaml", ["camera.width=32", "camera.height=24",
                                                "world.train_rows=2"])
  world = generate_world("train", 0, cfg.world)
  doc = yaml.safe_load((BUILTIN_DIR / "jackal.yaml").read_text())
  doc["camera"]["pitch_deg"] = 4.0
  path = tmp_path_factory.mktemp("robot") / "pitched.yaml"
  path.write_text(yaml.safe_dump(doc))
  level = build_model(world, cfg)
  pitched = build_model(world, replace(cfg, robot={"name": str(path)}))
  lane = world.lanes[0].centerline
  datas = []
  for m in (level, pitched):
    d = mujoco.MjData(m)
    d.qpos[:3] = [*lane[len(lane) // 3], 0.3]
    d.qpos[3:7] = [math.cos(0.05), 0, 0, math.sin(0.05)]  # a little off the row's axis
    mujoco.mj_forward(m, d)
    datas.append(mjx.put_data(m, d))
  cam = depth_cam.DepthCamera.create(level, cfg.camera)
  mx = mjx.put_model(level)
  render = jax.jit(lambda d: depth_cam.render_depth(cam, mx, d))
  return render, datas[0], datas[1], cam.cam_id, cfg


def test_mount_pitch_is_a_pitched_camera(camera_scene):
  """A +4 deg pitch error turns the camera as a mount pitched 4 deg down does (the robot
  file's camera.pitch_deg): the same camera matrix, the same image."""
  render, level, pitched, cam_id, cfg = camera_scene
  robot = replace(cfg, robot={"mount_pitch_deg": (0.0, 5.0)}).robot
  f = robot_faults.draw(robot, jax.random.PRNGKey(0))._replace(
      mount=jp.array([math.radians(4.0), 0.0, 0.0], jp.float32))
  moved = robot_faults.mounted_camera(robot, level, cam_id, f)
  np.testing.assert_allclose(moved.cam_xmat[cam_id], pitched.cam_xmat[cam_id], atol=1e-6)
  np.testing.assert_array_equal(moved.cam_xpos, level.cam_xpos)  # no height error asked
  np.testing.assert_array_equal(moved.qpos, level.qpos)  # the physics is left alone
  image, expected, flat = render(moved), render(pitched), render(level)
  assert np.mean(np.abs(image - expected) < 1e-3) > 0.99
  assert np.mean(np.abs(flat - expected) > 0.05) > 0.2  # the pitch moved the image
  # more ground in view: nearer depths in the lower rows
  assert float(jp.mean(image[-6:])) < float(jp.mean(flat[-6:]))


def test_mount_roll_and_height(camera_scene):
  _, level, _, cam_id, cfg = camera_scene
  robot = replace(cfg, robot={"mount_roll_deg": (0.0, 5.0), "mount_height_m": (0.0, 0.1)}).robot
  roll, dz = math.radians(3.0), 0.04
  f = robot_faults.draw(robot, jax.random.PRNGKey(0))._replace(
      mount=jp.array([0.0, roll, dz], jp.float32))
  moved = robot_faults.mounted_camera(robot, level, cam_id, f)
  r0 = np.asarray(level.cam_xmat[cam_id]).reshape(3, 3)
  r1 = np.asarray(moved.cam_xmat[cam_id]).reshape(3, 3)
  # the optical axis stays; the image's x axis turns towards its y axis by the roll
  np.testing.assert_allclose(r1[:, 2], r0[:, 2], atol=1e-6)
  np.testing.assert_allclose(r1[:, 0], math.cos(roll) * r0[:, 0] + math.sin(roll) * r0[:, 1],
                             atol=1e-6)
  np.testing.assert_allclose(r1 @ r1.T, np.eye(3), atol=1e-6)
  np.testing.assert_allclose(moved.cam_xpos[cam_id] - level.cam_xpos[cam_id], [0, 0, dz],
                             atol=1e-6)
  off = replace(cfg, robot={"yaw_walk_deg": 1.0}).robot  # faults, but no mount error
  assert robot_faults.mounted_camera(off, level, cam_id, f) is level


# ------------------------------------------------------------------ in the env
@pytest.fixture(scope="module")
def faulty_env():
  from mjxvine.env import VineyardEnv
  env = VineyardEnv(faults_config(*FAULTS))
  reset_to = jax.jit(jax.vmap(lambda k, n: env.reset_to(k, 0, 1, 1.0, 2.0, 0.0, 0.0, n)))
  return env, reset_to, jax.jit(jax.vmap(env.step))


def test_env_drives_the_wheels_with_the_delayed_lagged_command(faulty_env):
  env, reset_to, step = faulty_env
  s = reset_to(jax.random.split(jax.random.PRNGKey(7), N), jp.zeros(N))
  f = s.info["robot"]
  assert np.all(f.latency_steps == 2) and np.allclose(f.lag_s, TAU_S)
  assert f.pending.shape == (N, 2, 2) and f.mount.shape == (N, 3)
  command = jp.tile(jp.array([[0.4, 0.3]]), (N, 1))
  dt = env.cfg.env.control_dt
  for n in range(1, 6):
    s = step(s, command)
    # the state's v_prev, w_prev: the policy's command; the wheels: 2 steps late, lagged
    np.testing.assert_array_equal(s.obs["state"][:, :2], command)
    u = (1 - math.exp(-(n - 2) * dt / TAU_S)) if n > 2 else 0.0
    expected = np.stack(wheel_speeds(0.4 * u, 0.3 * u, env.robot))
    np.testing.assert_allclose(s.pipeline_state.ctrl, np.tile(expected, (N, 1)), atol=1e-5)
    # the yaw input: wrap(yaw - yaw_ref + drift), the drift walking
    q = s.pipeline_state.qpos[:, 3:7]
    yaw = jax.vmap(quat_yaw)(q) - s.info["yaw_ref"] + s.info["robot"].yaw_drift
    np.testing.assert_allclose(s.obs["state"][:, 2], wrap(yaw), atol=1e-6)
  drift = np.asarray(s.info["robot"].yaw_drift)
  assert np.all(drift != 0) and len(set(drift.tolist())) == N
  assert set(s.info) >= {"robot", "pose", "rng", "prev_action"}


def test_env_renders_from_the_mounted_camera(faulty_env):
  """Noise-free starts at one pose: the physics is the same, each episode's mount error
  its own image."""
  _, reset_to, _ = faulty_env
  s = reset_to(jax.random.split(jax.random.PRNGKey(8), N), jp.zeros(N))
  np.testing.assert_array_equal(s.pipeline_state.qpos, np.tile(s.pipeline_state.qpos[:1], (N, 1)))
  depth = np.asarray(s.obs["depth"])
  mount = np.asarray(s.info["robot"].mount)
  assert len({tuple(m) for m in mount.tolist()}) == N
  for i in range(1, N):
    assert np.mean(np.abs(depth[i] - depth[0]) > 0.02) > 0.05, i


# ------------------------------------------------------------------ all at zero: as before
def _without_faults(env_module, monkeypatch):
  """The env as it was before the faults and the sensor: stand-ins that pass everything
  through, and `depth.add_noise` for the image."""
  stand_in = types.SimpleNamespace(
      draw=lambda robot, key: None, step=lambda cfg, faults, command, key: (command, None),
      mounted_camera=lambda robot, d, cam_id, faults: d,
      imu_yaw=lambda robot, yaw, faults: yaw, info_entry=lambda faults: {},
      RobotFaults=robot_faults.RobotFaults)
  monkeypatch.setattr(env_module, "robot_faults", stand_in)
  monkeypatch.setattr(env_module, "sensor", types.SimpleNamespace(
      observe=lambda image, key, camera, sensor, k: depth_cam.add_noise(image, key, camera, k)))


def test_all_factors_at_zero_compute_what_the_env_computed_without_them(monkeypatch):
  """Defaults: no stage, no `info["robot"]`, and the env's programs (reset_to, reset,
  step) are the same JAX programs as with stand-ins that pass everything through (the
  env before the faults, `depth.add_noise` for the sensor): the same states,
  observations and rewards bit for bit. (Traced, not compiled.)"""
  import mjxvine.env as env_module
  cfg = load_config("experiments/smoke.yaml", TINY)
  assert not robot_faults.enabled(cfg.robot)
  assert robot_faults.draw(cfg.robot, jax.random.PRNGKey(0)) is None
  command = jp.array([0.3, 0.1])
  wheels, faults = robot_faults.step(cfg, None, command, jax.random.PRNGKey(0))
  assert wheels is command and faults is None
  env = env_module.VineyardEnv(cfg)
  key = jax.random.PRNGKey(0)

  def programs():
    start, state = jax.make_jaxpr(lambda k: env.reset_to(k, 0, 1, 1.0, 2.0, 0.1, 0.05),
                                  return_shape=True)(key)
    return [start, jax.make_jaxpr(env.reset)(key), jax.make_jaxpr(env.step)(state, command)], state

  real, state = programs()
  old_keys = {"pose", "rng", "episodes", "episode_steps", "yaw_ref", "noise_factor",
              "prev_action", "dist", "truncation", "outcome", "episode_return", "last_return",
              "last_outcome", "last_length"}
  assert set(state.info) == old_keys
  _without_faults(env_module, monkeypatch)
  before, _ = programs()
  for a, b in zip(real, before):
    assert str(a) == str(b)


# ------------------------------------------------------------------ robot files
def test_a_robot_file_sets_the_faults(tmp_path):
  doc = yaml.safe_load(open("examples/my_robot.yaml"))
  doc["faults"] = {"latency_steps": [0, 2], "velocity_lag_s": [0.05, 0.2],
                   "mount_pitch_deg": [0, 2.0], "mount_roll_deg": [0, 1.0],
                   "mount_height_m": [0, 0.02],
                   "yaw_walk_deg": 0.5}
  path = tmp_path / "faulty.yaml"
  path.write_text(yaml.safe_dump(doc))
  cfg = load_config(None, [f"robot.name={path}"])
  r = cfg.robot
  assert (r.latency_steps, r.velocity_lag_s) == ((0, 2), (0.05, 0.2))
  assert (r.mount_pitch_deg, r.mount_roll_deg, r.mount_height_m, r.yaw_walk_deg) == (
      (0, 2.0), (0, 1.0), (0, 0.02), 0.5)
  # --set keeps precedence; the file's other values stay
  cfg = load_config(None, [f"robot.name={path}", "robot.latency_steps=[1, 1]"])
  assert cfg.robot.latency_steps == (1, 1) and cfg.robot.mount_pitch_deg == (0, 2.0)
  # a robot file without faults leaves the config's
  cfg = load_config(None, ["robot.name=examples/my_robot.yaml", "robot.yaw_walk_deg=0.2"])
  assert cfg.robot.yaw_walk_deg == 0.2 and cfg.robot.latency_steps == (0, 0)


@pytest.mark.parametrize("faults, message", [
    ({"latency_steps": [0, 1.5]}, "faults.latency_steps = 1.5: expected a whole number of "
     "control steps"),
    ({"latency_steps": 2}, "faults.latency_steps = 2: expected a range [min, max]"),
    ({"latency_steps": [0, 9]}, "faults.latency_steps = 9: must be in [0, 5] steps"),
    ({"velocity_lag_s": [0.3, 0.1]}, "faults.velocity_lag_s = [0.3, 0.1]: the range must be "
     "increasing"),
    ({"mount_height_m": [0, 0.5]}, "faults.mount_height_m = 0.5: must be in [0, 0.3] m"),
    ({"mount_pitch_deg": ["up", 1]}, "faults.mount_pitch_deg = 'up': expected a number"),
    ({"yaw_walk": 1.0}, "unknown key faults.yaw_walk; did you mean yaw_walk_deg?"),
])
def test_bad_fault_values_are_one_line(tmp_path, faults, message):
  doc = yaml.safe_load(open("examples/my_robot.yaml"))
  doc["faults"] = faults
  path = tmp_path / "bad.yaml"
  path.write_text(yaml.safe_dump(doc))
  with pytest.raises(ConfigError) as e:
    load_config(None, [f"robot.name={path}"])
  text = str(e.value)
  assert text.startswith(f"robot.name: {path}: ") and message in text and "\n" not in text, text


def test_robot_file_bounds_are_the_configs():
  """The `faults` group checks the `robot.*` keys' own bounds (robot_files cannot import
  the config: it is read by it)."""
  import dataclasses
  from mjxvine.config import RobotConfig
  from mjxvine.robot_files import CONFIG_KEYS, SCHEMA
  meta = {f.name: f.metadata for f in dataclasses.fields(RobotConfig)}
  for key, (field, lo, hi, required) in SCHEMA["faults"].items():
    assert CONFIG_KEYS[field] == f"robot.{key}" and not required
    assert (lo, hi) == (meta[key]["lo"], meta[key]["hi"]), key
    assert type(lo) is type(meta[key]["lo"]), key
