"""The conv tower's layers and their XLA formulations (docs/design.md, SAC
hyper-parameters; departures: the tower's padding).

The tower (`networks.ConvTower`) is 4 3x3 VALID convs (`CONV_LAYERS`: strides 2, 1, 2, 1,
a 2x2 max pool after the second), each with a ReLU, and a global mean. This module holds
what every formulation of it shares: the layer table, the covering size and the padding
that lets every pixel reach the output, XLA's reference conv (`lax_conv3x3`), and the
rewrite of its first conv for XLA's CPU backend (`conv_impl` "shift", as `CONV_HOOKS` for
`nn.Conv`). The hand-written CPU kernel of the whole tower ("native") is
`mjxvine.native`. Images are NHWC float32 (N, H, W, C), kernels HWIO (3, 3, C, F).
"""

from __future__ import annotations

import inspect
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


# `conv_impl="shift"` runs only the first conv, whose image has one channel, as
# `conv3x3_shift`: 1.25x the gradient steps/s of the trainer's CPU step for `cpu.yaml`.
# `conv_impl="native"` computes the whole tower as one hand-written CPU kernel call
# (`mjxvine.native.tower`, XLA FFI; float32, 8, 16 or 32 features), else as "shift".
# The default of these functions is "xla"; the trainer's choice is
# `networks.learner_conv_impl`.

CONV_IMPLS = ("xla", "shift", "native")


def _conv3x3_taps(x: jax.Array, stride: int) -> list[jax.Array]:
  """The 9 strided slices a 3x3 VALID conv reads: (N, H, W, C) -> 9 x (N, Ho, Wo, C),
  Ho = (H - 3) // stride + 1, in (kernel row, kernel column) order."""
  n, h, w, c = x.shape
  ho, wo = (h - 3) // stride + 1, (w - 3) // stride + 1
  return [jax.lax.slice(x, (0, i, j, 0),
                        (n, i + stride * (ho - 1) + 1, j + stride * (wo - 1) + 1, c),
                        (1, stride, stride, 1))
          for i in range(3) for j in range(3)]


def _is_tower_conv(rhs, window_strides, padding, lhs_dilation, rhs_dilation,
                   feature_group_count) -> bool:
  """Whether `lax.conv_general_dilated`'s arguments (as `nn.Conv` passes them) are one of
  the tower's convs: a 3x3 kernel, VALID, equal strides, no dilation or groups."""
  return (rhs.shape[:2] == (3, 3) and padding == "VALID" and len(set(window_strides)) == 1
          and all(d == 1 for d in (lhs_dilation or ()) + (rhs_dilation or ()))
          and feature_group_count == 1)


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


def _shift_conv_general_dilated(lhs, rhs, window_strides, padding, *args, **kw):
  """`lax.conv_general_dilated` (as `nn.Conv` calls it: its positional and keyword
  arguments passed on as they come): `conv3x3_shift` for a one-channel 3x3 VALID conv
  with equal strides and no dilation or groups (the tower's first), else XLA's."""
  bound = inspect.signature(jax.lax.conv_general_dilated).bind(
      lhs, rhs, window_strides, padding, *args, **kw).arguments
  if rhs.shape[2] == 1 and _is_tower_conv(
      rhs, window_strides, padding, bound.get("lhs_dilation"), bound.get("rhs_dilation"),
      bound.get("feature_group_count", 1)):
    return conv3x3_shift(lhs, rhs, int(window_strides[0]))
  return jax.lax.conv_general_dilated(lhs, rhs, window_strides, padding, *args, **kw)


# what `nn.Conv` calls instead of `lax.conv_general_dilated`, per `conv_impl` ("xla": none)
# ("native": where `native.tower` does not compute the tower, as "shift")
CONV_HOOKS = {"shift": _shift_conv_general_dilated, "native": _shift_conv_general_dilated}


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
