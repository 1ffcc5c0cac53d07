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
are written by `mjxvine.export.export_actor`. Each conv is an im2col (a strided view
copied into a preallocated buffer) and a single matmul; `python -m mjxvine.latency
policy.npz` times one decision on the machine at hand (measured numbers are in
docs/results/). On a busy CPU use one BLAS thread: OPENBLAS_NUM_THREADS=1 set before
numpy is imported, or `NumpyPolicy.load(path, blas_threads=1)` with threadpoolctl
installed: extra OpenBLAS threads that must wait for a core make each decision several
times slower. Inputs are checked (shape, NaN/inf);
errors are `PolicyInputError`, file problems `PolicyFormatError`. A real depth sensor
reports "no return" as NaN, inf or 0; the simulator renders it as the maximum range, so
`preprocess=True` maps those pixels to `max_depth_m` (or `invalid_depth`), never to 0 m,
which the policy would read as an obstacle at the lens.
Calls are thread-safe (buffers are per thread).
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


class PolicyError(ValueError):
  """A policy cannot be loaded or does not fit its use: the base class of the errors of
  `NumpyPolicy`, also raised by `mjxvine.evaluate` (as `evaluate.PolicyError`)."""


class PolicyFormatError(PolicyError):
  """The policy file is unreadable, of another format version, or incomplete."""


class PolicyInputError(PolicyError):
  """An input to the policy has the wrong shape or non-finite values."""


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
               invalid_depth: float | None = None):
    """Use `load`. `arrays` maps "tower/conv0/kernel" etc. to float32 arrays."""
    self.meta = meta
    self.preprocess = preprocess
    try:
      self.height, self.width = (int(v) for v in meta["image_size"])
      self.max_depth = float(meta["max_depth_m"])
      # what preprocessing puts where the sensor has no reading: by default the maximum
      # range, as the simulator renders a ray that hits nothing
      self.invalid_depth = self.max_depth if invalid_depth is None else float(invalid_depth)
      self.depth_scale = float(meta.get("depth_scale", 1.0))
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
        k = k * np.float32(self.depth_scale)
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

  @classmethod
  def load(cls, path: str | Path, preprocess: bool = False,
           blas_threads: int | None = None,
           invalid_depth: float | None = None) -> "NumpyPolicy":
    """Loads an .npz written by `mjxvine.export.export_actor`.

    preprocess: the default for calls; if True, invalid depth pixels (NaN, inf and
    readings <= 0: a real sensor's "no return") become `invalid_depth` and the image is
    clipped to [0, max_depth]; if False, NaN/inf is an error.
    invalid_depth: metres; None (default) is the camera's maximum range `max_depth_m`,
    what the simulator shows for a ray that hits nothing within range.
    blas_threads: if given, `set_blas_threads(blas_threads)` (process-wide; 1 is best on
    a busy CPU); None leaves BLAS as it is.
    """
    arrays, meta = read_policy_file(path)
    try:
      policy = cls(arrays, meta, preprocess, invalid_depth)
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

  def _check(self, depth, state, preprocess: bool) -> tuple[np.ndarray, np.ndarray, bool]:
    """Validates inputs -> (depth (B, H, W, 1) float32, state (B, S) float32, batched)."""
    h, w = self.height, self.width
    depth = np.asarray(depth, dtype=np.float32)
    shape = depth.shape
    if shape in ((h, w), (h, w, 1)):
      batched = False
    elif (depth.ndim == 3 and shape[1:] == (h, w)) or (depth.ndim == 4 and shape[1:] == (h, w, 1)):
      batched = True
    else:
      raise PolicyInputError(f"depth image of shape {shape}: expected ({h}, {w}), ({h}, {w}, 1), "
                             f"(B, {h}, {w}) or (B, {h}, {w}, 1)")
    depth = depth.reshape((shape[0] if batched else 1, h, w, 1))
    state = np.asarray(state, dtype=np.float32)
    want = (depth.shape[0], self.state_size) if batched else (self.state_size,)
    if state.shape != want:
      raise PolicyInputError(f"state of shape {state.shape}: expected {want} "
                             f"({', '.join(self.meta.get('state_layout', []))})")
    if not np.isfinite(state).all():
      raise PolicyInputError("state has NaN or inf values")
    if preprocess:
      depth = self.clean_depth(depth)
    elif not np.isfinite(depth).all():
      bad = int(np.size(depth) - np.count_nonzero(np.isfinite(depth)))
      raise PolicyInputError(f"depth image has {bad} NaN/inf pixels; pass preprocess=True to "
                             f"map them to {self.invalid_depth:g} m (no return) and clip to "
                             f"[0, {self.max_depth:g}] like the simulated sensor")
    return depth, state.reshape(depth.shape[0], -1), batched

  def clean_depth(self, depth) -> np.ndarray:
    """The preprocessing of `preprocess=True`: a depth image (any shape, metres) with NaN,
    inf and readings <= 0 (a sensor's "no return") set to `invalid_depth`, then clipped
    to [0, max_depth] as the simulated sensor is. Returns a new float32 array."""
    depth = np.array(depth, dtype=np.float32)
    with np.errstate(invalid="ignore"):
      invalid = ~np.isfinite(depth) | (depth <= 0.0)
    depth[invalid] = self.invalid_depth
    return np.clip(depth, 0.0, self.max_depth, out=depth)

  def action(self, depth, state, preprocess: bool | None = None) -> np.ndarray:
    """The action array: (A,) for one input, (B, A) for a batch; float32 in the box."""
    pre = self.preprocess if preprocess is None else preprocess
    x, s, batched = self._check(depth, state, pre)
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

  def __call__(self, depth, state, preprocess: bool | None = None):
    """(v, w): floats for one input, arrays (B,) for a batch (one per action dim)."""
    act = self.action(depth, state, preprocess)
    if act.ndim == 1:
      return tuple(float(a) for a in act)
    return tuple(act[:, i] for i in range(act.shape[1]))
