"""NumpyPolicy refuses impossible input (PolicyInputError naming what it got and what it
expects), gives the actions of before on valid input; the ROS depth helpers; the ROS 2
node stops on a refused input. numpy only (no jax): fast."""

import math
import os
import re
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from mjxvine.deploy import numpy_policy as npp
from mjxvine.deploy.numpy_policy import NumpyPolicy, PolicyError, PolicyInputError
import ros_stubs
from conftest import NUMPY_ONLY_PRELUDE, parse_source

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "jackal.npz"

# A tiny policy with fixed random weights (the shipped model's layout: 41x41, 4 convs,
# mirror averaging): its actions below were computed by NumpyPolicy before the input
# checks, so they pin the behaviour on valid inputs whatever the shipped model becomes.
TINY_META = {"format_version": 1, "image_size": [41, 41], "max_depth_m": 5.0,
             "depth_scale": 0.2, "action_low": [0.0, -1.0], "action_high": [0.5, 1.0],
             "state_layout": ["v_prev", "w_prev", "yaw"], "yaw_reference": "start",
             "conv_layers": [[2, False], [1, True], [2, False], [1, False]], "num_hidden": 2,
             "tower_pad": [0, 0], "mirror_average": True, "control_dt": 0.1}
BEFORE = np.array([[0.47880304, 0.08492941], [0.4579079, -0.5988701],
                   [0.4466464, 0.540048], [0.46767643, -0.3040387]], np.float32)
BEFORE_PREPROCESSED = np.array([0.4538827, -0.10252142], np.float32)


def _tiny_arrays(seed=0, features=4, hidden=8):
  rng = np.random.default_rng(seed)
  f32 = lambda *shape, s=1.0: (rng.standard_normal(shape) * s).astype(np.float32)
  arrays, c = {}, 1
  for i in range(4):
    arrays[f"tower/conv{i}/kernel"] = f32(3, 3, c, features, s=0.5)
    arrays[f"tower/conv{i}/bias"] = f32(features, s=0.1)
    c = features
  width = features + 3
  for i in range(2):
    arrays[f"dense{i}/kernel"] = f32(width, hidden, s=0.7)
    arrays[f"dense{i}/bias"] = f32(hidden, s=0.1)
    width = hidden
  arrays["mean/kernel"] = f32(width, 2, s=0.7)
  arrays["mean/bias"] = f32(2, s=0.1)
  return arrays


def _tiny(**kw):
  return NumpyPolicy(_tiny_arrays(), dict(TINY_META), **kw)


def _tiny_inputs():
  """depth (4, 41, 41, 1) m in [0.3, 5], state (4, 3) in the box, yaws up to +-pi."""
  rng = np.random.default_rng(1)
  depth = rng.uniform(0.3, 5.0, (4, 41, 41, 1)).astype(np.float32)
  depth[:, :12] = 5.0
  depth[1, :, :10] = 0.8
  depth[2, 20:, 25:] = 1.2
  state = np.array([[0.0, 0.0, 0.0], [0.5, -1.0, 3.14159], [0.25, 1.0, -3.14159],
                    [0.1, -0.3, 1.0]], np.float32)
  return depth, state


@pytest.fixture(scope="module")
def policy():
  return NumpyPolicy.load(MODEL)


