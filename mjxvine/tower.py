"""The conv tower's layers and their XLA formulations (docs/design.md, SAC
hyper-parameters; departures: the tower's padding).

The tower (`networks.ConvTower`) is 4 3x3 VALID convs (`CONV_LAYERS`: strides 2, 1, 2, 1,
a 2x2 max pool after the second), each with a ReLU, and a global mean. This module holds
what every formulation of it shares: the layer table, the covering size and the padding
that lets every pixel reach the output, XLA's reference conv (`lax_conv3x3`), and the
opt-in rewrites of its convs for XLA's CPU backend (`conv_impl` "dot" and "shift", as
`CONV_HOOKS` for `nn.Conv`). The hand-written CPU kernel of the whole tower ("native") is
`mjxvine.native`. Images are NHWC float32 (N, H, W, C), kernels HWIO (3, 3, C, F).
"""

from __future__ import annotations

from functools import partial
from typing import Sequence

import jax
import jax.numpy as jnp

# Layers of the conv tower: (stride, max-pool 2x2 after it), 3x3 kernels, VALID padding.
CONV_LAYERS = ((2, False), (1, True), (2, False), (1, False))


def covering_size(n: int, layers=CONV_LAYERS) -> int:
  """The smallest input size >= n of which every pixel reaches the tower's output.

  A VALID conv of stride s drops the trailing (n - 3) % s rows, a 2x2 pool an odd last
  row: only sizes whose every layer divides evenly are covered (8k + 1 for
  `CONV_LAYERS`: 41, 65, 113).
  """
  def covers(m):
    for stride, pool in layers:
      if m < 3 or (m - 3) % stride:
        return False
      m = (m - 3) // stride + 1
      if pool:
        if m % 2:
          return False
        m //= 2
    return m >= 1
  m = n
  while not covers(m):
    m += 1
  return m


MIN_IMAGE_SIZE = covering_size(1)  # 33


def tower_pad(hw: Sequence[int]) -> tuple[int, int]:
  """(bottom, right) rows / columns by which the tower pads an (H, W) image."""
  return tuple(covering_size(int(n)) - int(n) for n in hw)


def pad_for_tower(x: jax.Array) -> jax.Array:
  """Pads (N, H, W, C) at its bottom and right by repeating the edge, up to the covering
  size (a departure from the paper's VALID tower, which never sees the last 7 columns of
  a 112- or 40-wide image). Images of a covering size pass unchanged."""
  ph, pw = tower_pad(x.shape[-3:-1])
  if not (ph or pw):
    return x
  return jnp.pad(x, ((0, 0), (0, ph), (0, pw), (0, 0)), mode="edge")


# ----------------------------------------------------------------------------------------
# The tower's convolutions as matrix multiplies (`conv_impl="dot"`, opt-in).
#
# Each 3x3 VALID conv becomes im2col (9 strided slices, concatenated on the channel axis)
# and one dot, with a hand-written gradient that is dots and slices too (never XLA's
# convolution); max pooling becomes a reshape and a max. Exact to float32 rounding. On
# XLA's CPU backend (jax 0.10) the concatenation costs more than the convolutions it
# replaces, so "dot" is never a default; it is kept for
# `python -m mjxvine.bench update --conv-impl dot`.
# `conv_impl="shift"` runs only the first conv, whose image has one channel, as
# `conv3x3_shift`: 1.25x the gradient steps/s of the trainer's CPU step for `cpu.yaml`
# (docs/results/cpu-update-speed.md). The trainer uses it on the CPU
# (`sac.learner_conv_impl`); the default of these functions is "xla".

# `conv_impl="native"` computes the whole tower as one hand-written CPU kernel call
# (`mjxvine.native.tower`, XLA FFI; float32, 8, 16 or 32 features), else as "shift".

CONV_IMPLS = ("xla", "dot", "shift", "native")


def _conv3x3_taps(x: jax.Array, stride: int) -> list[jax.Array]:
  """The 9 strided slices a 3x3 VALID conv reads: (N, H, W, C) -> 9 x (N, Ho, Wo, C),
  Ho = (H - 3) // stride + 1, in (kernel row, kernel column) order."""
  n, h, w, c = x.shape
  ho, wo = (h - 3) // stride + 1, (w - 3) // stride + 1
  return [jax.lax.slice(x, (0, i, j, 0),
                        (n, i + stride * (ho - 1) + 1, j + stride * (wo - 1) + 1, c),
                        (1, stride, stride, 1))
          for i in range(3) for j in range(3)]


