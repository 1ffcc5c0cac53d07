"""The robot never acts on garbage: NumpyPolicy refuses broken and crafted policy files
(NaN weights, bad metadata, zip bombs) with PolicyError only, returns finite actions in
the box or none, holds no memory after a large batch; the ROS 2 node's logic
(`mjxvine.deploy.node_logic`) stops on every bad message, and the node on any exception.
numpy only (no jax, no rclpy): fast."""

import io
import json
import math
import struct
import subprocess
import sys
import tracemalloc
import zlib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import ros_stubs
from mjxvine.deploy import node_logic as nl
from mjxvine.deploy import numpy_policy as npp
from mjxvine.deploy.numpy_policy import NumpyPolicy, PolicyError, PolicyFormatError

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "jackal.npz"  # 41x41, 4 convs, mirror averaging, fov 60 x 46.8


def _model():
  """(arrays, meta) of the shipped model, as np.load reads them (every entry)."""
  with np.load(MODEL) as data:
    arrays = {k: data[k] for k in data.files}
  return arrays, json.loads(str(arrays.pop("__meta__")))


def _save(path, arrays, meta):
  np.savez(path, __meta__=np.array(json.dumps(meta)), **arrays)
  return path


def _view(h=41, w=41):
  depth = np.full((h, w), 3.0, np.float32)
  depth[:, : w // 3] = 1.0
  return depth, np.array([0.2, 0.1, 0.3], np.float32)


def _acts_or_refuses(make, what):
  """make() -> a policy: it loads and gives finite actions in its box, or raises a
  PolicyError with a one-line message; nothing else."""
  try:
    policy = make()
    depth, state = _view(getattr(policy, "height", 41), getattr(policy, "width", 41))
    for call in (lambda: policy.action(depth, state),
                 lambda: policy.action(np.stack([depth, depth[:, ::-1]]), [state, state])):
      act = call()
      assert np.isfinite(act).all(), (what, act)
      assert (act >= policy.low).all() and (act <= policy.high).all(), (what, act)
  except PolicyError as e:
    assert str(e) and "\n" not in str(e), (what, str(e))
    return str(e)
  except Exception as e:  # pragma: no cover - the failure this test looks for
    raise AssertionError(f"{what}: {type(e).__name__}: {e}") from e
  return None


# ------------------------------------------------------- 1. non-finite weights, outputs

def test_non_finite_weights_are_refused_at_load(tmp_path):
  arrays, meta = _model()
  for name in ("tower/conv0/kernel", "dense1/bias", "mean/kernel"):
    for bad in (np.nan, np.inf):
      broken = dict(arrays)
      broken[name] = arrays[name].copy()
      broken[name].flat[3] = bad
      path = _save(tmp_path / "nan.npz", broken, meta)
      with pytest.raises(PolicyFormatError, match=f"{name} has 1 NaN or inf weights"):
        NumpyPolicy.load(path)
  # float64 beyond float32's range would become inf: refused too
  broken = dict(arrays, **{"dense0/bias": arrays["dense0/bias"].astype(np.float64) * 1e300})
  with pytest.raises(PolicyFormatError, match="dense0/bias has .* NaN or inf"):
    NumpyPolicy.load(_save(tmp_path / "f64.npz", broken, meta))


def test_an_overflowing_network_gives_no_action():
  """Finite weights so large that a finite input overflows: PolicyError, not (nan, nan)."""
  arrays, meta = _model()
  for scale in (1e30, 1e37):
    huge = dict(arrays)
    for name in ("dense0/kernel", "dense1/kernel", "mean/kernel"):
      huge[name] = arrays[name] * np.float32(scale)
    policy = NumpyPolicy(huge, meta)
    depth, state = _view()
    with pytest.raises(PolicyError, match="not finite for a finite input"):
      policy(depth, state)


def test_actions_are_always_inside_the_box():
  """Saturated outputs (tanh = +-1) and the mirror average of a box that is not symmetric
  in w stay inside the box (float32 rounding included)."""
  arrays, meta = _model()
  arrays = dict(arrays, **{"mean/bias": np.array([50.0, -50.0], np.float32)})
  for low, high in (([0.0, -1.0], [0.5, 1.0]), ([0.1, -0.3], [0.7, 0.9]),
                    ([0.3, -1e-3], [0.30000003, 2.0])):
    for mirror in (False, True):
      p = NumpyPolicy(arrays, dict(meta, action_low=low, action_high=high,
                                   mirror_average=mirror))
      rng = np.random.default_rng(0)
      depth = rng.uniform(0.0, 5.0, (16, 41, 41)).astype(np.float32)
      state = np.clip([[0.2, 0.1, 0.3]] * 16, p.state_lo, p.state_hi)
      act = p.action(depth, state)
      assert act.dtype == np.float32 and np.isfinite(act).all()
      assert (act >= p.low).all() and (act <= p.high).all(), (low, high, mirror, act)


# ----------------------------------------------------------------- 2. metadata and shapes

def test_reported_metadata_crashes_are_policy_errors(tmp_path):
  """The probes: each was a ZeroDivisionError, KeyError or IndexError."""
  arrays, meta = _model()
  cases = {
      "stride 0": ({"conv_layers": [[0, False]] * 4}, {}, "conv_layers"),
      "no hidden layers": ({"num_hidden": 0}, {}, "num_hidden"),
      "scalar kernel": ({}, {"tower/conv0/kernel": np.float32(1.0)}, "tower/conv0/kernel"),
      "NaN action box": ({"action_low": [math.nan, -1.0]}, {}, "action_low"),
      "low = high": ({"action_low": [0.5, -1.0]}, {}, "action box"),
      "low > high": ({"action_low": [0.0, 2.0]}, {}, "action box"),
      "wrong rank": ({}, {"dense1/kernel": np.zeros(64, np.float32)}, "dense1/kernel"),
      "wrong shape": ({}, {"mean/bias": np.zeros(3, np.float32)}, "mean/bias"),
      "image too small": ({"image_size": [5, 5]}, {}, "too small"),
      "image huge": ({"image_size": [100000, 100000]}, {}, "image_size"),
      "a string for a number": ({"max_depth_m": "5"}, {}, "max_depth_m"),
  }
  for what, (meta_update, arrays_update, match) in cases.items():
    path = _save(tmp_path / "bad.npz", dict(arrays, **arrays_update), dict(meta, **meta_update))
    with pytest.raises(PolicyFormatError, match=match) as e:
      NumpyPolicy.load(path)
    assert str(e.value).startswith(str(path)) and "\n" not in str(e.value), what
    with pytest.raises(PolicyFormatError, match=match):
      NumpyPolicy(dict(arrays, **arrays_update), dict(meta, **meta_update))


_VALUES = [None, True, 0, -1, 0.5, 3, 1e300, 10**40, math.nan, math.inf, -math.inf, "x", "",
           [], [0], [1, 2, 3], [[1, 2]], [41, 41], [[2, True]], {"a": 1}]


def _meta_mutations(meta):
  for key in ("image_size", "max_depth_m", "depth_scale", "action_low", "action_high",
              "conv_layers", "num_hidden", "tower_pad", "mirror_average", "state_layout",
              "yaw_reference", "yaw_offset_deg", "control_dt", "fovx_deg", "fovy_deg"):
    yield f"no {key}", {k: v for k, v in meta.items() if k != key}
    for value in _VALUES:
      yield f"{key}={value!r}", dict(meta, **{key: value})
  for layers in ([[2, False]], [[2, False]] * 5, [[1, False]] * 4, [[9, False]] * 4,
                 [[2, "no"]] * 4, [[2.0, False]] * 4, [[2]] * 4):
    yield f"conv_layers={layers}", dict(meta, conv_layers=layers)
  for size in ([1, 1], [3, 3], [41], [41, 41, 41], [41.5, 41], [-41, 41], [512, 512]):
    yield f"image_size={size}", dict(meta, image_size=size)
  yield "num_hidden=3", dict(meta, num_hidden=3)
  yield "1 action", dict(meta, action_low=[0.0], action_high=[0.5])
  yield "3 actions", dict(meta, action_low=[0.0, -1.0, 0.0], action_high=[0.5, 1.0, 1.0])
  yield "a JSON list", [1, 2]


def _array_mutations(arrays, rng):
  names = ["tower/conv0/kernel", "tower/conv3/bias", "dense0/kernel", "dense1/bias",
           "mean/kernel", "mean/bias"]
  for name in names:
    a = arrays[name]
    yield f"no {name}", {k: v for k, v in arrays.items() if k != name}
    for label, value in (
        ("scalar", np.float32(1.0)), ("rank+1", a[None]), ("flat", a.reshape(-1)),
        ("empty", np.zeros((0,), np.float32)), ("last axis 0", a[..., :0]),
        ("last axis +1", np.concatenate([a, a[..., :1]], -1)), ("zeros", np.zeros_like(a)),
        ("NaN", np.full_like(a, np.nan)), ("inf", a * np.inf), ("huge", a * np.float32(1e38)),
        ("float64 1e300", a.astype(np.float64) * 1e300), ("int", a.astype(np.int32)),
        ("bool", a > 0), ("complex", a.astype(np.complex64)), ("str", np.array("x")),
        ("list", a.tolist()), ("random shape", rng.standard_normal(
            tuple(rng.integers(0, 5, rng.integers(0, 5)))).astype(np.float32))):
      yield f"{name} {label}", dict(arrays, **{name: value})


def test_fuzzed_metadata_and_arrays_raise_only_policy_errors(tmp_path):
  """Mutations of a valid policy's metadata and arrays (keys deleted, wrong types, zeros,
  NaN, huge values, wrong ranks and shapes): it loads and acts (finite, in the box) or
  raises PolicyError, built directly and, for the metadata, loaded from a file."""
  arrays, meta = _model()
  rng = np.random.default_rng(0)
  refused = 0
  for what, m in _meta_mutations(meta):
    refused += _acts_or_refuses(lambda: NumpyPolicy(arrays, m), what) is not None
    if isinstance(m, dict):
      path = _save(tmp_path / "fuzz.npz", arrays, m)
      _acts_or_refuses(lambda: NumpyPolicy.load(path), f"file {what}")
  for what, a in _array_mutations(arrays, rng):
    refused += _acts_or_refuses(lambda: NumpyPolicy(a, meta), what) is not None
  # random pairs of mutations
  metas, arrs = list(_meta_mutations(meta)), list(_array_mutations(arrays, rng))
  for i in rng.integers(0, len(metas), 60):
    j = rng.integers(0, len(arrs))
    _acts_or_refuses(lambda: NumpyPolicy(arrs[j][1], metas[i][1]), f"{metas[i][0]} + {arrs[j][0]}")
  assert refused > 300  # the mutations do break policies: the test can fail


def test_bad_arguments_and_inputs_raise_only_policy_errors():
  for kw in ({"depth_scale": "mm"}, {"depth_scale": 0}, {"depth_scale": math.nan},
             {"invalid_depth": -1.0}, {"invalid_depth": math.inf}, {"invalid_depth": "far"},
             {"blas_threads": "many"}, {"blas_threads": 0}):
    with pytest.raises(PolicyError):
      NumpyPolicy.load(MODEL, **kw)
  policy = NumpyPolicy.load(MODEL)
  depth, state = _view()
  for d, s in ((object(), state), ("x", state), (depth, "x"), (depth, [1, [2]]),
               (depth.astype(np.complex64), state), (depth, [math.nan] * 3),
               ([[1, 2], [3]], state), (depth[None, None], state)):
    with pytest.raises(PolicyError):
      policy(d, s)
  for args in ((math.nan, 0.0), ("x", 0.0), (0.0, math.inf), (0.0, None)):
    with pytest.raises(PolicyError):
      policy.yaw_input(*args)
  with pytest.raises(PolicyError):
    policy.clean_depth("x")


# ----------------------------------------------------------------------- 3. zip bombs

def _npy(array) -> bytes:
  buf = io.BytesIO()
  np.lib.format.write_array(buf, np.asanyarray(array), allow_pickle=False)
  return buf.getvalue()


def _zeros_entry(name: str, shape, dtype="<f4"):
  """A deflated .npy entry of zeros (name, method, data, crc, size), made in well under a
  second whatever its size: one 1 MiB block deflated after a full flush repeats."""
  buf = io.BytesIO()
  np.lib.format.write_array_header_1_0(buf, {"descr": dtype, "fortran_order": False,
                                             "shape": tuple(shape)})
  header, chunk = buf.getvalue(), bytes(1 << 20)
  zeros = math.prod(shape) * np.dtype(dtype).itemsize
  assert zeros % len(chunk) == 0
  c = zlib.compressobj(9, zlib.DEFLATED, -15)
  parts, crc = [c.compress(header)], zlib.crc32(header)
  if zeros:
    parts.append(c.compress(chunk) + c.flush(zlib.Z_FULL_FLUSH))
    block = c.compress(chunk) + c.flush(zlib.Z_FULL_FLUSH)
    parts += [block] * (zeros // len(chunk) - 1)
  parts.append(c.flush())
  for _ in range(zeros // len(chunk)):
    crc = zlib.crc32(chunk, crc)
  return name, 8, b"".join(parts), crc, len(header) + zeros


def _write_zip(path, entries):
  """A zip archive of (name, method 0 or 8, data, crc32, unpacked size) entries."""
  out, central = io.BytesIO(), []
  for name, method, data, crc, size in entries:
    offset, raw = out.tell(), name.encode()
    out.write(struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, method, 0, 0x21, crc, len(data),
                          size, len(raw), 0) + raw + data)
    central.append(struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, 0, method, 0, 0x21,
                               crc, len(data), size, len(raw), 0, 0, 0, 0, 0, offset) + raw)
  directory = b"".join(central)
  start = out.tell()
  out.write(directory + struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, len(entries),
                                    len(entries), len(directory), start, 0))
  Path(path).write_bytes(out.getvalue())
  return path


