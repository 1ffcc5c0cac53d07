"""Benchmarks: `python -m mjxvine.bench <sub-command> [--out FILE.json]`.

Each sub-command is a function `(args, cfg) -> rows` (a list of flat dicts; or `(rows,
extra)`, extra fields for the JSON) registered in
`COMMANDS` with the function that adds its own arguments; `write_results(name, rows,
out)` prints the rows as a table and writes them to JSON together with the device, the
JAX backend, library versions, the host's CPU count and load. Add a sub-command by
writing those two functions and one `COMMANDS` entry.

Sub-commands
- all: every sub-command with its defaults (`--quick`: small sizes), one bench.json.
- physics: env-steps/s of the batched MJX physics alone (0.1 s control steps), and the
  ratio against a Python loop over envs calling `mujoco.mj_step` (one thread).
- env: env-steps/s of the whole env step at the config's image size.
- update: SAC gradient steps/s at batch 128 and 512 (config image size and networks), the
  achieved GFLOP/s (XLA's cost analysis / time), this machine's matmul GFLOP/s (2048x2048
  float32) and their ratio; `--compare` adds the program under XLA's default options.
- train: end-to-end `mjxvine.train` env-steps/s and gradient-steps/s while learning
  (default `experiments/fast.yaml`), per env count.
- brax: brax's own SAC and mjxvine's SAC with one schedule on the vector-observation
  vineyard task (`VectorObsEnv`), scored by brax's `Evaluator`; env steps and wall-clock
  to a common success rate, as ratios.
- depth: images/s of `depth.render_depth` (vmapped over a batch of robot poses in one
  vineyard) for batch sizes 1, 16, 64, 256 (and 1024, 4096 on an accelerator) at 112x112
  and 64x64, compile time apart, agreement with `mujoco.mj_multiRay` on one image, and
  the ratio against the naive baseline (`mjx.ray` vmapped over every pixel; it ignores
  heightfields and cylinders in MJX 3.x, so it renders less than we do). On CPU, batches
  above 16 are also timed in `lax.map` chunks of 16. Each row gives
  wall-clock images/s and CPU ms per image (all threads): on a shared machine the latter
  is the steadier number.
- deploy: single-decision latency (median, p99 over 1,000 calls) of the exported actor
  (random weights, config image size) with `NumpyPolicy` and onnxruntime, at 1 and 2
  threads, beside the paper's TF (2.8-6.2 ms) and TFLite (0.63-1.96 ms) figures.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import platform
import sys
import time
from functools import partial
from importlib import metadata
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jp
import mujoco
import numpy as np
from mujoco import mjx

from mjxvine import config as config_lib


# ------------------------------------------------------------------ shared helpers

def environment() -> dict:
  """Device, backend, versions and host load: what a benchmark number depends on."""
  versions = {}
  for pkg in ("jax", "jaxlib", "mujoco", "mujoco-mjx", "brax", "flax", "numpy"):
    try:
      versions[pkg] = metadata.version(pkg)
    except metadata.PackageNotFoundError:
      pass
  dev = jax.devices()[0]
  kind = getattr(dev, "device_kind", "")
  if dev.platform == "cpu":
    try:
      with open("/proc/cpuinfo") as f:
        kind = next(l.split(":", 1)[1].strip() for l in f if l.startswith("model name"))
    except (OSError, StopIteration):
      kind = platform.processor() or kind
  return dict(device=f"{dev.platform}: {kind}",
              devices=len(jax.devices()), backend=jax.default_backend(), versions=versions,
              python=platform.python_version(), host=platform.node(), cpus=os.cpu_count(),
              load_avg=os.getloadavg() if hasattr(os, "getloadavg") else None,
              time=time.strftime("%Y-%m-%dT%H:%M:%S"))


def write_results(name: str, rows: list[dict], out: str | None = None, **extra) -> dict:
  """Prints `rows` as a table and, if `out` is given, writes them with `environment()`."""
  env = environment()
  result = dict(benchmark=name, **env, **extra, rows=rows)
  print(f"# {name}: {env['device']} ({env['backend']}), jax {env['versions'].get('jax')}, "
        f"mujoco {env['versions'].get('mujoco')}, load {env['load_avg']}")
  if rows:
    keys = list(dict.fromkeys(k for r in rows for k in r))
    cells = [[_fmt(r.get(k, "")) for k in keys] for r in rows]
    widths = [max(len(k), *(len(c[i]) for c in cells)) for i, k in enumerate(keys)]
    print("  ".join(k.rjust(w) for k, w in zip(keys, widths)))
    for c in cells:
      print("  ".join(v.rjust(w) for v, w in zip(c, widths)))
  for k, v in extra.items():
    print(f"{k}: {v}")
  if out:
    with open(out, "w") as f:
      json.dump(result, f, indent=1, default=_json_default)
    print(f"wrote {out}")
  return result


def _fmt(v) -> str:
  if isinstance(v, float):
    return f"{v:.4g}" if abs(v) < 1e5 else f"{v:.0f}"
  return str(v)


def _json_default(o):
  if isinstance(o, (np.generic,)):
    return o.item()
  if isinstance(o, np.ndarray):
    return o.tolist()
  raise TypeError(type(o))


def cost_analysis(compiled) -> dict:
  """XLA's own count of a compiled program's work: {"flops", "bytes_accessed"} per call
  (None where the backend gives none). It does not depend on the machine's load."""
  cost = compiled.cost_analysis()
  if isinstance(cost, (list, tuple)):  # older jax: one dict per device program
    cost = cost[0] if cost else {}
  cost = cost or {}
  get = lambda k: float(cost[k]) if k in cost else None
  return {"flops": get("flops"), "bytes_accessed": get("bytes accessed")}


