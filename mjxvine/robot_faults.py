"""The robot's faults (docs/your-robot.md, The robot's faults) inside the jit-compiled env
step: what makes a real robot answer and see differently from the simulated one. Each
episode draws its own from the `robot.*` keys (`RobotConfig`); every function works on one
env (vmap it).

  latency       the wheels act on the command of k control steps ago (before the episode's
                first command: [0, 0], at rest); k uniform in the integers of
                `latency_steps` [lo, hi]
  velocity lag  the wheels' setpoint u follows the delayed command c as a first-order lag
                of time constant tau (uniform in `velocity_lag_s`), held over each
                control step of dt = env.control_dt s:
                u_n = c_n + (u_{n-1} - c_n) exp(-dt / tau), so a step of c reaches
                1 - exp(-n dt / tau) of it after n steps (tau 0: u = c)
  camera mount  before rendering, the camera's world pose turned by a pitch error about
                its own x axis (positive looks down, as `camera.pitch_deg` of a robot
                file), then a roll error about its optical axis (positive turns the
                image's x axis towards its y axis), and raised by a height error; each
                of a size uniform in its key's [lo, hi] (`mount_pitch_deg`,
                `mount_roll_deg`, `mount_height_m`) and a random sign: [0, x] is uniform
                in +-x, [x, x] is +-x exactly
  IMU yaw drift the state's yaw input is wrap(yaw - yaw_ref + drift); the drift starts at
                0 (the IMU is zeroed at the episode's start) and walks by
                N(0, (sigma sqrt(dt))^2) per control step, sigma = `yaw_walk_deg` in rad
                per sqrt(s)

Which stages exist is decided in Python from the config's values: a factor at zero has no
stage, and with every factor at zero (the default) there are no faults at all (`enabled`
False, `draw` and `step` give None, no `info["robot"]`), so the env's states, observations
and rewards are the fault-free env's bit for bit. Random keys are folded from the env's
keys (`jax.random.fold_in`), never split from them: the env's own key sequence is the same
whatever the faults.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jp
import numpy as np
from mujoco import mjx

from mjxvine.config import Config, RobotConfig

KEY_TAG = 2  # fold_in tag of the faults' keys (the env folds 1 for its noise factor)


class RobotFaults(NamedTuple):
  """One episode's faults and their running state: `info["robot"]` of a `VineyardEnv`
  state (with the env's leading axes under vmap). L = the config's largest latency."""
  latency_steps: jax.Array  # () int32: control steps from a command to the wheels
  lag_s: jax.Array  # () float32: the velocity lag's time constant tau, s (0: none)
  mount: jax.Array  # (3,) float32: camera pitch error rad, roll error rad, height error m
  pending: jax.Array  # (L, 2) float32: the last L commands [v m/s, w rad/s], newest first
  setpoint: jax.Array  # (2,) float32: the lag's output [v m/s, w rad/s], what the wheels get
  yaw_drift: jax.Array  # () float32: the IMU yaw's error, rad


def enabled(robot: RobotConfig) -> bool:
  """Whether any of the robot's faults is on (static: from the config's values)."""
  return (robot.latency_steps[1] > 0 or robot.velocity_lag_s[1] > 0 or _has_mount(robot)
          or robot.yaw_walk_deg > 0)


def _has_mount(robot: RobotConfig) -> bool:
  return (robot.mount_pitch_deg[1] > 0 or robot.mount_roll_deg[1] > 0
          or robot.mount_height_m[1] > 0)


def draw(robot: RobotConfig, key: jax.Array) -> RobotFaults | None:
  """An episode's faults, at rest (no command yet, no drift), drawn with a key folded from
  `key` (an episode start's key); None when none is on."""
  if not enabled(robot):
    return None
  k_latency, k_lag, k_mount = jax.random.split(jax.random.fold_in(key, KEY_TAG), 3)
  lo, hi = robot.latency_steps
  latency = jax.random.randint(k_latency, (), lo, hi + 1, jp.int32)
  lag_s = jax.random.uniform(k_lag, (), jp.float32, *robot.velocity_lag_s)
  (p_lo, p_hi), (r_lo, r_hi), (h_lo, h_hi) = (robot.mount_pitch_deg, robot.mount_roll_deg,
                                               robot.mount_height_m)
  least = jp.array([np.deg2rad(p_lo), np.deg2rad(r_lo), h_lo], jp.float32)
  most = jp.array([np.deg2rad(p_hi), np.deg2rad(r_hi), h_hi], jp.float32)
  k_size, k_sign = jax.random.split(k_mount)
  size = least + jax.random.uniform(k_size, (3,), jp.float32) * (most - least)
  mount = jp.where(jax.random.bernoulli(k_sign, 0.5, (3,)), size, -size)
  return RobotFaults(latency_steps=latency, lag_s=lag_s, mount=mount,
                     pending=jp.zeros((hi, 2), jp.float32), setpoint=jp.zeros(2, jp.float32),
                     yaw_drift=jp.float32(0.0))


def delayed(faults: RobotFaults, command: jax.Array) -> tuple[jax.Array, RobotFaults]:
  """(the command [v, w] of `latency_steps` steps ago, the faults with `command` queued)."""
  queue = jp.concatenate([command[None], faults.pending])  # (L + 1, 2), newest first
  return queue[faults.latency_steps], faults._replace(pending=queue[:-1])


def lagged(faults: RobotFaults, command: jax.Array, dt: float
           ) -> tuple[jax.Array, RobotFaults]:
  """(the setpoint after a control step of `dt` s towards `command` [v, w], the faults
  holding it): the first-order lag's exact step, u + (u_prev - u) exp(-dt / tau)."""
  keep = jp.where(faults.lag_s > 0, jp.exp(-dt / jp.maximum(faults.lag_s, 1e-9)), 0.0)
  setpoint = command + (faults.setpoint - command) * keep
  return setpoint, faults._replace(setpoint=setpoint)


def step(cfg: Config, faults: RobotFaults | None, command: jax.Array, key: jax.Array
         ) -> tuple[jax.Array, RobotFaults | None]:
  """One control step: (the [v, w] that drives the wheels, the faults after it).

  command: the policy's [v m/s, w rad/s] (in the action box), queued (latency), then
  lagged; the yaw drift takes its step with a key folded from `key` (the step's).
  Without faults: (command, None)."""
  if faults is None:
    return command, None
  robot, dt = cfg.robot, cfg.env.control_dt
  wheels = command
  if robot.latency_steps[1] > 0:
    wheels, faults = delayed(faults, wheels)
  if robot.velocity_lag_s[1] > 0:
    wheels, faults = lagged(faults, wheels, dt)
  if robot.yaw_walk_deg > 0:
    sigma = np.deg2rad(robot.yaw_walk_deg) * np.sqrt(dt)  # rad per control step
    walk = sigma * jax.random.normal(jax.random.fold_in(key, KEY_TAG), (), jp.float32)
    faults = faults._replace(yaw_drift=faults.yaw_drift + walk)
  return wheels, faults


def imu_yaw(robot: RobotConfig, yaw: jax.Array, faults: RobotFaults | None) -> jax.Array:
  """The yaw (rad, before wrapping) that the IMU reports for the true `yaw`: plus the
  drift where the walk is on, else `yaw` itself."""
  if faults is None or robot.yaw_walk_deg <= 0:
    return yaw
  return yaw + faults.yaw_drift


def mount_turn(pitch: jax.Array, roll: jax.Array) -> jax.Array:
  """(3, 3) the camera frame's turn by a pitch error (rad, positive looks down: about the
  camera's x axis, by -pitch, since MuJoCo's cameras look along -z), then a roll error
  (rad) about the turned optical axis; the columns are the turned axes in the camera's
  own frame, so `R @ mount_turn(...)` is the turned camera's world matrix."""
  cp, sp, cr, sr = jp.cos(pitch), jp.sin(pitch), jp.cos(roll), jp.sin(roll)
  zero, one = jp.zeros_like(pitch), jp.ones_like(pitch)
  about_x = jp.array([[one, zero, zero], [zero, cp, sp], [zero, -sp, cp]])  # R_x(-pitch)
  about_z = jp.array([[cr, -sr, zero], [sr, cr, zero], [zero, zero, one]])  # R_z(roll)
  return about_x @ about_z


def mounted_camera(robot: RobotConfig, d: mjx.Data, cam_id: int,
                   faults: RobotFaults | None) -> mjx.Data:
  """`d` with camera `cam_id`'s world pose (`cam_xmat`, `cam_xpos`) moved by the episode's
  mount errors, for rendering only (the physics keeps `d`); `d` itself without them."""
  if faults is None or not _has_mount(robot):
    return d
  if robot.mount_pitch_deg[1] > 0 or robot.mount_roll_deg[1] > 0:
    turned = d.cam_xmat[cam_id].reshape(3, 3) @ mount_turn(faults.mount[0], faults.mount[1])
    d = d.replace(cam_xmat=d.cam_xmat.at[cam_id].set(turned.reshape(d.cam_xmat[cam_id].shape)))
  if robot.mount_height_m[1] > 0:
    d = d.replace(cam_xpos=d.cam_xpos.at[cam_id, 2].add(faults.mount[2]))
  return d


def info_entry(faults: RobotFaults | None) -> dict:
  """{"robot": faults} for the env state's info, or {} without faults."""
  return {} if faults is None else {"robot": faults}


__all__ = ["RobotFaults", "KEY_TAG", "enabled", "draw", "delayed", "lagged", "step", "imu_yaw",
           "mount_turn", "mounted_camera", "info_entry"]