def im2col(x: jax.Array, stride: int) -> jax.Array:
  """3x3 VALID patches: (N, H, W, C) -> (N, Ho, Wo, 9 C), Ho = (H - 3) // stride + 1, the
  last axis ordered (kernel row, kernel column, channel) like an HWIO kernel reshaped to
  (9 C, F)."""
  return jnp.concatenate(_conv3x3_taps(x, stride), axis=-1)


def _patch_dot(p: jax.Array, kernel: jax.Array) -> jax.Array:
  """(N, Ho, Wo, 9 C) patches times an HWIO (3, 3, C, F) kernel -> (N, Ho, Wo, F)."""
  return jax.lax.dot_general(p, kernel.reshape(-1, kernel.shape[-1]),
                             (((3,), (0,)), ((), ())))


@partial(jax.custom_vjp, nondiff_argnums=(2,))
def conv3x3_dot(x: jax.Array, kernel: jax.Array, stride: int) -> jax.Array:
  """A 3x3 VALID conv, NHWC x HWIO -> NHWC, as im2col and one dot: x (N, H, W, C),
  kernel (3, 3, C, F) -> (N, Ho, Wo, F). Equal to `lax.conv_general_dilated` to rounding;
  its gradient is dots and slices as well (never XLA's convolution)."""
  return _patch_dot(im2col(x, stride), kernel)


def _conv3x3_dot_fwd(x, kernel, stride):
  return conv3x3_dot(x, kernel, stride), (x, kernel)


def _conv3x3_dot_bwd(stride, res, dy):
  x, kernel = res
  _, h, w, _ = x.shape
  _, ho, wo, f = dy.shape
  # d kernel: patches^T dy, one dot contracting over N * Ho * Wo (the patches are rebuilt
  # from x rather than kept: slices are cheap, a 9x larger residual is not).
  p = im2col(x, stride).reshape(-1, kernel.shape[0] * kernel.shape[1] * kernel.shape[2])
  dk = jax.lax.dot_general(p, dy.reshape(-1, f), (((0,), (0,)), ((), ())))
  # d x: the transposed conv, i.e. a stride-1 conv of dy (dilated by the stride and padded
  # by 2, plus the rows and columns the strided conv skipped) with the flipped kernel.
  eh, ew = h - (stride * (ho - 1) + 3), w - (stride * (wo - 1) + 3)
  zero = jnp.zeros((), dy.dtype)
  dyp = jax.lax.pad(dy, zero, ((0, 0, 0), (2, 2 + eh, stride - 1), (2, 2 + ew, stride - 1),
                               (0, 0, 0)))
  dx = _patch_dot(im2col(dyp, 1), jnp.flip(kernel, (0, 1)).transpose(0, 1, 3, 2))
  return dx.astype(x.dtype), dk.reshape(kernel.shape).astype(kernel.dtype)


conv3x3_dot.defvjp(_conv3x3_dot_fwd, _conv3x3_dot_bwd)


def _is_tower_conv(rhs, window_strides, padding, lhs_dilation, rhs_dilation,
                   feature_group_count) -> bool:
  """Whether `lax.conv_general_dilated`'s arguments (as `nn.Conv` passes them) are one of
  the tower's convs: a 3x3 kernel, VALID, equal strides, no dilation or groups."""
  return (rhs.shape[:2] == (3, 3) and padding == "VALID" and len(set(window_strides)) == 1
          and all(d == 1 for d in (lhs_dilation or ()) + (rhs_dilation or ()))
          and feature_group_count == 1)


def _dot_conv_general_dilated(lhs, rhs, window_strides, padding, lhs_dilation=None,
                              rhs_dilation=None, dimension_numbers=None,
                              feature_group_count=1, precision=None, **_):
  """`lax.conv_general_dilated`'s signature (as `nn.Conv` calls it) for the tower's convs
  only: 3x3 kernels, VALID, equal strides, NHWC, no dilation or groups."""
  del dimension_numbers, precision  # nn.Conv passes NHWC / HWIO, default precision
  if not _is_tower_conv(rhs, window_strides, padding, lhs_dilation, rhs_dilation,
                        feature_group_count):
    raise NotImplementedError("conv3x3_dot: 3x3 VALID convs with equal strides only")
  return conv3x3_dot(lhs, rhs, int(window_strides[0]))