def time_compiled(fn: Callable, *args, min_time: float = 1.0, min_reps: int = 3) -> dict:
  """Steady-state seconds per call of a compiled `fn(*args)`: median, best, median CPU
  seconds, over at least `min_reps` calls and `min_time` seconds (after one warm-up)."""
  jax.block_until_ready(fn(*args))  # warm-up
  times, cpu, start = [], [], time.perf_counter()
  while len(times) < min_reps or time.perf_counter() - start < min_time:
    t, c = time.perf_counter(), time.process_time()
    jax.block_until_ready(fn(*args))
    times.append(time.perf_counter() - t)
    cpu.append(time.process_time() - c)
  return dict(call_s=float(np.median(times)), best_s=float(np.min(times)),
              cpu_s=float(np.median(cpu)), reps=len(times))


def time_call(fn: Callable, *args, min_time: float = 1.0, min_reps: int = 3) -> dict:
  """Compile time, steady-state seconds per call (`time_compiled`) and XLA's cost analysis
  (flops, bytes accessed per call) of a jitted `fn(*args)`."""
  t = time.perf_counter()
  fn = fn.lower(*args).compile()
  compile_s = time.perf_counter() - t
  return dict(compile_s=compile_s, **time_compiled(fn, *args, min_time=min_time,
                                                   min_reps=min_reps), **cost_analysis(fn))


def _per(cost: float | None, count: int) -> float | None:
  return None if cost is None else cost / count


# ------------------------------------------------------------------ depth

def _vineyard(cfg: config_lib.Config, seed: int):
  """(MjModel, world) of a train vineyard of `cfg` (needs mjxvine.worlds)."""
  from mjxvine.worlds import build_model, generate_world  # pylint: disable=import-outside-toplevel
  world = generate_world("train", seed, cfg.world)
  return build_model(world, cfg), world


# argparse types: a bad value is a usage error (exit status 2, one line), not a traceback
# halfway through a benchmark. Lists stay text: the benchmarks split them.

def _positive_int(text: str) -> int:
  try:
    value = int(text)
  except ValueError:
    value = 0
  if value < 1:
    raise argparse.ArgumentTypeError(f"{text!r}: expected a positive integer")
  return value


def _int_list(text: str) -> str:
  """Comma-separated positive integers ("1,16,64")."""
  for item in text.split(","):
    _positive_int(item)
  return text


def _size(text: str) -> str:
  """HxW of positive integers ("112x112")."""
  parts = text.lower().split("x")
  if len(parts) != 2:
    raise argparse.ArgumentTypeError(f"{text!r}: expected HxW, e.g. 112x112")
  for part in parts:
    _positive_int(part)
  return text


def _size_list(text: str) -> str:
  """Comma-separated HxW sizes ("112x112,64x64")."""
  for item in text.split(","):
    _size(item)
  return text


def _depth_args(p: argparse.ArgumentParser) -> None:
  p.add_argument("--batches", default=None, type=_int_list,
                 help="comma-separated batch sizes (default 1,16,64,256; with 1024,4096 on "
                      "an accelerator)")
  p.add_argument("--sizes", default="112x112,64x64", type=_size_list,
                 help="comma-separated HxW")
  p.add_argument("--baseline-batch", type=int, default=4,
                 help="batch of the naive mjx.ray baseline (0: skip it)")
  p.add_argument("--chunk", type=int, default=None,
                 help="also time lax.map over chunks of this many images for larger batches "
                      "(default 16 on CPU, 0 elsewhere; 0: skip)")
  p.add_argument("--min-time", type=float, default=1.0, help="seconds per measurement")
  p.add_argument("--seed", type=int, default=0)


