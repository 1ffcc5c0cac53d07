"""The batched vineyard environment: observation, reward, terminations, resets, NaN guard.

One small env (4 envs, 16x16 depth, 20-step episodes) and its jitted functions are
compiled once for the module."""

import jax
import jax.numpy as jp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from mjxvine.config import load_config
from mjxvine.env import (COLLISION, LEFT_LANE, REVERSED, SUCCESS, TIMEOUT, _wrap,
                         training_env)
from mjxvine.worlds.build import build_models

N = 4


@pytest.fixture(scope="module")
def env():
  cfg = load_config("experiments/smoke.yaml", [
      "camera.width=16", "camera.height=12", "env.max_steps=20", "world.pool_size=2"])
  return training_env(cfg, pose_reset_every=3)


@pytest.fixture(scope="module")
def fns(env):
  reset_to = jax.jit(jax.vmap(env.reset_to, in_axes=(0, 0, 0, 0, 0, 0, 0)))
  step = jax.jit(env.step_batch)
  return reset_to, step


def _start(fns, world=(0, 1, 0, 1), lane=(0, 1, 2, 0), direction=(1, -1, 1, -1),
           along=(2.0,) * N, lateral=(0.0,) * N, yaw=(0.0,) * N, seed=0):
  reset_to, _ = fns
  a = lambda x, t=jp.float32: jp.asarray(x, t)
  return reset_to(jax.random.split(jax.random.PRNGKey(seed), N), a(world, jp.int32),
                  a(lane, jp.int32), a(direction), a(along), a(lateral), a(yaw))


def test_observation_is_depth_and_state_only(env, fns):
  s = _start(fns)
  assert set(s.obs) == {"depth", "state"}
  assert s.obs["depth"].shape == (N, 12, 16, 1) and s.obs["depth"].dtype == jp.float32
  assert s.obs["state"].shape == (N, 3)
  assert float(s.obs["depth"].min()) >= 0 and float(s.obs["depth"].max()) <= 5.0
  # state = [v_prev, w_prev, yaw]: zero action before the first step; the yaw is relative
  # to the heading at the start (reset_to: no training jitter), so 0 in either direction
  np.testing.assert_allclose(s.obs["state"][:, :2], 0.0)
  np.testing.assert_allclose(s.obs["state"][:, 2], 0.0, atol=1e-3)
  # forward starts head +x, reverse ones -x
  np.testing.assert_allclose(np.cos(s.info["pose"]["yaw"]), [1, -1, 1, -1], atol=0.02)
  # two envs in different worlds see different vineyards
  assert not np.allclose(env.world_model(0).geom_pos, env.world_model(1).geom_pos)


@pytest.mark.slow  # over 20 s on a 2-core CPU: the fast suite stays within 12 minutes
def test_reward_matches_the_paper(env, fns):
  _, step = fns
  s = _start(fns)
  action = jp.tile(jp.array([[0.5, 0.2]]), (N, 1))
  s2, _ = step(s, action)
  d2 = s2.pipeline_state
  xy = np.asarray(d2.qpos[:, :2])
  q = np.asarray(d2.qpos[:, 3:7])
  yaw = np.arctan2(2 * (q[:, 0] * q[:, 3] + q[:, 1] * q[:, 2]), 1 - 2 * (q[:, 2]**2 + q[:, 3]**2))
  eor = np.asarray(s.info["pose"]["eor"])
  d_prev = np.linalg.norm(np.asarray(s.pipeline_state.qpos[:, :2]) - eor, axis=1)
  d_now = np.linalg.norm(xy - eor, axis=1)
  phi = np.asarray(_wrap(np.arctan2(eor[:, 1] - xy[:, 1], eor[:, 0] - xy[:, 0]) - yaw))
  expected = 0.6 * (1 - 2 * np.sqrt(np.abs(phi / np.pi))) + 35 * (d_prev - d_now)
  np.testing.assert_allclose(s2.reward, expected, rtol=1e-4, atol=1e-4)
  # the named terms, logged by the trainer, sum to the reward
  terms = {k[len("reward/"):]: np.asarray(v) for k, v in s2.metrics.items()
           if k.startswith("reward/")}
  assert set(terms) == {"heading", "progress", "success", "collision", "reverse"}
  np.testing.assert_allclose(sum(terms.values()), s2.reward, rtol=1e-6, atol=1e-6)
  np.testing.assert_allclose(terms["progress"], 35 * (d_prev - d_now), rtol=1e-4, atol=1e-4)
  assert all(np.all(terms[k] == 0) for k in ("success", "collision", "reverse"))
  assert np.all(s2.done == 0)
  np.testing.assert_allclose(s2.obs["state"][:, :2], action)
  assert np.all(d_prev - d_now > 0.01)  # it drove towards the EoR (from rest)


