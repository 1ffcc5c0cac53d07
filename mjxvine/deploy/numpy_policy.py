"""Run an exported actor with numpy alone (no jax, flax, mujoco or brax): for the robot.

    from mjxvine.deploy import NumpyPolicy
    policy = NumpyPolicy.load("policy.npz")
    v, w = policy(depth, state)      # depth (112, 112[, 1]) metres, state [v_prev, w_prev, yaw]
    v, w = policy(depths, states)    # batched: (B, 112, 112[, 1]) and (B, 3) -> (B,), (B,)

This file is the whole numpy policy: it imports only numpy and the standard library and
runs on Python 3.8+ (ROS 2 Humble's 3.10 included), so a robot needs no mjxvine install:
copy it there (e.g. as mjxvine_deploy.py) with the policy file.

The action is the deterministic test-time action of SAC: the tanh-squashed mean mapped
onto the action box; for a file with `mirror_average` (`sac.mirror_average`), the mean
of that action and the mirrored action on the mirrored image (one batch of two). Files
are written by `mjxvine.deploy.export.export_actor`. Each conv is an im2col (a strided view
copied into a preallocated buffer) and a single matmul; `python -m mjxvine.latency
policy.npz` times one decision on the machine at hand (measured numbers are in
docs/results/). On a busy CPU use one BLAS thread: OPENBLAS_NUM_THREADS=1 set before
numpy is imported, or `NumpyPolicy.load(path, blas_threads=1)` with threadpoolctl
installed: extra OpenBLAS threads that must wait for a core make each decision several
times slower. Calls are thread-safe (buffers are per thread).

Input contract. An input the policy was not trained for gets no action: it raises
`PolicyInputError` (a `PolicyError`, a `ValueError`) saying what was received and what is
expected; file problems raise `PolicyFormatError`. A robot should stop on either. The
checks are a few vectorised min/max passes (microseconds at 20 Hz).

- depth: (H, W), (H, W, 1), (B, H, W) or (B, H, W, 1) with B >= 1, H x W the metadata's
  `image_size`. Floating-point arrays are metres. Integer arrays (a sensor's counts, e.g.
  uint16 millimetres) need `depth_scale`, metres per count (0.001 for millimetres), given
  to `load`; without it they are refused, as a unit cannot be guessed. Booleans,
  strings, objects and complex numbers are refused. (The metadata key "depth_scale" is
  something else: the network's input multiplier, 1 / max_depth_m, `input_scale` here.)
- preprocess=False (the default): the image must be what the simulated sensor gives, in
  [0, depth_limit] m: no NaN/inf, nothing below 0 m, and nothing above
  `depth_limit` = DEPTH_LIMIT_FACTOR (2) x `max_depth_m` (10 m for a 5 m camera). Training
  images are clipped to [0, max_depth_m]; readings up to twice that pass unchanged, as
  before (the first layer sees at most twice its trained input), further ones are not
  the sensor's image (a raw image wants preprocess=True) or in another unit (millimetres
  read as metres are ~1000x too large).
- preprocess=True (a raw sensor image): NaN, inf and readings <= 0 m, a real sensor's
  "no return", become `invalid_depth` (default `max_depth_m`, what the simulator shows
  for a ray that hits nothing; never 0 m, which the policy would read as an obstacle at
  the lens), then the image is clipped to [0, max_depth_m]. Finite readings above
  SENSOR_DEPTH_LIMIT_M (1000 m) are refused: no depth camera measures that far (16UC1
  tops out at 65.535 m); it is a unit error. An image with no reading at all (every pixel
  NaN, inf or <= 0: a covered lens, an unplugged sensor, garbage such as -3 m everywhere)
  is refused too: the simulated camera always sees the ground. So negative readings are
  "no return" only with preprocess=True; without it they are refused.
- state: numbers (float or int), shape (S,) or (B, S), finite, in the order of the
  metadata's `state_layout` (v_prev m/s, w_prev rad/s, yaw rad). v_prev and w_prev are
  the previous command, within the action box (`action_low`..`action_high`) widened by
  STATE_TOLERANCE (5 %) of its width each side. yaw must lie in [-pi, pi] (+-1e-3 rad,
  float32 rounding): `yaw_input` gives it wrapped; `wrap_yaw=True` (on `load` or per
  call) wraps yaws outside [-pi, pi] into [-pi, pi) instead of refusing them.
- ROS images: `ros_depth_to_metres(array, encoding)` and `depth_from_ros(data, encoding,
  height, width, step, is_bigendian)` read 16UC1 (millimetres; 0, no return, -> NaN) and
  32FC1 (metres, passed through) as float32 metres; other encodings are refused.
"""

