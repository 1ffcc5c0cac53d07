"""`bench update`: SAC gradient steps/s (and samples/s) per batch size at the config's
image size and networks, the achieved GFLOP/s (XLA's cost-analysis flops / seconds), this
machine's matmul GFLOP/s (2048x2048 float32) and their ratio; `--compare` adds the
program under XLA's default options."""

from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jp
import numpy as np

from mjxvine import config as config_lib
from mjxvine.bench.common import (cost_analysis, int_list, per, positive_int,
                                  time_call, time_compiled)


def matmul_gflops(n: int = 2048, min_time: float = 1.0) -> float:
  """The machine's matrix-multiply rate, GFLOP/s: a jitted n x n float32 matmul (2 n^3
  flops), median of calls over `min_time` seconds. The yardstick of `bench update`."""
  a = jax.random.normal(jax.random.PRNGKey(0), (n, n), jp.float32)
  t = time_call(jax.jit(lambda x: x @ x), a, min_time=min_time)
  return 2.0 * n ** 3 / t["call_s"] / 1e9


def add_update_args(p: argparse.ArgumentParser) -> None:
  p.add_argument("--batch-sizes", default="128,512", type=int_list,
                 help="comma-separated SAC batch sizes")
  p.add_argument("--grad-steps", type=positive_int, default=None,
                 help="gradient steps per timed call (default sac.grad_steps_per_iter)")
  p.add_argument("--conv-impl", default=None, choices=("xla", "shift", "native"),
                 help="the conv tower's convolutions (mjxvine.tower.CONV_IMPLS; "
                      "default: the trainer's, train.conv_impl)")
  p.add_argument("--compare", action="store_true",
                 help="also time the program compiled with XLA's default options (on a "
                      "CPU: with YNNPACK's convolutions)")
  p.add_argument("--rounds", type=positive_int, default=3,
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
  compiled with `networks.learner_compiler_options()`, as the trainer compiles it ("options"
  column). With the native tower the flops are G times those of one step with XLA's
  convolutions (XLA's cost analysis does not count an FFI call's, nor a loop's trips)."""
  from mjxvine import networks as nw  # pylint: disable=import-outside-toplevel
  from mjxvine import sac as sac_lib  # pylint: disable=import-outside-toplevel
  from mjxvine.env import VineyardEnv  # pylint: disable=import-outside-toplevel
  from mjxvine.training.iteration import scan_chunks  # pylint: disable=import-outside-toplevel
  rows = []
  g = args.grad_steps or cfg.sac.grad_steps_per_iter
  host = not scan_chunks()
  tuned = nw.learner_compiler_options()
  variants = [("learner", tuned)] + ([("xla default", None)] if args.compare and tuned else [])
  conv_impl = args.conv_impl or nw.learner_conv_impl(cfg.train.conv_impl)
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
      flops = per(cost["flops"], per_call)  # per gradient step
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
                       bytes_per_grad_step=per(cost["bytes_accessed"], per_call),
                       gflops=None if flops is None else flops / step_s / 1e9,
                       matmul_gflops=float(np.median([r[1] for r in rounds])),
                       ratio=float(np.median(ratios)) if ratios else None,
                       ratio_range=(f"{min(ratios):.3f}-{max(ratios):.3f}" if ratios
                                    else None),
                       load_1m=os.getloadavg()[0] if hasattr(os, "getloadavg") else None))
  return rows
