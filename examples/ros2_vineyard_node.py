"""ROS 2 node: drive a robot along a vineyard row with an exported mjxvine policy.

Tested in simulation only (this repository's simulator and the numpy policy); it has not
yet driven a real robot. Treat the first field runs as tests: a low `max_speed`, a person
at the e-stop.

    python -m mjxvine.export --checkpoint runs/RUN --out policy.npz   # on the training machine
    python examples/ros2_vineyard_node.py --ros-args --params-file examples/ros2_jackal_params.yaml \
        -r depth:=/camera/depth/image_rect_raw -r camera_info:=/camera/depth/camera_info \
        -r imu:=/imu/data -r cmd_vel:=/cmd_vel

On the robot it needs numpy and the policy code only: mjxvine installed, or just the one
file mjxvine/deploy/numpy_policy.py copied next to this node as mjxvine_deploy.py (numpy
and the standard library, Python 3.8+), plus rclpy, sensor_msgs, geometry_msgs and std_srvs.

Subscribes to `depth` (sensor_msgs/Image, 32FC1 metres or 16UC1 millimetres, read by
`depth_from_ros`; other encodings are refused),
`camera_info` (sensor_msgs/CameraInfo of that image) and `imu` (sensor_msgs/Imu; yaw from
its orientation quaternion, rad) and publishes geometry_msgs/Twist on `cmd_vel` at
1 / control_dt (10 Hz): linear.x = v (m/s), angular.z = w (rad/s), from `NumpyPolicy` on
the state [v_prev, w_prev, yaw].

Parameters:
  policy (str): the .npz policy file.
  fov_crop (bool, true): crop the image to the policy's field of view (`fovx_deg`,
    `fovy_deg` in its metadata) around the optical axis, from the camera's CameraInfo
    (fx, fy, cx, cy), before resizing it to the policy's size (nearest neighbour). A
    camera narrower than the policy cannot be widened: the node warns. With fov_crop
    the node stops until a CameraInfo has arrived.
  max_speed (float, -1): a cap on v in m/s below the policy's own maximum (negative:
    none). The state's v_prev is the speed actually commanded.
  invalid_depth (float, -1): what pixels without a reading (NaN, inf, 0 mm) become, m;
    negative: the policy's maximum range `max_depth_m`, what the simulator shows for a
    ray that hits nothing (0 would read as an obstacle at the lens).
  timeout_s (float, 0.5): with no fresh image or IMU reading for this long, publish a stop.

Safety: an input the policy refuses (`PolicyInputError`: an unknown image encoding, depth
out of range or without any reading, a yaw or state out of range) or any other
`PolicyError` while running publishes a stop (zero velocities), never the last action,
and logs the reason (throttled); the node drives again once the inputs are valid.

The yaw input follows the policy's `yaw_reference` (metadata): "start" (this project's
default) is the IMU yaw relative to the heading at the row entrance. The node takes that
reference from the first IMU reading, so start it with the robot at the row entrance
facing down the row; before the next row, call the `zero_heading` service
(std_srvs/Trigger) with the robot placed the same way. "world" (the paper's input) is the
IMU yaw plus the policy's `yaw_offset_deg`.
"""

from __future__ import annotations

import math
import sys

import numpy as np
import rclpy
from geometry_msgs.msg import Twist
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image, Imu
from std_srvs.srv import Trigger

try:
  from mjxvine.deploy.numpy_policy import (NumpyPolicy, PolicyError, depth_from_ros,
                                           fov_window)
except ImportError:  # no mjxvine on the robot: numpy_policy.py copied as mjxvine_deploy.py
  from mjxvine_deploy import NumpyPolicy, PolicyError, depth_from_ros, fov_window

LOG_EVERY_S = 2.0  # throttle of repeated warnings and errors