def bench_depth(args: argparse.Namespace, cfg: config_lib.Config) -> list[dict]:
  from mjxvine import depth, worlds  # pylint: disable=import-outside-toplevel
  accel = jax.default_backend() != "cpu"
  batches = ([int(b) for b in args.batches.split(",")] if args.batches else
             [1, 16, 64, 256] + ([1024, 4096] if accel else []))
  if args.chunk is None:
    args.chunk = 0 if accel else 16
  rows = []
  for size in args.sizes.split(","):
    h, w = (int(v) for v in size.lower().split("x"))
    c = config_lib.replace(cfg, camera={"height": h, "width": w})
    model, world = _vineyard(c, args.seed)
    cam = depth.DepthCamera.create(model, c.camera)
    mx = mjx.put_model(model)
    pool = worlds.random_poses(model, world, 64, args.seed)
    template = mjx.put_data(model, pool[0])
    fields = ("cam_xpos", "cam_xmat", "geom_xpos", "geom_xmat")
    stacked = {f: np.stack([getattr(dd, f) for dd in pool]) for f in fields}
    for f in ("cam_xmat", "geom_xmat"):
      stacked[f] = stacked[f].reshape(len(pool), -1, 3, 3)

    def batch(b):
      return tuple(jp.asarray(np.resize(stacked[f], (b,) + stacked[f].shape[1:]), jp.float32)
                   for f in fields)

    def vmapped(fn, chunk=None):
      # The model is closed over (batch-constant) and only the pose-dependent arrays of
      # mjx.Data are passed, so that the host-side pytree handling of a full mjx.Data
      # does not enter the timing (inside a training step it does not exist either).
      # chunk: lax.map over chunks of that many images (on a CPU XLA's intermediates
      # then stay in cache).
      def one(*xs):
        return fn(mx, template.replace(**dict(zip(fields, xs))))
      if chunk is None:
        return jax.jit(jax.vmap(one))
      return jax.jit(lambda *xs: jax.lax.map(lambda x: one(*x), xs, batch_size=chunk))

    render = vmapped(partial(depth.render_depth, cam))
    base = None
    if args.baseline_batch > 0:
      rays = jp.asarray(cam.pixel_rays().reshape(-1, 3))

      def naive(m, d):
        o, rot = d.cam_xpos[cam.cam_id], d.cam_xmat[cam.cam_id]
        dist, _ = jax.vmap(lambda v: mjx.ray(m, d, o, rot @ v, geomgroup=(1, 1, 0, 0, 0, 0)))(rays)
        return jp.where(dist < 0, cam.max_depth, jp.minimum(dist, cam.max_depth)).reshape(h, w)

      bb = args.baseline_batch
      base = time_call(vmapped(naive), *batch(bb), min_time=args.min_time, min_reps=2)
      base_ips = bb / base["call_s"]
      rows.append(dict(size=f"{h}x{w}", impl="mjx.ray (naive)", batch=bb, images_per_s=base_ips,
                       ms_per_image=1e3 * base["call_s"] / bb,
                       cpu_ms_per_image=1e3 * base["cpu_s"] / bb, compile_s=base["compile_s"]))
    for b in batches:
      r = time_call(render, *batch(b), min_time=args.min_time)
      ips = b / r["call_s"]
      row = dict(size=f"{h}x{w}", impl="depth.render_depth", batch=b, images_per_s=ips,
                 ms_per_image=1e3 * r["call_s"] / b, cpu_ms_per_image=1e3 * r["cpu_s"] / b,
                 compile_s=r["compile_s"])
      if base is not None and b == args.baseline_batch:
        row["vs_naive"] = ips / base_ips
      rows.append(row)
      if b > args.chunk > 0:
        r = time_call(vmapped(partial(depth.render_depth, cam), args.chunk), *batch(b),
                      min_time=args.min_time)
        rows.append(dict(size=f"{h}x{w}", impl=f"render_depth, lax.map chunks of {args.chunk}",
                         batch=b, images_per_s=b / r["call_s"],
                         ms_per_image=1e3 * r["call_s"] / b,
                         cpu_ms_per_image=1e3 * r["cpu_s"] / b, compile_s=r["compile_s"]))
    if base is not None and args.baseline_batch not in batches:
      r = time_call(render, *batch(args.baseline_batch), min_time=args.min_time)
      rows.append(dict(size=f"{h}x{w}", impl="depth.render_depth", batch=args.baseline_batch,
                       images_per_s=args.baseline_batch / r["call_s"],
                       ms_per_image=1e3 * r["call_s"] / args.baseline_batch,
                       cpu_ms_per_image=1e3 * r["cpu_s"] / args.baseline_batch,
                       compile_s=r["compile_s"],
                       vs_naive=(args.baseline_batch / r["call_s"]) / base_ips))
    # Agreement with MuJoCo's C ray caster on the first pose (after the timings, so that
    # the batch-1 compile time is measured on a cold cache).
    img = np.asarray(render(*batch(1))[0])
    ref = depth.reference_depth(model, pool[0], cam)
    agree = float(np.mean(np.abs(img - ref) < 0.01))
    for row in rows:
      if row["size"] == f"{h}x{w}" and row["impl"] != "mjx.ray (naive)":
        row["agree_1cm"] = agree
  return rows


# ------------------------------------------------------------------ physics and env

def _sizes(args) -> list[int]:
  if args.sizes:
    return [int(x) for x in args.sizes.split(",")]
  return [1, 16, 64, 256] + ([1024, 4096, 16384] if jax.default_backend() != "cpu" else [])


def _env_args(p: argparse.ArgumentParser) -> None:
  p.add_argument("--sizes", default=None, type=_int_list,
                 help="comma-separated env counts (default 1,16,64,256, plus "
                      "1024,4096,16384 on an accelerator)")
  p.add_argument("--steps", type=_positive_int, default=10,
                 help="control steps per timed call")
  p.add_argument("--no-baseline", dest="baseline", action="store_false",
                 help="skip the Python loop over mujoco.mj_step (physics) baseline")


def _env_setup(cfg, n: int):
  from mjxvine.env import training_env  # pylint: disable=import-outside-toplevel
  env = training_env(cfg)
  state = jax.jit(lambda k: env.reset_batch(k, n))(jax.random.PRNGKey(0))
  action = jp.tile(jp.array([[0.3, 0.1]], jp.float32), (n, 1))
  return env, state, action