@pytest.mark.slow  # compiles another env step (~45 s, 2 cores)
def test_privileged_critics_observe_the_lane_state_and_its_mirror():
  cfg = load_config("experiments/smoke.yaml", [
      "camera.width=16", "camera.height=12", "env.max_steps=20", "world.pool_size=2",
      "sac.privileged_critics=true"])
  env = training_env(cfg)
  assert env.observation_size["lane"] == (3,)
  reset_to = jax.jit(jax.vmap(env.reset_to, in_axes=(0, 0, 0, 0, 0, 0, 0)))
  lateral, yaw = np.array([0.1, -0.2, 0.0, 0.15]), np.array([0.05, 0.0, -0.1, 0.2])
  s = _start((reset_to, None), lateral=lateral, yaw=yaw)
  lane = np.asarray(s.obs["lane"])
  half = np.array([float(env.lanes.lane(w, l)[3]) / 2 for w, l in [(0, 0), (1, 1), (0, 2),
                                                                     (1, 0)]])
  np.testing.assert_allclose(lane[:, 0], lateral / half, atol=2e-3)
  np.testing.assert_allclose(lane[:, 1], yaw, atol=2e-3)
  np.testing.assert_allclose(lane[:, 2], np.asarray(s.info["dist"]) / 10.0, rtol=1e-5)
  _, final_obs = jax.jit(env.step_batch)(s, jp.asarray([[0.5, 0.3]] * N))
  assert final_obs["lane"].shape == (N, 3) and not np.allclose(final_obs["lane"], lane)
  mirrored = env.mirror_obs(s.obs)
  np.testing.assert_array_equal(mirrored["lane"], lane * np.array([-1, -1, 1], np.float32))
  np.testing.assert_array_equal(mirrored["state"][:, 2], -np.asarray(s.obs["state"][:, 2]))


@pytest.mark.slow  # compiles the env step (~45 s, 2 cores); the trainer's tests step it
def test_terminations(env, fns):
  _, step = fns
  half = float(env.lanes.width_m[0, 0]) / 2
  # env 0: yawed 90 deg -> reversed; env 1: beside the row -> left lane;
  # env 2: on a plant -> collision; env 3: next to its EoR -> success.
  trunk = np.asarray(env.world_model(0).geom_pos[env._trunk_ids[0]])
  line = np.asarray(env.lanes.centerline[0, 0])
  s = _start(fns, world=(0, 0, 0, 0), lane=(0, 0, 0, 0), direction=(1, 1, 1, 1),
             along=(2.0, 2.0, float(trunk[0]), env.worlds[0].length_m - 0.2),
             lateral=(0.0, half + 0.45, float(trunk[1] - np.interp(trunk[0], *line.T)), 0.0),
             yaw=(np.pi / 2, 0.0, 0.0, 0.0))
  s2, _ = step(s, jp.zeros((N, 2)))
  outcome = list(np.asarray(s2.info["last_outcome"]))
  assert outcome == [REVERSED, LEFT_LANE, COLLISION, SUCCESS]
  np.testing.assert_allclose(s2.reward[:3], [-500, -500, -500], atol=5)
  np.testing.assert_allclose(s2.metrics["reward/reverse"], [-500, 0, 0, 0])
  np.testing.assert_allclose(s2.metrics["reward/collision"], [0, -500, -500, 0])
  np.testing.assert_allclose(s2.metrics["reward/success"], [0, 0, 0, 1000])
  assert 990 < float(s2.reward[3]) < 1010
  assert np.all(s2.done == 1) and np.all(s2.info["truncation"] == 0)
  # the auto-reset started them again, from the same start pose
  assert np.all(s2.info["episode_steps"] == 0) and np.all(s2.info["episodes"] == 1)
  np.testing.assert_allclose(s2.pipeline_state.qpos[:, :2], s.pipeline_state.qpos[:, :2],
                             atol=1e-5)