def _header_entry(name, descr, shape, data_bytes=0):
  """A stored .npy entry of a header declaring (descr, shape) and `data_bytes` zeros."""
  buf = io.BytesIO()
  np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False,
                                             "shape": shape})
  data = buf.getvalue() + bytes(data_bytes)
  return name, 0, data, zlib.crc32(data), len(data)


def _stored(name, array):
  data = _npy(array)
  return name, 0, data, zlib.crc32(data), len(data)


def _policy_entries(arrays, meta):
  return [_stored("__meta__.npy", np.array(json.dumps(meta)))] + [
      _stored(f"{k}.npy", v) for k, v in arrays.items()]


@pytest.fixture(scope="module")
def bomb(tmp_path_factory):
  """A valid policy file plus an entry "extra.npy" that unpacks to 1 GiB (1 MB on disk)."""
  arrays, meta = _model()
  path = tmp_path_factory.mktemp("bomb") / "bomb.npz"
  _write_zip(path, _policy_entries(arrays, meta) + [_zeros_entry("extra.npy", (1 << 28,))])
  assert path.stat().st_size < 2 << 20
  with np.load(MODEL) as data:
    assert len(data.files) == 17  # and np.load would unpack all 18, 1 GiB included
  return path


_MEASURE = """
import resource, sys, time
from mjxvine.deploy.numpy_policy import NumpyPolicy, PolicyFormatError, read_policy_file
t = time.perf_counter()
for load in (NumpyPolicy.load, read_policy_file):
  try:
    load(sys.argv[1])
  except PolicyFormatError as e:
    print(e)
  else:
    raise AssertionError("loaded")
# VmHWM: this process's own peak (ru_maxrss also counts the forked parent's pages)
hwm = [l for l in open("/proc/self/status") if l.startswith("VmHWM:")]
peak_kb = int(hwm[0].split()[1]) if hwm else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(time.perf_counter() - t, peak_kb / 1024)
"""