def bench_physics(args: argparse.Namespace, cfg: config_lib.Config) -> list[dict]:
  """Env-steps/s of the batched MJX physics alone: `VineyardEnv.physics` per control step
  (the wheel commands, then control_dt / physics_dt `mjx.step`s), each env in its own
  pool world."""
  rows = []
  for n in _sizes(args):
    env, state, action = _env_setup(cfg, n)

    def one(d, world, a):
      return env.physics(env.world_model(world), d, a)

    def run(d, worlds, a):
      step = jax.vmap(one)
      return jax.lax.fori_loop(0, args.steps, lambda _, x: step(x, worlds, a), d)

    t = time_call(jax.jit(run), state.pipeline_state, state.info["pose"]["world"], action)
    rate = n * args.steps / t["call_s"]
    rows.append(dict(envs=n, substeps=env.substeps, env_steps_per_s=rate,
                     compile_s=t["compile_s"],
                     cpu_ms_per_env_step=1e3 * t["cpu_s"] / (n * args.steps)))
  if args.baseline:
    base = mujoco_loop_rate(env, seconds=2.0)
    for row in rows:
      row.update(mj_step_loop_env_steps_per_s=base,
                 ratio_vs_mj_step_loop=row["env_steps_per_s"] / base)
  return rows


def mujoco_loop_rate(env, seconds: float = 2.0) -> float:
  """Env-steps/s of the baseline a NumPy user would write: a Python loop over envs calling
  the C library's `mujoco.mj_step` control_dt / physics_dt times per control step (one
  thread, the same world model and wheel commands)."""
  from mjxvine.worlds import wheel_speeds  # pylint: disable=import-outside-toplevel
  model = env.mj_model
  datas = [mujoco.MjData(model) for _ in range(8)]
  for d in datas:
    mujoco.mj_forward(model, d)
  ctrl = np.array(wheel_speeds(0.3, 0.1, env.robot), np.float64)
  steps, start = 0, time.perf_counter()
  while time.perf_counter() - start < seconds:
    for d in datas:
      d.ctrl[:] = ctrl
      for _ in range(env.substeps):
        mujoco.mj_step(model, d)
      steps += 1
  return steps / (time.perf_counter() - start)


def bench_env(args: argparse.Namespace, cfg: config_lib.Config) -> list[dict]:
  """Env-steps/s of the whole env step (physics, depth image and noise, reward,
  terminations, auto-reset) at the config's image size."""
  rows = []
  for n in _sizes(args):
    env, state, action = _env_setup(cfg, n)

    def run(s, a):
      return jax.lax.fori_loop(0, args.steps, lambda _, x: env.step_batch(x, a)[0], s)

    t = time_call(jax.jit(run), state, action)
    rows.append(dict(envs=n, image=f"{cfg.camera.height}x{cfg.camera.width}",
                     env_steps_per_s=n * args.steps / t["call_s"], compile_s=t["compile_s"],
                     cpu_ms_per_env_step=1e3 * t["cpu_s"] / (n * args.steps),
                     flops_per_env_step=_per(t["flops"], n * args.steps),
                     bytes_per_env_step=_per(t["bytes_accessed"], n * args.steps)))
  return rows


# ------------------------------------------------------------------ learner and trainer

def matmul_gflops(n: int = 2048, min_time: float = 1.0) -> float:
  """The machine's matrix-multiply rate, GFLOP/s: a jitted n x n float32 matmul (2 n^3
  flops), median of calls over `min_time` seconds. The yardstick of `bench update`."""
  a = jax.random.normal(jax.random.PRNGKey(0), (n, n), jp.float32)
  t = time_call(jax.jit(lambda x: x @ x), a, min_time=min_time)
  return 2.0 * n ** 3 / t["call_s"] / 1e9


def _update_args(p: argparse.ArgumentParser) -> None:
  p.add_argument("--batch-sizes", default="128,512", type=_int_list,
                 help="comma-separated SAC batch sizes")
  p.add_argument("--grad-steps", type=_positive_int, default=None,
                 help="gradient steps per timed call (default sac.grad_steps_per_iter)")
  p.add_argument("--conv-impl", default=None, choices=("xla", "dot", "shift", "native"),
                 help="the conv tower's convolutions (mjxvine.networks.CONV_IMPLS; "
                      "default: the trainer's, sac.conv_impl)")
  p.add_argument("--compare", action="store_true",
                 help="also time the program compiled with XLA's default options (on a "
                      "CPU: with YNNPACK's convolutions)")
  p.add_argument("--rounds", type=_positive_int, default=3,
                 help="times the update and the matmul are each timed, in turn (1 s "
                      "each); the row gives their medians")


