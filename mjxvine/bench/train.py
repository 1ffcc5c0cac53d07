"""`bench train`: end-to-end `mjxvine.train` throughput while learning (default
`experiments/fast.yaml`): env-steps/s and gradient-steps/s of whole learning chunks, per
env count, compile seconds apart."""

from __future__ import annotations

import argparse
import math
import time

import jax
import numpy as np

from mjxvine import config as config_lib
from mjxvine.bench.common import EXPERIMENTS, int_list, positive_int


def add_train_args(p: argparse.ArgumentParser) -> None:
  p.add_argument("--sizes", default=None, type=int_list,
                 help="comma-separated env counts (default 256,1024,4096,16384 on an "
                      "accelerator, 16,64 on a CPU)")
  p.add_argument("--iters", type=positive_int, default=None,
                 help="iterations per timed chunk (default train.iters_per_chunk)")
  p.set_defaults(config=str(EXPERIMENTS / "fast.yaml"))


def bench_train(args: argparse.Namespace, cfg: config_lib.Config) -> list[dict]:
  """End-to-end training throughput of `mjxvine.train` (default `experiments/fast.yaml`):
  env-steps/s and gradient-steps/s of whole learning chunks (env steps with exploration,
  replay inserts, gradient steps), after a first chunk that compiles and fills the replay
  beyond one batch. Compile time is the first chunk's excess over a steady one."""
  from mjxvine.training import programs  # pylint: disable=import-outside-toplevel
  rows = []
  if args.sizes:
    sizes = [int(x) for x in args.sizes.split(",")]
  else:
    sizes = [16, 64] if jax.default_backend() == "cpu" else [256, 1024, 4096, 16384]
  for n in sizes:
    iters = args.iters or cfg.train.iters_per_chunk
    c = config_lib.replace(cfg, env={"num_envs": n}, sac={"warmup_steps": 0},
                           train={"iters_per_chunk": iters})
    _, init_fn, chunk_fn = programs.compiled_trainer(c)
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