def lax_conv3x3(x: jax.Array, kernel: jax.Array, stride: int) -> jax.Array:
  """XLA's 3x3 VALID conv, x (N, H, W, C) x kernel (3, 3, C, F) -> (N, Ho, Wo, F): the
  reference the tower's other formulations equal, and their fallback."""
  return jax.lax.conv_general_dilated(x, kernel, (stride, stride), "VALID",
                                      dimension_numbers=("NHWC", "HWIO", "NHWC"))


@partial(jax.custom_vjp, nondiff_argnums=(2,))
def conv3x3_shift(x: jax.Array, kernel: jax.Array, stride: int) -> jax.Array:
  """A 3x3 VALID conv of a one-channel image as the sum of its 9 strided slices, each
  times one row of the kernel: x (N, H, W, 1), kernel (3, 3, 1, F) -> (N, Ho, Wo, F).

  One elementwise fusion, about 5x faster forward than XLA's convolution on the CPU for
  the tower's first conv; its gradient is XLA's convolution's (JAX's own derivative of
  the sum is slower). Equal to `lax.conv_general_dilated` to float32 rounding."""
  y = 0.0
  for k, tap in enumerate(_conv3x3_taps(x, stride)):
    y = y + tap * kernel[k // 3, k % 3, 0]
  return y.astype(x.dtype)


def _conv3x3_shift_fwd(x, kernel, stride):
  return conv3x3_shift(x, kernel, stride), (x, kernel)


def _conv3x3_shift_bwd(stride, res, dy):
  x, kernel = res
  return jax.vjp(lambda a, b: lax_conv3x3(a, b, stride), x, kernel)[1](dy)


conv3x3_shift.defvjp(_conv3x3_shift_fwd, _conv3x3_shift_bwd)


def _shift_conv_general_dilated(lhs, rhs, window_strides, padding, lhs_dilation=None,
                                rhs_dilation=None, dimension_numbers=None,
                                feature_group_count=1, precision=None, **kw):
  """`lax.conv_general_dilated`'s signature (as `nn.Conv` calls it): `conv3x3_shift` for
  a one-channel 3x3 VALID conv with equal strides (the tower's first), else XLA's."""
  if rhs.shape[2] == 1 and _is_tower_conv(rhs, window_strides, padding, lhs_dilation,
                                           rhs_dilation, feature_group_count):
    return conv3x3_shift(lhs, rhs, int(window_strides[0]))
  return jax.lax.conv_general_dilated(lhs, rhs, window_strides, padding, lhs_dilation,
                                      rhs_dilation, dimension_numbers, feature_group_count,
                                      precision=precision, **kw)


# what `nn.Conv` calls instead of `lax.conv_general_dilated`, per `conv_impl` ("xla": none)
# ("native": where `native.tower` does not compute the tower, as "shift")
CONV_HOOKS = {"dot": _dot_conv_general_dilated, "shift": _shift_conv_general_dilated,
               "native": _shift_conv_general_dilated}


def max_pool_2x2(x: jax.Array) -> jax.Array:
  """2x2 max pool, stride 2, VALID, of (N, H, W, C) -> (N, H // 2, W // 2, C) as a reshape
  and a max. Its gradient goes, like XLA's reduce_window / select_and_scatter, to the
  first maximum of each window in row-major order (also where several are equal)."""
  n, h, w, c = x.shape
  x = x[:, :h // 2 * 2, :w // 2 * 2].reshape(n, h // 2, 2, w // 2, 2, c)
  a, b, d, e = x[:, :, 0, :, 0], x[:, :, 0, :, 1], x[:, :, 1, :, 0], x[:, :, 1, :, 1]
  m = jax.lax.stop_gradient(jnp.maximum(jnp.maximum(a, b), jnp.maximum(d, e)))
  return jnp.where(a == m, a, jnp.where(b == m, b, jnp.where(d == m, d, e)))


def tower_output_size(hw: Sequence[int]) -> tuple[int, ...]:
  """Spatial size after the last conv for an image of size hw (after `pad_for_tower`)."""
  out = []
  for n in hw:
    n = covering_size(n)
    for stride, pool in CONV_LAYERS:
      n = (n - 3) // stride + 1
      n = n // 2 if pool else n
    out.append(n)
  return tuple(out)
