"""ROS 2 node: drive a robot along a vineyard row with an exported mjxvine policy.

Tested in simulation only (this repository's simulator and the numpy policy); it has not
yet driven a real robot. Treat the first field runs as tests: a low `max_speed`, a person
at the e-stop.

    python -m mjxvine.export --policy runs/RUN --out policy.npz   # on the training machine
    python examples/ros2_vineyard_node.py --ros-args --params-file examples/ros2_jackal_params.yaml \
        -r depth:=/camera/depth/image_rect_raw -r camera_info:=/camera/depth/camera_info \
        -r imu:=/imu/data -r cmd_vel:=/cmd_vel

On the robot it needs numpy and the policy code only: mjxvine installed, or the two files
mjxvine/deploy/numpy_policy.py and mjxvine/deploy/node_logic.py copied next to this node as
mjxvine_deploy.py and mjxvine_node_logic.py (numpy and the standard library, Python 3.8+),
plus rclpy, sensor_msgs, geometry_msgs, std_msgs and std_srvs.

Subscribes to `depth` (sensor_msgs/Image, 32FC1 metres or 16UC1 millimetres, read by
`depth_from_ros`; other encodings are refused),
`camera_info` (sensor_msgs/CameraInfo of that image) and `imu` (sensor_msgs/Imu; yaw from
its orientation quaternion, rad) and publishes geometry_msgs/Twist on `cmd_vel` at
1 / control_dt (10 Hz): linear.x = v (m/s), angular.z = w (rad/s), from `NumpyPolicy` on
the state [v_prev, w_prev, yaw].

Parameters:
  policy (str): the .npz policy file. A file the policy refuses: the node does not start.
  fov_crop (bool, true): crop the image to the policy's field of view (`fovx_deg`,
    `fovy_deg` in its metadata) around the optical axis, from the camera's CameraInfo
    (fx, fy, cx, cy), before resizing it to the policy's size (nearest neighbour). A
    camera narrower than the policy cannot be widened: the node warns. With fov_crop
    the node stops until a valid CameraInfo has arrived, and refuses images of another
    size than it says (a transposed image).
  max_speed (float, -1): a cap on v in m/s below the policy's own maximum (negative:
    none). The state's v_prev is the speed actually commanded.
  invalid_depth (float, -1): what pixels without a reading (NaN, inf, 0 mm) become, m;
    negative: the policy's maximum range `max_depth_m`, what the simulator shows for a
    ray that hits nothing (0 would read as an obstacle at the lens).
  timeout_s (float, 0.5): the most an image or IMU reading may be old, by its header
    stamp against the node's clock; older (or none): publish a stop.
  stop_at_row_end (bool, true): when the policy's end-of-row detector fires
    (`NumpyPolicy.step`: the image shows no plant of the row and the robot has driven the
    last plants' depth past them), publish a stop and keep stopping until `zero_heading`
    at the next row's entrance. Every cycle publishes std_msgs/Bool on `row_end`: true
    once the row has ended.

Safety: the checks and decisions are `mjxvine.deploy.node_logic.DriveLogic` (no ROS
needed; tested without it); this file is the rclpy glue. Any refused input (an unknown
encoding, a size or step that does not fit, a stale or unstamped message, an IMU without
orientation, a depth or state the policy refuses) and any exception in any callback
publishes a stop (zero velocities), never the last action, and logs the reason
(throttled); the node keeps running and drives again once the inputs are valid. The
table of faults is in docs/deployment.md.

The yaw input follows the policy's `yaw_reference` (metadata): "start" (this project's
default) is the IMU yaw relative to the heading at the row entrance. The node takes that
reference from the first valid IMU reading, so start it with the robot at the row entrance
facing down the row; before the next row, call the `zero_heading` service
(std_srvs/Trigger) with the robot placed the same way. "world" (the paper's input) is the
IMU yaw itself (`NumpyPolicy.yaw_input`).
"""

from __future__ import annotations

import signal
import sys

import rclpy
from geometry_msgs.msg import Twist
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image, Imu
from std_msgs.msg import Bool
from std_srvs.srv import Trigger

try:
  from mjxvine.deploy.node_logic import DriveLogic
  from mjxvine.deploy.numpy_policy import NumpyPolicy, PolicyError
except ImportError:  # no mjxvine on the robot: the two files copied next to this one
  from mjxvine_deploy import NumpyPolicy, PolicyError
  from mjxvine_node_logic import DriveLogic

LOG_EVERY_S = 2.0  # throttle of repeated warnings and errors


