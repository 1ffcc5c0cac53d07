"""`bench depth`: images/s of `depth.render_depth`, vmapped over a batch of robot poses in
one vineyard, per image size and batch size, with and without the config's sensor model
(`sensor.observe`), beside the naive baseline (`mjx.ray` vmapped over every pixel), and
the agreement of one image with MuJoCo's C ray caster
(`mujoco.mj_multiRay`). Each row: wall-clock images/s, ms per image, CPU ms per image
(all threads), compile seconds."""

from __future__ import annotations

import argparse
from functools import partial
from typing import Callable

import jax
import jax.numpy as jp
import numpy as np
from mujoco import mjx

from mjxvine import config as config_lib
from mjxvine.bench.common import int_list, size_list, time_call
from mjxvine.cli import seed_type

# The pose-dependent fields of mjx.Data: all that a depth image needs besides the model.
FIELDS = ("cam_xpos", "cam_xmat", "geom_xpos", "geom_xmat")
NAIVE = "mjx.ray (naive)"


def add_depth_args(p: argparse.ArgumentParser) -> None:
  p.add_argument("--batches", default=None, type=int_list,
                 help="comma-separated batch sizes (default 1,16,64,256; with 1024,4096 on "
                      "an accelerator)")
  p.add_argument("--sizes", default="112x112,64x64", type=size_list,
                 help="comma-separated HxW")
  p.add_argument("--baseline-batch", type=int, default=4,
                 help="batch of the naive mjx.ray baseline (0: skip it)")
  p.add_argument("--chunk", type=int, default=None,
                 help="also time lax.map over chunks of this many images for larger batches "
                      "(default 16 on CPU, 0 elsewhere; 0: skip)")
  p.add_argument("--min-time", type=float, default=1.0, help="seconds per measurement")
  p.add_argument("--seed", type=seed_type, default=0, metavar="N",
                 help="seed of the train vineyard rendered and of the random robot poses "
                      "in it (default 0)")


def bench_depth(args: argparse.Namespace, cfg: config_lib.Config) -> list[dict]:
  """Rows of every `--sizes` image size: the naive baseline at `--baseline-batch`, then
  `render_depth` per batch size (and in `lax.map` chunks of `--chunk` above it)."""
  accel = jax.default_backend() != "cpu"
  batches = ([int(b) for b in args.batches.split(",")] if args.batches else
             [1, 16, 64, 256] + ([1024, 4096] if accel else []))
  if args.chunk is None:
    args.chunk = 0 if accel else 16
  rows = []
  for size in args.sizes.split(","):
    h, w = (int(v) for v in size.lower().split("x"))
    rows += _bench_size(args, config_lib.replace(cfg, camera={"height": h, "width": w}),
                        batches)
  return rows


def _vineyard(cfg: config_lib.Config, seed: int):
  """(MjModel, world) of a train vineyard of `cfg` (needs mjxvine.worlds)."""
  from mjxvine.worlds import build_model, generate_world  # pylint: disable=import-outside-toplevel
  world = generate_world("train", seed, cfg.world)
  return build_model(world, cfg), world


def _bench_size(args: argparse.Namespace, c: config_lib.Config,
                batches: list[int]) -> list[dict]:
  """The rows of one image size (c.camera), agreement with the C ray caster included."""
  from mjxvine import depth  # pylint: disable=import-outside-toplevel
  from mjxvine import worlds  # pylint: disable=import-outside-toplevel
  h, w = c.camera.height, c.camera.width
  size = f"{h}x{w}"
  model, world = _vineyard(c, args.seed)
  cam = depth.DepthCamera.create(model, c.camera)
  mx = mjx.put_model(model)
  pool = worlds.random_poses(model, world, 64, args.seed)
  template = mjx.put_data(model, pool[0])
  batch = _pose_batches(pool)
  vmapped = partial(_vmapped, mx, template)
  render = vmapped(partial(depth.render_depth, cam))
  rows, base_ips = [], None
  if args.baseline_batch > 0:
    bb = args.baseline_batch
    base = time_call(vmapped(_naive_render(cam, h, w)), *batch(bb), min_time=args.min_time,
                     min_reps=2)
    base_ips = bb / base["call_s"]
    rows.append(_row(size, NAIVE, bb, base))
  observed = vmapped(partial(_observed, cam, c))
  sensed = f"render_depth + sensor.observe ({c.sensor.preset})"
  for b in batches:
    r = time_call(render, *batch(b), min_time=args.min_time)
    row = _row(size, "depth.render_depth", b, r)
    if base_ips is not None and b == args.baseline_batch:
      row["vs_naive"] = row["images_per_s"] / base_ips
    rows.append(row)
    rows.append(_row(size, sensed, b, time_call(observed, *batch(b), min_time=args.min_time)))
    if b > args.chunk > 0:
      r = time_call(vmapped(partial(depth.render_depth, cam), args.chunk), *batch(b),
                    min_time=args.min_time)
      rows.append(_row(size, f"render_depth, lax.map chunks of {args.chunk}", b, r))
  if base_ips is not None and args.baseline_batch not in batches:
    r = time_call(render, *batch(args.baseline_batch), min_time=args.min_time)
    row = _row(size, "depth.render_depth", args.baseline_batch, r)
    row["vs_naive"] = row["images_per_s"] / base_ips
    rows.append(row)
  # Agreement with MuJoCo's C ray caster on the first pose (after the timings, so that
  # the batch-1 compile time is measured on a cold cache).
  img = np.asarray(render(*batch(1))[0])
  ref = depth.reference_depth(model, pool[0], cam)
  agree = float(np.mean(np.abs(img - ref) < 0.01))
  for row in rows:
    if row["impl"] != NAIVE:
      row["agree_1cm"] = agree
  return rows


