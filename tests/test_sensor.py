"""Tests of mjxvine.sensor (docs/design.md, The depth sensor): the ideal preset is the
paper's noise bit for bit; each fault's statistics match its formula within sampling error
(4 sigma); the presets load. Tiny images, one compiled function per sensor config (shared
through a session fixture); the paper noise is off (k = 0) where a fault is measured, so
that a pixel without a return reads max_depth exactly and every other its true depth."""

from __future__ import annotations

import dataclasses
import functools
import math
import types

import jax
import jax.numpy as jp
import numpy as np
import pytest

from mjxvine import depth, sensor
from mjxvine.config import (SENSOR_PRESETS, CameraConfig, ConfigError, SensorConfig,
                            load_config)

CAMERA = CameraConfig(height=32, width=48)  # 60 x 46.8 deg, max depth 5 m
MAX = CAMERA.max_depth_m
NONE = SensorConfig()  # every fault off (the ideal preset's values)
D435 = SensorConfig(preset="d435", **SENSOR_PRESETS["d435"])


def faults(**values) -> SensorConfig:
  """A sensor with only the faults named (the rest off)."""
  return dataclasses.replace(NONE, **values)


@pytest.fixture(scope="session")
def images():
  """images(sensor, camera=CAMERA) -> jit f(image (H, W), keys (N,), k) -> (N, H, W):
  N observations of one true image, compiled once per (sensor, camera)."""
  cache = {}

  def make(sens: SensorConfig, camera=CAMERA):
    if (sens, camera) not in cache:
      one = lambda image, key, k: sensor.observe(image, key, camera, sens, k)
      cache[sens, camera] = jax.jit(jax.vmap(one, in_axes=(None, 0, None)))
    return cache[sens, camera]
  return make


def keys(n: int, seed: int = 0) -> jax.Array:
  return jax.random.split(jax.random.key(seed), n)