def bench_update(args: argparse.Namespace, cfg: config_lib.Config) -> list[dict]:
  """SAC gradient steps/s (sample from a full replay, twin-critic, actor and target
  updates) at the config's image size and networks, per batch size, timed as the trainer
  runs them: `update_many`, the G steps of an iteration in one program, on accelerators
  and with the native tower; else (a chunk as a host loop, `trainer.scan_chunks`, with
  XLA's convolutions, which XLA:CPU runs about 3x slower inside a loop:
  docs/results/cpu-update-speed.md) one jitted gradient step (`update_from`) per call, G
  calls per iteration.

  Each row also gives the achieved GFLOP/s (XLA's cost-analysis flops per gradient step
  / median seconds per gradient step), the machine's matmul GFLOP/s (`matmul_gflops`) and
  their ratio: the fraction of this machine's matrix-multiply rate the update runs at.
  The update and the matmul are timed in turn, `--rounds` times each, so that both see
  the same load; the row gives the medians, the ratio the median of the rounds' ratios
  (and their range): steadier than gradient steps/s on a shared machine. The program is
  compiled with `sac.learner_compiler_options()`, as the trainer compiles it ("options"
  column). With the native tower the flops are G times those of one step with XLA's
  convolutions (XLA's cost analysis does not count an FFI call's, nor a loop's trips)."""
  from mjxvine import networks as nw  # pylint: disable=import-outside-toplevel
  from mjxvine import sac as sac_lib  # pylint: disable=import-outside-toplevel
  from mjxvine.env import VineyardEnv  # pylint: disable=import-outside-toplevel
  from mjxvine.trainer import scan_chunks  # pylint: disable=import-outside-toplevel
  rows = []
  g = args.grad_steps or cfg.sac.grad_steps_per_iter
  host = not scan_chunks(cfg)
  tuned = sac_lib.learner_compiler_options()
  variants = [("learner", tuned)] + ([("xla default", None)] if args.compare and tuned else [])
  conv_impl = args.conv_impl or sac_lib.learner_conv_impl(cfg.sac.conv_impl)
  # the vineyard's mirror image, for configs with sac.mirror_augment / mirror_average
  mirror = (VineyardEnv.mirror_obs, VineyardEnv.mirror_action)
  for b in (int(x) for x in args.batch_sizes.split(",")):
    c = config_lib.replace(cfg, sac={"batch_size": b, "grad_steps_per_iter": g})
    nets = nw.make_networks_from_config(c, conv_impl=conv_impl)
    sac = sac_lib.make_sac(nets, c.sac, mirror=mirror)
    h, w = c.camera.height, c.camera.width
    n = 16
    obs = {"depth": jp.ones((n, h, w, 1)), "state": jp.zeros((n, 3))}
    buffer = sac_lib.init_buffer(obs, 2, max(4 * b, 64 * n), c.camera.max_depth_m,
                                 jp.dtype(c.sac.replay_depth_dtype))
    buffer = buffer.replace(rows_written=jp.int32(buffer.num_rows))  # full (zeros)
    learner = sac.init(jax.random.PRNGKey(0), obs)
    native = nw.native_towers(nets)
    one_step = host and not native  # G calls of one step (as the trainer's host loop)
    step = sac.update_from if one_step else sac.update_many
    if native:  # XLA does not count an FFI call's work: count XLA's convs', G times
      xla_sac = sac_lib.make_sac(nw.make_networks_from_config(c, conv_impl="xla"), c.sac,
                                 mirror=mirror)
      xla_cost = cost_analysis(jax.jit(xla_sac.update_from, compiler_options=tuned).lower(
          learner, buffer, jax.random.PRNGKey(1)).compile())
    per_call = 1 if one_step else g  # gradient steps per timed call
    key = jax.random.PRNGKey(1)
    for name, options in variants:
      start = time.perf_counter()
      compiled = jax.jit(step, compiler_options=options).lower(learner, buffer, key).compile()
      compile_s = time.perf_counter() - start
      cost = cost_analysis(compiled)
      if native:  # per call: G steps' flops; no count of an FFI call's memory traffic
        cost = {"flops": xla_cost["flops"] * g, "bytes_accessed": None}
      flops = _per(cost["flops"], per_call)  # per gradient step
      # the step and the matmul timed in turn, so that both see the same load
      rounds = [(time_compiled(compiled, learner, buffer, key)["call_s"] / per_call,
                 matmul_gflops()) for _ in range(args.rounds)]
      step_s = float(np.median([r[0] for r in rounds]))
      ratios = [] if flops is None else [flops / s / 1e9 / mm for s, mm in rounds]
      rows.append(dict(batch=b, image=f"{h}x{w}", conv=conv_impl, options=name,
                       program="update_from (host loop)" if one_step else "update_many",
                       grad_steps_per_call=per_call, grad_steps_per_s=1.0 / step_s,
                       samples_per_s=b / step_s, compile_s=compile_s,
                       flops_per_grad_step=flops,
                       bytes_per_grad_step=_per(cost["bytes_accessed"], per_call),
                       gflops=None if flops is None else flops / step_s / 1e9,
                       matmul_gflops=float(np.median([r[1] for r in rounds])),
                       ratio=float(np.median(ratios)) if ratios else None,
                       ratio_range=(f"{min(ratios):.3f}-{max(ratios):.3f}" if ratios
                                    else None),
                       load_1m=os.getloadavg()[0] if hasattr(os, "getloadavg") else None))
  return rows


def _train_args(p: argparse.ArgumentParser) -> None:
  p.add_argument("--sizes", default=None, type=_int_list,
                 help="comma-separated env counts (default 256,1024,4096,16384 on an "
                      "accelerator, 16,64 on a CPU)")
  p.add_argument("--iters", type=_positive_int, default=None,
                 help="iterations per timed chunk (default train.iters_per_chunk)")
  p.set_defaults(config=str(EXPERIMENTS / "fast.yaml"))