from __future__ import annotations

import json
import math
import threading
import zipfile
from pathlib import Path

import numpy as np
from numpy.lib.stride_tricks import as_strided

FORMAT_VERSION = 1
META_KEY = "__meta__"
# The left-right mirror image of the state [v_prev, w_prev, yaw] and the action [v, w]
# (depth columns reversed): also what `mjxvine.env.VineyardEnv.mirror_obs` /
# `mirror_action` use in training.
MIRROR_STATE_SIGN = np.array([1.0, -1.0, -1.0], np.float32)
MIRROR_ACTION_SIGN = np.array([1.0, -1.0], np.float32)
# Input bounds (the module docstring's input contract). Without preprocessing depth may
# reach this many times max_depth_m (training images are clipped at 1x).
DEPTH_LIMIT_FACTOR = 2.0
# With preprocessing, finite readings above this (m) are refused: no depth sensor reads
# that far (16UC1 millimetres end at 65.535 m), so it is a unit error.
SENSOR_DEPTH_LIMIT_M = 1000.0
# v_prev / w_prev may leave the action box by this fraction of its width each side
# (a measured speed or float rounding instead of the exact previous command).
STATE_TOLERANCE = 0.05
# yaw in [-pi, pi] up to this (rad): float32(pi) is above math.pi.
YAW_TOLERANCE = 1e-3
STATE_UNITS = {"v_prev": "m/s", "w_prev": "rad/s", "yaw": "rad"}
# ROS sensor_msgs/Image depth encodings (REP 118): (dtype, metres per count or None for
# metres); 16UC1 0 means no return.
ROS_DEPTH_ENCODINGS = {"16UC1": (np.uint16, 0.001), "32FC1": (np.float32, None)}


class PolicyError(ValueError):
  """A policy cannot be loaded or does not fit its use: the base class of the errors of
  `NumpyPolicy`, also raised by the evaluation policies (`mjxvine.evaluation.policies`)."""


class PolicyFormatError(PolicyError):
  """The policy file is unreadable, of another format version, or incomplete."""


class PolicyInputError(PolicyError):
  """An input to the policy is impossible or outside what it was trained for: wrong
  shape, dtype or unit, non-finite, or out of range (the module's input contract)."""


def _windows(x: np.ndarray, ho: int, wo: int, stride: int) -> np.ndarray:
  """The 3x3 windows of x (B, H, W, C) as a strided view (B, ho, wo, 3, 3, C)."""
  sb, sh, sw, sc = x.strides
  return as_strided(x, (x.shape[0], ho, wo, 3, 3, x.shape[3]),
                    (sb, sh * stride, sw * stride, sh, sw, sc), writeable=False)


