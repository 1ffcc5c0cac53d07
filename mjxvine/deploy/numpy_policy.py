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

Errors. Everything `NumpyPolicy` raises, loading or acting, is a `PolicyError` (a
`ValueError`) with a one-line message; a robot should stop on any. An input the policy was
not trained for gets no action: it raises `PolicyInputError` saying what was received and
what is expected (a few vectorised min/max passes: microseconds at 20 Hz). A file that is
unreadable, incomplete, inconsistent or has non-finite weights raises `PolicyFormatError`
at load; a network output that is not finite for a finite input (an overflow) raises
`PolicyError`. Any action returned is finite and inside the action box.

Policy file limits, checked on the zip directory and on each entry's .npy header before
any entry is unpacked (a crafted entry that unpacks to gigabytes is refused unread):
MAX_FILE_BYTES (128 MiB) on disk, MAX_DIRECTORY_BYTES (1 MiB) of zip directory and
MAX_ENTRIES (256) entries; `__meta__` at most MAX_META_BYTES (1 MiB) unpacked, a
0-d unicode array holding a JSON object; the actor's arrays ("tower/conv<i>/", "dense<i>/",
"mean/", "log_std/" + "kernel" or "bias") floating point, each at most MAX_ARRAY_BYTES
(32 MiB) unpacked and all read at most MAX_TOTAL_BYTES (64 MiB); any other entry at most
MAX_OTHER_BYTES (64 KiB), never read. `NumpyPolicy.load` reads only `__meta__` and the
arrays its metadata names; the metadata is checked field by field (`policy_layout`):
images of at most MAX_IMAGE_SIDE (512) pixels a side, at most MAX_LAYERS (16) conv and 16
hidden layers, strides 1..MAX_STRIDE (4), a finite action box with low < high.

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

import ast
import json
import math
import re
import struct
import threading
import zipfile
from pathlib import Path
from typing import NamedTuple

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
# Policy file limits (the module docstring), checked before anything is unpacked: the
# paper's actor is 0.4 MB of arrays and a 14 kB __meta__, so these leave >100x room.
MAX_FILE_BYTES = 128 << 20
MAX_DIRECTORY_BYTES = 1 << 20  # the zip's central directory: names and sizes of entries
MAX_ENTRIES = 256
MAX_META_BYTES = 1 << 20
MAX_ARRAY_BYTES = 32 << 20
MAX_TOTAL_BYTES = 64 << 20
MAX_OTHER_BYTES = 64 << 10
MAX_NPY_HEADER_BYTES = 10000  # numpy's own bound on an .npy header
# Metadata bounds (`policy_layout`): the network a file may describe.
MAX_IMAGE_SIDE = 512
MAX_LAYERS = 16  # conv layers; also hidden layers
MAX_STRIDE = 4
MAX_TOWER_PAD = 16
MAX_ACTIONS = 16
MAX_STATE = 64
# The actor's entries by name ("dense0/kernel"); others are not read.
ACTOR_ENTRY = re.compile(r"(tower/conv\d{1,2}|dense\d{1,2}|mean|log_std)/(kernel|bias)")
# Conv buffers of one chunk of a batch (bytes): a batch runs in chunks of at most this
# much workspace (one image at least), and each thread keeps the buffers of its last
# CACHED_SHAPES input shapes only, so a call on thousands of images holds no more after.
WORKSPACE_BYTES = 32 << 20
CACHED_SHAPES = 2


# ----------------------------------------------------------------------------------------
# The end of the row, from the depth image and the robot's own speed: no pose, no map.
#
# In a lane, the plants of both rows fill the image above the horizon; past the last plant
# the headland does not. Per frame, the cue (`row_cue`) is the share of the pixels at least
# `RowEnd.min_elevation_deg` above the optical axis (so the ground never counts) that read
# nearer than `RowEnd.near_m`, and their mean depth. A frame sees the row when that share
# exceeds `RowEnd.seen_share`. The last frame that saw it shows the last plants just inside
# the field of view, at about that mean depth; the detector (`row_update`) then adds up
# the distance driven (commanded speed x control step) and says "row ended" once it passes
# that depth plus `RowEnd.margin_m` (the end of a row lies a little past its last plant).
# A gap of missing plants in one row does not fire it: the other row fills the image.
# The functions take numpy or jax.numpy (`xp`): the evaluator (`evaluate --past-end`) and
# this policy compute one formula.

class RowEnd(NamedTuple):
  """The detector's settings (a policy file's metadata "row_end" holds them)."""
  near_m: float = 3.0  # a pixel nearer than this (m) is a plant (or post) of the lane
  seen_share: float = 0.01  # a frame sees the row above this share of the band's pixels
  min_elevation_deg: float = 3.0  # the band: rows whose centres lie this far above the axis
  margin_m: float = 0.3  # driven past the last plant's depth before the row has ended

  @classmethod
  def from_meta(cls, meta: dict | None) -> "RowEnd":
    """The settings of a policy file's "row_end" metadata (the defaults where absent);
    ValueError naming a key that is unknown or not a finite number > 0."""
    meta = meta or {}
    unknown = sorted(set(meta) - set(cls._fields))
    if unknown:
      raise ValueError(f"row_end: unknown key {unknown[0]!r} (known: {', '.join(cls._fields)})")
    for k, v in meta.items():
      if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
          or v <= 0:
        raise ValueError(f"row_end.{k} = {v!r}: must be a finite number > 0")
    return cls(**{k: float(v) for k, v in meta.items()})


