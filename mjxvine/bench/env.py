"""`bench env`: env-steps/s of the whole env step (physics, depth image and noise,
reward, terminations, auto-reset) at the config's image size, per env count, with CPU ms
and XLA's flops and bytes per env step."""

from __future__ import annotations

import argparse

import jax

from mjxvine import config as config_lib
from mjxvine.bench.common import add_env_count_args, env_counts, env_setup, per, time_call


def add_env_args(p: argparse.ArgumentParser) -> None:
  add_env_count_args(p)  # --no-baseline too (physics' flag; no effect here)


def bench_env(args: argparse.Namespace, cfg: config_lib.Config) -> list[dict]:
  """Env-steps/s of the whole env step (physics, depth image and noise, reward,
  terminations, auto-reset) at the config's image size."""
  rows = []
  for n in env_counts(args):
    env, state, action = env_setup(cfg, n)

    def run(s, a):
      return jax.lax.fori_loop(0, args.steps, lambda _, x: env.step_batch(x, a)[0], s)

    t = time_call(jax.jit(run), state, action)
    rows.append(dict(envs=n, image=f"{cfg.camera.height}x{cfg.camera.width}",
                     env_steps_per_s=n * args.steps / t["call_s"], compile_s=t["compile_s"],
                     cpu_ms_per_env_step=1e3 * t["cpu_s"] / (n * args.steps),
                     flops_per_env_step=per(t["flops"], n * args.steps),
                     bytes_per_env_step=per(t["bytes_accessed"], n * args.steps)))
  return rows