def bands(depths, height=CAMERA.height, width=CAMERA.width) -> np.ndarray:
  """(H, W) float32: len(depths) vertical bands of equal width, each at its depth."""
  cols = np.repeat(np.asarray(depths, np.float32), width // len(depths))
  return np.broadcast_to(cols, (height, width)).copy()


def linear_rate(rates, z):
  return rates[0] + (rates[1] - rates[0]) * min(z / MAX, 1.0)


# ------------------------------------------------------------------ ideal

def test_ideal_is_the_paper_noise_bit_for_bit():
  image = jp.asarray(np.random.default_rng(0).uniform(0, MAX, (CAMERA.height, CAMERA.width)),
                     jp.float32)
  ideal = load_config(None, ["sensor.preset=ideal"]).sensor
  ours = lambda img, key, k: sensor.observe(img, key, CAMERA, ideal, k)
  paper = lambda img, key, k: depth.add_noise(img, key, CAMERA, k)
  args = (image, jax.random.key(7), jp.float32(2.5))
  np.testing.assert_array_equal(np.asarray(ours(*args)), np.asarray(paper(*args)))
  # the same traced graph (so the same compiled program): no stage of the sensor exists
  assert str(jax.make_jaxpr(ours)(*args)) == str(jax.make_jaxpr(paper)(*args))


# ------------------------------------------------------------------ stereo error

def stereo_std(z, sens: SensorConfig) -> float:
  return z * z * sens.stereo_subpixel_px / (sens.stereo_focal_px * sens.stereo_baseline_m)


def test_the_d435_stereo_error_is_the_documented_one():
  # docs/design.md: 3.6 / 14 / 32 / 57 mm at 1 / 2 / 3 / 4 m
  got = [stereo_std(z, D435) for z in (1, 2, 3, 4)]
  np.testing.assert_allclose(got, [0.0036, 0.0143, 0.0322, 0.0573], atol=2e-4)


def test_stereo_error_std_is_z_squared_s_over_f_b(images):
  stereo = faults(stereo_baseline_m=D435.stereo_baseline_m,
                  stereo_focal_px=D435.stereo_focal_px,
                  stereo_subpixel_px=D435.stereo_subpixel_px)
  depths = (1.0, 2.0, 4.0)
  out = np.asarray(images(stereo)(bands(depths), keys(16), 0.0))  # (16, 32, 48)
  for i, z in enumerate(depths):
    err = out[:, :, 16 * i:16 * (i + 1)].ravel() - z
    n, want = err.size, stereo_std(z, stereo)
    # the sample std's relative sampling error is 1 / sqrt(2 n); a simulator that
    # squares the term (rms^2 as the std) is off by orders of magnitude
    assert abs(err.std() / want - 1) < 4 / math.sqrt(2 * n), (z, err.std(), want)
    assert abs(err.mean()) < 4 * want / math.sqrt(n)


# ------------------------------------------------------------------ no return

def missing_share(out: np.ndarray, depths) -> list[np.ndarray]:
  """Per band: (N,) share of pixels reading max_depth (no return) of each image."""
  width = out.shape[-1] // len(depths)
  return [(out[:, :, width * i:width * (i + 1)] == MAX).mean(axis=(1, 2))
          for i in range(len(depths))]


def neighbour_agreement(band: np.ndarray) -> float:
  """P(the right neighbour has no return | the pixel has none) in (N, H, W) images."""
  missing = band == MAX
  left, right = missing[..., :-1], missing[..., 1:]
  return (left & right).sum() / left.sum()


DEPTHS = (0.5, 2.5, 4.5)
RATES = (0.05, 0.45)


def test_single_pixel_dropout_rate(images):
  out = np.asarray(images(faults(dropout_rate=RATES))(bands(DEPTHS), keys(32), 0.0))
  for z, share in zip(DEPTHS, missing_share(out, DEPTHS)):
    p, n = linear_rate(RATES, z), share.size * out[0, :, :16].size
    assert abs(share.mean() - p) < 4 * math.sqrt(p * (1 - p) / n), (z, share.mean(), p)
  # independent pixels: a neighbour's no return says nothing
  p = linear_rate(RATES, DEPTHS[2])
  assert abs(neighbour_agreement(out[..., 32:]) - p) < 0.05
  assert ((out == MAX) | (out == bands(DEPTHS))).all()  # the rest is untouched (k = 0)


PATCHES = faults(patch_rate=RATES, patch_size_deg=10.0)  # cells of 8 x 7 pixels
N_PATCHES = 256  # images per patch test (one batch size: one compiled function)


def test_patch_rate_and_correlation(images):
  n = N_PATCHES
  out = np.asarray(images(PATCHES)(bands(DEPTHS), keys(n, seed=1), 0.0))
  # pixels of an image are correlated: the sampling error is from the images' spread
  for z, share in zip(DEPTHS, missing_share(out, DEPTHS)):
    p = linear_rate(RATES, z)
    assert abs(share.mean() - p) < 4 * share.std() / math.sqrt(n) + 1e-3, (z, share.mean(), p)
  # spatially correlated: a neighbour of a pixel in a patch is mostly in one too (0.41
  # if independent)
  assert neighbour_agreement(out[..., 32:]) > 0.8
  assert ((out == MAX) | (out == bands(DEPTHS))).all()


def test_patches_follow_the_view_not_the_resolution(images):
  extents = []
  for cam in (CAMERA, CameraConfig(height=2 * CAMERA.height, width=2 * CAMERA.width)):
    image = np.full((cam.height, cam.width), 2.5, np.float32)  # rate 0.25
    missing = np.asarray(images(PATCHES, cam)(image, keys(N_PATCHES, seed=2), 0.0)) == MAX
    # the mean run of no return along a row, as a share of the image's width
    starts = (missing[..., 1:] & ~missing[..., :-1]).sum() + missing[..., 0].sum()
    extents.append(missing.sum() / starts / cam.width)
  assert abs(extents[0] / extents[1] - 1) < 0.1, extents


def test_min_range_and_quantisation(images):
  # 7 mm steps: 5 m is no whole number of them, yet "no return" reads 5 m exactly
  near_steps = faults(min_depth_m=0.3, quantum_m=0.007)
  image = np.linspace(0.05, MAX, CAMERA.height * CAMERA.width, dtype=np.float32).reshape(
      CAMERA.height, CAMERA.width)
  f = images(near_steps)
  clean, noisy = (np.asarray(f(image, keys(1), k))[0] for k in (0.0, 1.0))
  near = image < 0.3
  assert (clean[near] == MAX).all() and (noisy[near] == MAX).all()
  # the rest: its depth rounded to 7 mm steps
  np.testing.assert_allclose(clean[~near], np.round(image[~near] / 0.007) * 0.007,
                             rtol=0, atol=1e-5)
  measured = noisy[~near & (noisy < MAX)]
  quanta = measured / 0.007
  assert np.abs(quanta - np.round(quanta)).max() < 1e-3


# ------------------------------------------------------------------ the per-pixel draws

def test_pixel_words_are_uniform_and_independent():
  """The hash's words: 16-bit halves uniform (mean, variance), neighbours and the
  streams of two keys uncorrelated; the near-normal has mean 0, std 1 and no value
  beyond 3.45."""
  n = 1 << 16
  words = jax.jit(lambda k: sensor._pixel_words(k, (2, n)))
  a, b = words(jax.random.key(0)), words(jax.random.key(1))
  tol = 4 / math.sqrt(n)
  for high in (True, False):
    u = np.asarray(sensor._uniform16(a, high))
    assert 0 < u.min() and u.max() < 1
    assert abs(u.mean() - 0.5) < tol * math.sqrt(1 / 12)
    assert abs(u.var() - 1 / 12) < tol * math.sqrt(1 / 180)  # the sample variance's std
    assert abs(np.corrcoef(u[0, :-1], u[0, 1:])[0, 1]) < tol
    assert abs(np.corrcoef(u[0], u[1])[0, 1]) < tol
    other = np.asarray(sensor._uniform16(b, high))
    assert abs(np.corrcoef(u[0], other[0])[0, 1]) < tol
  x = np.asarray(sensor._near_normal(a)).ravel()
  assert abs(x.mean()) < 4 / math.sqrt(x.size) and abs(x.std() - 1) < 4 / math.sqrt(2 * x.size)
  assert np.abs(x).max() <= 3.4506
  # beyond 2 std: the normal 4.6 %, the sum of four bytes 4.3 % (its exact distribution:
  # four uniform bytes convolved)
  byte = np.full(256, 1 / 256)
  total = functools.reduce(np.convolve, [byte] * 4)
  tail = total[np.abs((np.arange(total.size) - 510) / math.sqrt(4 * (256**2 - 1) / 12)) > 2].sum()
  assert abs((np.abs(x) > 2).mean() - tail) < 0.0022  # 4 sigma; a normal: 0.0029 off


def test_the_patch_threshold_table_gives_the_rate():
  from statistics import NormalDist
  z = np.linspace(0.0, 6.0, 2001, dtype=np.float32)  # past max depth: the far rate
  for rates, tol in (((0.02, 0.1), 1e-5), ((0.05, 0.45), 1e-5), ((0.0, 0.45), 3e-3)):
    got = np.asarray(sensor._patch_threshold(rates, jp.asarray(z), MAX))
    rate = np.array([NormalDist().cdf(float(t)) for t in got])
    np.testing.assert_allclose(rate, [linear_rate(rates, float(d)) for d in z], atol=tol)


# ------------------------------------------------------------------ flying pixels

def test_flying_pixels_lie_between_the_sides_of_an_edge(images):
  # a ramp of 0.2 m per column (no edge) up to 3.2 m, then a step to 4 m: columns 11 and
  # 12 are the only edge pixels
  cols = np.r_[1.0 + 0.2 * np.arange(12), np.full(12, 4.0)].astype(np.float32)
  image = np.broadcast_to(cols, (16, 24)).copy()
  cam = CameraConfig(height=16, width=24)
  out = np.asarray(images(faults(flying_pixel_rate=0.5), cam)(image, keys(64), 0.0))
  edge = np.zeros(24, bool)
  edge[[11, 12]] = True
  np.testing.assert_array_equal(out[..., ~edge], np.broadcast_to(image[:, ~edge],
                                                                 out[..., ~edge].shape))
  at_edge = out[..., edge]
  assert ((at_edge >= 3.2 - 1e-6) & (at_edge <= 4.0 + 1e-6)).all()
  flew = at_edge != image[:, edge]
  n = flew.size
  assert abs(flew.mean() - 0.5) < 4 * math.sqrt(0.25 / n)
  # uniform between the two sides: mean in the middle, std (0.8 / sqrt(12))
  values = at_edge[flew]
  assert abs(values.mean() - 3.6) < 4 * 0.8 / math.sqrt(12 * values.size)


def test_flying_pixels_take_the_largest_step_to_a_neighbour():
  """Against the definition: each pixel's step to its 4-neighbours (up, down, left,
  right; the first of equal size; none across the border), on edges of every direction
  (the same pixels fly; their depths to float32 rounding, which XLA may fuse)."""
  rng = np.random.default_rng(3)
  z = rng.choice(np.float32([0.5, 1.0, 2.7, 4.9]), (13, 17)) + rng.uniform(
      0, 0.2, (13, 17)).astype(np.float32)
  u = rng.uniform(0, 1, z.shape).astype(np.float32)
  measured = z + np.float32(0.01)
  rate = 0.6
  got = np.asarray(jax.jit(sensor._flying, static_argnums=3)(z, measured, u, rate))
  pad = np.pad(z, 1, mode="edge")
  step = np.zeros_like(z)
  for neighbour in (pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]):
    step = np.where(np.abs(neighbour - z) > np.abs(step), neighbour - z, step)
  fly = (np.abs(step) > sensor.EDGE_STEP_M) & (u < rate)
  want = np.where(fly, z + (u / np.float32(rate)) * step, measured)
  assert 0.1 < fly.mean() < 0.9  # both kinds of pixel
  np.testing.assert_array_equal(got != measured, fly)
  np.testing.assert_allclose(got, want, rtol=1e-6, atol=0)


