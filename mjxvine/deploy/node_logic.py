"""The ROS 2 node's decisions, without ROS: `examples/ros2_vineyard_node.py` is rclpy glue
around `DriveLogic`, which checks every depth image, CameraInfo and IMU message (given as
message objects with the sensor_msgs fields, or their fields as plain values) and gives
the command to publish or the reason to stop.

    logic = DriveLogic(NumpyPolicy.load(path, preprocess=True), timeout_s=0.5)
    logic.take_camera_info(info_msg)          # with fov_crop: the crop window, the size
    logic.take_depth(image_msg, now_s)        # now_s: the node's clock, s
    logic.take_imu(imu_msg, now_s)
    decision = logic.decide(now_s)            # (v m/s, w rad/s, reason, level, row_end)
    logic.commanded(decision.v, decision.w)   # what was published: the next v_prev, w_prev

Nothing here raises on a bad message: a refused message is recorded (`depth_error`,
`imu_error`, `camera_error`) and `decide` returns a stop (0, 0) with the reason until a
valid one arrives; `decide` itself never raises and never returns a non-finite command.
Every check is in the fault table of docs/deployment.md.

numpy and the numpy policy only: on a robot without mjxvine, copy this file next to the
node as mjxvine_node_logic.py with numpy_policy.py as mjxvine_deploy.py.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

try:
  from mjxvine.deploy.numpy_policy import (ROS_DEPTH_ENCODINGS, PolicyError, depth_from_ros,
                                           finite_number, fov_window)
except ImportError:  # no mjxvine on the robot: numpy_policy.py copied as mjxvine_deploy.py
  from mjxvine_deploy import (ROS_DEPTH_ENCODINGS, PolicyError, depth_from_ros, finite_number,
                              fov_window)

# A message stamped up to this far after the node's clock is accepted (s): clocks of
# two machines synchronised by NTP or PTP differ by milliseconds.
STAMP_TOLERANCE_S = 0.05
# Largest image side accepted (px) and row padding (bytes past width x pixel size).
MAX_IMAGE_SIDE_PX = 8192
MAX_ROW_PADDING_BYTES = 63
# An IMU quaternion's norm must lie within 1 +- this (drivers publish unit quaternions;
# a zero or garbage one has no orientation).
QUATERNION_NORM_TOLERANCE = 0.01


class Refused(ValueError):
  """A message that must not be driven on; its text (one line) says why."""


class Decision(NamedTuple):
  """The command to publish: v (m/s), w (rad/s); reason: why it is a stop (None when it
  is the policy's action); level: "error" (a refused input), "warn" (no fresh input) or
  "info" (the end of the row); row_end: the row has ended (the node publishes it)."""
  v: float
  w: float
  reason: str | None = None
  level: str | None = None
  row_end: bool = False


def _stop(reason: str, level: str = "error") -> Decision:
  return Decision(0.0, 0.0, f"{reason}: stop", level)


def _fault(e: BaseException) -> str:
  """An exception as one line: a refusal's own text, else its type and first line."""
  text = str(e).strip().splitlines()[0][:300] if str(e).strip() else ""
  if isinstance(e, (Refused, PolicyError)):
    return text
  return f"{type(e).__name__}: {text}" if text else type(e).__name__


def _int(v, what: str, lo: int, hi: int) -> int:
  if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
    raise Refused(f"{what} {v!r}: expected an integer in [{lo}, {hi}]")
  return int(v)


def _float(v, what: str) -> float:
  return finite_number(v, what, Refused)


def stamp_seconds(stamp) -> float:
  """A builtin_interfaces/Time (sec, nanosec) in seconds; Refused for a zero stamp (the
  driver does not stamp its messages) or fields that are not a valid time."""
  sec = _int(getattr(stamp, "sec", None), "stamp sec", -2**31, 2**31 - 1)
  nanosec = _int(getattr(stamp, "nanosec", None), "stamp nanosec", 0, 999_999_999)
  if sec == 0 and nanosec == 0:
    raise Refused("header stamp is zero: the driver does not stamp its messages")
  return sec + nanosec * 1e-9


def message_stamp(msg, now_s: float) -> float:
  """The header stamp of a message, s (`stamp_seconds`). A ROS message always has a
  header; an object without one (a test double, not a message) is stamped `now_s`."""
  header = getattr(msg, "header", None)
  return now_s if header is None else stamp_seconds(getattr(header, "stamp", None))


def check_age(stamp_s: float, now_s: float, max_age_s: float, what: str) -> str | None:
  """Why a message stamped `stamp_s` is not fresh at `now_s` (node clock, s), or None:
  older than `max_age_s`, or stamped more than STAMP_TOLERANCE_S in the future."""
  age = now_s - stamp_s
  if age > max_age_s:
    return f"{what} is {age:.3f} s old (timeout_s {max_age_s:g})"
  if age < -STAMP_TOLERANCE_S:
    return (f"{what} is stamped {-age:.3f} s after the node's clock (clocks not "
            f"synchronised?; tolerance {STAMP_TOLERANCE_S:g} s)")
  return None


def image_metres(data, encoding: str, height, width, step, is_bigendian,
                 expect: tuple[int, int] | None = None) -> np.ndarray:
  """A sensor_msgs/Image's fields -> (height, width) float32 metres (`depth_from_ros`:
  16UC1 mm with 0 -> NaN, 32FC1 m), after strict checks: a depth encoding (REP 118),
  sizes in [1, MAX_IMAGE_SIDE_PX], the size `expect` (the CameraInfo's (height, width))
  if given, step = width x pixel size plus at most MAX_ROW_PADDING_BYTES, exactly
  height x step bytes of data. Refused otherwise: a transposed or mislabelled image."""
  if encoding not in ROS_DEPTH_ENCODINGS:
    raise Refused(f"depth image encoding {str(encoding)[:40]!r}: expected one of "
                  f"{', '.join(ROS_DEPTH_ENCODINGS)} (REP 118 depth)")
  height = _int(height, "image height", 1, MAX_IMAGE_SIDE_PX)
  width = _int(width, "image width", 1, MAX_IMAGE_SIDE_PX)
  if expect is not None and (height, width) != tuple(expect):
    raise Refused(f"depth image of {height}x{width} px (height x width), camera_info says "
                  f"{expect[0]}x{expect[1]}: transposed, or another camera's")
  row = width * np.dtype(ROS_DEPTH_ENCODINGS[encoding][0]).itemsize
  step = _int(step, "image step", 0, row + MAX_ROW_PADDING_BYTES)
  if step < row:
    raise Refused(f"{encoding} image step {step} bytes: expected width {width} x "
                  f"{row // width} bytes (+ at most {MAX_ROW_PADDING_BYTES} padding)")
  size = len(data)
  if size != height * step:
    raise Refused(f"{encoding} image of {size} bytes: expected height {height} x step {step} "
                  f"= {height * step}")
  if is_bigendian not in (0, 1):
    raise Refused(f"image is_bigendian {is_bigendian!r}: expected 0 or 1")
  return depth_from_ros(data, encoding, height, width, step, bool(is_bigendian))


def imu_yaw(x, y, z, w, covariance=None) -> float:
  """Yaw (rad, about z, in (-pi, pi]) of an IMU orientation quaternion. Refused when the
  IMU gives no orientation: orientation_covariance[0] == -1 (REP 145), a quaternion with a
  NaN/inf, or one whose norm is not 1 +- QUATERNION_NORM_TOLERANCE (a zero quaternion)."""
  if covariance is not None and len(covariance) and float(covariance[0]) == -1.0:
    raise Refused("IMU gives no orientation (orientation_covariance[0] = -1, REP 145)")
  q = [_float(v, "IMU orientation") for v in (x, y, z, w)]
  norm = math.sqrt(sum(v * v for v in q))
  if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
    raise Refused(f"IMU orientation quaternion of norm {norm:.4g}: expected a unit "
                  "quaternion (a zero one means no orientation)")
  x, y, z, w = (v / norm for v in q)
  return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def camera_window(height, width, k, fovx_deg: float | None, fovy_deg: float | None):
  """((rows, cols) of the image inside the policy's field of view, the camera's horizontal
  field of view in degrees) from a CameraInfo's height, width and K (3x3 row-major: fx at
  0, cx at 2, fy at 4, cy at 5). Refused for sizes out of range, a K that is not finite,
  a focal length <= 0 or a principal point outside the image."""
  height = _int(height, "camera_info height", 1, MAX_IMAGE_SIDE_PX)
  width = _int(width, "camera_info width", 1, MAX_IMAGE_SIDE_PX)
  if k is None or len(k) != 9:
    raise Refused("camera_info K: expected 9 numbers")
  fx, cx, fy, cy = (_float(k[i], "camera_info K") for i in (0, 2, 4, 5))
  if fx <= 0 or fy <= 0:
    raise Refused(f"camera_info has no focal length (K fx {fx:g}, fy {fy:g})")
  if not (0 <= cx <= width and 0 <= cy <= height):
    raise Refused(f"camera_info principal point ({cx:g}, {cy:g}) outside the {height}x{width} "
                  "image")
  window = (fov_window(height, fy, cy, fovy_deg or 180.0),
            fov_window(width, fx, cx, fovx_deg or 180.0))
  return window, math.degrees(2 * math.atan(width / (2 * fx)))


def resize_nearest(img: np.ndarray, height: int, width: int) -> np.ndarray:
  """(h, w) -> (height, width), nearest neighbour (pixel centres)."""
  rows = ((np.arange(height) + 0.5) * img.shape[0] / height).astype(np.intp)
  cols = ((np.arange(width) + 0.5) * img.shape[1] / width).astype(np.intp)
  return img[rows[:, None], cols[None, :]]


class DriveLogic:
  """Depth + IMU -> the policy's command or a stop; the node's state (module docstring).

  policy: a `NumpyPolicy` (loaded with preprocess=True for raw sensor images).
  timeout_s: the most a depth image or IMU reading may be old (by its header stamp
  against the node's clock) to be driven on. max_speed: a cap on v (m/s; negative: none).
  fov_crop: crop images to the policy's field of view from CameraInfo, and refuse images
  of another size than the CameraInfo's; until a valid one arrives, stop.
  stop_at_row_end: stop for good when the policy's end-of-row detector fires
  (`NumpyPolicy.step`) until `zero_heading` at the next row's entrance; off for a policy
  file without the detector (`NumpyPolicy.has_row_end`: files exported before it).
  """

  def __init__(self, policy, timeout_s: float = 0.5, max_speed: float = -1.0,
               fov_crop: bool = True, stop_at_row_end: bool = True):
    self.policy = policy
    self.timeout = float(timeout_s)
    self.max_speed = float(max_speed)
    if not (math.isfinite(self.timeout) and self.timeout > 0):
      raise ValueError(f"timeout_s {timeout_s!r}: expected seconds > 0")
    if not math.isfinite(self.max_speed):
      raise ValueError(f"max_speed {max_speed!r}: expected m/s (negative: no cap)")
    self.fov_crop = bool(fov_crop)
    self.window = None  # (rows, cols) of the image inside the policy's field of view
    self.camera_size = None  # (height, width) of the last valid CameraInfo
    self.camera_fovx = None  # deg
    self.depth = self.depth_stamp = self.yaw = self.yaw_stamp = None
    self.depth_error = self.imu_error = self.camera_error = None  # why the last was refused
    self.imu_yaw = self.yaw_ref = None  # raw IMU yaw and the reference it is measured from
    self.v_prev = self.w_prev = 0.0
    self.stop_at_row_end = bool(stop_at_row_end) and bool(getattr(policy, "has_row_end",
                                                                  False))
    self.row_ended = False  # the detector fired in this row: stopped until zero_heading

  # ----------------------------------------------------------------- messages in

  def take_camera_info(self, msg) -> str | None:
    """A sensor_msgs/CameraInfo (height, width, k): the crop window. Returns a line to
    log when the window changed (None otherwise); a bad one is recorded (`camera_error`)
    and the node stops until a valid one arrives."""
    try:
      fovx, fovy = self.policy.layout["fovx_deg"], self.policy.layout["fovy_deg"]
      window, cam_fovx = camera_window(msg.height, msg.width, msg.k, fovx, fovy)
    except Exception as e:  # noqa: BLE001 - no crop from a bad CameraInfo
      self.window = self.camera_size = None
      self.camera_error = f"camera_info refused: {_fault(e)}"
      return None
    self.camera_error = None
    size = (int(msg.height), int(msg.width))
    if (window, size) == (self.window, self.camera_size):
      return None
    self.window, self.camera_size, self.camera_fovx = window, size, cam_fovx
    note = (f"field-of-view crop: rows {window[0]}, columns {window[1]} of "
            f"{size[0]}x{size[1]}")
    if fovx is not None and cam_fovx < fovx - 1.0:
      note += (f"; the camera sees {cam_fovx:.1f} deg across, the policy was trained with "
               f"{fovx:g} deg: it cannot be widened")
    return note

  def take_depth(self, msg, now_s: float) -> None:
    """A sensor_msgs/Image: checked (`image_metres`, its stamp), cropped to the field of
    view, resized to the policy's size; a refused one clears the image until the next."""
    self.depth = self.depth_stamp = None  # nothing is driven on until this one passes
    try:
      stamp = message_stamp(msg, now_s)
      stale = check_age(stamp, now_s, self.timeout, "depth image")
      if stale:
        raise Refused(stale)
      expect = self.camera_size if self.fov_crop else None
      if self.fov_crop and self.window is None:
        self.depth_error = None
        return  # waiting for camera_info: `decide` says so
      img = image_metres(msg.data, msg.encoding, msg.height, msg.width, msg.step,
                         msg.is_bigendian, expect)
      if self.fov_crop:
        (r0, r1), (c0, c1) = self.window
        img = img[r0:r1, c0:c1]
      self.depth = resize_nearest(img, self.policy.height, self.policy.width)
      self.depth_stamp, self.depth_error = stamp, None
    except Exception as e:  # noqa: BLE001 - never drive on an image that failed any check
      self.depth_error = f"depth image refused: {_fault(e)}"

  def take_imu(self, msg, now_s: float) -> None:
    """A sensor_msgs/Imu: its orientation's yaw (`imu_yaw`, REP 145) as the policy's yaw
    input; the first valid reading is the row entrance's reference. A refused one clears
    the yaw until the next."""
    self.yaw = self.yaw_stamp = None
    try:
      stamp = message_stamp(msg, now_s)
      stale = check_age(stamp, now_s, self.timeout, "IMU reading")
      if stale:
        raise Refused(stale)
      q = msg.orientation
      yaw = imu_yaw(q.x, q.y, q.z, q.w, getattr(msg, "orientation_covariance", None))
      if self.yaw_ref is None:  # the first reading: the robot stands at the row entrance
        self.yaw_ref = yaw
      self.imu_yaw = yaw
      self.yaw = self.policy.yaw_input(yaw, self.yaw_ref)
      self.yaw_stamp, self.imu_error = stamp, None
    except Exception as e:  # noqa: BLE001 - no yaw is better than a wrong one
      self.yaw = None
      self.imu_error = f"IMU reading refused: {_fault(e)}"

  def zero_heading(self) -> bool:
    """The robot faces down the next row from its entrance: measure yaw from the last
    valid IMU reading. False (nothing changed) without one."""
    if self.imu_yaw is None:
      return False
    self.yaw_ref = self.imu_yaw
    self.yaw = self.policy.yaw_input(self.imu_yaw, self.yaw_ref)
    self.v_prev = self.w_prev = 0.0
    self.row_ended = False  # a new row: the end-of-row detector starts afresh
    self.policy.reset_row()
    return True

  def invalidate(self, what: str, reason: str) -> None:
    """An input whose callback failed outside these checks (`what`: "depth", "imu" or
    "camera_info"): not driven on until the next valid one."""
    if what == "depth":
      self.depth, self.depth_error = None, reason
    elif what == "imu":
      self.yaw, self.imu_error = None, reason
    elif what == "camera_info":
      self.window = self.camera_size = None
      self.camera_error = reason

  # ----------------------------------------------------------------- command out

  def decide(self, now_s: float) -> Decision:
    """The command now: the policy's action on fresh valid inputs, else a stop with the
    reason. Never raises; the command is always finite."""
    try:
      d = self._decide(now_s)
      if not (math.isfinite(d.v) and math.isfinite(d.w)):  # the policy never gives it
        return _stop(f"non-finite command ({d.v}, {d.w})")
      return d
    except Exception as e:  # noqa: BLE001 - whatever failed, the robot stops
      return _stop(f"decision failed ({_fault(e)})")

  def _decide(self, now_s: float) -> Decision:
    if self.row_ended:
      return Decision(0.0, 0.0, "the end of the row: stop (zero_heading at the next row "
                      "drives again)", "info", True)
    for error in (self.camera_error if self.fov_crop else None, self.depth_error,
                  self.imu_error):
      if error is not None:
        return _stop(error)
    if self.fov_crop and self.window is None:
      return _stop("waiting for camera_info (fov_crop)", "warn")
    if self.depth is None or self.yaw is None:
      missing = " and ".join(n for n, v in (("depth image", self.depth), ("IMU yaw", self.yaw))
                             if v is None)
      return _stop(f"no fresh {missing}", "warn")
    for stamp, what in ((self.depth_stamp, "depth image"), (self.yaw_stamp, "IMU reading")):
      stale = check_age(stamp, now_s, self.timeout, what)
      if stale:
        return _stop(stale, "warn")
    # The previous command as the policy was trained on it: inside its action box (a
    # stop is outside a box whose v starts above 0).
    prev = np.clip([self.v_prev, self.w_prev], self.policy.low, self.policy.high)
    state = np.array([prev[0], prev[1], self.yaw], np.float32)
    try:
      if self.stop_at_row_end:
        (v, w), ended = self.policy.step(self.depth, state)
        if ended:
          self.row_ended = True
          return self._decide(now_s)
      else:
        v, w = self.policy(self.depth, state)
    except PolicyError as e:  # never the last action: it was for another view
      return _stop(f"policy refused its input: {_fault(e)}")
    if self.max_speed >= 0:
      v = min(v, self.max_speed)
    return Decision(float(v), float(w))

  def commanded(self, v: float, w: float) -> None:
    """What was published: the next decision's v_prev, w_prev."""
    self.v_prev, self.w_prev = float(v), float(w)