def bench_train(args: argparse.Namespace, cfg: config_lib.Config) -> list[dict]:
  """End-to-end training throughput of `mjxvine.train` (default `experiments/fast.yaml`):
  env-steps/s and gradient-steps/s of whole learning chunks (env steps with exploration,
  replay inserts, gradient steps), after a first chunk that compiles and fills the replay
  beyond one batch. Compile time is the first chunk's excess over a steady one."""
  from mjxvine import train as train_lib  # pylint: disable=import-outside-toplevel
  rows = []
  if args.sizes:
    sizes = [int(x) for x in args.sizes.split(",")]
  else:
    sizes = [16, 64] if jax.default_backend() == "cpu" else [256, 1024, 4096, 16384]
  for n in sizes:
    iters = args.iters or cfg.train.iters_per_chunk
    c = config_lib.replace(cfg, env={"num_envs": n}, sac={"warmup_steps": 0},
                           train={"iters_per_chunk": iters})
    _, init_fn, chunk_fn = train_lib.compiled_trainer(c)
    ts = init_fn(jax.random.split(jax.random.PRNGKey(0), 1))
    # Warm-up chunks: compile, and fill the replay past one batch so that every iteration
    # of the timed chunk learns (the CPU path compiles its learning program on first use).
    warm = 2 + math.ceil((c.sac.batch_size / n + 1) / iters)
    times = []
    for _ in range(warm + 1):
      t = time.perf_counter()
      ts, m = chunk_fn(ts)
      jax.block_until_ready(m)
      times.append(time.perf_counter() - t)
    steady = times[-1]
    g = iters * c.sac.grad_steps_per_iter
    rows.append(dict(envs=n, image=f"{c.camera.height}x{c.camera.width}",
                     batch=c.sac.batch_size, grad_steps_per_iter=c.sac.grad_steps_per_iter,
                     env_steps_per_s=n * iters / steady, grad_steps_per_s=g / steady,
                     compile_s=max(sum(times[:-1]) - warm * steady, 0.0),
                     finite=bool(np.all(m["finite"]))))
  return rows


# ------------------------------------------------------------------ brax's SAC

def _brax_args(p: argparse.ArgumentParser) -> None:
  p.add_argument("--steps", type=_positive_int, default=20_000, help="env steps per learner")
  p.add_argument("--evals", type=_positive_int, default=10, help="evaluations along the way")
  p.add_argument("--eval-envs", type=_positive_int, default=64, help="episodes per evaluation")
  p.add_argument("--pool", default="8x8", type=_size,
                 help="depth average-pooled to HxW cells")
  p.add_argument("--target", type=float, default=0.5,
                 help="success rate whose env steps and wall-clock are compared")
  p.set_defaults(config=str(EXPERIMENTS / "compare.yaml"))