@pytest.mark.slow  # compiles the env step (~45 s, 2 cores); the trainer's tests step it
def test_timeout_is_a_truncation_and_poses_change_every_k_episodes(env, fns):
  _, step = fns
  s = _start(fns, along=(3.0,) * N)
  starts, done_steps = [], []
  zero = jp.zeros((N, 2))
  for episode in range(4):
    dones = []
    for _ in range(20):
      s, _ = step(s, zero)
      dones.append(np.asarray(s.done))
    done_steps.append(np.sum(dones, axis=0))
    assert np.all(s.info["truncation"] == 1)
    assert np.all(s.info["last_outcome"] == TIMEOUT)
    starts.append(np.asarray(s.pipeline_state.qpos[:, :2]))
  assert all(np.all(d == 1) for d in done_steps)
  # pose_reset_every = 3: episodes 1, 2 restart at the same pose, episode 3 at a new one
  np.testing.assert_allclose(starts[0], starts[1], atol=1e-5)
  assert np.all(np.linalg.norm(starts[2] - starts[1], axis=1) > 1e-3)
  np.testing.assert_allclose(starts[2], starts[3], atol=1e-5)


def test_a_start_poses_the_robot_and_camera_as_mujoco_does(env, fns):
  """A reset computes the kinematics alone, not `mjx.forward`: the bodies and the camera
  stand where MuJoCo's own `mj_forward` puts them for the same qpos (the first image is
  rendered from them)."""
  s = _start(fns)
  models = build_models(env.worlds, env.cfg, plants=False)
  for i, world in enumerate(np.asarray(s.info["pose"]["world"])):
    model = models[world]
    data = mujoco.MjData(model)
    data.qpos[:] = np.asarray(s.pipeline_state.qpos[i])
    mujoco.mj_forward(model, data)
    for field in ("xpos", "xquat", "cam_xpos", "cam_xmat"):
      want = getattr(data, field)
      np.testing.assert_allclose(np.reshape(getattr(s.pipeline_state, field)[i], want.shape),
                                 want, atol=1e-5, err_msg=field)


@pytest.mark.slow  # compiles the env step (~45 s, 2 cores); the trainer's tests step it
def test_a_start_steps_as_one_after_mjx_forward(env, fns):
  """The physics after a reset is that of a reset through `mjx.forward`: `mjx.step`
  reads nothing of the start that kinematics alone leaves out (`mjx.forward`, compiled
  apart, moves the quaternion by a float32 ulp: hence the tolerances)."""
  _, step = fns
  s = _start(fns)
  forward = jax.jit(jax.vmap(lambda w, d: mjx.forward(env.physics_model(w), d)))
  full = s.replace(pipeline_state=forward(s.info["pose"]["world"], s.pipeline_state))
  action = jp.tile(jp.array([[0.4, 0.3]], jp.float32), (N, 1))
  for _ in range(3):
    s, full = step(s, action)[0], step(full, action)[0]
  np.testing.assert_allclose(np.asarray(s.pipeline_state.qpos),
                             np.asarray(full.pipeline_state.qpos), atol=1e-6)
  np.testing.assert_allclose(np.asarray(s.obs["depth"]), np.asarray(full.obs["depth"]),
                             atol=2e-4)


