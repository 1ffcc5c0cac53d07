"""`bench env`: env-steps/s of the whole env step (physics, depth image and noise,
reward, terminations, auto-reset) at the config's image size, per env count, with CPU ms
and XLA's flops and bytes per env step.

`--against CONFIG` times instead the env step of `--config` and of the YAML file CONFIG
in turn, and reports the first's time over CONFIG's (`ratio`, the median over rounds): what
a config's factors cost against another's (e.g. experiments/realism.yaml against
experiments/jackal.yaml).

`--block ROWSxLENGTH` (e.g. 12x200) times instead the same env step on two worlds, the
24 m test world and a generated block of ROWS plant rows of LENGTH m (the config's world
settings otherwise, as train world 0), all envs in the one world,
the two compiled programs called in turn, and reports the block's time over the test
world's (`ratio`, the median over rounds): how the step's cost follows the world's size.
"""

from __future__ import annotations

import argparse
import dataclasses

import jax

from mjxvine import config as config_lib
from mjxvine.bench.common import (add_env_count_args, compile_call, env_counts, env_setup,
                                  per, positive_int, time_alternating, time_call)
from mjxvine.cli import int_range


MAX_BLOCK_ROWS = 100  # a large vineyard block (world.train_rows stops at 12: train worlds)


def block_size(text: str) -> tuple[int, float]:
  """ROWSxLENGTH ("12x200"): plant rows, 2 to `MAX_BLOCK_ROWS`, and row length (m) in
  world.train_length_m's range."""
  parts = text.lower().split("x")
  if len(parts) != 2:
    raise argparse.ArgumentTypeError(f"{text!r}: expected ROWSxLENGTH, e.g. 12x200")
  try:
    rows = int_range(2, MAX_BLOCK_ROWS)(parts[0])
  except argparse.ArgumentTypeError as e:
    raise argparse.ArgumentTypeError(f"ROWS {e}") from None
  try:
    return rows, config_lib.check_value("world.train_length_m", parts[1])
  except config_lib.ConfigError as e:
    raise argparse.ArgumentTypeError(str(e)) from None


def add_env_args(p: argparse.ArgumentParser) -> None:
  add_env_count_args(p)  # --no-baseline too (physics' flag; no effect here)
  what = p.add_mutually_exclusive_group()  # each times two programs in turn
  what.add_argument("--block", type=block_size, default=None, metavar="ROWSxLENGTH",
                    help="time the env step on a generated block of ROWS plant rows x "
                         "LENGTH m (e.g. 12x200; rows 2-100, length 4-300 m) beside the 24 m "
                         "test world, in turn, and report the ratio (default --sizes: "
                         "env.num_envs)")
  what.add_argument("--against", type=config_file, default=None, metavar="CONFIG",
                    help="time the env step of CONFIG (a YAML file) in turn with --config's "
                         "and report --config's time over CONFIG's (default --sizes: "
                         "env.num_envs)")
  p.add_argument("--rounds", type=positive_int, default=10,
                 help="with --block or --against: timed calls of each program, in turn")


def config_file(path: str) -> config_lib.Config:
  """The config of the YAML file `path`; a missing or invalid file is a usage error."""
  try:
    return config_lib.load_config(path)
  except config_lib.ConfigError as e:
    raise argparse.ArgumentTypeError(f"expected a valid config file: {e}") from None


def bench_env(args: argparse.Namespace, cfg: config_lib.Config) -> list[dict]:
  """Env-steps/s of the whole env step (physics, depth image and noise, reward,
  terminations, auto-reset) at the config's image size."""
  if args.block:
    return bench_block(args, cfg)
  if args.against:
    return bench_against(args, cfg)
  rows = []
  for n in env_counts(args):
    env, state, action = env_setup(cfg, n)
    t = time_call(jax.jit(_steps(env, args.steps)), state, action)
    rows.append(dict(envs=n, image=f"{cfg.camera.height}x{cfg.camera.width}",
                     env_steps_per_s=n * args.steps / t["call_s"], compile_s=t["compile_s"],
                     cpu_ms_per_env_step=1e3 * t["cpu_s"] / (n * args.steps),
                     flops_per_env_step=per(t["flops"], n * args.steps),
                     bytes_per_env_step=per(t["bytes_accessed"], n * args.steps)))
  return rows