@pytest.fixture(scope="module")
def view(policy):
  """A valid (41, 41) image (m) and state of the shipped model."""
  depth = np.full((policy.height, policy.width), 3.0, np.float32)
  depth[:, : policy.width // 3] = 1.0
  return depth, np.array([0.2, 0.1, 0.3], np.float32)


def test_valid_inputs_give_the_actions_of_before():
  p = _tiny()
  depth, state = _tiny_inputs()
  np.testing.assert_allclose(p.action(depth, state), BEFORE, atol=1e-6)
  np.testing.assert_allclose(p.action(depth[..., 0].astype(np.float64), state.tolist()),
                             BEFORE, atol=1e-6)  # (B, H, W) float64, a list state
  for i in range(4):
    np.testing.assert_allclose(p(depth[i, ..., 0], state[i]), BEFORE[i], atol=1e-6)
  np.testing.assert_array_equal(p.action(depth, state, wrap_yaw=True), p.action(depth, state))
  # preprocess: NaN, inf, 0 and negative readings are no return (-> 5 m), 7 m is clipped
  raw = depth[0].copy()
  raw[3, 4], raw[5, 6], raw[7, 8], raw[9, 10], raw[11, 12], raw[13, 14] = (
      np.nan, 0.0, 7.0, -np.inf, -1.0, np.inf)
  np.testing.assert_allclose(p.action(raw, state[3], preprocess=True), BEFORE_PREPROCESSED,
                             atol=1e-6)
  np.testing.assert_allclose(_tiny(preprocess=True).action(raw, state[3]),
                             BEFORE_PREPROCESSED, atol=1e-6)
  # the whole accepted range still acts: 0 m, 2 x max_depth, the tolerances
  edge = np.full((41, 41), 10.0, np.float32)
  edge[:5] = 0.0
  p(edge, [0.5 + 0.02, -1.0 - 0.09, -np.float32(np.pi)])
  p(edge, [-0.02, 1.09, np.float32(np.pi)])


def test_negative_depth_is_refused(policy, view):
  state = view[1]
  with pytest.raises(PolicyInputError, match=r"1681 pixels below 0 m \(min -3 m\): expected "
                     r"metres in \[0, 10\]"):
    policy(np.full((41, 41), -3.0, np.float32), state)
  one = view[0].copy()
  one[4, 5] = -0.01
  with pytest.raises(PolicyInputError, match=r"1 pixels below 0 m \(min -0.01 m\)"):
    policy(one, state)


def test_depth_beyond_the_bound_is_refused(policy, view):
  """Without preprocessing depth may reach 2 x max_depth_m (10 m here), no further."""
  state = view[1]
  assert policy.depth_limit == 2 * policy.max_depth == 10.0
  with pytest.raises(PolicyInputError, match=r"1681 pixels above 10 m \(max 1e\+06 m\): "
                     r"expected metres in \[0, 10\] \(2 x max_depth_m 5 m\). Millimetres"):
    policy(np.full((41, 41), 1e6, np.float32), state)
  mm = view[0] * 1000.0  # millimetres passed as metres
  with pytest.raises(PolicyInputError, match=r"max 3000 m.*expected metres in \[0, 10\]"):
    policy(mm, state)
  far = view[0].copy()
  far[0, 0] = 7.0  # beyond the range but possible: passes, unclipped, as before
  policy(far, state)
  far[0, 0] = 10.5
  with pytest.raises(PolicyInputError, match="1 pixels above 10 m"):
    policy(far, state)


def test_non_finite_depth_is_refused_without_preprocess(policy, view):
  bad = view[0].copy()
  bad[1, 2], bad[3, 4] = np.nan, -np.inf
  with pytest.raises(PolicyInputError, match=r"2 NaN/inf pixels: expected finite metres; "
                     r"pass preprocess=True"):
    policy(bad, view[1])


def test_preprocess_refuses_what_no_sensor_gives(policy, view):
  state = view[1]
  with pytest.raises(PolicyInputError, match=r"1681 readings above 1000 m \(max 1e\+06 m\): "
                     r"expected metres"):
    policy(np.full((41, 41), 1e6, np.float32), state, preprocess=True)
  with pytest.raises(PolicyInputError, match=r"max 3000 m"):  # millimetres as metres
    policy(view[0] * 1000.0, state, preprocess=True)
  # no reading at all: garbage, a covered lens or an unplugged sensor
  for blind in (np.full((41, 41), -3.0), np.zeros((41, 41)), np.full((41, 41), np.nan)):
    with pytest.raises(PolicyInputError, match=r"without a single reading .*: expected some "
                       r"pixels in \(0, 1000\] m"):
      policy(blind, state, preprocess=True)
  batch = np.stack([view[0], np.zeros((41, 41), np.float32)])
  with pytest.raises(PolicyInputError, match=r"\(batch row 1\) without a single reading"):
    policy(batch, np.stack([state, state]), preprocess=True)
  # 50 m (a far 16UC1 reading) is a real sensor's: clipped to max_depth as before
  far = view[0].copy()
  far[:10] = 50.0
  clipped = far.copy()
  clipped[:10] = policy.max_depth
  np.testing.assert_array_equal(policy(far, state, preprocess=True), policy(clipped, state))
  # clean_depth itself still refuses nothing
  assert (policy.clean_depth(np.full((2, 2), -3.0)) == policy.max_depth).all()


def test_integer_depth_needs_depth_scale(policy, view):
  depth, state = view
  counts = np.round(depth * 1000.0).astype(np.uint16)  # millimetres
  for ints in (counts, counts.astype(np.int32)):
    with pytest.raises(PolicyInputError, match=rf"dtype {ints.dtype} without a unit: expected "
                       r"float metres, or give depth_scale \(metres per count, 0.001"):
      policy(ints, state)
  mm = NumpyPolicy.load(MODEL, depth_scale=0.001)
  assert mm.depth_scale == 0.001 and policy.depth_scale is None
  metres = counts.astype(np.float32) * np.float32(0.001)
  np.testing.assert_array_equal(mm(counts, state), policy(metres, state))
  np.testing.assert_array_equal(mm(counts.astype(np.int32), state), policy(metres, state))
  np.testing.assert_array_equal(mm(depth, state), policy(depth, state))  # floats: metres
  # 0 mm, no return: with preprocess the maximum range, as for float images
  counts[:3] = 0
  pre = NumpyPolicy.load(MODEL, depth_scale=0.001, preprocess=True)
  metres[:3] = np.nan
  np.testing.assert_array_equal(pre(counts, state), policy(metres, state, preprocess=True))
  for bad in (0.0, -0.001, float("nan"), float("inf")):
    with pytest.raises(PolicyInputError, match=r"depth_scale .*: expected metres per count > 0"):
      NumpyPolicy.load(MODEL, depth_scale=bad)


def test_yaw_out_of_range_is_refused_unless_wrapped(policy, view):
  depth, state = view
  for yaw, shown in ((1e9, "1e+09"), (3.2, "3.2"), (-4.0, "-4")):
    with pytest.raises(PolicyInputError, match=rf"state yaw {re.escape(shown)} rad: expected "
                       r"\[-pi, pi\] rad.*wrap_yaw=True"):
      policy(depth, [0.2, 0.1, yaw])
  wrapped = math.remainder(1e9, 2 * math.pi)  # in [-pi, pi]
  expected = policy(depth, [0.2, 0.1, wrapped])
  np.testing.assert_allclose(policy(depth, [0.2, 0.1, 1e9], wrap_yaw=True), expected, atol=1e-6)
  loaded = NumpyPolicy.load(MODEL, wrap_yaw=True)
  np.testing.assert_allclose(loaded(depth, [0.2, 0.1, 1e9]), expected, atol=1e-6)
  with pytest.raises(PolicyInputError, match="state yaw"):
    loaded(depth, [0.2, 0.1, 1e9], wrap_yaw=False)
  np.testing.assert_allclose(policy(depth, [0.2, 0.1, 3 * math.pi / 2], wrap_yaw=True),
                             policy(depth, [0.2, 0.1, -math.pi / 2]), atol=1e-6)
  for edge in (math.pi, -math.pi, np.float32(math.pi)):  # float32(pi) > math.pi
    policy(depth, [0.2, 0.1, edge])
  with pytest.raises(PolicyInputError, match="state has NaN or inf"):
    policy(depth, [0.2, 0.1, np.inf], wrap_yaw=True)


def test_previous_command_out_of_the_action_box_is_refused(policy, view):
  depth = view[0]
  for state, match in (([-0.5, 0.0, 0.0], r"state v_prev -0.5 m/s: expected \[0, 0.5\] m/s"),
                       ([0.9, 0.0, 0.0], r"state v_prev 0.9 m/s: expected \[0, 0.5\] m/s"),
                       ([0.2, 1.5, 0.0], r"state w_prev 1.5 rad/s: expected \[-1, 1\] rad/s"),
                       ([0.2, -57.3, 0.0], r"state w_prev -57.3 rad/s")):  # deg/s
    with pytest.raises(PolicyInputError, match=match + ".*action box"):
      policy(depth, state)
  batch = np.array([[0.1, 0.0, 0.0], [0.1, 2.0, 0.0]])
  with pytest.raises(PolicyInputError, match=r"w_prev 2 rad/s \(batch row 1\)"):
    policy(np.stack([depth, depth]), batch)
  assert policy.state_layout == ["v_prev", "w_prev", "yaw"]


def test_empty_batches_and_wrong_dtypes_are_refused(policy, view):
  depth, state = view
  with pytest.raises(PolicyInputError, match=r"empty batch: depth of shape \(0, 41, 41\); "
                     r"expected B >= 1"):
    policy(np.zeros((0, 41, 41), np.float32), np.zeros((0, 3), np.float32))
  for bad, dtype in (("abc", "<U3"), (["a", "b", "c"], "<U1"), (None, "object"),
                     ([0.2, 0.1, None], "object"), (np.array([1, 0, 0], bool), "bool"),
                     (np.zeros(3, complex), "complex128")):
    with pytest.raises(PolicyInputError, match=rf"state of dtype {dtype}: expected numbers "
                       r"\[v_prev, w_prev, yaw\]"):
      policy(depth, bad)
  for bad, dtype in ((depth.astype(bool), "bool"), (depth.astype(complex), "complex128"),
                     (depth.astype(str), "<U32"), (np.full((41, 41), None), "object")):
    with pytest.raises(PolicyInputError, match=rf"depth image of dtype {dtype}: expected "
                       r"float metres \(or integers with depth_scale\)"):
      policy(bad, state)
  with pytest.raises(PolicyInputError, match=r"state is not an array .*: expected numbers"):
    policy(depth, [[0.2, 0.1], [0.3]])  # ragged
  policy(depth, [0, 0, 0])  # integers are numbers
  assert issubclass(PolicyInputError, PolicyError) and issubclass(PolicyInputError, ValueError)


def test_checks_are_cheap():
  """The checks are a few vectorised passes: far under a millisecond on a 112x112 image
  (the bound is loose: a shared CI machine)."""
  meta = dict(TINY_META, image_size=[112, 112])
  p = NumpyPolicy(_tiny_arrays(), meta)
  depth = np.full((112, 112), 3.0, np.float32)
  state = np.array([0.2, 0.1, 0.3], np.float32)
  for pre in (False, True):
    times = []
    for _ in range(50):
      t = time.perf_counter()
      p._check(depth, state, pre, False)  # pylint: disable=protected-access
      times.append(time.perf_counter() - t)
    assert sorted(times)[25] < 2e-3, (pre, sorted(times)[25])


def test_ros_depth_helpers():
  mm = np.array([[0, 1000, 2500], [65535, 1, 300]], np.uint16)
  got = npp.ros_depth_to_metres(mm, "16UC1")
  assert got.dtype == np.float32 and np.isnan(got[0, 0])  # 0 mm: no return
  np.testing.assert_allclose(got[~np.isnan(got)], [1.0, 2.5, 65.535, 0.001, 0.3], rtol=1e-6)
  metres = np.array([[np.nan, 1.5], [0.0, np.inf]], np.float32)
  passed = npp.ros_depth_to_metres(metres, "32FC1")
  np.testing.assert_array_equal(passed, metres)  # as sent: the policy judges it
  # sensor_msgs/Image fields: little and big endian, rows padded (step > width x 2)
  data = np.zeros((2, 4), "<u2")
  data[:, :3] = mm
  got_le = npp.depth_from_ros(data.tobytes(), "16UC1", 2, 3, step=8)
  np.testing.assert_array_equal(got_le, got)
  got_be = npp.depth_from_ros(mm.astype(">u2").tobytes(), "16UC1", 2, 3, is_bigendian=True)
  np.testing.assert_array_equal(got_be, got)
  import array
  got_arr = npp.depth_from_ros(array.array("B", metres.tobytes()), "32FC1", 2, 2)  # rclpy's
  np.testing.assert_array_equal(got_arr, metres)
  np.testing.assert_array_equal(npp.depth_from_ros(list(metres.tobytes()), "32FC1", 2, 2),
                                metres)
  for encoding in ("mono16", "bgr8", "32FC2", "16SC1", ""):
    with pytest.raises(PolicyInputError, match=rf"encoding '{encoding}': expected one of 16UC1, "
                       "32FC1"):
      npp.depth_from_ros(b"\0" * 16, encoding, 2, 2)
    with pytest.raises(PolicyInputError, match="expected one of 16UC1, 32FC1"):
      npp.ros_depth_to_metres(mm, encoding)
  with pytest.raises(PolicyInputError, match=r"16UC1 image of 10 bytes, height 2, width 3, "
                     r"step 6: expected height x step >= 2 x 6 bytes"):
    npp.depth_from_ros(b"\0" * 10, "16UC1", 2, 3)
  with pytest.raises(PolicyInputError, match="16UC1 depth image of dtype float32: expected uint16"):
    npp.ros_depth_to_metres(metres, "16UC1")
  with pytest.raises(PolicyInputError, match="32FC1 depth image of dtype uint16: expected float32"):
    npp.ros_depth_to_metres(mm, "32FC1")


def test_ros_image_through_the_policy(policy, view):
  """16UC1 millimetres -> metres, no return -> the maximum range with preprocess."""
  depth, state = view
  counts = np.round(depth * 1000.0).astype("<u2")
  counts[:5] = 0
  img = npp.depth_from_ros(counts.tobytes(), "16UC1", 41, 41)
  expected = depth.copy()
  expected[:5] = policy.max_depth
  np.testing.assert_allclose(policy(img, state, preprocess=True), policy(expected, state),
                             atol=1e-6)
  with pytest.raises(PolicyInputError, match="205 NaN/inf pixels"):  # 0 mm without preprocess
    policy(img, state)


_ALONE = NUMPY_ONLY_PRELUDE + textwrap.dedent("""
  import numpy as np
  from mjxvine_deploy import (NumpyPolicy, PolicyInputError, depth_from_ros,
                              ros_depth_to_metres)
  policy = NumpyPolicy.load(sys.argv[1])
  depth = np.full((41, 41), 3.0, np.float32)
  for bad in (depth.astype(np.uint16), -depth, depth * 1e6):
    try:
      policy(bad, np.zeros(3))
    except PolicyInputError as e:
      pass
    else:
      raise AssertionError("not refused")
  img = depth_from_ros(np.full((41, 41), 3000, "<u2").tobytes(), "16UC1", 41, 41)
  assert np.allclose(policy(img, [0.0, 0.0, 0.0]), policy(depth, [0.0, 0.0, 0.0]), atol=1e-6)
  assert not [m for m in sys.modules if m.split(".")[0] in BLOCKED + ("mjxvine",)]
  print("ok")
""")


def test_the_policy_file_alone_checks_inputs_with_numpy_only(tmp_path):
  """numpy_policy.py copied alone (as mjxvine_deploy.py) refuses bad input and reads ROS
  images with numpy and the standard library only, and parses as Python 3.8."""
  import shutil

  src = Path(npp.__file__)
  parse_source(src.read_text(), feature_version=(3, 8))
  shutil.copy(src, tmp_path / "mjxvine_deploy.py")
  env = dict(os.environ, OPENBLAS_NUM_THREADS="1", PYTHONPATH=str(tmp_path))
  out = subprocess.run([sys.executable, "-c", _ALONE, str(MODEL)], capture_output=True,
                       text=True, env=env, timeout=60, cwd=tmp_path)
  assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


# ---------------------------------------------------------------- the ROS 2 node, no ROS

@pytest.fixture
def node(monkeypatch):
  """A VineyardNode of examples/ros2_vineyard_node.py on stub rclpy and message modules,
  driving models/jackal.npz without fov_crop."""
  return ros_stubs.load_node_module(
      monkeypatch, {"policy": str(MODEL), "fov_crop": False}).VineyardNode()


def _image(counts, encoding="16UC1"):
  counts = np.asarray(counts, "<u2")
  return SimpleNamespace(data=counts.tobytes(), encoding=encoding, height=counts.shape[0],
                         width=counts.shape[1], step=2 * counts.shape[1], is_bigendian=0)


def _imu(yaw):
  return SimpleNamespace(orientation=SimpleNamespace(x=0.0, y=0.0, z=math.sin(yaw / 2),
                                                     w=math.cos(yaw / 2)))


def _command(node):
  node.on_timer()
  twist = node.published[-1]
  return twist.linear.x, twist.angular.z


def test_ros2_node_stops_on_a_refused_input(node):
  """A bad encoding, an image without a reading or an impossible state: a stop (0, 0),
  not the last action, with the reason logged (throttled); valid input drives again."""
  policy = NumpyPolicy.load(MODEL, preprocess=True)
  counts = np.full((41, 41), 5000)  # far above the horizon, the ground nearer below it
  counts[20:] = np.linspace(5000, 1000, 21).round()[:, None]
  node.on_imu(_imu(0.4))  # the row entrance
  node.on_imu(_imu(0.6))
  node.on_depth(_image(counts))
  v, w = _command(node)
  expected = policy(counts * np.float32(0.001), [0.0, 0.0, 0.2])
  np.testing.assert_allclose((v, w), expected, atol=1e-5)
  assert v > 0.05  # it drives: a stop below is not the last action by chance

  def assert_stops(reason):
    node.t += 0.1
    assert _command(node) == (0.0, 0.0)
    level, msg, kw = node.get_logger().records[-1]
    assert level == "error" and reason in msg and kw["throttle_duration_sec"] > 0, msg
    assert (node.v_prev, node.w_prev) == (0.0, 0.0)

  node.on_depth(_image(counts, encoding="mono16"))  # maybe an IR image: never as depth
  assert_stops("encoding 'mono16': expected one of 16UC1, 32FC1")
  node.on_depth(_image(np.zeros((41, 41))))  # a covered lens: no reading at all
  assert_stops("without a single reading")
  node.on_depth(_image(counts))
  node.t += 0.1
  assert _command(node)[0] > 0.05  # valid again: drives (from v_prev 0)
  node.yaw = 1e9  # what no IMU gives: refused by the policy itself
  assert_stops("policy refused its input: state yaw 1e+09 rad")
