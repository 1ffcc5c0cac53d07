"""Robot models (docs/design.md, Robots): a robot (Jackal, Husky or a robot file,
docs/your-robot.md) as a free-joint chassis on four driven sphere wheels, with the depth
camera at its mount. Lengths in metres, masses in kg. The robots' dimensions (`RobotSpec`,
`ROBOTS`, `robot_spec`) come from `mjxvine.robot_files` through `mjxvine.config`, which
validates configs against them; they are re-exported here."""

from __future__ import annotations

import math

import mujoco

from mjxvine.config import ROBOTS, RobotSpec, robot_spec

__all__ = ["ROBOTS", "RobotSpec", "robot_spec", "WHEEL_SIDES", "add_robot", "wheel_speeds"]

# Wheel order of the actuators: front-left, rear-left, front-right, rear-right.
WHEEL_SIDES = (1, 1, -1, -1)  # +1 left, -1 right
# The wheels' drive, per kg of robot: a velocity servo's gain (N m s / rad / kg) and the
# motor's armature (kg m^2 / kg); the tyres' sliding friction.
WHEEL_KV_PER_KG = 1.0
WHEEL_ARMATURE_PER_KG = 0.005
WHEEL_FRICTION = 0.8


def add_robot(spec: mujoco.MjSpec, robot: RobotSpec, *, fovy_deg: float,
              max_wheel_speed: float) -> None:
  """Adds the robot body `chassis` (frame origin at axle height) to `spec`.

  Geoms are group 2 and only the wheels collide (with the terrain); the plants never
  collide physically (collisions with plants are a geometric test of the environment).
  """
  r = robot.wheel_radius
  chassis = spec.worldbody.add_body(name="chassis", pos=[0, 0, r + 0.01])
  chassis.add_freejoint(name="root")
  top = robot.height - r
  chassis.add_geom(
      name="chassis", type=mujoco.mjtGeom.mjGEOM_BOX,
      size=[robot.length / 2, robot.width / 2 - 0.3 * r, top / 2 + 0.01],
      pos=[0, 0, top / 2 - 0.01], mass=robot.chassis_mass, contype=0, conaffinity=0,
      group=2, rgba=[0.85, 0.65, 0.1, 1])
  for i, (fx, side) in enumerate(zip((1, -1, 1, -1), WHEEL_SIDES)):
    wheel = chassis.add_body(name=f"wheel{i}",
                             pos=[fx * robot.wheelbase / 2, side * robot.track / 2, 0])
    # Armature: the reflected inertia of the geared motor; it also keeps the stiff
    # velocity servo stable at the coarse physics step.
    wheel.add_joint(name=f"wheel{i}", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 1, 0],
                    armature=WHEEL_ARMATURE_PER_KG * robot.mass)
    wheel.add_geom(name=f"wheel{i}", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[r, 0, 0],
                   mass=robot.wheel_mass, friction=[WHEEL_FRICTION, 0.005, 0.0001], condim=3,
                   group=2, rgba=[0.1, 0.1, 0.1, 1])
    act = spec.add_actuator(name=f"wheel{i}", target=f"wheel{i}",
                            trntype=mujoco.mjtTrn.mjTRN_JOINT)
    act.set_to_velocity(kv=WHEEL_KV_PER_KG * robot.mass)
    act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
    act.ctrlrange = [-max_wheel_speed, max_wheel_speed]
  # MuJoCo cameras look along -z with +y up: x_cam = -y_body (right), y_cam = +z_body
  # turned about the body's y axis by the pitch, so the view (-z_cam) tips down by it;
  # pitch 0 is exactly [0, -1, 0, 0, 0, 1].
  pitch = math.radians(robot.camera_pitch_deg)
  chassis.add_camera(name="depth", pos=[robot.camera_ahead, 0, robot.camera_height - r],
                     xyaxes=[0, -1, 0, math.sin(pitch), 0, math.cos(pitch)], fovy=fovy_deg)


def wheel_speeds(v, w, robot: RobotSpec):
  """Skid-steer wheel angular speeds (rad/s) for body speeds v (m/s), w (rad/s), as
  (front-left, rear-left, front-right, rear-right); works on numpy and jax arrays.

  Skid-steering slips sideways when turning; the usual kinematic model widens the track
  by a factor chi (`track_slip`), calibrated so that the simulated yaw rate follows w.
  """
  half = robot.track_slip * robot.track / 2
  left = (v - w * half) / robot.wheel_radius
  right = (v + w * half) / robot.wheel_radius
  return left, left, right, right
