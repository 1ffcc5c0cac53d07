"""The conv tower on the CPU as a hand-written kernel (XLA FFI calls), for the learner.

XLA's CPU backend runs the tower's small convolutions (8-32 channels, 3x3) and the ops
around them (ReLUs, max pool, their gradients: a few hundred small ops a gradient step)
far below the machine's matrix-multiply rate. `mjxvine/native/tower.cc` computes the
whole tower (`tower.CONV_LAYERS`: 4 convs with biases and ReLUs, the max pool, the
mean) in one call, each image in one thread through every layer in buffers that stay in
the core's cache: `tower(x, params) -> (N, F)`, and its gradient w.r.t. the params in one
more. Equal to XLA's tower (`xla_tower`) to float32 rounding (tests/test_native_conv.py);
docs/results/cpu-update-speed.md has what it gains.

A call cuts its images into runs and hands them to XLA's own intra-op thread pool, the
one XLA's CPU ops run on, and returns at once (an asynchronous FFI call): tower calls
that XLA runs side by side, and XLA's other ops, share the cores rather than each
starting threads of its own. `MJXVINE_NATIVE_THREADS=n` caps the threads of one call
(default: the pool's size); the results are the same bits for any n.

The library is compiled on first use with the system's C++ compiler (`$CXX` or `g++`)
into `$MJXVINE_CACHE` (default `~/.cache/mjxvine`), one file per source, flags, jax
version and compiler, and registered with `jax.ffi`: with AVX-512 on CPUs that have it
(`instruction_set()`), else with AVX2 and FMA. Its sums are not in XLA's order (nor the
same for the two builds), so a run with it leaves a run without it at the first rounding
difference; they do not depend on the number of threads. `available()` is False, with the
reason in `unavailable_reason()`, when the machine is not x86-64 Linux with AVX2 and FMA,
when no compiler builds it, or when `MJXVINE_NATIVE_CONV=0` (`MJXVINE_NATIVE_CONV=avx2`
takes the AVX2 build on an AVX-512 CPU); `conv_impl="native"` (`train.conv_impl: native`)
then fails with that reason.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from mjxvine.tower import CONV_LAYERS, lax_conv3x3

SOURCE = Path(__file__).parent / "tower.cc"
FLAGS = ("-O3", "-mavx2", "-mfma", "-shared", "-fPIC", "-std=c++17", "-w")
AVX512 = ("avx512f", "avx512dq", "avx512bw", "avx512vl")  # the CPU flags of the second build
AVX512_FLAGS = FLAGS + tuple(f"-m{f}" for f in AVX512)
TOWER, TOWER_TRAIN, TOWER_GRAD = "mjxvine_tower", "mjxvine_tower_train", "mjxvine_tower_grad"
TOWER_LAYERS = ((2, False), (1, True), (2, False), (1, False))  # what the kernel computes
TOWER_FEATURES = (8, 16, 32)


def _cpu_flags() -> set[str]:
  try:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
      if line.startswith("flags"):
        return set(line.split(":", 1)[1].split())
  except OSError:
    pass
  return set()


def _build(flags: tuple[str, ...]) -> Path:
  """Compile the library (once per source, flags, jax version and compiler) -> its
  path."""
  cxx = os.environ.get("CXX") or shutil.which("g++") or shutil.which("c++")
  if not cxx:
    raise RuntimeError("no C++ compiler (set $CXX or install g++)")
  include = jax.ffi.include_dir()
  key = hashlib.sha256(SOURCE.read_bytes() + " ".join(flags).encode()
                       + jax.__version__.encode() + cxx.encode()).hexdigest()[:16]
  cache = Path(os.environ.get("MJXVINE_CACHE", Path.home() / ".cache" / "mjxvine"))
  lib = cache / f"tower-{key}.so"
  if lib.is_file():
    return lib
  cache.mkdir(parents=True, exist_ok=True)
  with tempfile.TemporaryDirectory(dir=cache) as tmp:
    out = Path(tmp) / lib.name
    done = subprocess.run([cxx, *flags, f"-I{include}", str(SOURCE), "-o", str(out)],
                          capture_output=True, text=True, check=False)
    if done.returncode != 0:
      raise RuntimeError(f"{cxx} could not build {SOURCE.name} (exit {done.returncode}): "
                         f"{done.stderr.strip()[-500:]}")
    os.replace(out, lib)  # atomic: a second process never loads a half-written file
  return lib


def _choice() -> str:
  return os.environ.get("MJXVINE_NATIVE_CONV", "1")


def instruction_set() -> str:
  """"avx512" where the CPU has `AVX512` and `MJXVINE_NATIVE_CONV` is not "avx2", else
  "avx2": the build that `available()` loads."""
  return "avx512" if _choice() != "avx2" and set(AVX512) <= _cpu_flags() else "avx2"


@functools.cache
def _load() -> str | None:
  """Build and register the FFI targets; None on success, else why not."""
  if _choice() == "0":
    return "disabled by MJXVINE_NATIVE_CONV=0"
  if platform.system() != "Linux" or platform.machine() not in ("x86_64", "AMD64"):
    return f"needs x86-64 Linux (this is {platform.system()} {platform.machine()})"
  if not {"avx2", "fma"} <= _cpu_flags():
    return "needs a CPU with AVX2 and FMA"
  flags = AVX512_FLAGS if instruction_set() == "avx512" else FLAGS
  try:
    lib = ctypes.cdll.LoadLibrary(str(_build(flags)))
  except (RuntimeError, OSError) as e:
    return str(e)
  for name in (TOWER, TOWER_TRAIN, TOWER_GRAD):
    jax.ffi.register_ffi_target(name, jax.ffi.pycapsule(getattr(lib, name)), platform="cpu")
  return None


def available() -> bool:
  """Whether the native tower runs here (builds the library on the first call)."""
  return _load() is None


def unavailable_reason() -> str | None:
  return _load()


def supports_tower(features: int, layers=CONV_LAYERS) -> bool:
  """Whether `tower` computes a float32 tower of these features and layers."""
  return features in TOWER_FEATURES and tuple(layers) == TOWER_LAYERS


def xla_tower(x: jax.Array, params) -> jax.Array:
  """The tower `tower` computes, in XLA's ops: x (N, H, W, C) float32 and params [(kernel
  (3, 3, C_i, F), bias (F,))] * 4 -> features (N, F)."""
  for (stride, pool), (kernel, bias) in zip(TOWER_LAYERS, params):
    x = jax.nn.relu(lax_conv3x3(x, kernel, stride) + bias)
    if pool:
      x = jax.lax.reduce_window(x, -jnp.inf, jax.lax.max, (1, 2, 2, 1), (1, 2, 2, 1), "VALID")
  return jnp.mean(x, axis=(1, 2))


def _activations_size(h: int, w: int, features: int) -> int:
  """Floats per image that the gradient keeps of the forward pass: each conv's output and
  the pooled output, each on whole 64-byte lines (as the kernel lays them out)."""
  lines = lambda n: -(-n // 16) * 16
  size = 0
  for stride, pool in TOWER_LAYERS:
    h, w = (h - 3) // stride + 1, (w - 3) // stride + 1
    size += lines(h * w * features)
    if pool:
      h, w = h // 2, w // 2
      size += lines(h * w * features)
  return size


def _flat(params) -> list[jax.Array]:
  return [a for kernel_bias in params for a in kernel_bias]


def _call(target: str, x: jax.Array, params, activations: bool = False):
  if not available():
    raise RuntimeError(f"the native conv is not available: {unavailable_reason()}")
  n, h, w, _ = x.shape
  f = params[0][0].shape[-1]
  out = [jax.ShapeDtypeStruct((n, f), jnp.float32)]
  if activations:
    out.append(jax.ShapeDtypeStruct((n, _activations_size(h, w, f)), jnp.float32))
  return jax.ffi.ffi_call(target, out, vmap_method="sequential")(x, *_flat(params))


@jax.custom_vjp
def tower(x: jax.Array, params) -> jax.Array:
  """The conv tower (`TOWER_LAYERS`) as one FFI call: x (N, H, W, C) float32, params
  [(kernel (3, 3, C_i, F), bias (F,))] * 4 -> features (N, F), F in `TOWER_FEATURES`.
  Equal to `xla_tower` to float32 rounding.

  Differentiated, the forward call also returns each image's activations, and the
  gradient w.r.t. the params is one more call; w.r.t. x it is XLA's (`xla_tower`'s),
  which XLA drops where nothing uses it, as in SAC, whose observations are not
  differentiated."""
  return _call(TOWER, x, params)[0]


def _tower_fwd(x, params):
  feat, acts = _call(TOWER_TRAIN, x, params, activations=True)
  return feat, (x, params, acts)


def _tower_bwd(res, dfeat):
  x, params, acts = res
  shapes = [jax.ShapeDtypeStruct(a.shape, jnp.float32) for a in _flat(params)]
  grads = jax.ffi.ffi_call(TOWER_GRAD, shapes, vmap_method="sequential")(
      x, *_flat(params), acts, dfeat)
  dparams = type(params)((grads[2 * i], grads[2 * i + 1]) for i in range(len(params)))
  dx = jax.vjp(lambda a: xla_tower(a, params), x)[1](dfeat)[0]
  return dx, dparams


tower.defvjp(_tower_fwd, _tower_bwd)
