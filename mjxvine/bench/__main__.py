"""`python -m mjxvine.bench <sub-command>`: the command line of the benchmarks (see the
package docstring): parses, runs the sub-command, prints and writes its rows."""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any, Callable

import mjxvine.bench
from mjxvine import config as config_lib
from mjxvine import atomic
from mjxvine.atomic import OutputError, check_output
from mjxvine.bench.brax_envs import add_brax_args, bench_brax
from mjxvine.bench.common import environment, json_default, write_results
from mjxvine.bench.deploy import add_deploy_args, bench_deploy
from mjxvine.bench.depth import add_depth_args, bench_depth
from mjxvine.bench.env import add_env_args, bench_env
from mjxvine.bench.physics import add_physics_args, bench_physics
from mjxvine.bench.train import add_train_args, bench_train
from mjxvine.bench.update import add_update_args, bench_update
from mjxvine.cli import CommandParser

# name -> (run(args, cfg) -> rows, add_arguments(parser), one-line help)
COMMANDS: dict[str, tuple[Callable[[argparse.Namespace, Any], list[dict]],
                          Callable[[argparse.ArgumentParser], None], str]] = {
    "depth": (bench_depth, add_depth_args, "depth camera images/s vs batch and size"),
    "physics": (bench_physics, add_physics_args, "MJX physics env-steps/s vs number of envs"),
    "env": (bench_env, add_env_args, "whole env step (physics + depth + reward) env-steps/s"),
    "deploy": (bench_deploy, add_deploy_args,
               "single-decision latency: NumpyPolicy, onnxruntime"),
    "update": (bench_update, add_update_args, "SAC gradient steps/s vs batch size"),
    "train": (bench_train, add_train_args, "end-to-end training env-steps/s and grad-steps/s"),
    "brax": (bench_brax, add_brax_args, "brax's SAC vs mjxvine's SAC on the same task"),
}

# `all --quick`: one small size each, 40x40 images (as experiments/default.yaml; the conv
# tower needs 33x33) and two pool worlds. On a CPU the time goes mostly to XLA compilation.
_SMALL = ["--set", "camera.width=40", "--set", "camera.height=40", "--set",
          "world.pool_size=2"]
QUICK_ARGS = {
    "depth": ["--batches", "1,4", "--sizes", "40x40", "--baseline-batch", "1",
              "--min-time", "0.2"],
    "physics": ["--sizes", "4", "--steps", "2", *_SMALL],
    "env": ["--sizes", "4", "--steps", "2", *_SMALL],
    "deploy": ["--calls", "100", "--threads", "1", *_SMALL],
    "update": ["--batch-sizes", "32", "--rounds", "1", *_SMALL],
    "train": ["--sizes", "4", "--iters", "2", *_SMALL, "--set", "sac.batch_size=16",
              "--set", "sac.buffer_size=1024", "--set", "sac.grad_steps_per_iter=1"],
    "brax": ["--steps", "2000", "--evals", "1", "--eval-envs", "16"],
}


# Rough wall-clock minutes of each sub-command on a 2-core x86-64 CPU (the machine of
# docs/results/cpu-2core.md): (with its defaults, at `QUICK_ARGS`). Estimates, not
# measurements of these exact runs: compile seconds and rates of the bench-*-cpu-2core.json
# records times the default sizes; `train` is fast.yaml's 64 gradient steps of batch 512 at
# 112x112 per iteration, about 2.6 s each (cpu-update-speed.md), for 4-5 chunks of 20
# iterations at each of 16 and 64 envs; `brax` is the 336 s of compare.yaml's two learners.
CPU_MINUTES = {"depth": (2, 0.5), "physics": (2, 0.5), "env": (5, 1), "deploy": (1, 0.5),
               "update": (3, 1), "train": (420, 2), "brax": (6, 4)}


def _duration(minutes: float) -> str:
  """"about 40 minutes", "about 7 hours"."""
  if minutes < 1:
    return "under a minute"
  if minutes < 90:
    return f"about {minutes:.0f} minute{'s' if round(minutes) != 1 else ''}"
  return f"about {minutes / 60:.0f} hours"