def test_a_zip_bomb_is_refused_unread(bomb):
  """Refused from the zip directory: well under 500 MB peak and 10 s (a subprocess, so
  that its peak memory is its own)."""
  out = subprocess.run([sys.executable, "-c", _MEASURE, str(bomb)], capture_output=True,
                       text=True, timeout=60)
  assert out.returncode == 0, out.stderr
  *errors, last = out.stdout.strip().splitlines()
  seconds, peak_mb = (float(v) for v in last.split())
  assert len(errors) == 2 and all("extra.npy" in e and "1073741952 bytes" in e for e in errors)
  assert seconds < 10.0 and peak_mb < 500.0, (seconds, peak_mb)


def test_crafted_archives_are_refused_before_unpacking(tmp_path):
  arrays, meta = _model()
  good = _policy_entries(arrays, meta)
  cases = {
      # a known name, declared far over its bound
      "dense0/kernel of 64 MiB": ([e for e in good if e[0] != "dense0/kernel.npy"] +
                                  [_zeros_entry("dense0/kernel.npy", (1 << 12, 1 << 12))],
                                 f"at most {npp.MAX_ARRAY_BYTES}"),
      "__meta__ of 64 MiB": ([e for e in good if e[0] != "__meta__.npy"] +
                             [_zeros_entry("__meta__.npy", (1 << 24,))],
                             f"at most {npp.MAX_META_BYTES}"),
      # each under the bound, together over it
      "arrays over the total": (good + [_zeros_entry(f"dense{i}/kernel.npy", (7 << 20,))
                                        for i in (6, 7, 8, 9)],
          f"arrays of .* bytes: at most {npp.MAX_TOTAL_BYTES}"),
      # a header that declares 40 GB in a small entry
      "lying header": ([e for e in good if e[0] != "mean/kernel.npy"] +
                       [_header_entry("mean/kernel.npy", "<f4", (100000, 100000))],
                       "header declares 40000000000 bytes"),
      "too many entries": (good + [_stored(f"junk{i}.npy", np.zeros(1)) for i in range(300)],
                           f"at most {npp.MAX_ENTRIES}"),
      "pickled objects": ([e for e in good if e[0] != "mean/bias.npy"] +
                          [_header_entry("mean/bias.npy", "|O", (2,), 16)],
                          "mean/bias.npy holds pickled object arrays"),
  }
  for what, (entries, match) in cases.items():
    path = _write_zip(tmp_path / "crafted.npz", entries)
    for load in (NumpyPolicy.load, npp.read_policy_file):
      if what == "arrays over the total" and load == NumpyPolicy.load:
        NumpyPolicy.load(path)  # reads only the arrays it needs: the extra 128 MiB unread
        continue
      with pytest.raises(PolicyFormatError, match=match) as e:
        load(path)
      assert str(e.value).startswith(str(path)) and "\n" not in str(e.value), what
  # other small entries are not read, and harmless
  path = _write_zip(tmp_path / "extra.npz", good + [_stored("notes.npy", np.zeros(10))])
  assert "notes" not in npp.read_policy_file(path)[0]
  NumpyPolicy.load(path)