class RowMemory(NamedTuple):
  """What the detector keeps between frames: `driven_m`, the distance driven since the
  last frame that saw the row (m), and `last_depth_m`, that frame's mean plant depth
  (m; inf before the row was first seen, so the detector cannot fire before it). Arrays of
  one shape (the robots' batch shape)."""
  driven_m: object
  last_depth_m: object


def row_start(shape=(), xp=np) -> "RowMemory":
  """The memory at the start of a row: nothing driven, the row not seen yet."""
  return RowMemory(xp.zeros(shape, xp.float32), xp.full(shape, xp.inf, xp.float32))


def band_rows(height: int, fovy_deg: float, min_elevation_deg: float) -> int:
  """How many image rows, from the top, have centres at least `min_elevation_deg` above the
  optical axis of a pinhole camera `height` rows high with vertical field `fovy_deg`."""
  f = (height / 2) / math.tan(math.radians(fovy_deg) / 2)
  centres = height / 2 - (np.arange(height) + 0.5)  # rows above the axis, pixels
  return int(np.sum(np.arctan2(centres, f) >= math.radians(min_elevation_deg)))


def row_cue(depth, rows: int, settings: RowEnd, xp=np):
  """(share, mean depth m) of the band's plant pixels: `depth` (..., H, W) metres, the image
  the policy sees; the top `rows` rows (`band_rows`). Mean depth is 0 where none."""
  band = depth[..., :rows, :]
  plant = band < settings.near_m
  count = xp.sum(plant, axis=(-2, -1)).astype(xp.float32)
  share = count / float(band.shape[-2] * band.shape[-1])
  depth_sum = xp.sum(xp.where(plant, band, 0.0), axis=(-2, -1))
  return share, depth_sum / xp.maximum(count, 1.0)


def row_update(memory: RowMemory, share, mean_depth_m, speed_m_s, dt_s: float, settings: RowEnd,
               xp=np) -> tuple:
  """One frame: the new memory and whether the row has ended (bool, the memory's shape).
  `share`, `mean_depth_m`: this frame's `row_cue`; `speed_m_s`: the speed commanded for the
  last control step (the policy's v input); `dt_s`: the control step (s)."""
  seen = share > settings.seen_share
  driven = xp.where(seen, 0.0, memory.driven_m + xp.maximum(speed_m_s, 0.0) * dt_s)
  last = xp.where(seen, mean_depth_m, memory.last_depth_m)
  ended = ~seen & (driven >= last + settings.margin_m)
  return RowMemory(driven.astype(xp.float32), last.astype(xp.float32)), ended


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


def _first_line(e: BaseException) -> str:
  """An exception's message as one short line (its type when it has none)."""
  text = str(e).strip()
  return text.splitlines()[0][:160] if text else type(e).__name__


def _zip_directory_bytes(path: Path, size: int) -> int:
  """The size of the central directory of the zip archive at `path` (`size` bytes), from
  its end record, found as zipfile finds it; PolicyFormatError for a zip64 archive (a
  policy file never needs one) or none."""
  with open(path, "rb") as f:
    n = min(size, 22 + 0xFFFF)  # the end record (22 bytes) and at most a 64 kB comment
    f.seek(size - n)
    tail = f.read(n)
  at = len(tail) - 22
  if not (at >= 0 and tail[at:at + 4] == b"PK\x05\x06" and tail[-2:] == b"\0\0"):
    at = tail.rfind(b"PK\x05\x06")
  if at < 0 or at + 22 > len(tail):
    raise PolicyFormatError("no zip end record")
  if at >= 20 and tail[at - 20:at - 16] == b"PK\x06\x07":
    raise PolicyFormatError("a zip64 archive (a policy file is far smaller)")
  return struct.unpack("<I", tail[at + 12:at + 16])[0]


