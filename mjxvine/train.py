"""`python -m mjxvine.train`: SAC on the batched vineyard env, on one or many devices.

  python -m mjxvine.train --config experiments/smoke.yaml --out runs/smoke
  python -m mjxvine.train --resume runs/smoke --set train.total_env_steps=20000
  python -m mjxvine.train                       # the default run (experiments/default.yaml)
  python -m mjxvine.train --config experiments/default.yaml --seed 1 --out runs/seed1
  python -m mjxvine.train --config experiments/default.yaml --num-seeds 3 \\
      --sweep sac.learning_rate=2e-4,1e-3
  python -m mjxvine.train --config experiments/adapt.yaml --init models/jackal.npz \\
      --robot examples/my_robot.yaml --set world.train_files=examples/vineyard-block.geojson

The command line of `mjxvine.training.loop.train`: it resolves the config (a new run's,
or a resumed run's own with the keys that may change), checks the run directory, trains,
and maps each failure to one line and an exit code (`mjxvine.rundir`). `--num-seeds K`
and `--sweep` train several members at once (vmap); `--distributed` trains over the devices
of several processes (`jax.distributed`).
"""

from __future__ import annotations

import argparse
import datetime
import errno
import functools
import json
import os
import sys
from pathlib import Path

import jax

from mjxvine.atomic import OutputError, check_output, command_main
from mjxvine.config import (DEFAULT_CONFIG_NAME, PACKAGED_CONFIGS, Config, ConfigError,
                            add_config_args, config_from_args, enable_compile_cache,
                            load_run_config, resolve_config_path)
from mjxvine.cli import CommandParser, key_type
from mjxvine.formatting import first_line
from mjxvine.rundir import (EXIT_NON_FINITE, EXIT_USAGE, EXIT_WRITE, Interrupted,
                            ResumeRefused, RunDirBusy, WriteError, busy_message, exit_code,
                            lock_holder, write_failure)
from mjxvine.training.iteration import NonFiniteError
from mjxvine.training.loop import check_memory, train

# With no --config: the documented default run, shipped inside the package (a copy of
# experiments/default.yaml), so that it is found however mjxvine was installed.
DEFAULT_CONFIG = PACKAGED_CONFIGS / DEFAULT_CONFIG_NAME
# What a failed write of the run files (logs, config.yaml) reports in one line (exit 4).
_WRITE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EIO,
                 errno.EACCES)


def parser() -> argparse.ArgumentParser:
  p = CommandParser(prog="python -m mjxvine.train", description=__doc__)
  add_config_args(p, default=None)
  p.add_argument("--out", default=None, metavar="RUN_DIR",
                 help="the new run's directory (default runs/<time>); it must not hold a "
                 "run yet (continue one with --resume)")
  p.add_argument("--resume", default=None, metavar="RUN_DIR",
                 help="continue an interrupted run from its newest intact checkpoint (else "
                 "its best); --set may change its budget and what runs around the "
                 "training (train.total_env_steps, evaluations, the choice, eval.*), "
                 "never networks, images, replay or envs")
  p.add_argument("--restart", action="store_true",
                 help="with --resume: when no checkpoint of the run can be restored, start "
                 "it afresh in its directory (its old outputs set aside in previous-<time>/)")
  p.add_argument("--seed", type=key_type("train.seed"), default=None, metavar="N",
                 help="the seed of the run's randomness (network weights, exploration, "
                 "starts, depth noise; the train worlds have seeds 0 on); sets train.seed, "
                 "as --set train.seed=N does")
  p.add_argument("--init", type=key_type("train.init_from"), default=None, metavar="FILE",
                 help="start from a trained agent: a policy file with its agent file beside "
                 "it (models/jackal.npz: models/jackal.sac.npz) or the agent file; sets "
                 "train.init_from (docs/adapt.md)")
  p.add_argument("--robot", type=key_type("robot.name"), default=None,
                 metavar="NAME|FILE.yaml", help="the robot to train: jackal, husky or a robot "
                 "file (docs/your-robot.md); sets robot.name")
  p.add_argument("--num-seeds", type=key_type("train.num_seeds"), default=None,
                 metavar="K", help="train K members at once (vmap), 1-1024, their keys split "
                 "from train.seed's; sets train.num_seeds")
  p.add_argument("--sweep", action="append", default=[], metavar="SECTION.KEY=V1,V2",
                 help="also sweep a hyper-parameter at once (vmap); sets train.sweep. "
                 "Repeatable: values of one key add up (--sweep K=a --sweep K=b is "
                 "K=a,b), different keys make a grid (every combination, times the seeds; "
                 "at most 1024 members)")
  p.add_argument("--no-eval", action="store_true", help="skip the final evaluation")
  dist = p.add_argument_group(
      "several processes or hosts (jax.distributed)",
      "Start the same command once per process. Each flag falls back on its environment "
      "variable, and without either JAX detects SLURM, Open MPI or Kubernetes.")
  dist.add_argument("--distributed", action="store_true",
                    help="call jax.distributed.initialize() and train over the devices of "
                    "every process")
  dist.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                    help="process 0's address (default $JAX_COORDINATOR_ADDRESS)")
  dist.add_argument("--num-processes", type=int, default=None, metavar="P",
                    help="number of processes (default $JAX_NUM_PROCESSES)")
  dist.add_argument("--process-id", type=int, default=None, metavar="I",
                    help="this process's id, 0..P-1 (default $JAX_PROCESS_ID)")
  return p