def bench_brax(args: argparse.Namespace, cfg: config_lib.Config) -> list[dict]:
  """brax's SAC (`brax.training.agents.sac`) and mjxvine's SAC side by side on the same
  vineyard task, with the same schedule (envs, batch, gradient steps per env step,
  learning rate, gamma, tau, replay, warm-up, reward scale, automatic temperature), both
  evaluated by brax's own `Evaluator` (deterministic policy, `--eval-envs` episodes).

  brax's SAC takes vector observations only, so both learn on `VectorObsEnv`: the depth
  image average-pooled to `--pool` cells plus the state (the paper's conv tower cannot
  be given to brax's SAC). Each row is one evaluation: env steps, training wall-clock
  (compilation included, evaluation excluded) and success rate."""
  import tempfile  # pylint: disable=import-outside-toplevel
  from brax import envs as brax_envs  # pylint: disable=import-outside-toplevel
  from brax.training.acting import Evaluator  # pylint: disable=import-outside-toplevel
  from brax.training.agents.sac import train as brax_sac  # pylint: disable=import-outside-toplevel
  from mjxvine import wrappers  # pylint: disable=import-outside-toplevel
  from mjxvine.env import VectorObsEnv  # pylint: disable=import-outside-toplevel
  from mjxvine import checkpoint  # pylint: disable=import-outside-toplevel
  from mjxvine import policies  # pylint: disable=import-outside-toplevel
  from mjxvine import train as train_lib  # pylint: disable=import-outside-toplevel

  pool = tuple(int(x) for x in args.pool.split("x"))
  venv = VectorObsEnv(cfg, pool)
  c, length, n = cfg.sac, cfg.env.max_steps, cfg.env.num_envs
  per_eval = args.steps // args.evals
  rows: list[dict] = []

  # brax: progress_fn runs after each evaluation; "training/walltime" is brax's own clock
  # of its training epochs (compilation included, evaluation excluded).
  def progress(step, metrics):
    rows.append(dict(learner="brax.sac", env_steps=int(step),
                     train_s=float(metrics.get("training/walltime", 0.0)),
                     success=float(metrics["eval/episode_success"]),
                     episode_return=float(metrics["eval/episode_reward"])))

  with _brax_jax_compat():
    brax_sac.train(
        environment=venv, num_timesteps=args.steps, episode_length=length, num_envs=n,
        num_eval_envs=args.eval_envs, learning_rate=c.learning_rate, discounting=c.gamma,
        seed=cfg.train.seed, batch_size=c.batch_size, num_evals=args.evals + 1,
        reward_scaling=c.reward_scale, tau=c.tau, min_replay_size=c.warmup_steps,
        max_replay_size=c.buffer_size, grad_updates_per_step=c.grad_steps_per_iter,
        deterministic_eval=True, progress_fn=progress)

  # mjxvine: the same setting through wrappers.brax_env, evaluated by the same Evaluator.
  ours = config_lib.replace(
      cfg, sac={"auto_alpha": True, "alpha": 1.0, "target_entropy": -1.0, "eps_start": 0.0,
                "eps_min": 0.0},
      train={"iters_per_chunk": max(1, per_eval // n // 4)})
  adapter = wrappers.brax_env(venv, length)
  sac, _, _ = train_lib.compiled_trainer(ours, env=adapter)
  evaluator = Evaluator(
      brax_envs.training.wrap(venv, episode_length=length),
      lambda params: policies.actor_policy(sac.nets, params, brax=True),
      num_eval_envs=args.eval_envs, episode_length=length, action_repeat=1,
      key=jax.random.PRNGKey(cfg.train.seed + 1))
  run = Path(tempfile.mkdtemp(prefix="bench-brax-"))
  template = train_lib.compiled_trainer(ours, env=adapter)[1](
      jax.random.split(jax.random.PRNGKey(cfg.train.seed), 1))
  train_s = 0.0
  for k in range(args.evals + 1):
    steps = max(k * per_eval, 1)
    t = time.perf_counter()
    if k:
      train_lib.train(config_lib.replace(ours, train={"total_env_steps": steps}), run,
                      resume=k > 1, evaluate_at_end=False, quiet=True, env=adapter)
    train_s += time.perf_counter() - t
    restored = checkpoint.Checkpoints(run, False).restore(template) if k else None
    state = restored[1] if restored else template
    m = evaluator.run_evaluation(state.learner.policy_params, training_metrics={})
    rows.append(dict(learner="mjxvine.sac", env_steps=int(state.env_steps), train_s=train_s,
                     success=float(m["eval/episode_success"]),
                     episode_return=float(m["eval/episode_reward"])))
  return rows, {"summary": brax_summary(rows, args.target), "target_success": args.target}


@contextlib.contextmanager
def _brax_jax_compat():
  """brax 0.14's SAC still calls `jax.device_put_replicated`, which JAX 0.10 removed;
  provide its replacement (a leading device axis, as `jax.pmap` expects) while it runs."""
  if "device_put_replicated" in vars(jax):
    yield
    return

  def device_put_replicated(x, devices):
    return jax.tree.map(lambda a: jax.device_put(jp.stack([jp.asarray(a)] * len(devices))), x)

  jax.device_put_replicated = device_put_replicated
  try:
    yield
  finally:
    del jax.device_put_replicated


def brax_summary(rows: list[dict], target: float) -> dict:
  """Env steps and training seconds each learner took to first reach `target` success,
  and mjxvine's speed-up (brax / mjxvine) where both did."""
  out = {}
  for name in ("brax.sac", "mjxvine.sac"):
    hit = [r for r in rows if r["learner"] == name and r["success"] >= target]
    out[name] = dict(env_steps=hit[0]["env_steps"], train_s=hit[0]["train_s"]) if hit else None
  if out["brax.sac"] and out["mjxvine.sac"]:
    out["wall_clock_ratio"] = out["brax.sac"]["train_s"] / max(out["mjxvine.sac"]["train_s"], 1e-9)
    out["env_steps_ratio"] = out["brax.sac"]["env_steps"] / max(out["mjxvine.sac"]["env_steps"], 1)
  return out


# ------------------------------------------------------------------ deploy

def _deploy_args(p: argparse.ArgumentParser) -> None:
  p.add_argument("--calls", type=_positive_int, default=1000,
                 help="timed single-image calls per row")
  p.add_argument("--threads", default="1,2", type=_int_list,
                 help="comma-separated BLAS (numpy) / intra-op (onnxruntime) thread counts")
  p.add_argument("--seed", type=int, default=0, help="seed of the random actor weights")


def bench_deploy(args: argparse.Namespace, cfg: config_lib.Config) -> list[dict]:
  """Single-decision latency (median and p99 over `--calls` calls, one image of the
  config's size) of `NumpyPolicy` and onnxruntime on this CPU, per thread count, beside
  the paper's TF / TFLite figures. The actor has random weights of the config's sizes
  (the paper's: 104,100 parameters at 112x112). Each row runs `python -m
  mjxvine.latency` in a fresh process, so that OPENBLAS_NUM_THREADS takes effect;
  load_1m is the host's load when the row started (the machine may be shared)."""
  import subprocess  # pylint: disable=import-outside-toplevel
  import tempfile  # pylint: disable=import-outside-toplevel
  from pathlib import Path  # pylint: disable=import-outside-toplevel
  from mjxvine import deploy, export, networks  # pylint: disable=import-outside-toplevel
  h, w = cfg.camera.height, cfg.camera.width
  nets = networks.make_networks_from_config(cfg)
  obs = {"depth": jp.zeros((1, h, w, 1)), "state": jp.zeros((1, 3))}
  params, _ = networks.init_params(nets, jax.random.PRNGKey(args.seed), obs)
  common = dict(image=f"{h}x{w}", actor_params=networks.num_params(params))
  root = str(Path(__file__).resolve().parents[1])

  def latency(path, threads, *flags):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]))
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
      env[var] = str(threads)
    cmd = [sys.executable, "-m", "mjxvine.latency", str(path), "--calls", str(args.calls),
           *flags]
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    if out.returncode != 0:
      raise RuntimeError(f"{' '.join(cmd)} failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])

  rows = []
  with tempfile.TemporaryDirectory() as tmp:
    npz = export.export_actor(params, Path(tmp) / "policy.npz", export.meta_from_config(cfg))
    threads = [int(t) for t in args.threads.split(",")]
    for n in threads:
      rows.append(dict(impl="NumpyPolicy", threads=n, **common, **latency(npz, n)))
    try:
      import onnxruntime as ort  # pylint: disable=import-outside-toplevel
      onnx_path = export.export_onnx(npz, Path(tmp) / "policy.onnx")
    except ImportError as e:
      rows.append(dict(impl="onnxruntime", **common, note=f"not available ({e}); "
                       "pip install mjxvine[onnx]"))
    else:
      # Agreement of the two on a few random images (max |action difference|).
      rng = np.random.default_rng(args.seed)
      depth = rng.uniform(0.0, cfg.camera.max_depth_m, (4, h, w, 1)).astype(np.float32)
      state = rng.uniform(-1.0, 1.0, (4, 3)).astype(np.float32)
      sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
      diff = float(np.abs(sess.run(["action"], {"depth": depth, "state": state})[0] -
                          deploy.NumpyPolicy.load(npz).action(depth, state)).max())
      version = metadata.version("onnxruntime")
      for n in threads:
        for spin in ([True, False] if n > 1 else [True]):
          flags = ["--threads", str(n)] + ([] if spin else ["--no-spinning"])
          rows.append(dict(impl=f"onnxruntime {version}", threads=n, spinning=spin, **common,
                           **latency(onnx_path, 1, *flags), max_abs_diff_vs_numpy=diff))
  # Actor inference per decision on the paper's robot CPUs (docs/design.md, Evaluation
  # protocol), ms.
  paper = {"TF (paper, robot CPU)": (2.8, 6.2), "TFLite (paper, robot CPU)": (0.63, 1.96)}
  for name, (low, high) in paper.items():
    rows.append(dict(impl=name, image="112x112", paper_low_ms=low, paper_high_ms=high))
  return rows


# ------------------------------------------------------------------ CLI

# name -> (run(args, cfg) -> rows, add_arguments(parser), one-line help)
COMMANDS: dict[str, tuple[Callable[[argparse.Namespace, Any], list[dict]],
                          Callable[[argparse.ArgumentParser], None], str]] = {
    "depth": (bench_depth, _depth_args, "depth camera images/s vs batch and size"),
    "physics": (bench_physics, _env_args, "MJX physics env-steps/s vs number of envs"),
    "env": (bench_env, _env_args, "whole env step (physics + depth + reward) env-steps/s"),
    "deploy": (bench_deploy, _deploy_args, "single-decision latency: NumpyPolicy, onnxruntime"),
    "update": (bench_update, _update_args, "SAC gradient steps/s vs batch size"),
    "train": (bench_train, _train_args, "end-to-end training env-steps/s and grad-steps/s"),
    "brax": (bench_brax, _brax_args, "brax's SAC vs mjxvine's SAC on the same task"),
}
EXPERIMENTS = Path(__file__).resolve().parent.parent / "experiments"


def main(argv: list[str] | None = None) -> int:
  parser = argparse.ArgumentParser(prog="python -m mjxvine.bench", description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
  sub = parser.add_subparsers(dest="command", required=True)
  for name, (_, add_args, doc) in COMMANDS.items():
    p = sub.add_parser(name, help=doc)
    p.add_argument("--out", default=f"bench-{name}.json",
                   help="write the results to this JSON file ('' for none)")
    config_lib.add_config_args(p)
    add_args(p)
  p = sub.add_parser("all", help="every sub-command with its defaults; one bench.json")
  p.add_argument("--out", default="bench.json", help="the combined JSON file")
  p.add_argument("--quick", action="store_true",
                 help="small sizes (a CPU smoke run: 4 envs, 40x40 images, batch 32)")
  args = parser.parse_args(argv)
  if args.command == "all":
    return run_all(args.out, args.quick)
  cfg = config_lib.config_from_args(args)
  run, _, _ = COMMANDS[args.command]
  rows, extra = _rows_and_extra(run(args, cfg))
  write_results(args.command, rows, args.out or None, config_hash=config_lib.config_hash(cfg),
                **extra)
  return 0


def _rows_and_extra(result) -> tuple[list[dict], dict]:
  """A sub-command returns its rows, or (rows, extra fields for the JSON)."""
  return result if isinstance(result, tuple) else (result, {})


def run_all(out: str, quick: bool = False) -> int:
  """Runs every sub-command with its default arguments (`quick`: small sizes) and writes
  one JSON: {"environment": ..., "<command>": {"rows": [...], ...}}."""
  # Quick: one small size each, 40x40 images (as experiments/default.yaml; the conv tower
  # needs 33x33) and two pool worlds. On a CPU the time goes mostly to XLA compilation.
  small = ["--set", "camera.width=40", "--set", "camera.height=40", "--set", "world.pool_size=2"]
  quick_args = {
      "depth": ["--batches", "1,4", "--sizes", "40x40", "--baseline-batch", "1",
                "--min-time", "0.2"],
      "physics": ["--sizes", "4", "--steps", "2", *small],
      "env": ["--sizes", "4", "--steps", "2", *small],
      "deploy": ["--calls", "100", "--threads", "1", *small],
      "update": ["--batch-sizes", "32", "--rounds", "1", *small],
      "train": ["--sizes", "4", "--iters", "2", *small, "--set", "sac.batch_size=16",
                "--set", "sac.buffer_size=1024", "--set", "sac.grad_steps_per_iter=1"],
      "brax": ["--steps", "2000", "--evals", "1", "--eval-envs", "16"],
  }
  doc = {"environment": environment()}
  for name, (run, add_args, _) in COMMANDS.items():
    p = argparse.ArgumentParser()
    config_lib.add_config_args(p)
    add_args(p)
    args = p.parse_args(quick_args.get(name, []) if quick else [])
    cfg = config_lib.config_from_args(args)
    rows, extra = _rows_and_extra(run(args, cfg))
    doc[name] = write_results(name, rows, None, config_hash=config_lib.config_hash(cfg),
                              **extra)
  if out:
    Path(out).write_text(json.dumps(doc, indent=1, default=_json_default))
  return 0


if __name__ == "__main__":
  sys.exit(main())