# ----------------------------------------------------------------- 4. memory after a batch

def test_a_large_batch_holds_no_memory_afterwards():
  """4,000 images: the conv buffers were cached per batch size (2.1 GB held after the
  call); now batches run in chunks and each thread keeps two shapes' buffers."""
  policy = NumpyPolicy.load(MODEL)
  depth = np.full((4000, 41, 41), 3.0, np.float32)
  state = np.tile([0.2, 0.1, 0.3], (4000, 1))
  tracemalloc.start()
  try:
    before = tracemalloc.get_traced_memory()[0]
    act = policy.action(depth, state)
    held = tracemalloc.get_traced_memory()[0] - before - act.nbytes
    peak = tracemalloc.get_traced_memory()[1] - before
  finally:
    tracemalloc.stop()
  assert held <= npp.CACHED_SHAPES * npp.WORKSPACE_BYTES + (2 << 20), held / 1e6
  assert peak < 400e6, peak / 1e6
  np.testing.assert_allclose(act[1234], policy(depth[0], state[0]), atol=1e-6)


def test_chunked_batches_give_the_same_actions(monkeypatch):
  policy = NumpyPolicy.load(MODEL)
  rng = np.random.default_rng(3)
  depth = rng.uniform(0.3, 5.0, (5, 41, 41)).astype(np.float32)
  state = np.array([[0.2, 0.1, 0.3]] * 5) * rng.uniform(-1, 1, (5, 3))
  state[:, 0] = np.abs(state[:, 0])
  whole = policy.action(depth, state)
  # 2 images (of 2 x 2 with the mirror) per chunk: chunks of 2, 2 and 1
  monkeypatch.setattr(npp, "WORKSPACE_BYTES", 4 * policy._work_bytes)
  np.testing.assert_allclose(policy.action(depth, state), whole, atol=1e-6)
  for i in range(5):
    np.testing.assert_allclose(policy.action(depth[i], state[i]), whole[i], atol=1e-6)