@pytest.mark.slow  # compiles the env step (~45 s, 2 cores); the trainer's tests step it
def test_nan_physics_resets_only_that_env(env, fns):
  _, step = fns
  s = _start(fns)
  bad = s.pipeline_state.replace(qvel=s.pipeline_state.qvel.at[1].set(jp.nan))
  s2, _ = step(s.replace(pipeline_state=bad), jp.full((N, 2), 0.3, jp.float32))
  assert np.all(np.isfinite(np.asarray(s2.pipeline_state.qpos)))
  assert np.isfinite(np.asarray(s2.reward)).all()
  assert list(np.asarray(s2.done)) == [0, 1, 0, 0]
  assert float(s2.metrics["physics"][1]) == 1 and float(s2.info["truncation"][1]) == 1
  assert float(jp.sum(s2.metrics["physics"])) == 1


@pytest.mark.slow  # over 20 s on a 2-core CPU: the fast suite stays within 12 minutes
def test_world_yaw_input_and_both_directions():
  """yaw_reference=world (the paper's input): the yaw input is the world yaw; random
  starts take both travel directions, reverse ones with a world yaw near +-pi."""
  cfg = load_config("experiments/smoke.yaml", [
      "camera.width=16", "camera.height=12", "world.pool_size=1", "env.yaw_reference=world"])
  env = training_env(cfg)
  s = jax.jit(lambda k: env.reset_batch(k, 16))(jax.random.PRNGKey(3))
  direction = np.asarray(s.info["pose"]["direction"])
  assert (direction > 0).any() and (direction < 0).any()
  world_yaw = np.asarray(s.info["pose"]["yaw"])
  observed = np.asarray(s.obs["state"][:, 2])
  np.testing.assert_allclose(np.cos(observed - world_yaw), 1.0, atol=1e-4)
  assert np.all(np.cos(world_yaw[direction < 0]) < -0.9)


def test_start_points_along_the_lane(env):
  """Random starts lie uniformly over the fractions `along` of the row length from the
  lane's start in the travel direction: `START_ALONG` by default, or the range given
  (the fresh-start evaluation's fixed [0, 0.6])."""
  from mjxvine.env import START_ALONG
  def fractions(env, along):
    e = env.env
    poses = jax.jit(jax.vmap(lambda k: e.sample_pose(k, None, along)))(
        jax.random.split(jax.random.PRNGKey(5), 256))
    line = np.asarray(e.lanes.centerline)[np.asarray(poses["world"]), np.asarray(poses["lane"])]
    k = line.shape[1]
    # the start point is a centerline sample shifted by the lateral jitter (< 0.3 m)
    idx = np.argmin(np.sum((line - np.asarray(poses["xy"])[:, None]) ** 2, -1), -1)
    forward = np.asarray(poses["direction"]) > 0
    return np.where(forward, idx, k - 1 - idx) / (k - 1), forward
  assert START_ALONG == (0.0, 0.6)
  for along in [None, (0.8, 0.95)]:
    lo, hi = (0.0, 0.6) if along is None else along
    frac, forward = fractions(env, along)
    slack = 0.02  # a centerline sample is 1/80 of the row; the lateral jitter shifts little
    assert np.all(frac >= lo - slack) and np.all(frac <= hi + slack), (along, frac.min(), frac.max())
    assert frac.max() - frac.min() > 0.8 * (hi - lo)  # spread over the range
    assert forward.any() and (~forward).any()