def resumed_config(p: argparse.ArgumentParser, args) -> tuple[Config, Path]:
  """The config of the run in --resume: its config.yaml with the --set overrides (only
  the keys in `rundir.RESUME_FREE` may change: `train` refuses others)."""
  run_dir = Path(args.resume)
  resolved = run_dir / "config.yaml"
  if not run_dir.is_dir():
    p.error(f"--resume {run_dir}: no such run directory")
  if not resolved.is_file():
    p.error(f"--resume {run_dir}: no config.yaml there (not a run directory)")
  # the same run or a refusal (exit 2): `train` compares it with the config it started
  # with (run.json) before anything is built
  try:
    cfg = load_run_config(resolved, args.overrides)
  except ConfigError as e:
    p.exit(2, f"config error: {e}\n")
  if (args.seed is not None or args.num_seeds is not None or args.sweep or args.init
      or args.robot):
    p.error("--resume: the seed, seeds, sweep, --init and --robot come from the run's "
            "config.yaml")
  if args.out:
    p.error(f"--resume {run_dir} continues the run in its own directory: give no --out")
  check_train_files(p, cfg)
  check_fits(cfg)
  return cfg, run_dir


def new_config(p: argparse.ArgumentParser, args) -> tuple[Config, Path]:
  """The config of a new run (--config, or the default run's) with --seed, --num-seeds,
  --sweep and --set, and its run directory."""
  say = print if jax.process_index() == 0 else (lambda *a, **k: None)  # process 0 speaks
  if args.config is None:
    args.config = str(DEFAULT_CONFIG)
    say(f"config: {DEFAULT_CONFIG} (the default run, experiments/{DEFAULT_CONFIG_NAME}; "
        "--config picks another)", flush=True)
  else:
    say(f"config: {resolve_config_path(args.config)}", flush=True)
  extra = [f"train.seed={args.seed}"] if args.seed is not None else []
  if args.init is not None:
    extra.append(f"train.init_from={args.init}")
  if args.robot is not None:
    extra.append(f"robot.name={args.robot}")
  if args.num_seeds is not None:
    extra.append(f"train.num_seeds={args.num_seeds}")
  if args.sweep:  # `config.parse_sweep` adds up the values of a key given twice
    extra.append("train.sweep=" + "; ".join(args.sweep))
  cfg = config_from_args(args, extra)
  run_dir = Path(args.out or f"runs/{datetime.datetime.now():%Y%m%d-%H%M%S}")
  if run_dir.exists() and not run_dir.is_dir():
    p.error(f"--out {run_dir}: exists and is not a directory")
  if (run_dir / "checkpoints").exists():
    p.error(f"{run_dir} already holds a run: use --resume {run_dir} or another --out")
  check_train_files(p, cfg)  # before the run directory is made
  check_init(cfg)
  check_fits(cfg)
  try:  # before anything is compiled
    check_output(run_dir, "--out", directory=True)
  except OutputError as e:
    p.error(str(e))
  return cfg, run_dir


def run(cfg: Config, run_dir: Path, args) -> int:
  """Trains; each failure is one line on stderr (process 0) and its exit code."""
  primary = jax.process_index() == 0
  error = functools.partial(print, file=sys.stderr, flush=True) if primary else (
      lambda *a: None)
  try:
    row = train(cfg, run_dir, resume=bool(args.resume), evaluate_at_end=not args.no_eval,
                restart=args.restart)
  except (RunDirBusy, ResumeRefused) as e:
    error(f"error: {e}")
    return EXIT_USAGE
  except NonFiniteError as e:
    error(f"error: {e}")
    return EXIT_NON_FINITE
  except WriteError as e:
    error(f"error: {e}")
    return EXIT_WRITE
  except OSError as e:
    if e.errno not in _WRITE_ERRNOS:
      raise
    error(f"error: {write_failure(Path(e.filename or run_dir), 'the run files', e)}")
    return EXIT_WRITE
  except Interrupted as e:
    error(f"{e}; resume with: python -m mjxvine.train --resume {run_dir}"
          + (" --distributed" if args.distributed else ""))
    return exit_code(e.signum)
  if primary:
    print(json.dumps({k: row.get(k) for k in (
        "env_steps", "episodes", "return_mean", "success_rate", "sps",
        "best_eval_success_forward", "best_eval_success_reverse", "best_eval_mae_m",
        "eval_test_success", "eval_test_runs", "profile")}))
  return 0