# ------------------------------------------------------------------------- 5. latency

def test_latency_command_prints_one_line_on_a_bad_policy(tmp_path, bomb, capsys):
  from mjxvine import latency
  from mjxvine.deploy.latency import numpy_latency

  arrays, meta = _model()
  bad = {"nan": (dict(arrays, **{"mean/bias": np.full(2, np.nan, np.float32)}), meta),
         "stride0": (arrays, dict(meta, conv_layers=[[0, False]] * 4)),
         "overflow": (dict(arrays, **{k: arrays[k] * np.float32(1e37) for k in
                                      ("dense0/kernel", "dense1/kernel")}), meta)}
  paths = [_save(tmp_path / f"{k}.npz", *v) for k, v in bad.items()] + [bomb]
  for path in paths:
    capsys.readouterr()
    assert latency.main(["--policy", str(path), "--calls", "2"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"latency error: {path}") and err.count("\n") == 1, err
    with pytest.raises(PolicyError):
      numpy_latency(path, calls=2)


# ------------------------------------------------------------- 6. the node's logic, no ROS

NOW = 1000.0


def _stamp(t):
  sec = math.floor(t)
  return SimpleNamespace(sec=sec, nanosec=int(round((t - sec) * 1e9)))


def _image(counts=None, stamp=NOW, encoding="16UC1", **fields):
  if counts is None:
    counts = np.full((41, 41), 5000)
    counts[20:] = np.linspace(5000, 1000, 21).round()[:, None]
  counts = np.asarray(counts, "<u2")
  msg = dict(header=SimpleNamespace(stamp=_stamp(stamp)), data=counts.tobytes(),
             encoding=encoding, height=counts.shape[0], width=counts.shape[1],
             step=2 * counts.shape[1], is_bigendian=0)
  return SimpleNamespace(**{**msg, **fields})


def _imu(yaw, stamp=NOW, cov0=0.0, q=None):
  x, y, z, w = q if q is not None else (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
  return SimpleNamespace(header=SimpleNamespace(stamp=_stamp(stamp)),
                         orientation=SimpleNamespace(x=x, y=y, z=z, w=w),
                         orientation_covariance=np.array([cov0] + [0.0] * 8))


def _info(height=41, width=41, fx=35.5):
  return SimpleNamespace(height=height, width=width,
                         k=[fx, 0.0, width / 2, 0.0, fx, height / 2, 0.0, 0.0, 1.0])


@pytest.fixture(scope="module")
def policy():
  return NumpyPolicy.load(MODEL, preprocess=True)


def _driving(policy, **kw):
  """A DriveLogic that has had a valid image and IMU reading at NOW (row entrance yaw 0)."""
  logic = nl.DriveLogic(policy, timeout_s=0.5, fov_crop=kw.pop("fov_crop", False), **kw)
  if logic.fov_crop:
    logic.take_camera_info(_info())
  logic.take_imu(_imu(0.0), NOW)
  logic.take_depth(_image(), NOW)
  d = logic.decide(NOW)
  assert d.reason is None and d.v > 0.05, d
  return logic


def _assert_stop(logic, now, reason, level="error"):
  d = logic.decide(now)
  assert (d.v, d.w) == (0.0, 0.0) and d.level == level and reason in d.reason, d
  return d


def test_the_end_of_the_row_stops_the_robot_until_the_next_row(policy):
  """Plants on both sides, then none: the end-of-row detector fires once the robot has
  driven the last plants' depth past them; the logic stops (level info, row_end) until
  zero_heading at the next row's entrance. stop_at_row_end=False drives on."""
  row = np.full((41, 41), 5000)
  row[20:] = np.linspace(5000, 1000, 21).round()[:, None]
  row[:20, :8] = row[:20, -8:] = 1500  # plants 1.5 m ahead on both sides
  for stop in (True, False):
    logic = nl.DriveLogic(policy, timeout_s=0.5, fov_crop=False, stop_at_row_end=stop)
    logic.take_imu(_imu(0.0), NOW)
    decisions = []
    for i in range(200):
      t = NOW + 0.1 * i
      logic.take_imu(_imu(0.0, stamp=t), t)
      logic.take_depth(_image(row if i < 10 else None, stamp=t), t)
      d = logic.decide(t)
      logic.commanded(d.v, d.w)
      decisions.append(d)
    ended = [d.row_end for d in decisions]
    if not stop:
      assert not any(ended) and all(d.v > 0 for d in decisions)
      continue
    first = ended.index(True)
    # 1.5 m + the 0.3 m margin at the policy's speed (about 0.05 m per decision)
    assert 10 + 1.8 / 0.05 - 1 <= first <= 10 + 1.8 / 0.02 and all(ended[first:])
    assert all(d.v > 0 for d in decisions[:first])
    assert all((d.v, d.w, d.level) == (0.0, 0.0, "info") for d in decisions[first:])
    assert "end of the row" in decisions[-1].reason
    assert logic.zero_heading()  # the next row's entrance: driving again
    # (the view `_driving` drives on: how fast the policy starts is its own, not the logic's)
    logic.take_depth(_image(stamp=NOW + 20.0), NOW + 20.0)
    logic.take_imu(_imu(0.0, stamp=NOW + 20.0), NOW + 20.0)
    d = logic.decide(NOW + 20.0)
    assert d.reason is None and d.v > 0.05 and not d.row_end


def test_a_policy_file_without_the_detector_still_drives(tmp_path):
  """A file exported before the end-of-row detector (no fovy_deg): the logic drives
  without the stop, as before; NumpyPolicy.step says why it cannot."""
  arrays, meta = _model()
  meta.pop("fovy_deg")
  old = NumpyPolicy.load(_save(tmp_path / "old.npz", arrays, meta), preprocess=True)
  assert not old.has_row_end
  with pytest.raises(PolicyFormatError, match="no end-of-row detector"):
    old.step(*_view())
  logic = _driving(old)
  assert not logic.stop_at_row_end and not logic.decide(NOW).row_end


def test_imu_without_orientation_is_no_yaw(policy):
  """REP 145: orientation_covariance[0] == -1 means no orientation; a zero or non-unit
  quaternion has none either. Never yaw 0: a stop, with the reason."""
  for msg, reason in ((_imu(0.3, cov0=-1.0), "orientation_covariance[0] = -1"),
                      (_imu(0.0, q=(0.0, 0.0, 0.0, 0.0)), "norm 0"),
                      (_imu(0.0, q=(0.0, 0.0, 0.0, 2.0)), "norm 2"),
                      (_imu(0.0, q=(0.0, 0.0, math.nan, 1.0)), "IMU orientation nan"),
                      (SimpleNamespace(header=_imu(0).header), "orientation")):
    logic = _driving(policy)
    logic.take_imu(msg, NOW + 0.05)
    assert logic.yaw is None
    _assert_stop(logic, NOW + 0.05, "IMU reading refused: ")
    _assert_stop(logic, NOW + 0.05, reason)
  # the first IMU reading without orientation does not become the row-entrance reference
  logic = nl.DriveLogic(policy, fov_crop=False)
  logic.take_imu(_imu(0.0, q=(0.0, 0.0, 0.0, 0.0)), NOW)
  assert logic.yaw_ref is None and not logic.zero_heading()
  logic.take_imu(_imu(0.7), NOW)
  assert logic.yaw_ref == pytest.approx(0.7) and logic.yaw == pytest.approx(0.0)
  # a slightly denormalised quaternion (float32 in the driver) is read as the unit one
  assert nl.imu_yaw(0.0, 0.0, 0.5 * 1.004, 0.866 * 1.004) == pytest.approx(
      nl.imu_yaw(0.0, 0.0, 0.5, 0.866), abs=1e-9)


def test_freshness_is_judged_by_header_stamps(policy):
  logic = _driving(policy)
  # an image that arrives now but was taken 1 s ago (a queue, a slow link)
  logic.take_depth(_image(stamp=NOW - 1.0), NOW)
  _assert_stop(logic, NOW, "depth image is 1.000 s old (timeout_s 0.5)")
  logic.take_depth(_image(stamp=NOW + 1.0), NOW)  # from the future: clocks disagree
  _assert_stop(logic, NOW, "stamped 1.000 s after the node's clock")
  logic.take_depth(_image(stamp=0.0), NOW)  # a driver that does not stamp
  _assert_stop(logic, NOW, "header stamp is zero")
  logic.take_depth(_image(stamp=NOW + 0.02), NOW)  # within the clock tolerance
  assert logic.decide(NOW).reason is None
  # no new message: the stamps age with the node's clock
  _assert_stop(logic, NOW + 0.6, "depth image is 0.580 s old", "warn")
  logic.take_depth(_image(stamp=NOW + 0.6), NOW + 0.6)
  _assert_stop(logic, NOW + 0.6, "IMU reading is 0.600 s old", "warn")
  logic.take_imu(_imu(0.0, stamp=NOW - 0.7), NOW + 0.6)
  _assert_stop(logic, NOW + 0.6, "IMU reading is 1.300 s old")


def test_images_that_do_not_fit_are_refused(policy):
  """Transposed (height and width swapped against camera_info), a wrong step, a wrong
  encoding for its data, a short or long buffer: refused, never resized and driven on."""
  logic = _driving(policy, fov_crop=True)
  counts = np.tile(np.linspace(800, 5000, 41).round(), (41, 1))
  cases = {
      "transposed": (_image(counts[:, :30].T), dict(height=41, width=30), "transposed"),
      "step": (_image(counts), {}, "image step 182"),
      "encoding": (_image(counts, encoding="32FC1"), {}, "expected height 41 x step 164"),
      "short": (_image(counts), {}, "expected height 41 x step 82"),
      "long": (_image(counts), {}, "expected height 41 x step 82"),
      "mono16": (_image(counts, encoding="mono16"), {}, "expected one of 16UC1, 32FC1"),
      "bigendian": (_image(counts), {}, "is_bigendian 2"),
  }
  cases["step"][0].step = 182
  cases["encoding"][0].step = 164
  cases["short"][0].data = cases["short"][0].data[:-2]
  cases["long"][0].data = cases["long"][0].data + b"\0\0"
  cases["bigendian"][0].is_bigendian = 2
  for what, (msg, info, reason) in cases.items():
    logic.take_camera_info(_info(**info) if info else _info())
    logic.take_depth(msg, NOW)
    assert logic.depth is None, what
    _assert_stop(logic, NOW, reason)
    logic.take_camera_info(_info())
    logic.take_depth(_image(), NOW)
    assert logic.decide(NOW).reason is None, what  # valid again: drives
  # a square image's height and width cannot be told apart: its step and size must fit
  padded = np.pad(counts, ((0, 0), (0, 1))).astype("<u2").tobytes()
  logic.take_depth(_image(counts, step=84, data=padded), NOW)
  assert logic.decide(NOW).reason is None  # 2 bytes of row padding are fine
  for bad in (_info(fx=0.0), _info(fx=math.nan), SimpleNamespace(height=41, width=41, k=[1])):
    logic.take_camera_info(bad)
    _assert_stop(logic, NOW, "camera_info refused")


class _Broken:
  """A policy stand-in whose call fails in a chosen way."""

  def __init__(self, policy, result):
    self._policy, self._result = policy, result

  def __getattr__(self, name):
    return getattr(self._policy, name)

  def __call__(self, depth, state):
    if isinstance(self._result, Exception):
      raise self._result
    return self._result

  def step(self, depth, state):  # the node's call: the action and the end of the row
    return self(depth, state), False


def test_any_failure_is_a_stop(policy):
  for result, reason in ((RuntimeError("boom"), "decision failed (RuntimeError: boom)"),
                         (MemoryError(), "decision failed (MemoryError)"),
                         ((math.nan, 0.0), "non-finite command"),
                         ((0.3, math.inf), "non-finite command"),
                         (PolicyError("odd"), "policy refused its input: odd")):
    logic = _driving(policy)
    logic.policy = _Broken(policy, result)
    _assert_stop(logic, NOW, reason)
  logic = _driving(policy)
  logic.take_depth(None, NOW)  # not even a message
  _assert_stop(logic, NOW, "depth image refused: AttributeError")
  logic = _driving(policy, max_speed=0.1)
  assert 0.05 < logic.decide(NOW).v <= 0.1
  with pytest.raises(ValueError, match="max_speed"):
    nl.DriveLogic(policy, max_speed=math.nan)
  with pytest.raises(ValueError, match="timeout_s"):
    nl.DriveLogic(policy, timeout_s=0.0)


_ALONE = """
import math, sys
from types import SimpleNamespace as NS
import numpy as np
from mjxvine_deploy import NumpyPolicy
from mjxvine_node_logic import DriveLogic
logic = DriveLogic(NumpyPolicy.load(sys.argv[1], preprocess=True), fov_crop=False)
counts = np.full((41, 41), 3000, "<u2")
logic.take_imu(NS(orientation=NS(x=0.0, y=0.0, z=0.0, w=1.0)), 5.0)
logic.take_depth(NS(data=counts.tobytes(), encoding="16UC1", height=41, width=41, step=82,
                    is_bigendian=0), 5.0)
d = logic.decide(5.0)
assert d.reason is None and d.v > 0.0, d
assert not [m for m in sys.modules if m.split(".")[0] in BLOCKED + ("mjxvine",)]
print("ok")
"""


def test_the_node_logic_runs_copied_next_to_the_policy_file(tmp_path):
  """node_logic.py and numpy_policy.py copied onto a robot (as mjxvine_node_logic.py and
  mjxvine_deploy.py) run with numpy alone and parse as Python 3.8."""
  import os
  import shutil

  from conftest import NUMPY_ONLY_PRELUDE, parse_source

  for src, name in ((nl.__file__, "mjxvine_node_logic.py"), (npp.__file__, "mjxvine_deploy.py")):
    parse_source(Path(src).read_text(), feature_version=(3, 8))
    shutil.copy(src, tmp_path / name)
  env = dict(os.environ, OPENBLAS_NUM_THREADS="1", PYTHONPATH=str(tmp_path))
  code = NUMPY_ONLY_PRELUDE.replace('"orbax")', '"orbax", "mjxvine")') + _ALONE
  out = subprocess.run([sys.executable, "-c", code, str(MODEL)], capture_output=True,
                       text=True, env=env, timeout=60, cwd=tmp_path)
  assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


# ------------------------------------------------------------ the node itself, stub rclpy

@pytest.fixture
def node_module(monkeypatch):
  """examples/ros2_vineyard_node.py on stub rclpy and message modules."""
  return ros_stubs.load_node_module(monkeypatch, {"policy": str(MODEL)}, clock_s=NOW)


def _command(node):
  node.on_timer()
  twist = node.published[-1]
  return twist.linear.x, twist.angular.z


def test_the_node_stops_on_any_exception_and_keeps_running(node_module):
  node = node_module.VineyardNode()
  node.on_camera_info(_info())
  node.on_imu(_imu(0.0))
  node.on_depth(_image())
  assert _command(node)[0] > 0.05
  assert [m.data for m in node.topics["row_end"]] == [False]  # published with each command
  # a callback that raises: a stop at once, logged; the input is not driven on
  node.take_depth = lambda msg, now: 1 / 0
  node.on_depth(_image())
  assert (node.published[-1].linear.x, node.published[-1].angular.z) == (0.0, 0.0)
  level, msg, kw = node.get_logger().records[-1]
  assert level == "error" and "depth failed (ZeroDivisionError" in msg and kw
  assert _command(node) == (0.0, 0.0)
  del node.take_depth
  node.on_depth(_image())
  assert _command(node)[0] > 0.05  # still running: drives again
  node.decide = lambda now: {}["x"]
  assert _command(node) == (0.0, 0.0) and "timer failed (KeyError" in (
      node.get_logger().records[-1][1])
  del node.decide
  node.on_imu(_imu(0.0, cov0=-1.0))  # an IMU without orientation
  assert _command(node) == (0.0, 0.0)
  assert "orientation_covariance[0] = -1" in node.get_logger().records[-1][1]
  node.on_imu(_imu(0.0))
  node.t += 0.1
  node.on_depth(_image(stamp=node.t - 0.7))  # old when it arrives
  assert _command(node) == (0.0, 0.0) and "s old" in node.get_logger().records[-1][1]
  response = node.on_zero_heading(None, SimpleNamespace())
  assert response.success


def test_the_node_does_not_start_on_a_bad_policy(node_module, tmp_path, monkeypatch, capsys):
  arrays, meta = _model()
  path = _save(tmp_path / "nan.npz", dict(arrays, **{"mean/bias": np.full(2, np.nan,
                                                                         np.float32)}), meta)
  monkeypatch.setattr(ros_stubs.Node, "params", {"policy": str(path)})
  assert node_module.main([]) == 2
  assert "mean/bias has 2 NaN or inf weights" in capsys.readouterr().err
