"""Planar angles of the robot in JAX: the yaw of a body quaternion and angles wrapped to
[-pi, pi). The env, its reference driver and the IMU drift (`robot_faults`) share them."""

from __future__ import annotations

import jax
import jax.numpy as jp


def quat_yaw(quat: jax.Array) -> jax.Array:
  """Yaw (rad, about world z) of a unit quaternion (4,) [w, x, y, z]."""
  w, x, y, z = quat[0], quat[1], quat[2], quat[3]
  return jp.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def wrap(angle: jax.Array) -> jax.Array:
  """`angle` (rad, any shape) wrapped to [-pi, pi)."""
  return (angle + jp.pi) % (2 * jp.pi) - jp.pi


__all__ = ["quat_yaw", "wrap"]