def main(argv=None) -> int:
  """The CLI. Exit codes (`mjxvine.rundir`): 0 done, 2 a bad argument or config, a run
  directory in use or a resume refused, 3 a non-finite loss, 4 a failed write (disk full,
  ...), 130 / 143 stopped by SIGINT / SIGTERM (the last intact checkpoint kept)."""
  p = parser()
  args = p.parse_args(argv)
  enable_compile_cache()
  if args.distributed:
    _initialize_distributed(p, args)
  elif args.coordinator or args.num_processes is not None or args.process_id is not None:
    p.error("--coordinator, --num-processes and --process-id go with --distributed")
  if args.restart and not args.resume:
    p.error("--restart goes with --resume RUN_DIR")
  cfg, run_dir = resumed_config(p, args) if args.resume else new_config(p, args)
  # One process checks the lock here; with several, train() takes it in process 0 and every
  # process refuses together (process 0's own lock would stop the others here).
  if jax.process_count() == 1 and lock_holder(run_dir) is not None:
    print(f"error: {busy_message(run_dir)}", file=sys.stderr)
    return EXIT_USAGE
  return run(cfg, run_dir, args)


def check_fits(cfg: Config) -> None:
  """Refuses a run that would not fit in this machine's memory (`loop.check_memory`), in
  one line (exit 2), before the run directory is made or anything compiled."""
  try:
    check_memory(cfg)
  except ConfigError as e:
    print(f"config error: {e}", file=sys.stderr)
    raise SystemExit(2) from None


def check_init(cfg: Config) -> None:
  """Reads the agent of `train.init_from` and checks it against the config's networks
  before anything is made or compiled: one line (exit 2) when it is missing or does not
  fit (`training.warm_start.load_agent`)."""
  if not cfg.train.init_from:
    return
  from mjxvine.training.warm_start import load_agent, network_shapes
  try:
    load_agent(cfg.train.init_from, network_shapes(cfg))
  except ConfigError as e:
    print(f"config error: {e}", file=sys.stderr)
    raise SystemExit(2) from None


def check_train_files(p: argparse.ArgumentParser, cfg: Config) -> None:
  """Reads `world.train_files` once before anything is made or compiled: a missing or bad
  vineyard file is one line (`p.error`, exit 2)."""
  from mjxvine.worlds import world_of
  from mjxvine.worlds.store import train_files
  for path in train_files(cfg.world):
    try:
      world_of(path, cfg, flag="world.train_files")
    except (ValueError, FileNotFoundError) as e:  # WorldFileError is a ValueError
      p.error(str(e))


def _initialize_distributed(p: argparse.ArgumentParser, args) -> None:
  """`jax.distributed.initialize` from the flags, else $JAX_COORDINATOR_ADDRESS,
  $JAX_NUM_PROCESSES and $JAX_PROCESS_ID, else JAX's own cluster detection (SLURM, Open
  MPI, Kubernetes). A missing or bad value is a usage error in one line."""
  env_int = lambda name: int(os.environ[name]) if os.environ.get(name) else None
  try:
    coordinator = args.coordinator or os.environ.get("JAX_COORDINATOR_ADDRESS") or None
    count = args.num_processes if args.num_processes is not None else env_int(
        "JAX_NUM_PROCESSES")
    pid = args.process_id if args.process_id is not None else env_int("JAX_PROCESS_ID")
  except ValueError as e:
    p.error(f"--distributed: {e} (JAX_NUM_PROCESSES and JAX_PROCESS_ID are integers)")
  if count is not None and pid is not None and not 0 <= pid < count:
    p.error(f"--distributed: process id {pid} is not in 0..{count - 1}")
  try:
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=count,
                               process_id=pid)
  except (ValueError, RuntimeError) as e:
    p.error(f"--distributed: {first_line(e)} (give --coordinator, --num-processes and "
            "--process-id, or run under SLURM / Open MPI / Kubernetes)")


if __name__ == "__main__":
  # SIGINT / SIGTERM at any moment: exit 130 / 143 within seconds; the run's outputs stay
  # (a resume continues them), a partial checkpoint is removed
  command_main(main, keep_outputs=True)
