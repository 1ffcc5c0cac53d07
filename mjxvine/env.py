"""The vineyard-row task as a pure-functional, jit-compiled brax `Env` (docs/design.md,
Observation and action; Reward and terminations).

One `VineyardEnv` holds a pool of worlds batched into one `mjx.Model` (per-world fields with
a leading axis, `in_axes`); every env carries the index of its world in its state and
reads that world's fields, so N envs under `jax.vmap` drive in N different vineyards.

Observation: {"depth": (H, W, 1) float32 noisy z-depth in metres, "state": (3,)
[v_prev m/s, w_prev rad/s, yaw rad]}. The yaw is relative to a reference (`env.yaw_reference`):
the heading at the episode start plus a random training offset ("start", as a robot zeroes
its IMU heading at the row entrance), or the world yaw ("world", the paper's input).
Action: [v, w] in physical units, v in [v_min, v_max] m/s (v_min 0 in the paper), w in
[-w_max, w_max] rad/s. Pose, lane and End of Row (EoR) live in `info` only.
The robot's faults (`robot_faults`: command latency, velocity lag, camera mount errors, IMU
yaw drift), where the `robot.*` keys turn them on, are drawn at every episode start (random
and `reset_to` starts alike) and kept in `info["robot"]`: the wheels get the lagged command
of `latency` steps ago, the state's v_prev, w_prev stay the policy's command.

`step` advances one env by one control step and does not reset it (brax's convention):
`done` marks the end of an episode, `info["truncation"]` is 1 where it ended by time-out or
a physics reset (learners bootstrap through those), and `metrics` holds the step's outcome
flags and its named reward terms ("reward/<term>" of `REWARD_WEIGHTS`, summing to
`reward`). `restart(state, new_start)` starts the next episode from the same start pose or
a new random one (random world, lane, point, direction, jitter); `training_env(cfg)`: the
trainer's auto-resetting envs (`wrappers.AutoResetBatch`), a new pose every 10 episodes.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import jax
import jax.numpy as jp
import mujoco
import numpy as np
from brax.envs.base import Env, State
from mujoco import mjx

from mjxvine import depth as depth_cam, robot_faults, sensor
from mjxvine.angles import quat_yaw as _yaw, wrap as _wrap
from mjxvine.config import PHYSICS_DT_S, Config, action_box, depth_input_scale
from mjxvine.deploy import MIRROR_ACTION_SIGN, MIRROR_STATE_SIGN
from mjxvine.driver import pure_pursuit  # noqa: F401 (the reference driver, read from here)
# Outcome codes and lane geometry are also read from here (starts, evaluate, tests).
from mjxvine.episodes import (COLLISION, LEFT_LANE, OUTCOMES, PHYSICS, REVERSED,  # noqa: F401
                              REWARD_PREFIX, RUNNING, SUCCESS, TIMEOUT)
from mjxvine.lanes import MIRROR_LANE_SIGN, LaneTable, lane_frame, point_ahead  # noqa: F401
from mjxvine.nearby import NearbyIndex
from mjxvine.wrappers import AutoResetBatch
from mjxvine.worlds.layout import CENTERLINE_STEP_M
from mjxvine.worlds.build import PARKED_Z
from mjxvine.worlds import (Vineyard, batch_models, build_models, camera_limits, pool_worlds,
                            plant_geom_ids, plant_slots_for, take_world, wheel_speeds)

# The paper's reward weights, yaw limit (reversed beyond it) and success radius around the EoR
REWARD_WEIGHTS = dict(heading=0.6, progress=35.0, success=1000.0, collision=-500.0, reverse=-500.0)
YAW_LIMIT_DEG, SUCCESS_RADIUS_M = 85.0, 0.4  # (docs/design.md, Reward and terminations)
MAX_QVEL = 50.0  # beyond this (m/s or rad/s) the physics has exploded
START_ALONG = (0.0, 0.6)  # training starts: this fraction of the row from the lane's start
YAW_REFERENCE_JITTER_DEG = 20.0  # yaw_reference=start: +- this on the reference in training
COLLISION_MARGIN_M = 0.05  # a plant nearer than this to the robot's footprint is a collision
PARKED_BELOW_M = PARKED_Z / 2  # a plant below this height is an unused slot


class PoolWorld(NamedTuple):
  """A pool world as the step reads it: its index and physics model (`physics_model`)."""
  index: jax.Array
  model: mjx.Model


class VineyardEnv(Env):
  """Batched vineyard-navigation environment over a pool of worlds (brax `Env`)."""

  def __init__(self, cfg: Config, worlds: Sequence[Vineyard] | None = None, *,
               noise_factor: float | None = None):
    """`worlds` defaults to the config's pool of train worlds (`worlds.pool_worlds`:
    generated ones, seeds 0 ..., and the blocks of `world.train_files`)."""
    # the blocks of world.train_files close the default pool: `world.train_files_share` of
    # the random starts are theirs
    self.file_worlds = 0
    if worlds is None:
      worlds = pool_worlds(cfg)
      self.file_worlds = len(worlds) - cfg.world.pool_size
    self.cfg = cfg
    self.worlds = list(worlds)
    self.robot = cfg.robot.spec
    self.noise_factor = depth_cam.NOISE_FACTOR if noise_factor is None else noise_factor
    models = build_models(self.worlds, cfg)
    self.mj_model = models[0]
    self.model, self.model_axes = batch_models(models)
    # more primitives per view than classic plants' in the other seasons
    self.camera = depth_cam.DepthCamera.create(self.mj_model, cfg.camera,
                                               **camera_limits(self.worlds, cfg.camera))
    self.lanes = LaneTable(self.worlds, cfg.env.max_steps)
    # metres of x between centerline samples (at most CENTERLINE_STEP_M in file worlds)
    self.sample_m = (self.worlds[0].length_m / (self.lanes.centerline.shape[2] - 1)
                     if self.lanes.uniform else CENTERLINE_STEP_M)
    self._trunk_ids, _ = plant_geom_ids(self.mj_model, plant_slots_for(self.worlds))
    self.substeps = int(round(cfg.env.control_dt / PHYSICS_DT_S))
    low, high = action_box(cfg)
    self.action_low, self.action_high = jp.array(low, jp.float32), jp.array(high, jp.float32)
    # The physics steps the models without plants (no plant takes part in a contact: MJX
    # would pose every plant geom at every substep); the camera and the collision check
    # read the plants posed once, those near the robot (`nearby`). Same results.
    physics = build_models(self.worlds, cfg, plants=False)
    self._physics_model, self._physics_axes = batch_models(physics, like=self.model_axes)
    data = mujoco.MjData(physics[0])
    mujoco.mj_forward(physics[0], data)
    # on this process's device (see `worlds.batch.batch_models`)
    self._data0 = mjx.put_data(physics[0], data, device=jax.local_devices()[0])
    self._hfield = (int(physics[0].hfield_nrow[0]), int(physics[0].hfield_ncol[0]))
    self._terrain_geom = mujoco.mj_name2id(physics[0], mujoco.mjtObj.mjOBJ_GEOM, "terrain")
    if self.camera.terrain_geom not in (-1, self._terrain_geom):
      raise ValueError("the terrain must come before the plants in the model")
    self._plants, self._near_plants = self._plant_prims(physics[0])
    self._trunks, self._near_trunks = self._trunk_table()
    # (Wd,) m, the static terrain's, computed as the step did (model constant, data argument)
    ref = jax.jit(lambda w, d: depth_cam.terrain_reference(self.camera, self.physics_model(w), d))
    self._terrain_ref = jp.stack([ref(w, self._data0) for w in range(len(self.worlds))])

  # ------------------------------------------------------------------ brax Env API
  @property
  def observation_size(self):
    c, lane = self.cfg.camera, {"lane": (3,)} if self.cfg.sac.privileged_critics else {}
    return {"depth": (c.height, c.width, 1), "state": (3,), **lane}

  @property
  def action_size(self) -> int:
    return 2

  @property
  def backend(self) -> str:
    return "mjx"

  # ------------------------------------------------------------------ mirror symmetry
  # Left-right symmetry: mirrored about the robot's forward axis, a vineyard is another
  # (random plants, terrain and noise; the camera on the robot's centre plane, its columns
  # symmetric; reward and start jitter even in lateral offset and yaw), so (mirror_obs(o),
  # mirror_action(a), r, mirror_obs(o')) is a valid transition (`sac.mirror_augment`).

  @staticmethod
  def mirror_obs(obs: dict) -> dict:
    """The observation mirrored left-right (any leading batch dims): the depth image's
    columns reversed, the previous turn rate and the yaw negated (and the lateral offset
    and heading error of obs["lane"], where present)."""
    mirrored = {"depth": jp.flip(obs["depth"], axis=-2),
                "state": obs["state"] * jp.asarray(MIRROR_STATE_SIGN, obs["state"].dtype)}
    if "lane" in obs:
      mirrored["lane"] = obs["lane"] * jp.asarray(MIRROR_LANE_SIGN, obs["lane"].dtype)
    return mirrored

  @staticmethod
  def mirror_action(action: jax.Array) -> jax.Array:
    """[v, w] mirrored left-right: [v, -w] (the turn-rate box is symmetric)."""
    return action * jp.asarray(MIRROR_ACTION_SIGN, action.dtype)

  def world_model(self, world: jax.Array) -> mjx.Model:
    """The mjx.Model of pool world `world`, plants included (a traced index is fine)."""
    return take_world(self.model, self.model_axes, world)

  def physics_model(self, world: jax.Array) -> mjx.Model:
    """`world_model` without the plants (`worlds.build_spec`): what simulates pool world
    `world`; `pipeline_state` is its mjx.Data."""
    return take_world(self._physics_model, self._physics_axes, world)

  # ------------------------------------------------------------------ plants near the robot
  def _plant_prims(self, physics: mujoco.MjModel) -> tuple[depth_cam.Prims, NearbyIndex]:
    """The camera's primitives of every pool world posed once ((Wd, P) arrays: they
    stand on the world body) and their index by AABB centre, for queries within
    `camera.reach` of the camera."""
    cam = self.camera
    if np.any(self.mj_model.geom_bodyid[cam.prim_geom] != 0):
      raise ValueError("the depth camera sees a moving geom: only static ones are posed once")
    pose = lambda m: depth_cam.camera_prims(cam, m, mjx.kinematics(m, mjx.make_data(m)))
    prims = jax.jit(jax.vmap(pose, in_axes=(self.model_axes,), axis_size=len(self.worlds)))(
        self.model)
    centre, ext = np.asarray(prims.centre), np.asarray(prims.ext)
    reach = cam.reach(float(np.linalg.norm(ext, axis=-1).max(initial=0.0)))
    # The camera stays above the terrain (`depth`), so over the heightfield geom's base:
    # a primitive more than `reach` below it (a parked plant slot) is never in view.
    floor = physics.geom_pos[self._terrain_geom, 2] if cam.terrain_geom >= 0 else -np.inf
    return prims, NearbyIndex.build(centre[..., :2], centre[..., 2] > floor - reach, reach)

  def _trunk_table(self) -> tuple[jax.Array, NearbyIndex]:
    """Trunks of every pool world, (Wd, S, 4) [x, y, z, radius] m, and their index by
    centre, for queries within collision reach of the robot (`plant_clearance`)."""
    ids = self._trunk_ids
    table = np.stack([np.concatenate([np.asarray(m.geom_pos)[ids],
                                      np.asarray(m.geom_size)[ids, :1]], -1)
                      for m in map(self.world_model, range(len(self.worlds)))])
    corner = np.hypot(self.robot.length / 2, self.robot.width / 2)
    reach = corner + float(table[..., 3].max(initial=0.0)) + COLLISION_MARGIN_M
    keep = table[..., 2] > PARKED_BELOW_M
    return jp.asarray(table), NearbyIndex.build(table[..., :2], keep, reach)

  def reset(self, rng: jax.Array, direction: float | None = None,
            along: tuple[float, float] | None = None) -> State:
    """A fresh env at a random start pose of a random pool world; `direction` (+1
    forward, -1 reverse) forces the travel direction instead of either at random,
    `along` (fractions of the row length) the range of the start point instead of
    `START_ALONG`."""
    k_pose, k_obs, k_next = jax.random.split(rng, 3)
    pose = self.sample_pose(k_pose, direction, along)
    return self._start(pose, k_obs, k_next, episodes=jp.int32(0))

  def reset_to(self, rng: jax.Array, world, lane, direction, along=0.0, lateral=0.0,
               yaw=0.0, noise_factor=None) -> State:
    """An env at a given start: lane index (0-based), direction (+1 forward, -1 reverse),
    `along` (m from the lane's start in the travel direction), lateral offset (m) and yaw
    offset (rad). Used by the evaluation protocol: the yaw reference is the start heading,
    without the training jitter. `noise_factor` (may be traced): the episode's depth noise
    factor instead of the env's. The robot's faults are drawn from the config's ranges (a
    range [2, 2] fixes one)."""
    k_obs, k_next = jax.random.split(rng)
    pose = self._pose(jp.int32(world), jp.int32(lane), jp.float32(direction),
                      jp.float32(along), jp.float32(lateral), jp.float32(yaw))
    return self._start(pose, k_obs, k_next, episodes=jp.int32(0), ref_jitter=False,
                       noise_factor=noise_factor)

  def restart(self, state: State, new_start: jax.Array) -> State:
    """The episode after `state`'s: from its start pose, or from a new random one where
    `new_start`; keys from `state.info["rng"]` (see `wrappers.AutoResetBatch`)."""
    info = state.info
    k_pose, k_obs, k_next = jax.random.split(info["rng"], 3)
    pose = jax.tree.map(lambda a, b: jp.where(new_start, a, b), self.sample_pose(k_pose),
                        info["pose"])
    return self._start(pose, k_obs, k_next, info["episodes"])

  # ------------------------------------------------------------------ start poses
  def sample_pose(self, key: jax.Array, direction: float | None = None,
                  along: tuple[float, float] | None = None) -> dict:
    """A random start: pool world, lane, direction (either at random unless given: +1
    forward, -1 reverse), point along the lane (uniform over the fractions `along` of the
    row length from the lane's start, `START_ALONG` unless given), jitter."""
    kw, kl, kd, ka, kx, ky = jax.random.split(key, 6)
    env = self.cfg.env
    if self.file_worlds:  # a file block with probability train_files_share
      generated = len(self.worlds) - self.file_worlds
      k_file, k_gen, k_which = jax.random.split(kw, 3)
      world = jp.where(jax.random.bernoulli(k_which, self.cfg.world.train_files_share),
                       jax.random.randint(k_file, (), generated, len(self.worlds)),
                       jax.random.randint(k_gen, (), 0, generated))
    else:
      world = jax.random.randint(kw, (), 0, len(self.worlds))
    lane = jax.random.randint(kl, (), 0, self.lanes.count[world])
    if direction is None:
      direction = jp.where(jax.random.bernoulli(kd, 0.5), jp.float32(1), jp.float32(-1))
    else:
      direction = jp.float32(direction)
    length = self.lanes.lane(world, lane)[2]
    lo, hi = START_ALONG if along is None else along
    along = jax.random.uniform(ka, (), minval=lo * length, maxval=hi * length)
    lateral = jax.random.uniform(kx, (), minval=-1.0, maxval=1.0) * env.start_lateral_jitter_m
    yaw = jax.random.uniform(ky, (), minval=-1.0, maxval=1.0) * jp.deg2rad(
        env.start_yaw_jitter_deg)
    return self._pose(world, lane, direction, along, lateral, yaw)

  def _pose(self, world, lane, direction, along, lateral, yaw) -> dict:
    line, k, length, _ = self.lanes.lane(world, lane)
    step = length / (k - 1)
    idx = jp.clip(jp.round(along / step).astype(jp.int32), 0, k - 1)
    idx = jp.where(direction > 0, idx, k - 1 - idx)
    i, t, _, _ = lane_frame(line, line[idx], direction, k)
    normal = jp.array([-t[1], t[0]])
    xy = line[idx] + lateral * normal
    heading = jp.arctan2(t[1], t[0]) + yaw
    eor = jp.where(direction > 0, line[k - 1], line[0])
    return dict(world=world, lane=lane, direction=direction, xy=xy, yaw=_wrap(heading), eor=eor)

  def physics(self, m: mjx.Model, d: mjx.Data, action: jax.Array) -> mjx.Data:
    """One control step of the physics alone: the wheel speeds of `action` [v, w] (in the
    box), then `substeps` (control_dt / `PHYSICS_DT_S`) `mjx.step`s of `m`, a
    `physics_model`."""
    d = d.replace(ctrl=jp.stack(wheel_speeds(action[0], action[1], self.robot)))
    return jax.lax.fori_loop(0, self.substeps, lambda _, x: mjx.step(m, x), d)

  def terrain_height(self, m: mjx.Model, xy: jax.Array) -> jax.Array:
    """Height (m) of the heightfield of model `m` at xy (bilinear)."""
    nrow, ncol = self._hfield
    size = m.hfield_size[0]
    pos = m.geom_pos[self._terrain_geom]
    data = m.hfield_data.reshape(nrow, ncol)
    u = jp.clip((xy[0] - pos[0] + size[0]) / (2 * size[0]) * (ncol - 1), 0, ncol - 1.001)
    v = jp.clip((xy[1] - pos[1] + size[1]) / (2 * size[1]) * (nrow - 1), 0, nrow - 1.001)
    j, i = jp.floor(u).astype(jp.int32), jp.floor(v).astype(jp.int32)
    fu, fv = u - j, v - i
    h = (data[i, j] * (1 - fu) * (1 - fv) + data[i, j + 1] * fu * (1 - fv) +
         data[i + 1, j] * (1 - fu) * fv + data[i + 1, j + 1] * fu * fv)
    return pos[2] + h * size[2]

  def _pose_data(self, pose: dict) -> tuple[PoolWorld, mjx.Data]:
    """The pose's world and data, robot at rest: kinematics only (`mjx.step` does the rest)."""
    w = PoolWorld(pose["world"], self.physics_model(pose["world"]))
    z = self.terrain_height(w.model, pose["xy"]) + self.robot.wheel_radius + 0.01
    qpos = self._data0.qpos.at[:3].set(jp.array([pose["xy"][0], pose["xy"][1], z]))
    qpos = qpos.at[3:7].set(jp.array([jp.cos(pose["yaw"] / 2), 0, 0, jp.sin(pose["yaw"] / 2)]))
    qpos = qpos.at[7:].set(0.0)
    d = self._data0.replace(qpos=qpos, qvel=jp.zeros_like(self._data0.qvel),
                            ctrl=jp.zeros_like(self._data0.ctrl))
    return w, mjx.camlight(w.model, mjx.kinematics(w.model, d))

  def _yaw_reference(self, pose: dict, key: jax.Array, jitter: bool) -> jax.Array:
    """World yaw (rad) that the state's yaw is measured from, for an episode from `pose`."""
    env = self.cfg.env
    if env.yaw_reference == "world":
      return jp.float32(0.0)
    if not jitter:
      return pose["yaw"]
    half = np.deg2rad(YAW_REFERENCE_JITTER_DEG)
    return pose["yaw"] + jax.random.uniform(key, (), minval=-half, maxval=half)

  def _start(self, pose: dict, k_obs, k_next, episodes, ref_jitter: bool = True,
             noise_factor=None) -> State:
    w, d = self._pose_data(pose)
    prev_action = jp.zeros(2, jp.float32)
    k_obs, k_ref = jax.random.split(k_obs)
    yaw_ref = self._yaw_reference(pose, k_ref, ref_jitter)
    noise = (self._noise_factor(jax.random.fold_in(k_ref, 1), ref_jitter)
             if noise_factor is None else jp.float32(noise_factor))
    faults = robot_faults.draw(self.cfg.robot, k_ref)
    obs = self._observe(w, d, prev_action, k_obs, yaw_ref, noise, faults, pose)
    info = dict(
        pose=pose, rng=k_next, episodes=episodes, episode_steps=jp.int32(0), yaw_ref=yaw_ref,
        noise_factor=noise, **robot_faults.info_entry(faults),
        prev_action=prev_action, dist=jp.linalg.norm(d.qpos[:2] - pose["eor"]),
        truncation=jp.float32(0), outcome=jp.int32(RUNNING), episode_return=jp.float32(0),
        last_return=jp.float32(0), last_outcome=jp.int32(RUNNING), last_length=jp.int32(0))
    metrics = {name: jp.float32(0) for name in OUTCOMES[1:]}
    metrics.update({REWARD_PREFIX + k: jp.float32(0) for k in REWARD_WEIGHTS})
    return State(pipeline_state=d, obs=obs, reward=jp.float32(0), done=jp.float32(0),
                 metrics=metrics, info=info)

  # ------------------------------------------------------------------ dynamics
  def _noise_factor(self, key: jax.Array, training: bool) -> jax.Array:
    """The depth noise factor k of an episode: drawn from `env.train_noise_factor` (as
    `env.train_noise_draw` says) for training starts when that range is set, else the
    env's own."""
    lo, hi = self.cfg.env.train_noise_factor
    if not training or hi <= 0:
      return jp.float32(self.noise_factor)
    if self.cfg.env.train_noise_draw == "log_uniform":
      return jp.exp(jax.random.uniform(key, (), minval=np.log(lo), maxval=np.log(hi)))
    return jax.random.uniform(key, (), minval=lo, maxval=hi)

  def _observe(self, w: PoolWorld, d, prev_action, key, yaw_ref, noise_factor,
               faults: robot_faults.RobotFaults | None = None, pose: dict | None = None) -> dict:
    cam = robot_faults.mounted_camera(self.cfg.robot, d, self.camera.cam_id, faults)
    ids = self._near_plants.near(w.index, cam.cam_xpos[self.camera.cam_id, :2])
    image = depth_cam.render_depth(self.camera, w.model, cam, self._plants.take(ids, w.index),
                                   self._terrain_ref[w.index])
    noisy = sensor.observe(image, key, self.cfg.camera, self.cfg.sensor, noise_factor)
    yaw = _wrap(robot_faults.imu_yaw(self.cfg.robot, _yaw(d.qpos[3:7]) - yaw_ref, faults))
    obs = {"depth": noisy[..., None], "state": jp.array([prev_action[0], prev_action[1], yaw])}
    if self.cfg.sac.privileged_critics:  # what only the critics read
      obs["lane"] = self.lanes.lane_state(pose, d.qpos[:2], _yaw(d.qpos[3:7]))
    return obs

  def plant_clearance(self, world: jax.Array, xy: jax.Array, yaw: jax.Array) -> jax.Array:
    """Smallest distance (m) from the robot footprint rectangle at (xy, yaw) to a plant trunk
    surface of pool world `world` (parked slots ignored), exact up to
    `COLLISION_MARGIN_M`: trunks farther away are left out (inf where none is near)."""
    ids = self._near_trunks.near(world, xy)
    trunk = self._trunks[world, jp.minimum(ids, self._near_trunks.count - 1)]
    centre, radius = trunk[:, :3], trunk[:, 3]
    c, s = jp.cos(yaw), jp.sin(yaw)
    rel = centre[:, :2] - xy
    local = jp.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]], -1)
    half = jp.array([self.robot.length / 2, self.robot.width / 2])
    outside = jp.maximum(jp.abs(local) - half, 0.0)
    dist = jp.linalg.norm(outside, axis=-1) - radius
    live = (ids < self._near_trunks.count) & (centre[:, 2] > PARKED_BELOW_M)
    return jp.min(jp.where(live, dist, jp.inf))

  def step(self, state: State, action: jax.Array) -> State:
    """Physics, reward and termination of one 0.1 s control step of one env, no reset
    (the observation is rendered after the physics)."""
    env, info, pose = self.cfg.env, state.info, state.info["pose"]
    action = jp.clip(action, self.action_low, self.action_high)
    w = PoolWorld(pose["world"], self.physics_model(pose["world"]))
    # the wheels get the command of latency steps ago, lagged; prev_action stays `action`
    wheels, faults = robot_faults.step(self.cfg, info.get("robot"), action, info["rng"])
    d = self.physics(w.model, state.pipeline_state, wheels)

    finite = jp.all(jp.isfinite(d.qpos)) & jp.all(jp.isfinite(d.qvel))
    exploded = ~finite | (jp.max(jp.abs(d.qvel[:6])) > MAX_QVEL)
    d = jax.tree.map(lambda new, old: jp.where(exploded, old, new), d, state.pipeline_state)

    xy, yaw = d.qpos[:2], _yaw(d.qpos[3:7])
    line, k, _, width = self.lanes.lane(pose["world"], pose["lane"])
    _, tangent, lateral, _ = lane_frame(line, xy, pose["direction"], k)
    dist = jp.linalg.norm(xy - pose["eor"])
    to_eor = pose["eor"] - xy
    phi = _wrap(jp.arctan2(to_eor[1], to_eor[0]) - yaw)
    heading_err = _wrap(yaw - jp.arctan2(tangent[1], tangent[0]))
    half_lane = width / 2
    # Past the end line: beyond the EoR along the lane's end tangent, inside the lane.
    end_t = jp.where(pose["direction"] > 0, line[k - 1] - line[k - 2], line[0] - line[1])
    crossed = (xy - pose["eor"]) @ end_t > 0

    if env.past_end_m > 0:  # on into the headland; sideways there is no lane to leave
      ahead = (xy - pose["eor"]) @ end_t / jp.linalg.norm(end_t)
      success = ahead > env.past_end_m
      lateral = jp.where(crossed, 0.0, lateral)
    else:
      success = (dist < SUCCESS_RADIUS_M) | (crossed & (jp.abs(lateral) < half_lane))
    collision = self.plant_clearance(pose["world"], xy, yaw) < COLLISION_MARGIN_M
    left_lane = jp.abs(lateral) > half_lane
    reversed_ = jp.abs(heading_err) > jp.deg2rad(YAW_LIMIT_DEG)
    steps = info["episode_steps"] + 1
    timeout = steps >= self.lanes.steps_limit(pose["world"], pose["lane"])
    outcome = jp.select(
        [exploded, success, collision, left_lane, reversed_, timeout],
        [PHYSICS, SUCCESS, COLLISION, LEFT_LANE, REVERSED, TIMEOUT], RUNNING).astype(jp.int32)
    r_heading = 1.0 - 2.0 * jp.sqrt(jp.abs(phi / jp.pi))
    if env.heading_reward == "speed_weighted":
      forward_speed = d.qvel[:2] @ jp.array([jp.cos(yaw), jp.sin(yaw)])
      r_heading = r_heading * jp.clip(forward_speed / env.v_max, 0.0, 1.0)
    # The named terms (a physics reset earns nothing); the reward is their sum.
    terms = {
        "heading": REWARD_WEIGHTS["heading"] * r_heading,
        "progress": REWARD_WEIGHTS["progress"] * (info["dist"] - dist),
        "success": jp.where(outcome == SUCCESS, REWARD_WEIGHTS["success"], 0.0),
        "collision": jp.where((outcome == COLLISION) | (outcome == LEFT_LANE),
                              REWARD_WEIGHTS["collision"], 0.0),
        "reverse": jp.where(outcome == REVERSED, REWARD_WEIGHTS["reverse"], 0.0)}
    terms = {k: jp.where(exploded, 0.0, v).astype(jp.float32) for k, v in terms.items()}
    reward = sum(terms.values())
    done = outcome != RUNNING
    truncation = (outcome == TIMEOUT) | (outcome == PHYSICS)

    k_obs, k_next = jax.random.split(info["rng"])
    obs = self._observe(w, d, action, k_obs, info["yaw_ref"], info["noise_factor"], faults, pose)
    ret = info["episode_return"] + reward
    new_info = dict(info, rng=k_next, episode_steps=steps, prev_action=action, dist=dist,
                    **robot_faults.info_entry(faults),
                    truncation=truncation.astype(jp.float32), outcome=outcome,
                    episode_return=ret,
                    last_return=jp.where(done, ret, info["last_return"]),
                    last_outcome=jp.where(done, outcome, info["last_outcome"]),
                    last_length=jp.where(done, steps, info["last_length"]))
    metrics = {name: (outcome == code).astype(jp.float32)
               for code, name in enumerate(OUTCOMES) if code != RUNNING}
    metrics.update({REWARD_PREFIX + k: v for k, v in terms.items()})
    return state.replace(pipeline_state=d, obs=obs, reward=reward.astype(jp.float32),
                         done=done.astype(jp.float32), metrics=metrics, info=new_info)


