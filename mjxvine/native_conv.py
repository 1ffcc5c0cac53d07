"""The conv tower's 3x3 convolutions as a hand-written CPU kernel (an XLA FFI call).

XLA's CPU convolution runs the tower's small convs at a fraction of the machine's matmul
rate, worst for 8 output channels and for the gradient w.r.t. the kernel;
`mjxvine/native/tower_conv.cc` computes them with AVX2 / FMA and OpenMP. Used where it
measured faster than XLA's (`scripts/time_tower_convs.py`,
docs/results/cpu-update-speed.md): the gradient w.r.t. the kernel (8 and 16 channels,
2-7x), the forward conv with 8 output channels (2-5x), and, at stride 1 with 8 input
channels, the gradient w.r.t. the input as the forward conv of the padded gradient with
the flipped kernel (5x); the rest is XLA's (16 channels forward, stride-2 input
gradients). Equal to `lax.conv_general_dilated` to float32 rounding
(tests/test_native_conv.py).

The library is compiled on first use with the system's C++ compiler (`$CXX` or `g++`)
into `$MJXVINE_CACHE` (default `~/.cache/mjxvine`), one file per source, flags, jax
version and compiler, and registered with `jax.ffi`. `available()` is False, with the reason
in `unavailable_reason()`, when the machine is not x86-64 Linux with AVX2 and FMA, when
no compiler builds it, or when `MJXVINE_NATIVE_CONV=0`; `conv_impl="native"`
(`sac.conv_impl: native`) then fails with that reason. The default, `sac.conv_impl: auto`,
does not use it.
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

from mjxvine.networks import lax_conv3x3

SOURCE = Path(__file__).parent / "native" / "tower_conv.cc"
FLAGS = ("-O3", "-mavx2", "-mfma", "-fopenmp", "-shared", "-fPIC", "-std=c++17", "-w")
FORWARD, KERNEL_GRAD = "mjxvine_tower_conv", "mjxvine_tower_conv_kernel_grad"
OUT_FEATURES = (8, 16)  # output channels the kernel computes
FAST_FORWARD_FEATURES = 8  # output channels where its forward conv beats XLA's


def _cpu_flags() -> set[str]:
  try:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
      if line.startswith("flags"):
        return set(line.split(":", 1)[1].split())
  except OSError:
    pass
  return set()


def _build() -> Path:
  """Compile the library (once per source, flags, jax version and compiler) -> its
  path."""
  cxx = os.environ.get("CXX") or shutil.which("g++") or shutil.which("c++")
  if not cxx:
    raise RuntimeError("no C++ compiler (set $CXX or install g++)")
  include = jax.ffi.include_dir()
  key = hashlib.sha256(SOURCE.read_bytes() + " ".join(FLAGS).encode()
                       + jax.__version__.encode() + cxx.encode()).hexdigest()[:16]
  cache = Path(os.environ.get("MJXVINE_CACHE", Path.home() / ".cache" / "mjxvine"))
  lib = cache / f"tower_conv-{key}.so"
  if lib.is_file():
    return lib
  cache.mkdir(parents=True, exist_ok=True)
  with tempfile.TemporaryDirectory(dir=cache) as tmp:
    out = Path(tmp) / lib.name
    done = subprocess.run([cxx, *FLAGS, f"-I{include}", str(SOURCE), "-o", str(out)],
                          capture_output=True, text=True, check=False)
    if done.returncode != 0:
      raise RuntimeError(f"{cxx} could not build {SOURCE.name} (exit {done.returncode}): "
                         f"{done.stderr.strip()[-500:]}")
    os.replace(out, lib)  # atomic: a second process never loads a half-written file
  return lib


@functools.cache
def _load() -> str | None:
  """Build and register the FFI targets; None on success, else why not."""
  if os.environ.get("MJXVINE_NATIVE_CONV", "1") == "0":
    return "disabled by MJXVINE_NATIVE_CONV=0"
  if platform.system() != "Linux" or platform.machine() not in ("x86_64", "AMD64"):
    return f"needs x86-64 Linux (this is {platform.system()} {platform.machine()})"
  if not {"avx2", "fma"} <= _cpu_flags():
    return "needs a CPU with AVX2 and FMA"
  try:
    lib = ctypes.cdll.LoadLibrary(str(_build()))
  except (RuntimeError, OSError) as e:
    return str(e)
  for name in (FORWARD, KERNEL_GRAD):
    jax.ffi.register_ffi_target(name, jax.ffi.pycapsule(getattr(lib, name)), platform="cpu")
  return None


def available() -> bool:
  """Whether the native conv runs here (builds the library on the first call)."""
  return _load() is None


def unavailable_reason() -> str | None:
  return _load()


def supports(in_features: int, out_features: int, stride: int) -> bool:
  """Whether the kernel computes a 3x3 VALID conv of these channels and stride."""
  return out_features in OUT_FEATURES and in_features % 4 == 0 and stride in (1, 2)


def _out(n: int, stride: int) -> int:
  return (n - 3) // stride + 1


def _forward(x: jax.Array, kernel: jax.Array, stride: int) -> jax.Array:
  n, h, w, _ = x.shape
  out = jax.ShapeDtypeStruct((n, _out(h, stride), _out(w, stride), kernel.shape[-1]),
                             jnp.float32)
  return jax.ffi.ffi_call(FORWARD, out, vmap_method="sequential")(
      x, kernel, stride=np.int64(stride))


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def conv3x3(x: jax.Array, kernel: jax.Array, stride: int) -> jax.Array:
  """A 3x3 VALID conv, x (N, H, W, C) float32 x kernel (3, 3, C, F) -> (N, Ho, Wo, F),
  Ho = (H - 3) // stride + 1, on the CPU (`supports(C, F, stride)`; `available()`)."""
  if not available():
    raise RuntimeError(f"the native conv is not available: {unavailable_reason()}")
  if kernel.shape[-1] == FAST_FORWARD_FEATURES:
    return _forward(x, kernel, stride)
  return lax_conv3x3(x, kernel, stride)


def _conv3x3_fwd(x, kernel, stride):
  return conv3x3(x, kernel, stride), (x, kernel)


def _conv3x3_bwd(stride, res, dy):
  x, kernel = res
  dk = jax.ffi.ffi_call(KERNEL_GRAD, jax.ShapeDtypeStruct(kernel.shape, jnp.float32),
                        vmap_method="sequential")(x, dy, stride=np.int64(stride))
  c = x.shape[-1]
  if stride == 1 and c == FAST_FORWARD_FEATURES and supports(kernel.shape[-1], c, 1):
    # the transposed conv: dy padded by 2 conv'd with the flipped, transposed kernel
    dyp = jnp.pad(dy, ((0, 0), (2, 2), (2, 2), (0, 0)))
    dx = _forward(dyp, jnp.flip(kernel, (0, 1)).transpose(0, 1, 3, 2), 1)
  else:
    dx = jax.vjp(lambda a: lax_conv3x3(a, kernel, stride), x)[1](dy)[0]
  return dx, dk


conv3x3.defvjp(_conv3x3_fwd, _conv3x3_bwd)