def test_training_noise_factor_draws():
  """env.train_noise_factor [lo, hi]: training episodes draw k uniformly or (train_noise_draw
  = log_uniform) log-uniformly from it, evaluation episodes keep the env's factor; a
  log-uniform draw needs lo > 0."""
  from types import SimpleNamespace
  from mjxvine.config import ConfigError
  from mjxvine.env import VineyardEnv
  keys = jax.random.split(jax.random.PRNGKey(6), 4000)
  for draw, share_high in [("uniform", 5 / 9.5), ("log_uniform", np.log(2) / np.log(20))]:
    cfg = load_config("experiments/smoke.yaml", [
        "env.train_noise_factor=[0.5, 10]", f"env.train_noise_draw={draw}"])
    fake = SimpleNamespace(cfg=cfg, noise_factor=1.5)
    k = np.asarray(jax.vmap(lambda key: VineyardEnv._noise_factor(fake, key, True))(keys))
    assert k.min() >= 0.5 - 1e-5 and k.max() <= 10 + 1e-5
    np.testing.assert_allclose(np.mean(k >= 5), share_high, atol=0.03)
    if draw == "log_uniform":  # as many draws in [1, 2] as in [5, 10]
      np.testing.assert_allclose(np.mean((k >= 1) & (k <= 2)), share_high, atol=0.03)
    assert float(VineyardEnv._noise_factor(fake, keys[0], False)) == 1.5
  with pytest.raises(ConfigError, match="env.train_noise_factor"):
    load_config("experiments/smoke.yaml", ["env.train_noise_factor=[0, 10]",
                                            "env.train_noise_draw=log_uniform"])


@pytest.mark.slow  # over 20 s on a 2-core CPU: the fast suite stays within 12 minutes
def test_yaw_relative_to_the_episode_start(env):
  """yaw_reference=start: the yaw input is the world yaw minus the heading at the episode
  start plus a training jitter within +-YAW_REFERENCE_JITTER_DEG (20, drawn anew at
  every episode start); the protocol's reset_to uses no jitter (the observation test:
  both directions start at 0)."""
  s = jax.jit(lambda k: env.reset_batch(k, 16))(jax.random.PRNGKey(4))
  directions = np.asarray(s.info["pose"]["direction"])
  assert (directions > 0).any() and (directions < 0).any()
  observed = np.asarray(s.obs["state"][:, 2])
  from mjxvine.env import YAW_REFERENCE_JITTER_DEG
  half = np.deg2rad(YAW_REFERENCE_JITTER_DEG)
  assert env.cfg.env.yaw_reference == "start" and half > 0
  assert np.all(np.abs(observed) <= half + 1e-5)
  assert np.std(observed) > half / 4  # jittered, not all zero
  world = np.asarray(s.info["pose"]["yaw"])
  ref = np.asarray(s.info["yaw_ref"])
  np.testing.assert_allclose(np.cos(observed - (world - ref)), 1.0, atol=1e-4)