def training_env(cfg: Config, worlds: Sequence[Vineyard] | None = None,
                 pose_reset_every: int = 10) -> AutoResetBatch:
  """The batch of auto-resetting vineyard envs the trainer uses (`episodes.TrainEnv`): a new
  start pose every `pose_reset_every` episodes (the paper's 10), the same one in between."""
  return AutoResetBatch(VineyardEnv(cfg, worlds), pose_reset_every)


# ---------------------------------------------------------------------- vector observations
class VectorObsEnv(Env):
  """The vineyard task with one flat observation vector, for learners that take vectors
  only (brax's own SAC): the noisy depth image average-pooled to `pool` (h, w) cells and
  scaled to [0, 1] of the camera's range, then [v_prev, w_prev, yaw]. Actions are in
  [-1, 1]^2, mapped affinely onto [0, v_max] x [-w_max, w_max]. The vineyard env does not
  auto-reset: brax's training wrappers (or `wrappers.brax_env`) do. `metrics["success"]`
  is 1 at a successful step, so brax's evaluator reports `eval/episode_success`."""

  def __init__(self, cfg, pool: tuple[int, int] = (8, 8)):
    cam = cfg.camera
    if cam.height % pool[0] or cam.width % pool[1]:
      raise ValueError(f"camera {cam.height}x{cam.width} is not a multiple of pool {pool}")
    self.cfg = cfg
    self.pool = pool
    self.inner = VineyardEnv(cfg)

  def _flat(self, obs: dict) -> jax.Array:
    h, w = self.pool
    d = obs["depth"][..., 0]
    d = d.reshape(h, d.shape[0] // h, w, d.shape[1] // w).mean(axis=(1, 3))
    return jp.concatenate([d.reshape(-1) * depth_input_scale(self.cfg), obs["state"]])

  def reset(self, rng: jax.Array) -> State:
    state = self.inner.reset(rng)
    return state.replace(obs=self._flat(state.obs))

  def step(self, state: State, action: jax.Array) -> State:
    low, high = self.inner.action_low, self.inner.action_high
    physical = low + (jp.clip(action, -1.0, 1.0) + 1.0) * 0.5 * (high - low)
    new = self.inner.step(state, physical)
    # keep metrics that wrappers added (brax's EpisodeWrapper tracks "reward")
    return new.replace(obs=self._flat(new.obs), metrics={**state.metrics, **new.metrics})

  @property
  def observation_size(self) -> int:
    return self.pool[0] * self.pool[1] + 3

  @property
  def action_size(self) -> int:
    return self.inner.action_size

  @property
  def backend(self) -> str:
    return self.inner.backend