def plan_line(command: str, quick: bool = False) -> str | None:
  """What `bench <command>` is about to run and its rough cost on this backend, in one line;
  None for a sub-command off the CPU (no estimates there)."""
  import jax  # pylint: disable=import-outside-toplevel
  backend = jax.default_backend()
  cores = "a 2-core CPU" + ("" if os.cpu_count() == 2 else f" (this one has {os.cpu_count()})")
  full = sum(m for m, _ in CPU_MINUTES.values())
  fast = sum(q for _, q in CPU_MINUTES.values())
  if command == "all":
    what = f"bench all{' --quick' if quick else ''} on {backend}: {len(COMMANDS)} " \
           f"benchmarks ({', '.join(COMMANDS)})"
    if backend != "cpu":
      return f"{what}; no time estimate for this backend (the estimates are a CPU's)"
    if quick:
      return f"{what} at small sizes, {_duration(fast)} on {cores} (an estimate)"
    return (f"{what}, {_duration(full)} on {cores}, nearly all of it bench train "
            f"(fast.yaml's updates); --quick: {_duration(fast)} (estimates)")
  if backend != "cpu":
    return None
  minutes, small = CPU_MINUTES[command]
  return (f"bench {command} on cpu: {_duration(minutes)} with its default sizes on {cores}; "
          f"at bench all --quick's sizes {_duration(small)} (estimates)")


def parser() -> argparse.ArgumentParser:
  """The command line: one sub-command per benchmark, and `all`."""
  p = CommandParser(prog="python -m mjxvine.bench", description=mjxvine.bench.__doc__)
  sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND",
                         help="the benchmark to run (each has its own --help)")
  for name, (_, add_args, doc) in COMMANDS.items():
    s = sub.add_parser(name, help=doc, description=doc)
    s.add_argument("--out", default=f"bench-{name}.json", metavar="FILE",
                   help=f"write the results to this JSON file (default bench-{name}.json; "
                        "'' for none)")
    config_lib.add_config_args(s)
    add_args(s)
  s = sub.add_parser("all", help="every sub-command with its defaults; one bench.json",
                     description="every sub-command with its defaults; one bench.json")
  s.add_argument("--out", default="bench.json", metavar="FILE",
                 help="the combined JSON file (default bench.json; '' for none)")
  s.add_argument("--quick", action="store_true",
                 help="small sizes (a CPU smoke run: 4 envs, 40x40 images, batch 32)")
  return p


def main(argv: list[str] | None = None) -> int:
  args = parser().parse_args(argv)
  if args.out:  # before the benchmark runs, not after
    try:
      check_output(args.out, "--out")
    except OutputError as e:
      print(f"error: {e}", file=sys.stderr)
      return 2
  line = plan_line(args.command, getattr(args, "quick", False))
  if line:
    print(line, file=sys.stderr, flush=True)
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
  """Runs every sub-command with its default arguments (`quick`: `QUICK_ARGS`, small
  sizes) and writes one JSON: {"environment": ..., "<command>": {"rows": [...], ...}}."""
  doc = {"environment": environment()}
  for name, (run, add_args, _) in COMMANDS.items():
    p = CommandParser()
    config_lib.add_config_args(p)
    add_args(p)
    args = p.parse_args(QUICK_ARGS.get(name, []) if quick else [])
    cfg = config_lib.config_from_args(args)
    rows, extra = _rows_and_extra(run(args, cfg))
    doc[name] = write_results(name, rows, None, config_hash=config_lib.config_hash(cfg),
                              **extra)
  if out:
    atomic.write_text(out, json.dumps(doc, indent=1, default=json_default))
  return 0


if __name__ == "__main__":
  from mjxvine.atomic import command_main
  # SIGINT / SIGTERM: 130 / 143 in one line, the outputs of the unfinished set removed
  command_main(main)