def _steps(env, steps: int):
  """`steps` env steps of the batch with one action: (state, action) -> state."""
  def run(s, a):
    return jax.lax.fori_loop(0, steps, lambda _, x: env.step_batch(x, a)[0], s)
  return run


def block_worlds(cfg: config_lib.Config, rows: int, length_m: float) -> list:
  """[the 24 m test world, a block of `rows` plant rows of `length_m` m] of `cfg`."""
  from mjxvine.worlds import generate_world, load_test_world  # (they read robot files)
  w = cfg.world
  block = dataclasses.replace(w, train_rows=rows, train_length_m=length_m,
                              train_wide_gap_rows=min(w.train_wide_gap_rows, rows))
  return [load_test_world(w), generate_world("train", 0, block)]


def bench_block(args: argparse.Namespace, cfg: config_lib.Config) -> tuple[list[dict], dict]:
  """The env step on the test world and on a block (`--block`), per env count: rows of
  both, the block's with its time and XLA flops over the test world's."""
  rows, ratios = [], {}
  worlds = block_worlds(cfg, *args.block)
  names = [f"test {len(worlds[0].lanes) + 1}x{worlds[0].length_m:g}",
           f"block {args.block[0]}x{args.block[1]:g}"]
  for n in _paired_counts(args, cfg):
    timed = _in_turn(args, n, [(cfg, [world]) for world in worlds])
    for name, world, row in zip(names, worlds, timed):
      rows.append(dict(envs=n, world=name, plants=len(world.plant_xy), **row))
    ratios[str(n)] = rows[-1]["ratio"]
  return rows, {"block": f"{args.block[0]}x{args.block[1]:g}", "block_ratio": ratios}


def bench_against(args: argparse.Namespace, cfg: config_lib.Config
                  ) -> tuple[list[dict], dict]:
  """The env step of `--against`'s config and of `cfg`, per env count, in turn: rows of
  both (the config's hash names each), `cfg`'s with its time and XLA flops over the
  other's."""
  rows, ratios = [], {}
  configs = [args.against, cfg]
  for n in _paired_counts(args, cfg):
    for c, row in zip(configs, _in_turn(args, n, [(c, None) for c in configs])):
      rows.append(dict(envs=n, config=config_lib.config_hash(c), **row))
    ratios[str(n)] = rows[-1]["ratio"]
  return rows, {"against": config_lib.config_hash(args.against), "ratio": ratios}


def _paired_counts(args: argparse.Namespace, cfg: config_lib.Config) -> list[int]:
  """The env counts of a comparison in turn (`--block`, `--against`): `--sizes`, else the
  config's env.num_envs alone (each count compiles two programs)."""
  return env_counts(args) if args.sizes else [cfg.env.num_envs]


def _in_turn(args: argparse.Namespace, n: int, setups: list) -> list[dict]:
  """The env step of each (config, worlds or None: its pool) of `setups` for `n` envs,
  compiled, then timed in turn (`time_alternating`, `--rounds`): a row each, its `ratio`
  and `flops_ratio` over the first's."""
  calls, infos, images = [], [], []
  for c, worlds in setups:
    env, state, action = env_setup(c, n, worlds)
    fn, info = compile_call(jax.jit(_steps(env, args.steps)), state, action)
    calls.append((fn, (state, action)))
    infos.append(info)
    images.append(f"{c.camera.height}x{c.camera.width}")
  count = n * args.steps
  return [dict(image=image, env_steps_per_s=count / t["call_s"], compile_s=info["compile_s"],
               cpu_ms_per_env_step=1e3 * t["cpu_s"] / count,
               flops_per_env_step=per(info["flops"], count),
               bytes_per_env_step=per(info["bytes_accessed"], count), ratio=t["ratio"],
               flops_ratio=per(info["flops"], infos[0]["flops"] or None))
          for image, info, t in zip(images, infos, time_alternating(calls, args.rounds))]