def _observed(cam, c: config_lib.Config, m, d) -> jax.Array:
  """The image the policy sees: `render_depth` through the config's sensor model
  (`sensor.observe`, the paper's noise factor), in one program as in the env
  step; its key folded from the pose, so that XLA cannot fold the draws into constants."""
  from mjxvine import depth, sensor  # pylint: disable=import-outside-toplevel
  key = jax.random.fold_in(jax.random.PRNGKey(0),
                           jax.lax.bitcast_convert_type(d.cam_xpos[cam.cam_id, 0], jp.int32))
  return sensor.observe(depth.render_depth(cam, m, d), key, c.camera, c.sensor,
                        depth.NOISE_FACTOR)


def _row(size: str, impl: str, b: int, r: dict) -> dict:
  """One row from `time_call`'s result `r` of a batch of `b` images."""
  return dict(size=size, impl=impl, batch=b, images_per_s=b / r["call_s"],
              ms_per_image=1e3 * r["call_s"] / b, cpu_ms_per_image=1e3 * r["cpu_s"] / b,
              compile_s=r["compile_s"])


def _pose_batches(pool: list) -> Callable:
  """`batch(b)`: the FIELDS of the first b poses of `pool` (cycled), as float32 arrays
  with a leading batch axis (rotations as (..., 3, 3))."""
  stacked = {f: np.stack([getattr(dd, f) for dd in pool]) for f in FIELDS}
  for f in ("cam_xmat", "geom_xmat"):
    stacked[f] = stacked[f].reshape(len(pool), -1, 3, 3)

  def batch(b):
    return tuple(jp.asarray(np.resize(stacked[f], (b,) + stacked[f].shape[1:]), jp.float32)
                 for f in FIELDS)
  return batch


def _vmapped(mx, template, fn, chunk=None):
  """`fn(mx, data)` jitted over a batch of the FIELDS arrays (`_pose_batches`)."""
  # The model is closed over (batch-constant) and only the pose-dependent arrays of
  # mjx.Data are passed, so that the host-side pytree handling of a full mjx.Data
  # does not enter the timing (inside a training step it does not exist either).
  # chunk: lax.map over chunks of that many images (on a CPU XLA's intermediates
  # then stay in cache).
  def one(*xs):
    return fn(mx, template.replace(**dict(zip(FIELDS, xs))))
  if chunk is None:
    return jax.jit(jax.vmap(one))
  return jax.jit(lambda *xs: jax.lax.map(lambda x: one(*x), xs, batch_size=chunk))


def _naive_render(cam, h: int, w: int):
  """The naive baseline `(m, d) -> (h, w)` depth image: `mjx.ray` vmapped over every pixel
  (it ignores heightfields and cylinders in MJX 3.x, so it renders less than we do)."""
  rays = jp.asarray(cam.pixel_rays().reshape(-1, 3))

  def naive(m, d):
    o, rot = d.cam_xpos[cam.cam_id], d.cam_xmat[cam.cam_id]
    dist, _ = jax.vmap(lambda v: mjx.ray(m, d, o, rot @ v, geomgroup=(1, 1, 0, 0, 0, 0)))(rays)
    return jp.where(dist < 0, cam.max_depth, jp.minimum(dist, cam.max_depth)).reshape(h, w)
  return naive
