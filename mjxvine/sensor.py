"""The depth sensor (docs/design.md, The depth sensor): a stereo depth camera's faults laid
on the ray-cast image, as data (`SensorConfig`), inside the jit-compiled env step.

`observe` is the image the policy sees. The stages that exist are decided in Python from
the config's values, so a fault set to zero costs nothing, and the `ideal` preset is the
paper's noise (`depth.add_noise`) and nothing else. Otherwise, on the true depth z:

  stereo error   z + N(0, 1) z^2 s / (f B)
  flying pixels  on a depth edge, with probability flying_pixel_rate: uniform between
                 the pixel's depth and its neighbour's across the edge
  paper noise    `depth.add_noise` (noise factor k)
  no return      z < min_depth_m; single pixels and patches at rates linear in z
  quantisation   round to quantum_m
  clip           [0, max_depth]

"No return" reads camera.max_depth_m, as the deployed preprocessing makes a 0 or NaN
reading (`NumpyPolicy(invalid_depth=None)`). Every function works on one image (H, W);
vmap it over envs.

The faults' per-pixel draws come from a counter-based hash seeded from the key
(`_pixel_words`), not from `jax.random`, whose threefry and inverse-normal transform take
about ten times the operations a word on a CPU. Each 32-bit word gives two 16-bit
uniforms or one near-normal (`_near_normal`).
"""

from __future__ import annotations

import itertools
import math
from statistics import NormalDist
from typing import NamedTuple

import jax
import jax.numpy as jp
import numpy as np

from mjxvine import depth
from mjxvine.config import CameraConfig, SensorConfig

# A depth edge: a pixel whose true depth differs from a 4-neighbour's by more than this (m).
EDGE_STEP_M = 0.25


class _View(NamedTuple):
  """What the sensor stages read of the camera: fields of view (deg), max depth (m)."""
  fovx_deg: float
  fovy_deg: float
  max_depth: float


def _view(camera) -> _View:
  """A CameraConfig's view, or a `depth.DepthCamera`'s (which keeps tan(fov / 2))."""
  if isinstance(camera, CameraConfig):
    return _View(camera.fovx_deg, camera.fovy_deg, camera.max_depth_m)
  # rounded: the config's degrees again, so that both give the same patch grid
  fov = (round(math.degrees(2 * math.atan(t)), 6) for t in (camera.tan_x, camera.tan_y))
  return _View(*fov, camera.max_depth)


def _rate(rates: tuple[float, float], z: jax.Array, max_depth: float) -> jax.Array:
  """A rate linear in the true depth z: rates[0] at 0 m, rates[1] at max_depth (clipped)."""
  lo, hi = rates
  return lo + (hi - lo) * jp.clip(z / max_depth, 0.0, 1.0)


def _draw(sample, key: jax.Array, shapes: dict[str, tuple[int, ...]]) -> dict[str, jax.Array]:
  """{name: array of its shape} cut from one draw of `sample` (jax.random.normal or
  uniform): one random program to compile, not one per array (XLA:CPU compiles each for
  about half a second)."""
  if not shapes:
    return {}
  sizes = [math.prod(shape) for shape in shapes.values()]
  flat = sample(key, (sum(sizes),), jp.float32)
  parts = jp.split(flat, list(itertools.accumulate(sizes))[:-1])
  return {name: part.reshape(shape) for (name, shape), part in zip(shapes.items(), parts)}


def _stereo_std(z: jax.Array, sensor: SensorConfig) -> jax.Array:
  """The stereo matcher's depth error std z^2 s / (f B) (m; not its square)."""
  return jp.square(z) * (sensor.stereo_subpixel_px
                         / (sensor.stereo_focal_px * sensor.stereo_baseline_m))


def _step_matrix(n: int) -> jax.Array:
  """(n, n) float32 D with (D v)[i] = v[i + 1] - v[i] and 0 for the last i."""
  return jp.asarray(np.eye(n, k=1, dtype=np.float32) - np.diag(
      np.r_[np.ones(n - 1, np.float32), 0.0]))


