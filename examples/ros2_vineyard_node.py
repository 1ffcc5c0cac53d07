"""ROS 2 sketch: drive a robot along a vineyard row with an exported mjxvine policy.

    python -m mjxvine.export --checkpoint runs/RUN --out policy.npz   # on the training machine
    python examples/ros2_vineyard_node.py --ros-args -p policy:=policy.npz \
        -r depth:=/camera/depth/image_rect_raw -r imu:=/imu/data -r cmd_vel:=/cmd_vel

Subscribes to `depth` (sensor_msgs/Image, 32FC1 metres or 16UC1 millimetres) and `imu`
(sensor_msgs/Imu; yaw from its orientation quaternion, rad) and publishes
geometry_msgs/Twist on `cmd_vel` at 1 / control_dt (10 Hz): linear.x = v (m/s), angular.z =
w (rad/s), from `NumpyPolicy` on the state [v_prev, w_prev, yaw]. The image is resized
to the policy's size (nearest neighbour, numpy only); invalid pixels (NaN, inf, 0 mm)
become the `invalid_depth` parameter (m), then the image is clipped to [0, max_depth]. The
camera's field of view should match the policy's meta (fovx_deg, fovy_deg): crop the
image first if it is wider. With no fresh image or IMU reading (older than `timeout_s`)
the node publishes a stop.

The yaw input follows the policy's `yaw_reference` (metadata): "start" (this project's
default) is the IMU yaw relative to the heading at the row entrance. The node takes that
reference from the first IMU reading, so start it with the robot at the row entrance
facing down the row; before the next row, call the `zero_heading` service
(std_srvs/Trigger) with the robot placed the same way. "world" (the paper's input) is the
IMU yaw plus the policy's `yaw_offset_deg`. Needs rclpy, sensor_msgs, geometry_msgs and
std_srvs (not mjxvine dependencies); numpy and mjxvine.deploy only otherwise.
"""

from __future__ import annotations

import math
import sys

import numpy as np
import rclpy
from geometry_msgs.msg import Twist
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image, Imu
from std_srvs.srv import Trigger

from mjxvine.deploy import NumpyPolicy


def image_to_metres(msg: Image, invalid: float) -> np.ndarray:
  """A 32FC1 (m) or 16UC1 (mm) Image -> (height, width) float32 metres; NaN/inf/0 mm ->
  `invalid`."""
  if msg.encoding == "32FC1":
    dtype, scale = np.dtype(np.float32), 1.0
  elif msg.encoding in ("16UC1", "mono16"):
    dtype, scale = np.dtype(np.uint16), 1e-3
  else:
    raise ValueError(f"unsupported depth encoding {msg.encoding!r} (32FC1 or 16UC1)")
  dtype = dtype.newbyteorder(">" if msg.is_bigendian else "<")
  rows = np.frombuffer(bytes(msg.data), dtype, count=msg.height * msg.step // dtype.itemsize)
  raw = rows.reshape(msg.height, -1)[:, : msg.width]
  img = raw.astype(np.float32) * np.float32(scale)
  bad = ~np.isfinite(img)
  if raw.dtype.kind == "u":
    bad |= raw == 0  # 0 mm: no return
  img[bad] = invalid
  return img


def resize_nearest(img: np.ndarray, height: int, width: int) -> np.ndarray:
  """(h, w) -> (height, width), nearest neighbour (pixel centres)."""
  rows = ((np.arange(height) + 0.5) * img.shape[0] / height).astype(np.intp)
  cols = ((np.arange(width) + 0.5) * img.shape[1] / width).astype(np.intp)
  return img[rows[:, None], cols[None, :]]


def quaternion_yaw(x: float, y: float, z: float, w: float) -> float:
  """Yaw (rad, about z, in (-pi, pi]) of a unit quaternion."""
  return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


class VineyardNode(Node):
  """Depth + IMU -> NumpyPolicy -> Twist at the policy's control rate."""

  def __init__(self):
    super().__init__("mjxvine_vineyard")
    path = self.declare_parameter("policy", "policy.npz").value
    self.timeout = float(self.declare_parameter("timeout_s", 0.5).value)
    # One BLAS thread (needs threadpoolctl; else set OPENBLAS_NUM_THREADS=1).
    self.policy = NumpyPolicy.load(path, preprocess=True, blas_threads=1)
    self.invalid = float(self.declare_parameter("invalid_depth", 0.0).value)
    self.depth = self.depth_time = self.yaw = self.yaw_time = None
    self.imu_yaw = self.yaw_ref = None  # raw IMU yaw and the reference it is measured from
    self.v_prev = self.w_prev = 0.0
    self.create_service(Trigger, "zero_heading", self.on_zero_heading)
    self.create_subscription(Image, "depth", self.on_depth, qos_profile_sensor_data)
    self.create_subscription(Imu, "imu", self.on_imu, qos_profile_sensor_data)
    self.cmd = self.create_publisher(Twist, "cmd_vel", 10)
    dt = float(self.policy.meta.get("control_dt", 0.1))
    self.create_timer(dt, self.on_timer)
    self.get_logger().info(f"{path}: {self.policy.height}x{self.policy.width} depth, "
                           f"fov {self.policy.meta.get('fovx_deg')} deg, {1 / dt:.0f} Hz")

  def now(self) -> float:
    return self.get_clock().now().nanoseconds * 1e-9

  def on_depth(self, msg: Image) -> None:
    try:
      img = image_to_metres(msg, self.invalid)
    except ValueError as e:
      self.get_logger().error(str(e), throttle_duration_sec=5.0)
      return
    self.depth = resize_nearest(img, self.policy.height, self.policy.width)
    self.depth_time = self.now()

  def on_imu(self, msg: Imu) -> None:
    q = msg.orientation
    self.imu_yaw = quaternion_yaw(q.x, q.y, q.z, q.w)
    if self.yaw_ref is None:  # the first reading: the robot stands at the row entrance
      self.yaw_ref = self.imu_yaw
    self.yaw, self.yaw_time = self.policy.yaw_input(self.imu_yaw, self.yaw_ref), self.now()

  def on_zero_heading(self, request, response):
    """The robot faces down the next row from its entrance: measure yaw from here."""
    self.yaw_ref = self.imu_yaw
    self.v_prev = self.w_prev = 0.0
    response.success = self.imu_yaw is not None
    response.message = "heading zeroed" if response.success else "no IMU reading yet"
    return response

  def on_timer(self) -> None:
    now, twist = self.now(), Twist()
    fresh = (self.depth is not None and self.yaw is not None and
             now - self.depth_time < self.timeout and now - self.yaw_time < self.timeout)
    if fresh:
      state = np.array([self.v_prev, self.w_prev, self.yaw], np.float32)
      v, w = self.policy(self.depth, state)
    else:
      v = w = 0.0
      self.get_logger().warn("no fresh depth image or IMU yaw: stop", throttle_duration_sec=2.0)
    twist.linear.x, twist.angular.z = float(v), float(w)
    self.cmd.publish(twist)
    self.v_prev, self.w_prev = float(v), float(w)


def main(args=None) -> None:
  rclpy.init(args=args)
  node = VineyardNode()
  try:
    rclpy.spin(node)
  except KeyboardInterrupt:
    pass
  finally:
    node.cmd.publish(Twist())  # stop
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
  main(sys.argv)