class VineyardNode(Node, DriveLogic):
  """Depth + IMU -> NumpyPolicy -> Twist at the policy's control rate. Each callback
  hands its message to `DriveLogic` and stops the robot on any exception."""

  def __init__(self):
    Node.__init__(self, "mjxvine_vineyard")
    path = self.declare_parameter("policy", "policy.npz").value
    timeout = float(self.declare_parameter("timeout_s", 0.5).value)
    invalid = float(self.declare_parameter("invalid_depth", -1.0).value)
    fov_crop = bool(self.declare_parameter("fov_crop", True).value)
    max_speed = float(self.declare_parameter("max_speed", -1.0).value)
    stop_at_row_end = bool(self.declare_parameter("stop_at_row_end", True).value)
    # One BLAS thread (needs threadpoolctl; else set OPENBLAS_NUM_THREADS=1). Invalid
    # pixels: the maximum range unless invalid_depth >= 0.
    policy = NumpyPolicy.load(path, preprocess=True, blas_threads=1,
                              invalid_depth=invalid if invalid >= 0 else None)
    DriveLogic.__init__(self, policy, timeout_s=timeout, max_speed=max_speed,
                        fov_crop=fov_crop, stop_at_row_end=stop_at_row_end)
    self.cmd = self.create_publisher(Twist, "cmd_vel", 10)
    self.row_end = self.create_publisher(Bool, "row_end", 10)
    self.create_service(Trigger, "zero_heading", self.on_zero_heading)
    self.create_subscription(Image, "depth", self.on_depth, qos_profile_sensor_data)
    if self.fov_crop:
      self.create_subscription(CameraInfo, "camera_info", self.on_camera_info,
                               qos_profile_sensor_data)
    self.create_subscription(Imu, "imu", self.on_imu, qos_profile_sensor_data)
    dt = policy.control_dt or 0.1
    self.create_timer(dt, self.on_timer)
    layout = policy.layout
    self.get_logger().info(
        f"{path}: {policy.height}x{policy.width} depth, fov {layout['fovx_deg']} x "
        f"{layout['fovy_deg']} deg{' (cropped from camera_info)' if self.fov_crop else ''}, "
        f"invalid depth -> {policy.invalid_depth:g} m, {1 / dt:.0f} Hz, inputs older than "
        f"{self.timeout:g} s refused"
        + (f", v <= {self.max_speed:g} m/s" if self.max_speed >= 0 else "")
        + (", stops at the end of the row" if self.stop_at_row_end else
           ", no end-of-row stop"))

  def now(self) -> float:
    """The node's clock (s): header stamps are judged against it (sim time in a sim)."""
    return self.get_clock().now().nanoseconds * 1e-9

  def publish(self, v: float, w: float) -> None:
    """Publishes (v m/s, w rad/s) and keeps it as the next v_prev, w_prev."""
    twist = Twist()
    twist.linear.x, twist.angular.z = float(v), float(w)
    self.cmd.publish(twist)
    self.commanded(v, w)

  def fault(self, where: str, error: Exception) -> None:
    """Any exception in a callback: stop now, log, keep running; the input it was about
    is not driven on until a valid one arrives."""
    text = str(error).strip()
    text = text.splitlines()[0][:200] if text else ""
    reason = f"{where} failed ({type(error).__name__}: {text})"
    try:
      self.invalidate(where, reason)
      self.get_logger().error(f"{reason}: stop", throttle_duration_sec=LOG_EVERY_S)
    finally:
      self.commanded(0.0, 0.0)
      try:
        self.cmd.publish(Twist())  # zero velocities
      except Exception:  # noqa: BLE001 - shutting down: nothing left to stop with
        pass

  def on_camera_info(self, msg: CameraInfo) -> None:
    try:
      note = self.take_camera_info(msg)
      if note:
        self.get_logger().info(note)
    except Exception as e:  # noqa: BLE001 - stop, never die
      self.fault("camera_info", e)

  def on_depth(self, msg: Image) -> None:
    try:
      self.take_depth(msg, self.now())
    except Exception as e:  # noqa: BLE001 - stop, never die
      self.fault("depth", e)

  def on_imu(self, msg: Imu) -> None:
    try:
      self.take_imu(msg, self.now())
    except Exception as e:  # noqa: BLE001 - stop, never die
      self.fault("imu", e)

  def on_zero_heading(self, request, response):
    """The robot faces down the next row from its entrance: measure yaw from here."""
    try:
      response.success = self.zero_heading()
      response.message = "heading zeroed" if response.success else "no valid IMU reading yet"
    except Exception as e:  # noqa: BLE001 - stop, never die
      self.fault("zero_heading", e)
      response.success, response.message = False, f"failed: {e}"
    return response

  def on_timer(self) -> None:
    """The command now (`DriveLogic.decide`): the policy's action or a stop, logged."""
    try:
      decision = self.decide(self.now())
      if decision.level == "error":
        self.get_logger().error(decision.reason, throttle_duration_sec=LOG_EVERY_S)
      elif decision.level == "info":
        self.get_logger().info(decision.reason, throttle_duration_sec=LOG_EVERY_S)
      elif decision.reason is not None:
        self.get_logger().warn(decision.reason, throttle_duration_sec=LOG_EVERY_S)
      self.publish(decision.v, decision.w)
      self.row_end.publish(Bool(data=decision.row_end))
    except Exception as e:  # noqa: BLE001 - stop, never die
      self.fault("timer", e)


def _stop_on(signum, frame):
  raise KeyboardInterrupt  # the node publishes its stop while ROS is still up


def main(args=None) -> int:
  try:  # rclpy's own SIGINT handler would shut ROS down before the node could say stop
    from rclpy.signals import SignalHandlerOptions
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
  except ImportError:  # rclpy before Humble
    rclpy.init(args=args)
  try:
    node = VineyardNode()
  except (PolicyError, ValueError) as e:  # a bad policy file or parameter: never start
    print(f"ros2_vineyard_node: {e}", file=sys.stderr)
    rclpy.try_shutdown()
    return 2
  signal.signal(signal.SIGINT, _stop_on)
  signal.signal(signal.SIGTERM, _stop_on)
  try:
    rclpy.spin(node)
  except KeyboardInterrupt:
    pass
  finally:
    try:
      node.cmd.publish(Twist())  # stop
    except Exception as e:  # noqa: BLE001 - ROS already down: nothing can be sent
      print(f"ros2_vineyard_node: could not publish the stop ({e})", file=sys.stderr)
    node.destroy_node()
    rclpy.try_shutdown()
  return 0


if __name__ == "__main__":
  sys.exit(main(sys.argv))