def _flying(z: jax.Array, measured: jax.Array, u_fly: jax.Array, rate: float) -> jax.Array:
  """`measured` where a pixel on a depth edge of z (the 4-neighbour with the largest step,
  if over EDGE_STEP_M) reads, with probability `rate`, a depth uniform between its own and
  that neighbour's true depth: a mixed pixel. u_fly: (H, W) uniform in (0, 1); where it
  is below `rate`, u_fly / rate is uniform in (0, 1) again: where between the sides.

  The steps to the neighbours below and to the right are products with a difference
  matrix (exact: one subtraction each; the image's border is no edge): a dot makes XLA
  keep z in memory, where a stencil on it would recompute the whole image for each
  neighbour inside the sensor's one fused loop (several times the cost of the image)."""
  hi = jax.lax.Precision.HIGHEST  # (no TF32 on GPUs: the differences stay exact)
  (h, w), zero = z.shape, jp.zeros((), z.dtype)
  down = jp.matmul(_step_matrix(h), z, precision=hi)  # z[i + 1, j] - z[i, j]
  right = jp.matmul(z, _step_matrix(w).T, precision=hi)  # z[i, j + 1] - z[i, j]
  up = -jp.pad(down[:-1], ((1, 0), (0, 0)), constant_values=zero)
  left = -jp.pad(right[:, :-1], ((0, 0), (1, 0)), constant_values=zero)
  step = jp.zeros_like(z)
  for neighbour_step in (up, down, left, right):
    step = jp.where(jp.abs(neighbour_step) > jp.abs(step), neighbour_step, step)
  fly = (jp.abs(step) > EDGE_STEP_M) & (u_fly < rate)
  return jp.where(fly, z + (u_fly / rate) * step, measured)


