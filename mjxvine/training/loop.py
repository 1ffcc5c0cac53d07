"""`train(cfg, run_dir)`: the host loop around the compiled chunks of training iterations.

The loop trains chunk after chunk (`mjxvine.training.iteration`) and hands each to its
hooks (`mjxvine.training.hooks`: fresh-start evaluations and the best checkpoint, logs,
checkpoints), checks for non-finite values and stop signals between chunks, and at the
end closes the logs, draws the learning curve, chooses the policy on validation worlds
(`train.select_worlds`, `mjxvine.evaluation.choice`) and writes the closing report
(`mjxvine.training.report`). `train.num_seeds` seeds times the `train.sweep` grid train at
once (vmap); envs and replay are split over the devices (`mjxvine.training.parallel`).

Run directory: config.yaml (resolved), run.json (the config it started with, which a
resume is held to), metrics.jsonl, TensorBoard events (tb/), checkpoints/ (orbax,
`mjxvine.rundir.checkpoints`; broken ones moved to checkpoints-broken/),
learning_curve.png, eval/ (the final evaluation report), lock (held while a process trains
there). Signals, the lock, write failures and the exit codes: `mjxvine.rundir`.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jp
import numpy as np

from mjxvine import networks as nw
from mjxvine import sac as sac_lib
from mjxvine import atomic
from mjxvine.config import (RELEASE_WITH_REMOVED, Config, ConfigError,
                            load_run_config, to_yaml)
from mjxvine.rundir import (Interrupted, ResumeRefused, RunDirBusy, RunLock, StopSignals,
                            original_config, record_fact, refuse_changes, set_aside,
                            write_run_record)
from mjxvine.rundir.checkpoints import Checkpoints, remove_partial_steps
from mjxvine.rundir.logs import Logger, clear_events, plot_learning_curve, truncate_metrics
from mjxvine.training import distributed, hooks, report
from mjxvine.training.iteration import (NonFiniteError, compile_key, init_members, scan_chunks,
                                        sweep_members)
from mjxvine.training.profile import Profile
from mjxvine.training.warm_start import warm_start
from mjxvine.training.programs import compiled_trainer, default_env, start_evaluator


def _say(quiet: bool) -> Callable:
  return (lambda *a, **k: None) if quiet else functools.partial(print, file=sys.stderr,
                                                                 flush=True)


# The memory check (`check_memory`): a run may plan on this share of the memory free when
# it starts (XLA's programs and scratch, the host's other work need the rest); per env, the
# physics state and its step's working arrays besides the frames (a vineyard env state is
# about 25 KB with a 40 x 40 image).
MEMORY_MARGIN = 0.9
ENV_BYTES = 256 << 10
FRAMES_PER_ENV = 8  # the observation, the rendered and noisy frames, the step's copies


def memory_estimate(cfg: Config, members: int, env=None) -> dict[str, int]:
  """Bytes a run of `cfg` holds, roughly, for its `members` together, known before
  anything is built: "replay" (exact: `replay.init_buffer`'s shapes, `jax.eval_shape`),
  "envs" (the training envs and the fresh-start evaluation's) and "batch" (a learner
  batch with its conv activations). `env`: a custom `TrainEnv` (its observation traced)."""
  n = cfg.env.num_envs
  if env is None:  # the vineyard env's observation (`env.VineyardEnv`)
    f32 = lambda *shape: jax.ShapeDtypeStruct(shape, jp.float32)
    obs = {"depth": f32(n, cfg.camera.height, cfg.camera.width, 1), "state": f32(n, 3)}
    action_size = 2
  else:
    obs = jax.eval_shape(lambda k: env.reset_batch(k, n).obs, jax.random.PRNGKey(0))
    action_size = env.action_size
  buffer = jax.eval_shape(lambda o: sac_lib.init_buffer(
      o, action_size, cfg.sac.buffer_size, cfg.camera.max_depth_m,
      depth_dtype=jp.dtype(cfg.sac.replay_depth_dtype)), obs)
  frame = sum(math.prod(x.shape[1:]) * x.dtype.itemsize for x in jax.tree.leaves(obs))
  envs = (n + 2 * cfg.train.eval_starts) * (FRAMES_PER_ENV * frame + ENV_BYTES)
  batch = cfg.sac.batch_size * frame * (2 + cfg.sac.conv_features)
  return {"replay": members * sac_lib.buffer_nbytes(buffer), "envs": members * envs,
          "batch": members * batch}


def available_memory() -> tuple[int, str] | None:
  """(bytes free, what they are) where a run's arrays will live: an accelerator's memory
  as JAX reports it (its allocator's limit less what is in use), else the host's
  MemAvailable (/proc/meminfo, else `os.sysconf`); None where it is not known."""
  device = jax.local_devices()[0]
  if device.platform != "cpu":
    try:
      stats = device.memory_stats() or {}
    except Exception:  # noqa: BLE001 - a backend without memory statistics
      stats = {}
    if stats.get("bytes_limit"):
      return (int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0)),
              f"the {device.device_kind}'s memory")
    return None
  try:
    for line in Path("/proc/meminfo").read_text().splitlines():
      if line.startswith("MemAvailable:"):
        return int(line.split()[1]) * 1024, "this machine's available memory (MemAvailable)"
  except (OSError, ValueError, IndexError):
    pass
  try:
    return (os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"),
            "this machine's free memory")
  except (ValueError, OSError, AttributeError):
    return None


def check_memory(cfg: Config, env=None) -> None:
  """Refuses a run that cannot fit, before anything is made or compiled: ConfigError, one
  line naming the keys, when `memory_estimate` (per device of `train.devices`) exceeds
  MEMORY_MARGIN of `available_memory`. MJXVINE_MEMORY_CHECK=0 skips it (swap, or memory
  that the figures do not see)."""
  if os.environ.get("MJXVINE_MEMORY_CHECK", "1") == "0":
    return
  free = available_memory()
  if free is None:
    return
  members = len(sweep_members(cfg))
  parts = memory_estimate(cfg, members, env)
  used = min(cfg.train.devices or jax.device_count(), jax.device_count())
  # the host holds what all of this process's devices hold; an accelerator its share
  share = (min(used, jax.local_device_count()) if jax.local_devices()[0].platform == "cpu"
           else 1) / used
  need = sum(parts.values()) * share
  available, where = free
  if need <= MEMORY_MARGIN * available:
    return
  mib = lambda b: f"{b * share / 2**20:,.0f} MiB"
  raise ConfigError(
      f"the run needs about {mib(sum(parts.values()))}, {where} is "
      f"{available / 2**20:,.0f} MiB: replay {mib(parts['replay'])} (sac.buffer_size "
      f"{cfg.sac.buffer_size} x sac.replay_depth_dtype {cfg.sac.replay_depth_dtype} x "
      f"{members} member(s): train.num_seeds, train.sweep), envs {mib(parts['envs'])} "
      f"(env.num_envs {cfg.env.num_envs}, train.eval_starts {cfg.train.eval_starts}), batch "
      f"{mib(parts['batch'])} (sac.batch_size {cfg.sac.batch_size}); lower them "
      f"(MJXVINE_MEMORY_CHECK=0 skips this check)")


def last_row(run_dir: Path) -> dict:
  """The last row of RUN_DIR/metrics.jsonl ({} if none): that of the last member."""
  path = run_dir / "metrics.jsonl"
  lines = path.read_text().splitlines() if path.is_file() else []
  return json.loads(lines[-1]) if lines else {}


def train(cfg: Config, run_dir: Path, *, resume: bool = False, evaluate_at_end: bool = True,
          quiet: bool = False, env=None, restart: bool = False) -> dict:
  """Trains (or resumes) a run; returns the final log row of member 0 (of a run found
  complete on resume: the last row of its metrics.jsonl, `last_row`). Trains
  `train.num_seeds` seeds times the `train.sweep` grid at once (vmap). `env` defaults to
  the config's vineyard pool; another `episodes.TrainEnv` (e.g. `wrappers.brax_env(...)`)
  trains the same way, without the vineyard evaluations.

  With the vineyard env, every `train.eval_every_chunks` chunks and at the end (with
  `evaluate_at_end` or eval_every_chunks > 0) the deterministic policy drives
  `train.eval_starts` fresh starts per direction (`hooks.FreshStartEvaluation`); the best
  of these evaluations (member 0) is kept as checkpoints/best (and, with several members,
  each member's own best actor as best_members/member<k>.npz), and the closing report
  (`evaluate_at_end`) evaluates that policy on the test world.

  A resume continues the same run or refuses (`rundir.ResumeRefused`): a config that
  differs from the one the run started with (RUN_DIR/run.json) in more than
  `rundir.RESUME_FREE`, or checkpoints none of which can be restored (broken steps are
  moved to RUN_DIR/checkpoints-broken/; the newest intact one is used, else the best);
  `restart` then starts the run afresh, its old outputs set aside (`rundir.set_aside`).

  The run holds RUN_DIR's lock throughout (`rundir.RunLock`; `rundir.RunDirBusy` if
  another process has it). A resume cuts metrics.jsonl and the TensorBoard events back to
  the restored checkpoint. SIGINT / SIGTERM end the current chunk, write a checkpoint and
  raise `rundir.Interrupted` (at once, keeping the last checkpoint, when they come while
  the run is set up or its first chunk compiles; a second Ctrl-C too); under
  `atomic.command_main` a run not stopped within `atomic.stop_grace()` is ended by its
  watchdog, the partial checkpoint of a save removed. A failed checkpoint write raises
  `rundir.WriteError`. With several processes (`jax.distributed`) every process calls
  this; all of them enter the same collectives, process 0 alone writes logs and prints.
  First of all, a run that would not fit in memory is refused (`check_memory`:
  ConfigError).
  """
  profile = Profile()  # where the wall-clock goes (run.json, the last line)
  primary = jax.process_index() == 0
  check_memory(cfg, env)  # before the run directory is made or anything compiled
  run_dir.mkdir(parents=True, exist_ok=True)
  lock, busy = None, None
  if primary:
    try:
      lock = RunLock(run_dir).acquire()
    except RunDirBusy as e:
      busy = e
  if distributed.max_over_processes(int(busy is not None)):  # every process refuses, or none
    raise busy or RunDirBusy(f"{run_dir} is in use (process 0 holds no lock)")
  try:
    with atomic.on_stop(functools.partial(_stop_cleanup, run_dir, lock)):
      return _train(cfg, run_dir, resume, evaluate_at_end, quiet or not primary, env,
                    restart, profile)
  finally:
    if lock is not None:
      lock.release()


def _stop_cleanup(run_dir: Path, lock: RunLock | None) -> str:
  """What a stop by a signal leaves of the run (`atomic.on_stop`, maybe from the watchdog
  thread while the main thread is in compiled code): the partial checkpoint of an
  interrupted save is removed (the newest intact one stays what a resume restores), and
  the lock file. Returns what the run keeps, for the line the stop says."""
  folder = run_dir / "checkpoints"
  if lock is not None:  # the run's one writer
    remove_partial_steps(folder)
    lock.drop_file()
  steps = sorted(int(p.name) for p in folder.iterdir() if p.name.isdigit()) \
      if folder.is_dir() else []
  kept = f"the run keeps checkpoint {steps[-1]}" if steps else "no checkpoint yet"
  return f"{kept}; resume with: python -m mjxvine.train --resume {run_dir}"


@dataclasses.dataclass
class _Run:
  """A run set up to train: its compiled programs, state and where it starts."""
  members: list[dict]
  sac: Any
  chunk_fn: Callable
  ts: Any
  ckpt: Checkpoints
  chunk_index: int
  total_chunks: int
  restored_steps: int
  vineyard: bool
  env: Any
  profile: Profile | None = None  # where the run's wall-clock goes


def _set_up(cfg: Config, run_dir: Path, resume: bool, restart: bool, env,
            primary: bool) -> _Run | dict:
  """Compiles the run's programs and builds (or restores) its state; cuts the logs back
  to the restored checkpoint. Returns the last row instead of a run already complete."""
  tell = _say(not primary)  # what a resume found is said even when quiet
  if resume:  # the same run or a clear refusal, before anything is built
    refuse_changes(run_dir, cfg, _config_yaml(run_dir, cfg), nw.resolve_conv_impl)
  tower = nw.describe_conv_impl(cfg.train.conv_impl)
  if primary:  # the tower that runs, resolved: the same config trains the same way
    atomic.write_text(run_dir / "config.yaml",
                      f"# conv tower: {tower}\n{to_yaml(cfg)}")
    if not resume or original_config(run_dir) is None:
      write_run_record(run_dir, cfg, conv_tower=tower)
  members = sweep_members(cfg)
  vineyard = env is None
  env = default_env(compile_key(cfg)) if vineyard else env
  sac, init_fn, chunk_fn = compiled_trainer(cfg, len(members), env)
  ts = init_members(cfg, init_fn, members)
  ckpt = Checkpoints(run_dir, cfg.train.save_replay, clean=primary)
  ckpt.primary = primary
  steps_per_chunk = cfg.env.num_envs * cfg.train.iters_per_chunk
  total_chunks, chunk_index = math.ceil(cfg.train.total_env_steps / steps_per_chunk), 0
  if primary and getattr(ckpt, "removed", None):
    tell(f"removed {len(ckpt.removed)} partial checkpoint(s) that an interrupted or "
         f"failed save left: {', '.join(p.name for p in ckpt.removed)}")
  if resume:
    restored = _restore(run_dir, ckpt, ts, restart, primary, tell)
    if restored is not None:
      chunk_index, ts = restored
      if chunk_index >= total_chunks:
        row = last_row(run_dir)
        tell(f"{run_dir} is complete: {int(np.max(ts.env_steps))} env steps of "
             f"{cfg.train.total_env_steps}; raise train.total_env_steps to train on. "
             f"Its last figures: {report.summary_line(row, ckpt.best_scores())}")
        return row
      tell(f"resumed {run_dir} at chunk {chunk_index} ({int(np.max(ts.env_steps))} env "
           "steps)")
  if cfg.train.init_from and not chunk_index:  # a new run, or one with no checkpoint yet
    ts = ts.replace(learner=warm_start(ts.learner, cfg.train.init_from, tell))
  # The logs follow the checkpoint: rows written after it (by the run that stopped)
  # are dropped, so that every chunk appears once and the curves run forward.
  restored_steps = int(np.max(ts.env_steps)) if chunk_index else 0
  if primary:
    dropped = truncate_metrics(run_dir / "metrics.jsonl", restored_steps)
    if chunk_index == 0:
      clear_events(run_dir / "tb")
    if dropped:
      tell(f"dropped {dropped} row(s) of metrics.jsonl past the checkpoint "
           f"({restored_steps} env steps); TensorBoard purges them too")
  ts = ts.replace(budget=jp.full_like(ts.budget, cfg.train.total_env_steps))
  return _Run(members, sac, chunk_fn, ts, ckpt, chunk_index, total_chunks, restored_steps,
              vineyard, env)


def _config_yaml(run_dir: Path, cfg: Config) -> Config:
  """The run's config.yaml as it is on disk (`cfg` when it is gone)."""
  path = run_dir / "config.yaml"
  return load_run_config(path) if path.is_file() else cfg


def _restore(run_dir: Path, ckpt: Checkpoints, ts, restart: bool, primary: bool,
             tell: Callable):
  """(chunk, TrainState) to resume from: the newest intact checkpoint, else the best one;
  None to start afresh: a run with no checkpoint yet, or, with `restart`, one whose
  checkpoints are all broken (its outputs set aside first). ResumeRefused otherwise."""
  broken = run_dir / "checkpoints-broken"
  for meta in (run_dir / "checkpoints").glob("*/*/_METADATA"):
    if '"policy_params"' in meta.read_text(errors="replace"):  # LearnerState of 0.2.0
      raise ResumeRefused(f"--resume {run_dir}: its checkpoints were written by "
                          f"{RELEASE_WITH_REMOVED}, which resumes them; this release "
                          "evaluates, exports and chooses its policies but cannot continue it")
  had = bool(ckpt.manager.all_steps() or ckpt.best_manager.all_steps() or broken.exists()
             or (run_dir / "best.json").exists())
  restored = ckpt.restore(ts)
  if restored is None and ckpt.best_manager.all_steps():
    restored = ckpt.restore(ts, best=True)
    if restored is not None:
      tell(f"no intact checkpoint of the last chunks: resuming from the best checkpoint "
           f"(chunk {restored[0]})")
  if restored is not None or not had:
    if not had:
      tell(f"no checkpoint in {run_dir} yet; starting the run afresh")
    return restored
  if not restart:
    raise ResumeRefused(f"--resume {run_dir}: no checkpoint of it can be restored (the "
                        f"broken ones are in {broken}); --restart starts the run afresh "
                        "in its directory, its old outputs set aside")
  moved = set_aside(run_dir) if primary else None
  tell(f"no checkpoint of {run_dir} can be restored: starting afresh (--restart)"
       + (f"; its old outputs are in {moved}" if moved else ""))
  for manager in (ckpt.manager, ckpt.best_manager):
    Path(manager.directory).mkdir(parents=True, exist_ok=True)
    manager.reload()
  return None


def _describe(cfg: Config, run_dir: Path, run: _Run) -> str:
  nbytes = sac_lib.buffer_nbytes(run.ts.buffer)
  steps_per_chunk = cfg.env.num_envs * cfg.train.iters_per_chunk
  return (f"run {run_dir}: {len(run.members)} seed(s) x {cfg.env.num_envs} envs, "
          f"{run.total_chunks} chunks of {steps_per_chunk} env steps; replay "
          f"{nbytes / 2**20:.1f} MiB per seed "
          f"({nbytes / max(cfg.sac.buffer_size, 1):.0f} B/transition); device "
          f"{jax.devices()[0].device_kind} x {cfg.train.devices or jax.device_count()}"
          + (f" over {jax.process_count()} processes" if jax.process_count() > 1 else "")
          + f"; conv tower {nw.describe_conv_impl(cfg.train.conv_impl)}")


def _check_finite(m: dict, ts, chunk_index: int, ckpt: Checkpoints) -> None:
  if not np.all(m["finite"]) or not all(np.all(np.isfinite(v)) for v in m.values()):
    bad = [k for k, v in m.items() if not np.all(np.isfinite(v))]
    raise NonFiniteError(
        f"non-finite {'parameters' if not np.all(m['finite']) else ', '.join(bad)} at "
        f"env step {int(np.max(ts.env_steps))} (chunk {chunk_index + 1}); the last good "
        f"checkpoint is chunk {ckpt.manager.latest_step()} in {ckpt.dir}")


def _loop(run: _Run, chunk_hooks: list, stops: StopSignals, say: Callable):
  """Trains chunks until the budget or a stop signal; each chunk goes through `chunk_hooks`
  in order (each hook's time to its `phase` of `run.profile`). Returns (TrainState, chunks
  done, signal number or 0)."""
  ts, chunk_index, profile = run.ts, run.chunk_index, run.profile
  one_program = scan_chunks()  # a chunk is one program (scan), else the CPU's host loop
  t_compile, signum = None, 0
  while chunk_index < run.total_chunks:
    first = t_compile is None
    if first:
      say("compiling the training iteration (the first chunk includes it)...")
      # a signal during the compilation stops at once: the chunk holds nothing to keep
      stop_now, stops.stop_now = stops.stop_now, lambda: True
    # a signal during a compilation ends the run in seconds; one during a chunk lets the
    # chunk and its checkpoint end
    atomic.set_stop_grace(atomic.STOP_GRACE_S if first else atomic.CHUNK_STOP_GRACE_S)
    t0, timed = time.perf_counter(), profile.total()
    try:
      ts, m = run.chunk_fn(ts) if one_program else run.chunk_fn(ts, profile)
      m = jax.device_get(m)
    finally:
      if first:
        stops.stop_now = stop_now
    dt = time.perf_counter() - t0
    # one program: the chunk is one phase; the host loop timed its calls, and the rest of
    # the chunk is its bookkeeping
    profile.add(("compile" if first else "training_chunks") if one_program else
                "collection", dt - (profile.total() - timed))
    if t_compile is None:
      t_compile = dt
      say(f"first chunk done in {dt:.0f} s, compilation included")
    _check_finite(m, ts, chunk_index, run.ckpt)
    chunk_index += 1
    chunk = hooks.Chunk(chunk_index, ts, m, dt, t_compile, [])
    for hook in chunk_hooks:
      with profile.phase(hook.phase):
        hook.after_chunk(chunk)
    ts = chunk.ts
    # the same decision in every process: a signal to any of them stops all
    signum = distributed.max_over_processes(stops.requested) or (
        signal.SIGTERM if distributed.preempted(chunk_index) else 0)
    if signum:
      break
  return ts, chunk_index, signum


def _train(cfg: Config, run_dir: Path, resume: bool, evaluate_at_end: bool, quiet: bool,
           env, restart: bool, profile: Profile) -> dict:
  primary = jax.process_index() == 0
  say = _say(quiet)
  cfg = nw.resolve_conv_impl(cfg)  # `auto` as the tower it takes here
  phase = ["setup"]  # a signal stops at once but while training (nothing to keep)
  stops = StopSignals(stop_now=lambda: phase[0] != "training", say=say)
  with stops:
    run = _set_up(cfg, run_dir, resume, restart, env, primary)
    if isinstance(run, dict):  # complete already
      return run
    say(_describe(cfg, run_dir, run))
    run.profile = profile
    seeds = len(run.members)
    # The evaluations from fresh starts: every eval_every_chunks chunks and at the end, or
    # only at the end when the closing report is asked for.
    start_eval = (start_evaluator(cfg, seeds) if run.vineyard and (
        evaluate_at_end or cfg.train.eval_every_chunks) else None)
    evaluation = (hooks.FreshStartEvaluation(cfg, run_dir, start_eval, run.ckpt, seeds,
                                             run.total_chunks, primary, say)
                  if start_eval is not None else None)
    steps_per_chunk = cfg.env.num_envs * cfg.train.iters_per_chunk
    logger = Logger(run_dir, run.total_chunks * steps_per_chunk,
                    run.chunk_index * steps_per_chunk, enabled=primary,
                    purge_step=run.restored_steps + 1 if run.chunk_index else None)
    log = hooks.ChunkLog(cfg, run.members, logger)
    checkpoints = hooks.Checkpointing(run.ckpt, cfg.train.checkpoint_every_chunks,
                                      run.total_chunks, run.chunk_index)
    phase[0] = "training"
    profile.add("setup", time.perf_counter() - profile.start - profile.total())
    try:
      ts, chunk_index, signum = _loop(
          run, [h for h in (evaluation, log, checkpoints) if h is not None], stops, say)
      with profile.phase("checkpoints"):
        checkpoints.at_end(ts, chunk_index)  # stopped early (a signal)
      atomic.set_stop_grace(atomic.STOP_GRACE_S)
      phase[0] = "closing"
      if signum:
        # what a resume needs and no more, so that the stop fits in its grace (the
        # learning curve, a second or two, is drawn when the run ends)
        logger.close()
        raise Interrupted(signum, f"stopped by {signal.Signals(signum).name} after chunk "
                          f"{chunk_index} ({int(np.max(ts.env_steps))} env steps); "
                          f"checkpoint {chunk_index} written")
      if evaluation is not None:
        with profile.phase("fresh_start_evaluations"):
          log.last_row.update(evaluation.at_end(ts, chunk_index))
    finally:
      with profile.phase("logs"):
        logger.close()
    row = _finish(cfg, run_dir, dataclasses.replace(run, ts=ts), evaluation, log.last_row,
                  evaluate_at_end, primary, say)
    row["profile"] = profile.record()
    if primary:
      record_fact(run_dir, profile=row["profile"])
      say(profile.line())
    return row


def _finish(cfg: Config, run_dir: Path, run: _Run, evaluation, row: dict,
            evaluate_at_end: bool, primary: bool, say: Callable) -> dict:
  """After the loop (`run` with its last TrainState as `run.ts`): the learning curve, the
  best scores in the last row, the choice on validation worlds and the closing report
  (each timed in `run.profile`)."""
  from mjxvine.evaluation import choice
  profile = run.profile
  if primary:
    with profile.phase("logs"):
      plot_learning_curve(run_dir)
  best = evaluation.best if evaluation is not None else run.ckpt.best_scores()
  if best is not None:
    row.update({f"best_{k}": v for k, v in best.items()})
  selected = None
  if run.vineyard and cfg.train.select_worlds and primary and best is not None:
    with profile.phase("choice"):
      records = [choice.select(cfg, run_dir, say, member=k)  # each member its own
                 for k in choice.member_ids(len(run.members))]
    selected = records[0]["selected"]
    row["selected_env_steps"] = selected
  if run.vineyard and evaluate_at_end:
    summary = report.RunSummary(run_dir, run.sac, run.ckpt, run.ts, len(run.members), best,
                                selected)
    with profile.phase("closing_evaluation"):
      report.closing_report(cfg, summary, row, say, evaluation.start_eval, evaluation.key,
                            primary)
  return row
