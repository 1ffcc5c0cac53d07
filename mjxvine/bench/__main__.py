"""`python -m mjxvine.bench <sub-command>`: the command line of the benchmarks (see the
package docstring): parses, runs the sub-command, prints and writes its rows."""

from __future__ import annotations

import argparse
import json
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


def main(argv: list[str] | None = None) -> int:
  parser = argparse.ArgumentParser(prog="python -m mjxvine.bench",
                                   description=mjxvine.bench.__doc__,
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
  if args.out:  # before the benchmark runs, not after
    try:
      check_output(args.out, "--out")
    except OutputError as e:
      print(f"error: {e}", file=sys.stderr)
      return 2
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
    p = argparse.ArgumentParser()
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
  sys.exit(main())
