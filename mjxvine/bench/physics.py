"""`bench physics`: env-steps/s of the batched MJX physics alone (0.1 s control steps),
per env count, and the ratio against a Python loop over envs calling the C library's
`mujoco.mj_step` (one thread)."""

from __future__ import annotations

import argparse
import time

import jax
import mujoco
import numpy as np

from mjxvine import config as config_lib
from mjxvine.bench.common import add_env_count_args, env_counts, env_setup, time_call


def add_physics_args(p: argparse.ArgumentParser) -> None:
  add_env_count_args(p)


def bench_physics(args: argparse.Namespace, cfg: config_lib.Config) -> list[dict]:
  """Env-steps/s of the batched MJX physics alone: `VineyardEnv.physics` per control step
  (the wheel commands, then control_dt / `config.PHYSICS_DT_S` `mjx.step`s), each env in its own
  pool world."""
  rows = []
  for n in env_counts(args):
    env, state, action = env_setup(cfg, n)

    def one(d, world, a):
      return env.physics(env.physics_model(world), d, a)

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
  the C library's `mujoco.mj_step` control_dt / `config.PHYSICS_DT_S` times per control step (one
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