def _read_npy(zf: zipfile.ZipFile, info: zipfile.ZipInfo, kind: str) -> np.ndarray:
  """The array of one .npy entry, its header checked first: dtype kind `kind` ("f"
  floating point, "U" unicode), a shape whose bytes are the entry's declared size
  (`info.file_size`, checked against the limits before). Unpacks at most that size."""
  name = info.filename
  with zf.open(info) as f:
    magic = f.read(8)
    if len(magic) != 8 or magic[:6] != b"\x93NUMPY" or magic[6] not in (1, 2, 3):
      raise PolicyFormatError(f"{name} is not an .npy array")
    width = 2 if magic[6] == 1 else 4
    raw = f.read(width)
    size = int.from_bytes(raw, "little") if len(raw) == width else 0
    if not 0 < size <= MAX_NPY_HEADER_BYTES:
      raise PolicyFormatError(f"{name}: .npy header of {size} bytes")
    text = f.read(size)
    try:
      header = ast.literal_eval(text.decode("utf-8" if magic[6] == 3 else "latin1"))
      descr, shape, fortran = header["descr"], header["shape"], header["fortran_order"]
      if not (isinstance(descr, str) and isinstance(shape, tuple) and len(shape) <= 8 and
              all(type(d) is int and d >= 0 for d in shape) and isinstance(fortran, bool)):
        raise ValueError(header)
      dtype = np.dtype(descr)
    except Exception:  # noqa: BLE001 - whatever a crafted header makes of these
      raise PolicyFormatError(f"{name}: unreadable .npy header") from None
    if dtype.hasobject:  # numpy would unpickle it: never right for a policy
      raise PolicyFormatError(f"{name} holds pickled object arrays")
    if dtype.kind != kind:
      want = "floating point" if kind == "f" else "a unicode string"
      raise PolicyFormatError(f"{name} of dtype {dtype}: expected {want}")
    nbytes = math.prod(shape) * dtype.itemsize
    if 8 + width + size + nbytes != info.file_size:
      raise PolicyFormatError(f"{name}: its header declares {nbytes} bytes of {dtype} "
                              f"{shape}, the entry holds {info.file_size - 8 - width - size}")
    out = np.empty(shape[::-1] if fortran else shape, dtype)
    buf, got = out.reshape(-1).view(np.uint8), 0
    while got < nbytes:  # in 1 MiB pieces: zipfile copies each piece once more
      n = f.readinto(buf[got:got + (1 << 20)])
      if not n:
        raise PolicyFormatError(f"{name} is truncated")
      got += n
  return out.T if fortran else out


def _read_policy(path: str | Path, choose) -> tuple[dict[str, np.ndarray], dict]:
  """(arrays, meta) of an .npz policy file, reading the arrays `choose(meta, names)`
  picks of the actor's entries present; see `read_policy_file`."""
  path = Path(path)
  if not path.is_file():
    raise PolicyFormatError(f"{path}: no such policy file")
  invalid = f"{path}: not a valid policy file"
  # numpy reads a file that is not a zip archive as a pickle, and its error then suggests
  # allow_pickle=True: check the container first.
  if not zipfile.is_zipfile(path):
    raise PolicyFormatError(f"{invalid} (not an .npz archive)")
  try:
    size = path.stat().st_size
    if size > MAX_FILE_BYTES:
      raise PolicyFormatError(f"{size} bytes on disk: a policy file is at most "
                              f"{MAX_FILE_BYTES} bytes")
    directory = _zip_directory_bytes(path, size)
    if directory > MAX_DIRECTORY_BYTES:  # zipfile would hold all of its entries
      raise PolicyFormatError(f"a zip directory of {directory} bytes: at most "
                              f"{MAX_DIRECTORY_BYTES}")
    with zipfile.ZipFile(path) as zf:
      infos = zf.infolist()
      if len(infos) > MAX_ENTRIES:
        raise PolicyFormatError(f"{len(infos)} entries: at most {MAX_ENTRIES}")
      entries = {}
      for info in infos:  # the declared (unpacked) sizes, before anything is unpacked
        key = info.filename[:-4] if info.filename.endswith(".npy") else None
        if key != META_KEY and not (key and ACTOR_ENTRY.fullmatch(key)):
          if info.file_size > MAX_OTHER_BYTES:
            raise PolicyFormatError(f"entry {info.filename[:60]!r} of {info.file_size} bytes "
                                    f"is no policy array (others: at most {MAX_OTHER_BYTES})")
          continue  # not the policy's: never read
        limit = MAX_META_BYTES if key == META_KEY else MAX_ARRAY_BYTES
        if info.file_size > limit:
          raise PolicyFormatError(f"{info.filename} of {info.file_size} bytes: at most {limit}")
        if key in entries:
          raise PolicyFormatError(f"two {info.filename} entries")
        entries[key] = info
      if META_KEY not in entries:
        raise PolicyFormatError(f"{invalid} (no {META_KEY} entry: not an mjxvine policy file)")
      try:
        meta = json.loads(str(_read_npy(zf, entries.pop(META_KEY), "U")[()]))
        if not isinstance(meta, dict):
          raise ValueError(f"a JSON {type(meta).__name__}, not an object")
      except (ValueError, RecursionError) as e:
        raise PolicyFormatError(f"{invalid} (unreadable metadata: {_first_line(e)})") from None
      version = meta.get("format_version")
      if version != FORMAT_VERSION:
        raise PolicyFormatError(f"{path}: policy format version {repr(version)[:20]}; this "
                                f"mjxvine reads version {FORMAT_VERSION} (re-export the "
                                "checkpoint)")
      names = [n for n in choose(meta, sorted(entries)) if n in entries]
      total = sum(entries[n].file_size for n in names)
      if total > MAX_TOTAL_BYTES:
        raise PolicyFormatError(f"arrays of {total} bytes: at most {MAX_TOTAL_BYTES}")
      arrays = {n: _read_npy(zf, entries[n], "f") for n in names}
  except PolicyFormatError as e:
    text = str(e)
    raise PolicyFormatError(text if text.startswith(str(path)) else f"{invalid} ({text})") \
        from None
  except Exception as e:  # noqa: BLE001 - a truncated or corrupted archive (zipfile, zlib)
    raise PolicyFormatError(f"{invalid} ({_first_line(e)})") from None
  return arrays, meta