def image_to_metres(msg: Image) -> np.ndarray:
  """A 32FC1 (m) or 16UC1 (mm) Image -> (height, width) float32 metres (16UC1 0, no
  return, -> NaN, which the policy's preprocessing maps to `invalid_depth`; 32FC1 as
  sent). Another encoding or a short buffer: `PolicyInputError`."""
  return depth_from_ros(msg.data, msg.encoding, msg.height, msg.width, msg.step,
                        bool(msg.is_bigendian))


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
    invalid = float(self.declare_parameter("invalid_depth", -1.0).value)
    self.fov_crop = bool(self.declare_parameter("fov_crop", True).value)
    self.max_speed = float(self.declare_parameter("max_speed", -1.0).value)
    # One BLAS thread (needs threadpoolctl; else set OPENBLAS_NUM_THREADS=1). Invalid
    # pixels: the maximum range unless invalid_depth >= 0.
    self.policy = NumpyPolicy.load(path, preprocess=True, blas_threads=1,
                                   invalid_depth=invalid if invalid >= 0 else None)
    self.window = None  # (rows, cols) of the image inside the policy's field of view
    self.depth = self.depth_time = self.yaw = self.yaw_time = None
    self.depth_error = None  # why the last image was refused (None: it was not)
    self.imu_yaw = self.yaw_ref = None  # raw IMU yaw and the reference it is measured from
    self.v_prev = self.w_prev = 0.0
    self.create_service(Trigger, "zero_heading", self.on_zero_heading)
    self.create_subscription(Image, "depth", self.on_depth, qos_profile_sensor_data)
    if self.fov_crop:
      self.create_subscription(CameraInfo, "camera_info", self.on_camera_info,
                               qos_profile_sensor_data)
    self.create_subscription(Imu, "imu", self.on_imu, qos_profile_sensor_data)
    self.cmd = self.create_publisher(Twist, "cmd_vel", 10)
    dt = float(self.policy.meta.get("control_dt", 0.1))
    self.create_timer(dt, self.on_timer)
    self.get_logger().info(
        f"{path}: {self.policy.height}x{self.policy.width} depth, fov "
        f"{self.policy.meta.get('fovx_deg')} x {self.policy.meta.get('fovy_deg')} deg"
        f"{' (cropped from camera_info)' if self.fov_crop else ''}, invalid depth -> "
        f"{self.policy.invalid_depth:g} m, {1 / dt:.0f} Hz"
        + (f", v <= {self.max_speed:g} m/s" if self.max_speed >= 0 else ""))

  def now(self) -> float:
    return self.get_clock().now().nanoseconds * 1e-9

  def on_camera_info(self, msg: CameraInfo) -> None:
    """The rows and columns of the image inside the policy's field of view."""
    fx, cx, fy, cy = msg.k[0], msg.k[2], msg.k[4], msg.k[5]
    if fx <= 0 or fy <= 0:
      self.get_logger().error("camera_info has no focal length (K)", throttle_duration_sec=5.0)
      return
    meta = self.policy.meta
    window = (fov_window(msg.height, fy, cy, float(meta.get("fovy_deg", 180.0))),
              fov_window(msg.width, fx, cx, float(meta.get("fovx_deg", 180.0))))
    if window != self.window:
      self.window = window
      cam_fovx = math.degrees(2 * math.atan(msg.width / (2 * fx)))
      if cam_fovx < float(meta.get("fovx_deg", 0.0)) - 1.0:
        self.get_logger().warn(f"the camera sees {cam_fovx:.1f} deg across, the policy was "
                               f"trained with {meta.get('fovx_deg')} deg: it cannot be widened")
      self.get_logger().info(f"field-of-view crop: rows {window[0]}, columns {window[1]} of "
                             f"{msg.height}x{msg.width}")

  def on_depth(self, msg: Image) -> None:
    try:
      img = image_to_metres(msg)
    except PolicyError as e:  # stop now, not after timeout_s on the last good image
      self.depth, self.depth_error = None, f"depth image refused: {e}"
      return
    self.depth_error = None
    if self.fov_crop:
      if self.window is None:
        self.get_logger().warn("waiting for camera_info (fov_crop)", throttle_duration_sec=5.0)
        return
      (r0, r1), (c0, c1) = self.window
      img = img[r0:r1, c0:c1]
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

  def decide(self) -> tuple[float, float]:
    """(v m/s, w rad/s) to command now: the policy's action, or (0, 0), a stop, with no
    fresh valid input or when the policy refuses it (the reason is logged, throttled)."""
    now, log = self.now(), self.get_logger()
    if self.depth_error is not None:
      log.error(f"{self.depth_error}: stop", throttle_duration_sec=LOG_EVERY_S)
      return 0.0, 0.0
    fresh = (self.depth is not None and self.yaw is not None and
             now - self.depth_time < self.timeout and now - self.yaw_time < self.timeout)
    if not fresh:
      log.warn("no fresh depth image or IMU yaw: stop", throttle_duration_sec=LOG_EVERY_S)
      return 0.0, 0.0
    # The previous command as the policy was trained on it: inside its action box (a
    # stop is outside a box whose v starts above 0).
    prev = np.clip([self.v_prev, self.w_prev], self.policy.low, self.policy.high)
    state = np.array([prev[0], prev[1], self.yaw], np.float32)
    try:
      v, w = self.policy(self.depth, state)
    except PolicyError as e:  # never the last action: it was for another view
      log.error(f"policy refused its input: {e}: stop", throttle_duration_sec=LOG_EVERY_S)
      return 0.0, 0.0
    if self.max_speed >= 0:
      v = min(v, self.max_speed)
    return float(v), float(w)

  def on_timer(self) -> None:
    v, w = self.decide()
    twist = Twist()
    twist.linear.x, twist.angular.z = v, w
    self.cmd.publish(twist)
    self.v_prev, self.w_prev = v, w


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