@pytest.mark.slow  # over 20 s on a 2-core CPU: the fast suite stays within 12 minutes
def test_heading_to_the_eor_weighted_by_speed():
  """r_h's angle is measured to the end of the row (the paper's); speed_weighted scales
  r_h by forward speed / v_max; the reward is 0.6 r_h + 35 progress."""
  cfg = load_config("experiments/smoke.yaml", [
      "camera.width=16", "camera.height=12", "world.pool_size=1",
      "env.heading_reward=speed_weighted"])
  env = training_env(cfg)
  lateral = jp.array([0.0, 0.4, -0.4, 0.3])
  s = jax.jit(jax.vmap(env.reset_to))(
      jax.random.split(jax.random.PRNGKey(0), N), jp.zeros(N, jp.int32), jp.zeros(N, jp.int32),
      jp.array([1.0, 1.0, -1.0, -1.0]), jp.full(N, 2.0), lateral, jp.zeros(N))
  s2, _ = jax.jit(env.step_batch)(s, jp.tile(jp.array([[0.5, 0.0]]), (N, 1)))
  d = s2.pipeline_state
  xy, q = np.asarray(d.qpos[:, :2]), np.asarray(d.qpos[:, 3:7])
  yaw = np.arctan2(2 * (q[:, 0] * q[:, 3] + q[:, 1] * q[:, 2]), 1 - 2 * (q[:, 2]**2 + q[:, 3]**2))
  eor = np.asarray(s.info["pose"]["eor"])
  target = eor
  phi = np.asarray(_wrap(np.arctan2(target[:, 1] - xy[:, 1], target[:, 0] - xy[:, 0]) - yaw))
  v = np.sum(np.asarray(d.qvel[:, :2]) * np.stack([np.cos(yaw), np.sin(yaw)], 1), 1)
  r_h = (1 - 2 * np.sqrt(np.abs(phi / np.pi))) * np.clip(v / 0.5, 0, 1)
  progress = (np.linalg.norm(np.asarray(s.pipeline_state.qpos[:, :2]) - eor, axis=1)
              - np.linalg.norm(xy - eor, axis=1))
  np.testing.assert_allclose(s2.reward, 0.6 * r_h + 35 * progress, rtol=1e-4, atol=1e-4)
  assert np.all(v > 0.05), v


def test_mirror_image_of_a_vineyard_is_the_flipped_observation():
  """`mirror_obs` is what the camera sees in the mirrored vineyard (plants, terrain and
  pose reflected across y = 0): the depth columns reversed, the yaw negated. This is the
  symmetry that `sac.mirror_augment` rests on."""
  import dataclasses
  from mjxvine.env import VineyardEnv
  from mjxvine.worlds import generate_world
  cfg = load_config("experiments/smoke.yaml", [
      "camera.width=24", "camera.height=16", "world.pool_size=1"])
  world = generate_world("train", 0, cfg.world)
  x0, x1, y0, y1 = world.terrain_extent
  flip_y = np.array([1.0, -1.0])
  mirrored = dataclasses.replace(
      world, plant_xy=world.plant_xy * flip_y, plant_yaw=-world.plant_yaw,
      row_y0=-world.row_y0, terrain=world.terrain[::-1].copy(), terrain_extent=(x0, x1, -y1, -y0),
      lanes=tuple(dataclasses.replace(lane, centerline=lane.centerline * flip_y,
                                      eor_forward=lane.eor_forward * flip_y,
                                      eor_reverse=lane.eor_reverse * flip_y)
                  for lane in world.lanes))
  lane = world.lanes[1].centerline
  xy, yaw = lane[len(lane) // 3] + np.array([0.0, 0.15]), 0.3
  env = VineyardEnv(cfg, [world, mirrored], noise_factor=0.0)  # pool worlds 0 and 1

  @jax.jit
  def observe(world, sign):
    pose = dict(world=world, xy=jp.asarray(xy, jp.float32) * jp.array([1.0, sign]),
                yaw=jp.float32(yaw) * sign)
    m, d = env._pose_data(pose)
    return env._observe(m, d, jp.array([0.3, sign * 0.5]), jax.random.PRNGKey(0),
                        jp.float32(0.0), jp.float32(env.noise_factor))

  obs = [observe(0, 1.0), observe(1, -1.0)]
  mirrored_obs = VineyardEnv.mirror_obs(obs[0])
  np.testing.assert_allclose(mirrored_obs["state"], obs[1]["state"], atol=1e-6)
  depth, expected = np.asarray(obs[1]["depth"]), np.asarray(mirrored_obs["depth"])
  assert np.ptp(depth) > 0.5  # plants and ground in view, not an empty image
  # (the terrain is ray-marched: allow a few pixels off by a march step)
  assert np.mean(np.abs(depth - expected) < 0.02) > 0.97, np.abs(depth - expected).max()
  np.testing.assert_allclose(VineyardEnv.mirror_action(jp.array([0.4, 0.7])), [0.4, -0.7])