def _pixel_words(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
  """`shape` uint32 words, independent and uniform to all appearances: murmur3's 32-bit
  finaliser of a Weyl sequence (a counter times the golden ratio) started at a 32-bit
  seed drawn from `key`. Ten integer operations a word, against threefry's ~100."""
  x = (jax.random.bits(key, (), jp.uint32)
       + jp.arange(math.prod(shape), dtype=jp.uint32) * jp.uint32(0x9E3779B9))
  x = (x ^ (x >> 16)) * jp.uint32(0x85EBCA6B)
  x = (x ^ (x >> 13)) * jp.uint32(0xC2B2AE35)
  return (x ^ (x >> 16)).reshape(shape)


def _uniform16(words: jax.Array, high: bool) -> jax.Array:
  """Uniform in (0, 1) (float32, 2^16 levels) from the high or the low half of `words`."""
  half = (words >> 16) if high else (words & jp.uint32(0xFFFF))
  return (half.astype(jp.float32) + 0.5) * (1.0 / 65536.0)


def _near_normal(words: jax.Array) -> jax.Array:
  """Mean 0, std 1 from each word: the sum of its four bytes (Irwin-Hall), centred and
  scaled; the normal's shape within 3.45 std (nothing beyond), no transcendental."""
  total = sum(((words >> (8 * i)) & jp.uint32(0xFF)).astype(jp.float32) for i in range(4))
  return (total - 510.0) * (1.0 / math.sqrt(4 * (256.0 ** 2 - 1) / 12))


def _nodes(cells: float) -> int:
  """Grid nodes along an axis `cells` cells long: enough for a shift of up to one cell
  and every pixel's right-hand node."""
  return int(math.floor(cells)) + 3


def _interpolation(pixels: int, cells: float, shift: jax.Array) -> jax.Array:
  """(pixels, nodes) weights that interpolate a coarse grid linearly onto `pixels`, a
  grid cell being `pixels / cells` pixels wide, the grid shifted by `shift` (a share of a
  cell); each row scaled to unit norm, so that iid N(0, 1) nodes give N(0, 1) pixels."""
  nodes = _nodes(cells)
  u = (jp.arange(pixels, dtype=jp.float32) + 0.5) * (cells / pixels) + shift
  i0 = jp.floor(u)
  frac = u - i0
  i0 = i0.astype(jp.int32)
  weights = ((1 - frac)[:, None] * jax.nn.one_hot(i0, nodes)
             + frac[:, None] * jax.nn.one_hot(i0 + 1, nodes))
  return weights / jp.sqrt(jp.square(1 - frac) + jp.square(frac))[:, None]


def _grid_cells(view: _View, size_deg: float) -> tuple[float, float]:
  """The image's extent in patch cells (rows, columns): its field of view / size_deg."""
  return view.fovy_deg / size_deg, view.fovx_deg / size_deg


def _patch_field(grid: jax.Array, shift: jax.Array, shape: tuple[int, int], view: _View,
                 size_deg: float) -> jax.Array:
  """(H, W) Gaussian field, exactly N(0, 1) at every pixel and correlated over about
  `size_deg` of view: `grid` (ny, nx) iid N(0, 1) on cells size_deg wide (linear in the
  pixel index; a pinhole's angle per pixel varies a little), shifted by `shift` (2,)
  uniform in [0, 1) cells, interpolated bilinearly, each pixel divided by the norm of its
  weights. Independent of the image's resolution."""
  cells_y, cells_x = _grid_cells(view, size_deg)
  wy = _interpolation(shape[0], cells_y, shift[0])  # (H, ny)
  wx = _interpolation(shape[1], cells_x, shift[1])  # (W, nx)
  # HIGHEST: no reduced-precision (TF32) matmul on GPUs, so the field stays N(0, 1)
  hi = jax.lax.Precision.HIGHEST
  return jp.matmul(wy, jp.matmul(grid, wx.T, precision=hi), precision=hi)


THRESHOLD_STEPS = 256  # of the patch threshold's table over the depth range


def _patch_threshold(rates: tuple[float, float], z: jax.Array, max_depth: float) -> jax.Array:
  """Phi^-1(`_rate(rates, z, max_depth)`) (H, W), from a table of it at THRESHOLD_STEPS + 1
  depths, interpolated linearly: a look-up instead of an inverse normal per pixel. The
  rate it gives errs by under 1e-5 where the rates are 0.01 or more, by up to 0.003 at
  the depths next to a rate of 0."""
  steps = THRESHOLD_STEPS
  rate = rates[0] + (rates[1] - rates[0]) * np.linspace(0.0, 1.0, steps + 1)
  # rates of 0 and 1 as 1e-9 and 1 - 1e-9: thresholds of -6 and 6, no infinity
  table = jp.asarray([NormalDist().inv_cdf(min(max(p, 1e-9), 1 - 1e-9)) for p in rate],
                     jp.float32)
  at = jp.clip(z / max_depth, 0.0, 1.0) * steps
  below = jp.minimum(jp.floor(at), steps - 1)
  i = below.astype(jp.int32)
  return table[i] + (at - below) * (table[i + 1] - table[i])


def _has_stereo(sensor: SensorConfig) -> bool:
  return sensor.stereo_baseline_m > 0 and sensor.stereo_subpixel_px > 0


def _has_no_return(sensor: SensorConfig) -> bool:
  return sensor.min_depth_m > 0 or any(sensor.dropout_rate) or any(sensor.patch_rate)


def _has_faults(sensor: SensorConfig) -> bool:
  """Whether any stage beyond the paper's noise exists (False for the `ideal` preset)."""
  return (_has_stereo(sensor) or sensor.flying_pixel_rate > 0 or _has_no_return(sensor)
          or sensor.quantum_m > 0)


def _random_shapes(shape: tuple[int, int], view: _View, sensor: SensorConfig):
  """The draws of the stages that exist: the shapes of the normal and of the uniform ones
  (`_draw`: the patch grid's few numbers) and the names of the per-pixel ones
  (`_pixel_draws`)."""
  normal, uniform, pixel = {}, {}, []
  if _has_stereo(sensor):
    pixel.append("stereo")
  if any(sensor.dropout_rate):
    pixel.append("dropout")
  if sensor.flying_pixel_rate > 0:
    pixel.append("fly")
  if any(sensor.patch_rate):
    normal["grid"] = tuple(_nodes(c) for c in _grid_cells(view, sensor.patch_size_deg))
    uniform["shift"] = (2,)
  return normal, uniform, pixel


def _pixel_draws(key: jax.Array, shape: tuple[int, int], names: list[str]) -> dict:
  """{name: (H, W)} of the per-pixel draws `names` (`_random_shapes`): "stereo" near-normal,
  "dropout" and "fly" uniform in (0, 1), sharing one word where both exist."""
  k_stereo, k_halves = jax.random.split(key)
  out = {"stereo": _near_normal(_pixel_words(k_stereo, shape))} if "stereo" in names else {}
  halves = [n for n in names if n != "stereo"]
  if halves:
    # an array of its own for each word (not rows of one): XLA:CPU fuses rows of one
    # array, beside the patch field's matmul, into a step three times as slow
    words = _pixel_words(k_halves, shape)
    for name, high in zip(halves, (True, False)):
      out[name] = _uniform16(words, high)
  return out


def _no_return(z: jax.Array, normal: dict, uniform: dict, pixel: dict, view: _View,
               sensor: SensorConfig) -> jax.Array:
  """(H, W) bool: the pixels without a return, by the true depth z."""
  missing = jp.zeros(z.shape, bool)
  if sensor.min_depth_m > 0:
    missing |= z < sensor.min_depth_m
  if "dropout" in pixel:
    missing |= pixel["dropout"] < _rate(sensor.dropout_rate, z, view.max_depth)
  if "grid" in normal:
    field = _patch_field(normal["grid"], uniform["shift"], z.shape, view,
                         sensor.patch_size_deg)
    # field < Phi^-1(p) has probability p: the configured rate at every pixel
    missing |= field < _patch_threshold(sensor.patch_rate, z, view.max_depth)
  return missing


def observe(image: jax.Array, key: jax.Array, camera: CameraConfig, sensor: SensorConfig,
            noise_factor: float | jax.Array) -> jax.Array:
  """The (H, W) float32 depth image (m, in [0, max_depth]) the policy sees.

  image: (H, W) float32 noise-free z-depth in metres (`depth.render_depth`'s); key: a jax
  PRNG key; camera: its CameraConfig (or the `depth.DepthCamera` made of it); sensor: the
  faults (`SensorConfig`; static: they decide which stages exist); noise_factor: the
  paper noise's k (may be traced). With no fault (the `ideal` preset) this is
  `depth.add_noise(image, key, camera, noise_factor)`, bit for bit, and nothing more.
  """
  if not _has_faults(sensor):
    return depth.add_noise(image, key, camera, noise_factor)
  view = _view(camera)
  z = image
  k_noise, k_normal, k_uniform, k_pixel = jax.random.split(key, 4)
  normal_shapes, uniform_shapes, pixel_names = _random_shapes(z.shape, view, sensor)
  normal = _draw(jax.random.normal, k_normal, normal_shapes)
  uniform = _draw(jax.random.uniform, k_uniform, uniform_shapes)
  pixel = _pixel_draws(k_pixel, z.shape, pixel_names)

  measured = z
  if "stereo" in pixel:
    measured = z + _stereo_std(z, sensor) * pixel["stereo"]
  if "fly" in pixel:
    measured = _flying(z, measured, pixel["fly"], sensor.flying_pixel_rate)
  measured = depth.add_noise(measured, k_noise, camera, noise_factor)
  if sensor.quantum_m > 0:
    measured = jp.round(measured / sensor.quantum_m) * sensor.quantum_m
  # (quantised before "no return" is laid on, which then reads max_depth exactly even
  # where max_depth is no whole number of quanta)
  if _has_no_return(sensor):
    measured = jp.where(_no_return(z, normal, uniform, pixel, view, sensor),
                        view.max_depth, measured)
  return jp.clip(measured, 0.0, view.max_depth)


__all__ = ["EDGE_STEP_M", "observe"]