# ------------------------------------------------------------------ the whole chain

def test_the_d435_preset_in_a_batch_of_envs():
  cam = CameraConfig(height=41, width=41)
  # the env's DepthCamera keeps tan(fov / 2) and the noise: it gives the same image
  depth_camera = types.SimpleNamespace(
      tan_x=math.tan(math.radians(cam.fovx_deg / 2)),
      tan_y=math.tan(math.radians(cam.fovy_deg / 2)), max_depth=cam.max_depth_m,
      noise_sigma=depth.NOISE_SIGMA_M, noise_clip=depth.NOISE_CLIP_M,
      noise_factor=depth.NOISE_FACTOR)
  image = jp.asarray(bands((0.1, 1.0, 2.5, 4.9, 5.0), 41, 45)[:, :41])

  @jax.jit
  def batch(keys, k):  # per-env keys and noise factors, as the env vmaps
    return [jax.vmap(lambda key, k: sensor.observe(image, key, c, D435, k))(keys, k)
            for c in (cam, depth_camera)]
  out, again = (np.asarray(o) for o in batch(keys(4), jp.asarray([0.0, 1.0, 2.0, 10.0])))
  assert out.shape == (4, 41, 41) and out.dtype == np.float32
  assert np.isfinite(out).all() and out.min() >= 0.0 and out.max() <= MAX
  assert (out[:, :, :9] == MAX).all()  # 0.1 m: nearer than the D435's minimum range
  assert (out[:, :, 9:] < MAX).mean() > 0.5
  np.testing.assert_array_equal(again, out)


# ------------------------------------------------------------------ config

def test_presets_load_and_bad_values_are_one_line():
  for name, values in SENSOR_PRESETS.items():
    got = dataclasses.asdict(load_config(None, [f"sensor.preset={name}"]).sensor)
    assert got == {"preset": name, **{k: v for k, v in values.items()}}
  mixed = load_config(None, ["sensor.preset=d455", "sensor.min_depth_m=0.5"]).sensor
  assert mixed.min_depth_m == 0.5 and mixed.stereo_baseline_m == 0.095
  for item, key in (("sensor.preset=nope", "sensor.preset"),
                    ("sensor.dropout_rate=[0.1, 1.5]", "sensor.dropout_rate"),
                    ("sensor.patch_size_deg=0", "sensor.patch_size_deg")):
    with pytest.raises(ConfigError) as e:
      load_config(None, [item])
    assert key in str(e.value) and "\n" not in str(e.value)