class _ConvWork:
  """Preallocated buffers of one conv layer for one input shape (B, H, W, C).

  cols (B ho wo, 9 C + 1) float32 whose last column is 1 (the bias row of the kernel),
  with `patches` a (B, ho, wo, 3, 3, C) view of its first 9 C columns; out (B ho wo, F).
  With `pool` only the even-sized part of the output that a 2x2 max pool reads is used.
  """

  def __init__(self, shape: tuple[int, ...], features: int, stride: int, pool: bool):
    b, h, w, c = shape
    ho, wo = (h - 3) // stride + 1, (w - 3) // stride + 1
    if ho < 1 or wo < 1:
      raise PolicyInputError(f"image too small for the conv tower (a layer sees {h}x{w})")
    if pool:
      ho, wo = ho // 2 * 2, wo // 2 * 2
    self.stride, self.ho, self.wo = stride, ho, wo
    self.cols = np.ones((b * ho * wo, 9 * c + 1), np.float32)
    row = self.cols.strides[0]
    self.patches = as_strided(self.cols, (b, ho, wo, 3, 3, c),
                              (row * ho * wo, row * wo, row, 12 * c, 4 * c, 4))
    self.out = np.empty((b * ho * wo, features), np.float32)
    self.out4 = self.out.reshape(b, ho, wo, features)

  def __call__(self, x: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """x (B, H, W, C) -> conv + bias, without ReLU: (B, ho, wo, F) (a reused buffer)."""
    np.copyto(self.patches, _windows(x, self.ho, self.wo, self.stride))
    np.matmul(self.cols, kernel, out=self.out)
    return self.out4


def _maxpool2(x: np.ndarray) -> np.ndarray:
  """2x2 max pool, stride 2, of an even-sized (B, H, W, C) -> (B, H / 2, W / 2, C)."""
  top = np.maximum(x[:, 0::2, 0::2], x[:, 0::2, 1::2])
  return np.maximum(top, np.maximum(x[:, 1::2, 0::2], x[:, 1::2, 1::2]), out=top)


def read_policy_file(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
  """(arrays, meta) of an .npz policy file; `PolicyFormatError` if unreadable/another version."""
  path = Path(path)
  if not path.is_file():
    raise PolicyFormatError(f"{path}: no such policy file")
  invalid = f"{path}: not a valid policy file"
  # numpy reads a file that is not a zip archive as a pickle, and its error then suggests
  # allow_pickle=True: check the container first.
  if not zipfile.is_zipfile(path):
    raise PolicyFormatError(f"{invalid} (not an .npz archive)")
  try:
    with np.load(path, allow_pickle=False) as data:
      arrays = {k: data[k] for k in data.files}
  except Exception as e:  # noqa: BLE001 - a truncated or corrupted archive, object arrays
    text = str(e).splitlines()[0][:160] if str(e) else type(e).__name__
    if "allow_pickle" in text:  # numpy's hint to load pickles: never right for a policy
      text = "holds pickled object arrays"
    raise PolicyFormatError(f"{invalid} ({text})") from None
  if META_KEY not in arrays:
    raise PolicyFormatError(f"{invalid} (no {META_KEY} entry: not an mjxvine policy file)")
  try:
    meta = json.loads(str(arrays.pop(META_KEY)))
    if not isinstance(meta, dict):
      raise ValueError(f"a JSON {type(meta).__name__}, not an object")
  except ValueError as e:
    raise PolicyFormatError(f"{invalid} (unreadable metadata: {e})") from None
  version = meta.get("format_version")
  if version != FORMAT_VERSION:
    raise PolicyFormatError(f"{path}: policy format version {version!r}; this mjxvine reads "
                            f"version {FORMAT_VERSION} (re-export the checkpoint)")
  return arrays, meta


def set_blas_threads(n: int) -> bool:
  """Limits numpy's BLAS to `n` threads for the whole process, via threadpoolctl.

  Returns False (and changes nothing) when threadpoolctl is not installed; then set
  OPENBLAS_NUM_THREADS / OMP_NUM_THREADS before numpy is imported instead.
  """
  try:
    from threadpoolctl import threadpool_limits  # optional
  except ImportError:
    return False
  threadpool_limits(int(n), user_api="blas")
  return True


def _numbers(x, what: str, expected: str) -> np.ndarray:
  """x as an array of real numbers (float, int or uint dtype); else PolicyInputError."""
  try:
    a = np.asarray(x)
  except (TypeError, ValueError) as e:  # ragged nested lists and the like
    raise PolicyInputError(f"{what} is not an array ({e}): expected {expected}") from None
  if a.dtype.kind not in "fiu":
    raise PolicyInputError(f"{what} of dtype {a.dtype}: expected {expected}")
  return a


def _ros_encoding(encoding: str) -> tuple[type, float | None]:
  """(dtype, metres per count or None for metres) of a ROS depth encoding."""
  if encoding not in ROS_DEPTH_ENCODINGS:
    raise PolicyInputError(f"depth image encoding {encoding!r}: expected one of "
                           f"{', '.join(ROS_DEPTH_ENCODINGS)} (REP 118 depth)")
  return ROS_DEPTH_ENCODINGS[encoding]


def ros_depth_to_metres(array, encoding: str) -> np.ndarray:
  """A decoded ROS depth image (e.g. from cv_bridge), any shape -> float32 metres.

  encoding: "16UC1" (uint16 millimetres; 0, no return, -> NaN, which preprocess=True maps
  to `invalid_depth` and preprocess=False refuses) or "32FC1" (float32 metres, passed
  through: its NaN/inf/0 are left to the policy). Other encodings: PolicyInputError.
  """
  dtype, scale = _ros_encoding(encoding)
  kinds = "iu" if scale is not None else "f"
  a = _numbers(array, f"{encoding} depth image", f"{np.dtype(dtype)} values")
  if a.dtype.kind not in kinds:
    raise PolicyInputError(f"{encoding} depth image of dtype {a.dtype}: expected "
                           f"{np.dtype(dtype)}")
  if scale is None:
    return np.asarray(a, np.float32)
  metres = a.astype(np.float32) * np.float32(scale)
  metres[a == 0] = np.nan  # no return
  return metres


def depth_from_ros(data, encoding: str, height: int, width: int, step: int = 0,
                   is_bigendian: bool = False) -> np.ndarray:
  """A sensor_msgs/Image's fields -> (height, width) float32 metres, as
  `ros_depth_to_metres` (16UC1 mm with 0 -> NaN, 32FC1 m); data is its bytes (bytes,
  array.array or a buffer), step its row length in bytes (0: width x pixel size).
  A bad encoding or a buffer too short for the size: PolicyInputError."""
  dtype = np.dtype(_ros_encoding(encoding)[0]).newbyteorder(">" if is_bigendian else "<")
  height, width = int(height), int(width)
  row = width * dtype.itemsize
  step = int(step) or row
  try:
    raw = np.frombuffer(data, np.uint8)
  except TypeError:  # a list of byte values
    raw = np.asarray(data, np.uint8).ravel()
  if height < 1 or width < 1 or step < row or raw.size < height * step:
    raise PolicyInputError(f"{encoding} image of {raw.size} bytes, height {height}, width "
                           f"{width}, step {step}: expected height x step >= "
                           f"{height} x {row} bytes")
  rows = raw[: height * step].reshape(height, step)[:, :row]
  pixels = np.ascontiguousarray(rows).view(dtype).astype(dtype.newbyteorder("="))
  return ros_depth_to_metres(pixels, encoding)


def fov_window(size: int, focal: float, centre: float, fov_deg: float) -> tuple[int, int]:
  """The pixel range [start, stop) of one image axis that spans `fov_deg` degrees around
  the optical axis, for a pinhole camera of `size` pixels with focal length `focal` and
  principal point `centre` (pixels; from a CameraInfo's K: fx, cx or fy, cy). The whole
  axis when the camera's field of view is not wider than `fov_deg`."""
  half = focal * math.tan(math.radians(fov_deg) / 2.0)
  start = max(0, int(round(centre - half)))
  stop = min(size, int(round(centre + half)))
  return (start, stop) if stop - start >= 1 else (0, size)


class NumpyPolicy:
  """The actor's deterministic action, in numpy. Build with `NumpyPolicy.load(path)`."""

  def __init__(self, arrays: dict[str, np.ndarray], meta: dict, preprocess: bool = False,
               invalid_depth: float | None = None, depth_scale: float | None = None,
               wrap_yaw: bool = False):
    """Use `load` (its arguments). `arrays` maps "tower/conv0/kernel" etc. to float32
    arrays."""
    self.meta = meta
    self.preprocess = preprocess
    self.wrap_yaw = bool(wrap_yaw)
    # metres per count of integer depth images (None: integer images are refused)
    if depth_scale is not None:
      depth_scale = float(depth_scale)
      if not (math.isfinite(depth_scale) and depth_scale > 0.0):
        raise PolicyInputError(f"depth_scale {depth_scale!r}: expected metres per count > 0 "
                               "(0.001 for millimetres)")
    self.depth_scale = depth_scale
    try:
      self.height, self.width = (int(v) for v in meta["image_size"])
      self.max_depth = float(meta["max_depth_m"])
      # what preprocessing puts where the sensor has no reading: by default the maximum
      # range, as the simulator renders a ray that hits nothing
      self.invalid_depth = self.max_depth if invalid_depth is None else float(invalid_depth)
      # the network's input multiplier (1 / m, metadata "depth_scale"), not `depth_scale`
      self.input_scale = float(meta.get("depth_scale", 1.0))
      # largest depth accepted without preprocessing (m): the module's input contract
      self.depth_limit = DEPTH_LIMIT_FACTOR * self.max_depth
      self.low = np.asarray(meta["action_low"], np.float32)
      self.high = np.asarray(meta["action_high"], np.float32)
      layers = [(int(s), bool(p)) for s, p in meta["conv_layers"]]
      # bottom / right edge padding of the tower (files written before it existed: none)
      self.tower_pad = tuple(int(v) for v in meta.get("tower_pad", (0, 0)))
      # the mean of the actions on the image and on its mirror (files before it: no)
      self.mirror_average = bool(meta.get("mirror_average", False))
      num_hidden = int(meta["num_hidden"])
    except (KeyError, TypeError, ValueError) as e:
      raise PolicyFormatError(f"policy metadata is incomplete or invalid: {e!r}") from None
    need = [f"tower/conv{i}/{p}" for i in range(len(layers)) for p in ("kernel", "bias")]
    need += [f"dense{i}/{p}" for i in range(num_hidden) for p in ("kernel", "bias")]
    need += ["mean/kernel", "mean/bias"]
    missing = [n for n in need if n not in arrays]
    if missing:
      raise PolicyFormatError(f"policy file lacks arrays: {', '.join(missing)}")
    f32 = lambda n: np.ascontiguousarray(arrays[n], np.float32)

    def check(name, shape):
      for suffix, want in (("kernel", shape), ("bias", shape[-1:])):
        got = arrays[f"{name}/{suffix}"].shape
        if got != want:
          raise PolicyFormatError(f"{name}/{suffix} has shape {got}, expected {want}")

    self._convs, channels = [], 1
    for i, (stride, pool) in enumerate(layers):
      features = arrays[f"tower/conv{i}/kernel"].shape[-1]
      check(f"tower/conv{i}", (3, 3, channels, features))
      k = f32(f"tower/conv{i}/kernel")
      if i == 0:  # fold the input scaling into the first kernel
        k = k * np.float32(self.input_scale)
      # The bias is the last row: im2col buffers carry a column of ones.
      kernel = np.concatenate([k.reshape(-1, features), f32(f"tower/conv{i}/bias")[None]])
      self._convs.append((np.ascontiguousarray(kernel), pool))
      channels = features
    self._layers = layers
    self._local = threading.local()  # per-thread buffers, keyed by input shape
    self.state_size = arrays["dense0/kernel"].shape[0] - channels
    if self.state_size <= 0:
      raise PolicyFormatError("dense0/kernel is too small for the conv features")
    width = channels + self.state_size
    self._dense = []
    for i in range(num_hidden):
      hidden = arrays[f"dense{i}/kernel"].shape[-1]
      check(f"dense{i}", (width, hidden))
      self._dense.append((f32(f"dense{i}/kernel"), f32(f"dense{i}/bias")))
      width = hidden
    if self.low.ndim != 1 or self.low.shape != self.high.shape:
      raise PolicyFormatError(f"bad action box {self.low.tolist()}..{self.high.tolist()}")
    check("mean", (width, self.low.shape[0]))
    self._mean = (f32("mean/kernel"), f32("mean/bias"))
    self._state_bounds()

  def _state_bounds(self) -> None:
    """The accepted range of each state entry (`state_lo`, `state_hi`, (S,) float32) from
    `state_layout`: the k-th "*_prev" entry is action k's box, widened by STATE_TOLERANCE
    of its width; "yaw" is [-pi, pi] +- YAW_TOLERANCE; any other entry: finite only."""
    layout = self.meta.get("state_layout")
    if not layout and self.state_size == 3 and self.low.shape[0] == 2:
      layout = ["v_prev", "w_prev", "yaw"]  # files before the key: the only layout there was
    layout = [str(n) for n in layout or []]
    if len(layout) != self.state_size:
      layout = [f"state[{i}]" for i in range(self.state_size)]
    self.state_layout = layout
    lo = np.full(self.state_size, -np.inf, np.float32)
    hi = np.full(self.state_size, np.inf, np.float32)
    self._yaw_index, k = None, 0
    for i, name in enumerate(layout):
      if name.endswith("_prev") and k < self.low.shape[0]:
        slack = STATE_TOLERANCE * float(self.high[k] - self.low[k])
        lo[i], hi[i], k = self.low[k] - slack, self.high[k] + slack, k + 1
      elif name == "yaw":
        lo[i], hi[i], self._yaw_index = -math.pi - YAW_TOLERANCE, math.pi + YAW_TOLERANCE, i
    self.state_lo, self.state_hi = lo, hi

  @classmethod
  def load(cls, path: str | Path, preprocess: bool = False,
           blas_threads: int | None = None,
           invalid_depth: float | None = None, depth_scale: float | None = None,
           wrap_yaw: bool = False) -> "NumpyPolicy":
    """Loads an .npz written by `mjxvine.deploy.export.export_actor`.

    preprocess: the default for calls; if True, invalid depth pixels (NaN, inf and
    readings <= 0: a real sensor's "no return") become `invalid_depth` and the image is
    clipped to [0, max_depth]; readings above SENSOR_DEPTH_LIMIT_M are refused. If False,
    the image must lie in [0, depth_limit] m (2 x max_depth) and NaN/inf is an error.
    invalid_depth: metres; None (default) is the camera's maximum range `max_depth_m`,
    what the simulator shows for a ray that hits nothing within range.
    depth_scale: metres per count of integer depth images (0.001: uint16 millimetres);
    None (default) refuses integer images. Floating-point images are always metres.
    wrap_yaw: the default for calls; if True, a yaw outside [-pi, pi] is wrapped into
    [-pi, pi) instead of refused.
    blas_threads: if given, `set_blas_threads(blas_threads)` (process-wide; 1 is best on
    a busy CPU); None leaves BLAS as it is.
    """
    arrays, meta = read_policy_file(path)
    try:
      policy = cls(arrays, meta, preprocess, invalid_depth, depth_scale, wrap_yaw)
    except PolicyFormatError as e:
      raise PolicyFormatError(f"{path}: {e}") from None
    if blas_threads is not None:
      set_blas_threads(blas_threads)
    return policy

  # --------------------------------------------------------------------------------------

  def _workspace(self, shape: tuple[int, ...]) -> list[_ConvWork]:
    """The conv buffers for an input of `shape` (built on first use, per thread)."""
    cache = self._local.__dict__.setdefault("works", {})
    if shape not in cache:
      works, (b, h, w, c) = [], shape
      for (kernel, _), (stride, pool) in zip(self._convs, self._layers):
        work = _ConvWork((b, h, w, c), kernel.shape[1], stride, pool)
        works.append(work)
        h, w, c = work.ho, work.wo, kernel.shape[1]
        if pool:
          h, w = h // 2, w // 2
      if len(cache) >= 4:
        cache.clear()
      cache[shape] = works
    return cache[shape]

  def _check(self, depth, state, preprocess: bool,
             wrap_yaw: bool) -> tuple[np.ndarray, np.ndarray, bool]:
    """Validates inputs (the module's input contract) -> (depth (B, H, W, 1) float32
    metres, state (B, S) float32, batched)."""
    h, w = self.height, self.width
    depth = _numbers(depth, "depth image", "float metres (or integers with depth_scale)")
    shape = depth.shape
    if shape in ((h, w), (h, w, 1)):
      batched = False
    elif (depth.ndim == 3 and shape[1:] == (h, w)) or (depth.ndim == 4 and shape[1:] == (h, w, 1)):
      batched = True
    else:
      raise PolicyInputError(f"depth image of shape {shape}: expected ({h}, {w}), ({h}, {w}, 1), "
                             f"(B, {h}, {w}) or (B, {h}, {w}, 1)")
    n = shape[0] if batched else 1
    if n == 0:
      raise PolicyInputError(f"empty batch: depth of shape {shape}; expected B >= 1 images")
    if depth.dtype.kind in "iu":  # sensor counts: only with an explicit unit
      if self.depth_scale is None:
        raise PolicyInputError(f"depth image of dtype {depth.dtype} without a unit: expected "
                               "float metres, or give depth_scale (metres per count, 0.001 "
                               "for millimetres) to NumpyPolicy.load")
      depth = depth.astype(np.float32) * np.float32(self.depth_scale)
    depth = np.asarray(depth, np.float32).reshape((n, h, w, 1))
    state = _numbers(state, "state", f"numbers [{', '.join(self.state_layout)}]")
    want = (n, self.state_size) if batched else (self.state_size,)
    if state.shape != want:
      raise PolicyInputError(f"state of shape {state.shape}: expected {want} "
                             f"({', '.join(self.state_layout)})")
    state = state.reshape(n, -1)
    yi = self._yaw_index
    if wrap_yaw and yi is not None:  # in float64, before float32 rounds a large yaw
      yaw = state[:, yi].astype(np.float64)
      with np.errstate(invalid="ignore"):
        outside = np.abs(yaw) > math.pi
        if outside.any():  # only those: yaws in range stay bit for bit what they were
          state = state.astype(np.float64)
          state[:, yi] = np.where(outside, (yaw + math.pi) % (2 * math.pi) - math.pi, yaw)
    state = np.asarray(state, np.float32)
    if not np.isfinite(state).all():
      raise PolicyInputError(f"state has NaN or inf values ({state.tolist()[:4]}): expected "
                             "finite numbers")
    if not ((state >= self.state_lo) & (state <= self.state_hi)).all():
      raise self._state_error(state)
    if preprocess:
      depth = self._clean(depth, refuse=True)
    else:
      lo, hi = depth.min(), depth.max()  # NaN propagates: NaN fails both tests
      if not (lo >= 0.0 and hi <= self.depth_limit):
        raise self._depth_error(depth)
    return depth, state, batched

  def _state_error(self, state: np.ndarray) -> PolicyInputError:
    """The error for the first state entry outside [state_lo, state_hi], (B, S) state."""
    bad = (state < self.state_lo) | (state > self.state_hi)
    row, i = (int(j) for j in np.argwhere(bad)[0])
    name, value = self.state_layout[i], float(state[row, i])
    unit = STATE_UNITS.get(name, "")
    where = f" (batch row {row})" if state.shape[0] > 1 else ""
    if i == self._yaw_index:
      return PolicyInputError(
          f"state yaw {value:g} rad{where}: expected [-pi, pi] rad, wrapped as trained "
          "(NumpyPolicy.yaw_input gives it), or pass wrap_yaw=True to wrap it")
    k = [n.endswith("_prev") for n in self.state_layout[:i]].count(True)
    return PolicyInputError(
        f"state {name} {value:g} {unit}{where}: expected [{self.low[k]:g}, {self.high[k]:g}] "
        f"{unit} (the previous command, in the trained action box; +-{STATE_TOLERANCE:g} "
        "of its width tolerated)")

  def _depth_error(self, depth: np.ndarray) -> PolicyInputError:
    """The error for a depth image (float32 metres) outside [0, depth_limit] or non-finite
    (preprocess=False)."""
    finite = np.isfinite(depth)
    bad = int(depth.size - np.count_nonzero(finite))
    if bad:
      return PolicyInputError(
          f"depth image has {bad} NaN/inf pixels: expected finite metres; pass "
          f"preprocess=True to map them to {self.invalid_depth:g} m (no return) and clip to "
          f"[0, {self.max_depth:g}] like the simulated sensor")
    lo, hi = float(depth.min()), float(depth.max())
    if lo < 0.0:
      return PolicyInputError(
          f"depth image has {int(np.count_nonzero(depth < 0.0))} pixels below 0 m (min "
          f"{lo:g} m): expected metres in [0, {self.depth_limit:g}]; no sensor measures a "
          "negative depth (with preprocess=True readings <= 0 are no return)")
    return PolicyInputError(
        f"depth image has {int(np.count_nonzero(depth > self.depth_limit))} pixels above "
        f"{self.depth_limit:g} m (max {hi:g} m): expected metres in [0, {self.depth_limit:g}] "
        f"({DEPTH_LIMIT_FACTOR:g} x max_depth_m {self.max_depth:g} m). Millimetres? Give "
        "integer images with depth_scale, float ones in metres; a raw sensor image: "
        f"preprocess=True clips it to {self.max_depth:g} m")

  def _clean(self, depth, refuse: bool) -> np.ndarray:
    """`clean_depth` of metres (any shape; (B, H, W, 1) with `refuse`); with `refuse`,
    PolicyInputError for finite readings above SENSOR_DEPTH_LIMIT_M and for an image
    without any reading."""
    depth = np.array(depth, dtype=np.float32)
    with np.errstate(invalid="ignore"):
      invalid = ~np.isfinite(depth) | (depth <= 0.0)
    if refuse:
      blind = invalid.reshape(invalid.shape[0], -1).all(axis=1)
      if blind.any():  # a covered lens, an unplugged sensor, garbage: nothing to act on
        row = int(np.argmax(blind))
        where = f" (batch row {row})" if depth.shape[0] > 1 else ""
        raise PolicyInputError(
            f"depth image{where} without a single reading (all NaN, inf or <= 0 m, e.g. "
            f"{float(depth.flat[row * depth[0].size]):g}): expected some pixels in (0, "
            f"{SENSOR_DEPTH_LIMIT_M:g}] m (a camera looking down a row sees the ground)")
      hi = float(np.max(depth, where=~invalid, initial=0.0))
      if hi > SENSOR_DEPTH_LIMIT_M:
        count = int(np.count_nonzero(depth[~invalid] > SENSOR_DEPTH_LIMIT_M))
        raise PolicyInputError(
            f"depth image has {count} readings above {SENSOR_DEPTH_LIMIT_M:g} m (max {hi:g} "
            f"m): expected metres (no depth sensor reads that far; readings beyond "
            f"{self.max_depth:g} m are clipped). Millimetres? Give integer images with "
            "depth_scale, float ones in metres")
    depth[invalid] = self.invalid_depth
    return np.clip(depth, 0.0, self.max_depth, out=depth)

  def clean_depth(self, depth) -> np.ndarray:
    """The preprocessing of `preprocess=True`: a depth image (any shape, metres) with NaN,
    inf and readings <= 0 (a sensor's "no return") set to `invalid_depth`, then clipped
    to [0, max_depth] as the simulated sensor is. Returns a new float32 array. (It
    refuses nothing; a call with preprocess=True also refuses readings above
    SENSOR_DEPTH_LIMIT_M.)"""
    return self._clean(depth, refuse=False)

  def action(self, depth, state, preprocess: bool | None = None,
             wrap_yaw: bool | None = None) -> np.ndarray:
    """The action array: (A,) for one input, (B, A) for a batch; float32 in the box.
    preprocess, wrap_yaw: None is the policy's own (`load`). PolicyInputError for inputs
    outside the module's input contract."""
    pre = self.preprocess if preprocess is None else preprocess
    wrap = self.wrap_yaw if wrap_yaw is None else wrap_yaw
    x, s, batched = self._check(depth, state, pre, wrap)
    if self.mirror_average:  # one batch of the inputs and their mirror images
      b = x.shape[0]
      act = self._actor(np.concatenate([x, x[:, :, ::-1]]),
                        np.concatenate([s, s * MIRROR_STATE_SIGN]))
      act = 0.5 * (act[:b] + act[b:] * MIRROR_ACTION_SIGN)
    else:
      act = self._actor(x, s)
    return act if batched else act[0]

  def _actor(self, x: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The actor's action (B, A) for checked inputs: depth (B, H, W, 1), state (B, S)."""
    if any(self.tower_pad):  # repeat the last rows / columns, as the tower was trained
      x = np.pad(x, ((0, 0), (0, self.tower_pad[0]), (0, self.tower_pad[1]), (0, 0)), "edge")
    for (kernel, pool), work in zip(self._convs, self._workspace(x.shape)):
      x = work(x, kernel)
      if pool:  # max pool commutes with ReLU: apply it to 4x fewer values
        x = _maxpool2(x)
      np.maximum(x, 0.0, out=x)
    h = np.concatenate([x.mean(axis=(1, 2)), s], axis=-1)
    for kernel, bias in self._dense:
      h = h @ kernel
      h += bias
      np.maximum(h, 0.0, out=h)
    mean = h @ self._mean[0] + self._mean[1]
    return self.low + 0.5 * (np.tanh(mean) + 1.0) * (self.high - self.low)

  def yaw_input(self, imu_yaw: float, start_yaw: float | None = None) -> float:
    """The state's yaw (rad, in [-pi, pi)) from the IMU yaw (rad) as the policy was
    trained: relative to `start_yaw`, the IMU yaw at the row entrance with the robot facing
    down the row (metadata `yaw_reference` "start"), or the IMU yaw plus `yaw_offset_deg`
    ("world", the paper's input; also files exported before the key existed)."""
    if self.meta.get("yaw_reference", "world") == "start":
      if start_yaw is None:
        raise PolicyInputError("this policy reads the yaw relative to the row entrance: "
                               "give start_yaw, the IMU yaw there")
      yaw = imu_yaw - start_yaw
    else:
      yaw = imu_yaw + math.radians(float(self.meta.get("yaw_offset_deg", 0.0)))
    return (yaw + math.pi) % (2 * math.pi) - math.pi

  def __call__(self, depth, state, preprocess: bool | None = None,
               wrap_yaw: bool | None = None):
    """(v, w): floats for one input, arrays (B,) for a batch (one per action dim); see
    `action`."""
    act = self.action(depth, state, preprocess, wrap_yaw)
    if act.ndim == 1:
      return tuple(float(a) for a in act)
    return tuple(act[:, i] for i in range(act.shape[1]))