def read_policy_file(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
  """(arrays, meta) of an .npz policy file: the actor's arrays by name ("tower/conv0/kernel",
  "log_std/bias", ...; other entries are not read) and the metadata. `PolicyFormatError`
  if it is unreadable, of another format version, or over the module's file limits."""
  return _read_policy(path, lambda meta, names: names)


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


_MISSING = object()
# per image of the conv tower's buffers, bytes (the paper's 112x112 actor: 4 MB)
MAX_IMAGE_WORK_BYTES = 256 << 20


def _bad_meta(key: str, value, expected: str) -> PolicyFormatError:
  text = repr(value)
  return PolicyFormatError(f"policy metadata {key} {text if len(text) <= 60 else text[:57] + '...'}"
                           f": expected {expected}")


def _meta_value(meta: dict, key: str, default=_MISSING):
  if key in meta:
    return meta[key]
  if default is _MISSING:
    raise PolicyFormatError(f"policy metadata lacks {key}")
  return default


def _is_int(v) -> bool:
  return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:  # finite: JSON's NaN and Infinity read as floats
  return _is_int(v) or (isinstance(v, float) and math.isfinite(v))


def _meta_number(meta: dict, key: str, lo: float, hi: float, default=_MISSING) -> float:
  """meta[key], a number in (lo, hi]."""
  v = _meta_value(meta, key, default)
  if v is not default and not (_is_number(v) and lo < v <= hi):
    raise _bad_meta(key, v, f"a number in ({lo:g}, {hi:g}]")
  return v if v is None else float(v)


def _meta_ints(meta: dict, key: str, n: int, lo: int, hi: int, default=_MISSING) -> tuple:
  """meta[key], a list of n integers in [lo, hi]."""
  v = _meta_value(meta, key, default)
  if not (isinstance(v, (list, tuple)) and len(v) == n and
          all(_is_int(x) and lo <= x <= hi for x in v)):
    raise _bad_meta(key, v, f"{n} integers in [{lo}, {hi}]")
  return tuple(v)


def _tower_sizes(h: int, w: int, layers) -> list[tuple[int, int, int, int]]:
  """(ho, wo, h', w') of each conv layer (stride, pool) on an h x w input: its conv output
  as computed (even-sized with a pool) and the next layer's input size."""
  sizes = []
  for stride, pool in layers:
    ho, wo = (h - 3) // stride + 1, (w - 3) // stride + 1
    if pool:
      ho, wo = ho // 2 * 2, wo // 2 * 2
    h, w = (ho // 2, wo // 2) if pool else (ho, wo)
    sizes.append((ho, wo, h, w))
  return sizes


def policy_layout(meta: dict) -> dict:
  """The network and action box a policy's metadata describes, every field checked
  (`PolicyFormatError` naming the first bad one). Keys: image_size (H, W) px, max_depth_m,
  depth_scale (the input multiplier, 1 / m), action_low and action_high ((A,) float32,
  low < high), conv_layers [(stride, pool)], num_hidden, tower_pad (bottom, right) px,
  mirror_average, state_layout (names or None), yaw_reference ("start" or "world"),
  yaw_offset_deg, and control_dt (s), fovx_deg, fovy_deg (None where absent)."""
  if not isinstance(meta, dict):
    raise PolicyFormatError(f"policy metadata is a {type(meta).__name__}, not a JSON object")
  out = {"image_size": _meta_ints(meta, "image_size", 2, 1, MAX_IMAGE_SIDE),
         "max_depth_m": _meta_number(meta, "max_depth_m", 0.0, SENSOR_DEPTH_LIMIT_M),
         "depth_scale": _meta_number(meta, "depth_scale", 0.0, 1e6, 1.0)}
  for key in ("action_low", "action_high"):
    v = _meta_value(meta, key)
    if not (isinstance(v, (list, tuple)) and 1 <= len(v) <= MAX_ACTIONS and
            all(_is_number(x) and abs(x) <= 1e6 for x in v)):
      raise _bad_meta(key, v, f"1 to {MAX_ACTIONS} numbers in [-1e6, 1e6]")
    out[key] = np.asarray(v, np.float32)
  low, high = out["action_low"], out["action_high"]
  if low.shape != high.shape or not (low < high).all():
    raise PolicyFormatError(f"policy action box {low.tolist()}..{high.tolist()}: expected "
                            "as many lows as highs, each below its high")
  layers = _meta_value(meta, "conv_layers")
  if not (isinstance(layers, (list, tuple)) and 1 <= len(layers) <= MAX_LAYERS and
          all(isinstance(l, (list, tuple)) and len(l) == 2 and _is_int(l[0]) and
              1 <= l[0] <= MAX_STRIDE and isinstance(l[1], bool) for l in layers)):
    raise _bad_meta("conv_layers", layers, f"1 to {MAX_LAYERS} [stride 1..{MAX_STRIDE}, "
                    "pool true/false] pairs")
  out["conv_layers"] = [(int(s), bool(p)) for s, p in layers]
  num_hidden = _meta_value(meta, "num_hidden")
  if not (_is_int(num_hidden) and 1 <= num_hidden <= MAX_LAYERS):
    raise _bad_meta("num_hidden", num_hidden, f"an integer in [1, {MAX_LAYERS}]")
  out["num_hidden"] = num_hidden
  out["tower_pad"] = _meta_ints(meta, "tower_pad", 2, 0, MAX_TOWER_PAD, (0, 0))
  for key in ("mirror_average",):
    v = _meta_value(meta, key, False)
    if not isinstance(v, bool):
      raise _bad_meta(key, v, "true or false")
    out[key] = v
  names = _meta_value(meta, "state_layout", None)
  if names is not None and not (isinstance(names, (list, tuple)) and len(names) <= MAX_STATE and
                                all(isinstance(n, str) and len(n) <= 64 for n in names)):
    raise _bad_meta("state_layout", names, f"at most {MAX_STATE} names")
  out["state_layout"] = None if names is None else list(names)
  out["yaw_reference"] = _meta_value(meta, "yaw_reference", "world")
  if out["yaw_reference"] not in ("start", "world"):
    raise _bad_meta("yaw_reference", out["yaw_reference"], '"start" or "world"')
  out["yaw_offset_deg"] = _meta_number(meta, "yaw_offset_deg", -360.0 - 1e-9, 360.0, 0.0)
  out["control_dt"] = _meta_number(meta, "control_dt", 0.0, 10.0, None)
  try:  # the end-of-row detector's settings (files before it: the defaults)
    out["row_end"] = RowEnd.from_meta(_meta_value(meta, "row_end", None))
  except (ValueError, TypeError) as e:
    raise PolicyFormatError(f"policy metadata {e}") from None
  for key in ("fovx_deg", "fovy_deg"):
    out[key] = _meta_number(meta, key, 0.0, 180.0, None)
  h, w = out["image_size"]
  pad = out["tower_pad"]
  if min(min(ho, wo, h1, w1) for ho, wo, h1, w1 in
         _tower_sizes(h + pad[0], w + pad[1], out["conv_layers"])) < 1:
    raise PolicyFormatError(f"policy image_size {h}x{w} is too small for its "
                            f"{len(layers)} conv layers {out['conv_layers']}")
  return out


def _load_arg(value, name: str, zero: bool, what: str) -> float | None:
  """A `load` argument: None, or a finite number > 0 (>= 0 with `zero`)."""
  if value is None:
    return None
  try:
    v = float(value)
  except (TypeError, ValueError, OverflowError):
    v = math.nan
  if not (math.isfinite(v) and (v >= 0.0 if zero else v > 0.0)):
    raise PolicyInputError(f"{name} {str(value)[:40]!r}: expected {what}")
  return v


def _array_names(layout: dict) -> list[str]:
  """The arrays a policy of `layout` (`policy_layout`) computes with: what `load` reads."""
  names = [f"tower/conv{i}" for i in range(len(layout["conv_layers"]))]
  names += [f"dense{i}" for i in range(layout["num_hidden"])] + ["mean"]
  return [f"{n}/{p}" for n in names for p in ("kernel", "bias")]


def _outputs(arrays: dict, name: str, ndim: int) -> int:
  """The last axis of kernel `arrays[name]`, its rank checked to be `ndim`."""
  shape = np.shape(arrays[name])
  if len(shape) != ndim or shape[-1] < 1:
    raise PolicyFormatError(f"{name} has shape {shape}, expected {ndim} axes")
  return int(shape[-1])


def _weights(arrays: dict, name: str, shape: tuple) -> np.ndarray:
  """`arrays[name]` as float32, its dtype, shape and values checked."""
  a = np.asarray(arrays[name])
  if a.dtype.kind != "f":
    raise PolicyFormatError(f"{name} of dtype {a.dtype}: expected floating point")
  if a.shape != shape:
    raise PolicyFormatError(f"{name} has shape {a.shape}, expected {shape}")
  with np.errstate(over="ignore"):  # float64 beyond float32 becomes inf: refused below
    a = np.ascontiguousarray(a, np.float32)
  if not np.isfinite(a).all():
    raise PolicyFormatError(f"{name} has {a.size - np.count_nonzero(np.isfinite(a))} "
                            "NaN or inf weights (or beyond float32): a broken export")
  return a


def finite_number(value, what: str, error: type = PolicyInputError,
                  expected: str = "a finite number") -> float:
  """`value` as a finite float, else `error` naming `what` (one line)."""
  try:
    number = float(value)
  except (TypeError, ValueError, OverflowError):
    number = math.nan
  if not math.isfinite(number):
    raise error(f"{what} {value!r}: expected {expected}")
  return number


class NumpyPolicy:
  """The actor's deterministic action, in numpy. Build with `NumpyPolicy.load(path)`."""

  def __init__(self, arrays: dict[str, np.ndarray], meta: dict, preprocess: bool = False,
               invalid_depth: float | None = None, depth_scale: float | None = None,
               wrap_yaw: bool = False):
    """Use `load` (its arguments). `arrays` maps "tower/conv0/kernel" etc. to floating-point
    arrays, `meta` is the file's metadata (`policy_layout`). PolicyFormatError for bad or
    inconsistent ones (shapes, NaN/inf weights), PolicyInputError for a bad argument."""
    try:
      self._build(arrays, meta, preprocess, invalid_depth, depth_scale, wrap_yaw)
    except PolicyError:
      raise
    except Exception as e:  # noqa: BLE001 - only PolicyError leaves NumpyPolicy
      raise PolicyFormatError(f"policy does not load ({type(e).__name__}: "
                              f"{_first_line(e)})") from e

  def _build(self, arrays, meta, preprocess, invalid_depth, depth_scale, wrap_yaw) -> None:
    layout = policy_layout(meta)
    self.meta = meta
    self.preprocess = bool(preprocess)
    self.wrap_yaw = bool(wrap_yaw)
    # metres per count of integer depth images (None: integer images are refused)
    self.depth_scale = _load_arg(depth_scale, "depth_scale", False,
                                 "metres per count > 0 (0.001 for millimetres)")
    self.height, self.width = layout["image_size"]
    self.max_depth = layout["max_depth_m"]
    # what preprocessing puts where the sensor has no reading: by default the maximum
    # range, as the simulator renders a ray that hits nothing
    invalid_depth = _load_arg(invalid_depth, "invalid_depth", True,
                              "metres >= 0 (None: max_depth_m)")
    self.invalid_depth = self.max_depth if invalid_depth is None else invalid_depth
    # the network's input multiplier (1 / m, metadata "depth_scale"), not `depth_scale`
    self.input_scale = layout["depth_scale"]
    # largest depth accepted without preprocessing (m): the module's input contract
    self.depth_limit = DEPTH_LIMIT_FACTOR * self.max_depth
    self.low, self.high = layout["action_low"], layout["action_high"]
    layers = layout["conv_layers"]
    # bottom / right edge padding of the tower (files written before it existed: none)
    self.tower_pad = layout["tower_pad"]
    # the mean of the actions on the image and on its mirror (files before it: no)
    self.mirror_average = layout["mirror_average"]
    self.control_dt = layout["control_dt"]  # s per decision, None if the file lacks it
    num_hidden = layout["num_hidden"]
    missing = [n for n in _array_names(layout) if n not in arrays]
    if missing:
      raise PolicyFormatError(f"policy file lacks arrays: {', '.join(missing)}")

    def layer(name: str, shape: tuple) -> tuple[np.ndarray, np.ndarray]:
      return (_weights(arrays, f"{name}/kernel", shape),
              _weights(arrays, f"{name}/bias", shape[-1:]))

    self._convs, channels = [], 1
    for i, (stride, pool) in enumerate(layers):
      features = _outputs(arrays, f"tower/conv{i}/kernel", 4)
      k, b = layer(f"tower/conv{i}", (3, 3, channels, features))
      if i == 0:  # fold the input scaling into the first kernel
        k = k * np.float32(self.input_scale)
      # The bias is the last row: im2col buffers carry a column of ones.
      kernel = np.concatenate([k.reshape(-1, features), b[None]])
      if not np.isfinite(kernel).all():
        raise PolicyFormatError("tower/conv0/kernel times depth_scale overflows float32")
      self._convs.append((np.ascontiguousarray(kernel), pool))
      channels = features
    self._layers = layers
    self._local = threading.local()  # per-thread buffers, keyed by input shape
    self._work_bytes = self._workspace_bytes(1)
    if self._work_bytes > MAX_IMAGE_WORK_BYTES:
      raise PolicyFormatError(f"the conv tower needs {self._work_bytes} bytes of buffers per "
                              f"image: at most {MAX_IMAGE_WORK_BYTES}")
    _outputs(arrays, "dense0/kernel", 2)  # a matrix: its rows are the features and the state
    self.state_size = int(np.shape(arrays["dense0/kernel"])[0]) - channels
    if not 1 <= self.state_size <= MAX_STATE:
      raise PolicyFormatError(f"dense0/kernel has {self.state_size + channels} inputs for "
                              f"{channels} conv features: expected 1 to {MAX_STATE} more "
                              "(the state)")
    width = channels + self.state_size
    self._dense = []
    for i in range(num_hidden):
      hidden = _outputs(arrays, f"dense{i}/kernel", 2)
      self._dense.append(layer(f"dense{i}", (width, hidden)))
      width = hidden
    self._mean = layer("mean", (width, self.low.shape[0]))
    if self.mirror_average and (self.state_size, self.low.shape[0]) != (3, 2):
      raise PolicyFormatError(f"mirror_average needs the state [v_prev, w_prev, yaw] and the "
                              f"action [v, w]: this policy has {self.state_size} state and "
                              f"{self.low.shape[0]} action entries")
    self.layout = layout
    self._state_bounds()
    self.row_end = layout["row_end"]  # the end-of-row detector (`step`)
    self.row_memory = row_start()
    fovy = layout["fovy_deg"]  # the detector's band of image rows, once (0 without one)
    self._row_band = band_rows(self.height, fovy, self.row_end.min_elevation_deg) if fovy else 0

  def _workspace_bytes(self, batch: int) -> int:
    """Bytes of the conv buffers (`_ConvWork`: cols and out) for `batch` images."""
    sizes = _tower_sizes(self.height + self.tower_pad[0], self.width + self.tower_pad[1],
                         self._layers)
    return sum(4 * batch * ho * wo * (kernel.shape[0] + kernel.shape[1])
               for (kernel, _), (ho, wo, _, _) in zip(self._convs, sizes))

  def _state_bounds(self) -> None:
    """The accepted range of each state entry (`state_lo`, `state_hi`, (S,) float32) from
    `state_layout`: the k-th "*_prev" entry is action k's box, widened by STATE_TOLERANCE
    of its width; "yaw" is [-pi, pi] +- YAW_TOLERANCE; any other entry: finite only."""
    layout = self.layout["state_layout"]
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

    Reads only `__meta__` and the arrays it names, each checked against the module's file
    limits before it is unpacked. Raises PolicyError only: PolicyFormatError for the file,
    PolicyInputError for a bad argument.
    """
    path = Path(path)
    try:
      arrays, meta = _read_policy(path, lambda meta, names: _array_names(policy_layout(meta)))
      policy = cls(arrays, meta, preprocess, invalid_depth, depth_scale, wrap_yaw)
    except PolicyFormatError as e:
      text = str(e)
      raise PolicyFormatError(text if text.startswith(str(path)) else f"{path}: {text}") \
          from None
    if blas_threads is not None:
      try:
        threads = int(blas_threads)
        if threads < 1:
          raise ValueError(threads)
        set_blas_threads(threads)
      except Exception as e:  # noqa: BLE001 - a bad count, or threadpoolctl failing
        raise PolicyInputError(f"blas_threads {str(blas_threads)[:20]!r}: expected a count "
                               f">= 1 ({_first_line(e)})") from None
    return policy

  # --------------------------------------------------------------------------------------

  def _workspace(self, shape: tuple[int, ...]) -> list[_ConvWork]:
    """The conv buffers for an input of `shape` (built on first use, per thread; each
    thread keeps those of its last CACHED_SHAPES shapes)."""
    cache = self._local.__dict__.setdefault("works", {})
    works = cache.pop(shape, None)  # re-inserted below: the dict's order is last use
    if works is None:
      while len(cache) >= CACHED_SHAPES:  # the least recently used first
        del cache[next(iter(cache))]
      works, (b, h, w, c) = [], shape
      for (kernel, _), (stride, pool) in zip(self._convs, self._layers):
        work = _ConvWork((b, h, w, c), kernel.shape[1], stride, pool)
        works.append(work)
        h, w, c = work.ho, work.wo, kernel.shape[1]
        if pool:
          h, w = h // 2, w // 2
    cache[shape] = works
    return works

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
      raise PolicyInputError(f"state has NaN or inf values ({state[:4].tolist()}): expected "
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
    return self._clean(_numbers(depth, "depth image", "metres"), refuse=False)

  def action(self, depth, state, preprocess: bool | None = None,
             wrap_yaw: bool | None = None) -> np.ndarray:
    """The action array: (A,) for one input, (B, A) for a batch; float32, finite, in the
    box. preprocess, wrap_yaw: None is the policy's own (`load`). PolicyInputError for
    inputs outside the module's input contract, PolicyError for a network output that is
    not finite (an overflow); no other error (a MemoryError becomes a PolicyError too)."""
    return self._checked_action(depth, state, preprocess, wrap_yaw)[0]

  def _checked_action(self, depth, state, preprocess: bool | None,
                      wrap_yaw: bool | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(`action`'s array, the checked depth (B, H, W, 1) m and state (B, S) it acted on),
    with `action`'s errors."""
    try:
      return self._action(depth, state, preprocess, wrap_yaw)
    except PolicyError:
      raise
    except Exception as e:  # noqa: BLE001 - whatever it is, the caller gets no action
      raise PolicyError(f"no action ({type(e).__name__}: {_first_line(e)})") from e

  def _action(self, depth, state, preprocess: bool | None,
              wrap_yaw: bool | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pre = self.preprocess if preprocess is None else preprocess
    wrap = self.wrap_yaw if wrap_yaw is None else wrap_yaw
    x, s, batched = self._check(depth, state, pre, wrap)
    n = x.shape[0]
    mirror = self.mirror_average
    # chunks of at most WORKSPACE_BYTES of conv buffers: a large batch holds no more
    step = max(1, WORKSPACE_BYTES // ((2 if mirror else 1) * self._work_bytes))
    act = np.empty((n, self.low.shape[0]), np.float32)
    for i in range(0, n, step):
      xi, si = x[i:i + step], s[i:i + step]
      if mirror:  # one batch of the inputs and their mirror images
        b = xi.shape[0]
        both = self._actor(np.concatenate([xi, xi[:, :, ::-1]]),
                           np.concatenate([si, si * MIRROR_STATE_SIGN]))
        act[i:i + b] = 0.5 * (both[:b] + both[b:] * MIRROR_ACTION_SIGN)
      else:
        act[i:i + step] = self._actor(xi, si)
    # float32 rounding, and the mirror average of a box not symmetric in w, may leave it
    np.clip(act, self.low, self.high, out=act)
    return (act if batched else act[0]), x, s

  def _actor(self, x: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The actor's action (B, A) for checked inputs: depth (B, H, W, 1), state (B, S);
    PolicyError if the features or the output are not finite (finite weights and inputs:
    an overflow)."""
    if any(self.tower_pad):  # repeat the last rows / columns, as the tower was trained
      x = np.pad(x, ((0, 0), (0, self.tower_pad[0]), (0, self.tower_pad[1]), (0, 0)), "edge")
    with np.errstate(over="ignore", invalid="ignore"):  # checked below, once
      for (kernel, pool), work in zip(self._convs, self._workspace(x.shape)):
        x = work(x, kernel)
        if pool:  # max pool commutes with ReLU: apply it to 4x fewer values
          x = _maxpool2(x)
        np.maximum(x, 0.0, out=x)
      h = features = np.concatenate([x.mean(axis=(1, 2)), s], axis=-1)
      for kernel, bias in self._dense:
        h = h @ kernel
        h += bias
        np.maximum(h, 0.0, out=h)
      mean = h @ self._mean[0] + self._mean[1]
    if not (np.isfinite(features).all() and np.isfinite(mean).all()):
      raise PolicyError("the network's output is not finite for a finite input (an "
                        "overflow: weights too large for it?): no action")
    return self.low + 0.5 * (np.tanh(mean) + 1.0) * (self.high - self.low)

  def yaw_input(self, imu_yaw: float, start_yaw: float | None = None) -> float:
    """The state's yaw (rad, in [-pi, pi)) from the IMU yaw (rad) as the policy was
    trained: relative to `start_yaw`, the IMU yaw at the row entrance with the robot facing
    down the row (metadata `yaw_reference` "start"), or the IMU yaw plus `yaw_offset_deg`
    ("world", the paper's input; also files exported before the key existed; files of
    mjxvine 0.2.0 may carry an offset). PolicyInputError for a yaw that is not a finite
    number."""
    angle = lambda v, name: finite_number(v, name, PolicyInputError, "a finite angle in rad")
    imu_yaw = angle(imu_yaw, "imu_yaw")
    if self.layout["yaw_reference"] == "start":
      if start_yaw is None:
        raise PolicyInputError("this policy reads the yaw relative to the row entrance: "
                               "give start_yaw, the IMU yaw there")
      yaw = imu_yaw - angle(start_yaw, "start_yaw")
    else:
      yaw = imu_yaw + math.radians(self.layout["yaw_offset_deg"])
    return (yaw + math.pi) % (2 * math.pi) - math.pi

  def step(self, depth, state, preprocess: bool | None = None,
           wrap_yaw: bool | None = None) -> tuple[np.ndarray, bool]:
    """One robot's frame: (action (A,), whether the row has ended). The detector (the end
    of the row section above) reads the image as the policy sees it (cleaned with
    `preprocess`) and the state's v_prev, and keeps its memory (`row_memory`) from call to
    call: `reset_row()` at each row's entrance. Errors as `action`'s; PolicyInputError
    for a batch, PolicyFormatError for a file without the control step or vertical field
    of view the detector needs."""
    if not self.has_row_end:
      raise PolicyFormatError("this policy file lacks control_dt, fovy_deg or a v_prev "
                              "state entry: no end-of-row detector (export it again)")
    act, x, s = self._checked_action(depth, state, preprocess, wrap_yaw)
    if act.ndim != 1:
      raise PolicyInputError("step takes one robot's frame (depth (H, W), state (S,)); a "
                             "batch: action, and row_cue / row_update per robot")
    share, depth_m = row_cue(x[0, :, :, 0], self._row_band, self.row_end)
    self.row_memory, ended = row_update(self.row_memory, share, depth_m,
                                        s[0, self.state_layout.index("v_prev")],
                                        self.control_dt, self.row_end)
    return act, bool(ended)

  @property
  def has_row_end(self) -> bool:
    """Whether the file gives what the end-of-row detector needs (`step`): the control
    step, the vertical field of view and a v_prev state entry."""
    return (self.control_dt is not None and self.layout["fovy_deg"] is not None
            and "v_prev" in self.state_layout)

  def reset_row(self) -> None:
    """Forgets the last row: the end-of-row detector starts afresh (at a row's entrance)."""
    self.row_memory = row_start()

  def __call__(self, depth, state, preprocess: bool | None = None,
               wrap_yaw: bool | None = None):
    """(v, w): floats for one input, arrays (B,) for a batch (one per action dim); see
    `action`."""
    act = self.action(depth, state, preprocess, wrap_yaw)
    if act.ndim == 1:
      return tuple(float(a) for a in act)
    return tuple(act[:, i] for i in range(act.shape[1]))
