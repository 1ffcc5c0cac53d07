"""`python -m mjxvine.train`: SAC on the batched vineyard env, on one or many devices.

  python -m mjxvine.train --config experiments/smoke.yaml --run-dir runs/smoke
  python -m mjxvine.train --resume runs/smoke --set train.total_env_steps=20000
  python -m mjxvine.train                       # the default run (experiments/default.yaml)
  python -m mjxvine.train --config experiments/default.yaml --seeds 3 \
      --sweep sac.learning_rate=2e-4,1e-3

The run around the trainer (`mjxvine.trainer`: pure, compiled chunks of training
iterations): the CLI, resume, checkpoints (`mjxvine.checkpoint`), logs and plots, the
non-finite check between chunks, and, with the vineyard, the evaluations from fresh starts
during training (`mjxvine.starts`) and the closing test-world report (`mjxvine.evaluate`).
`--seeds K` and `--sweep` vmap the whole training state over the members (one compiled
program); envs and replay are split over the devices (`mjxvine.parallel`).

Run directory: config.yaml (resolved), metrics.jsonl, TensorBoard events (tb/),
checkpoints/ (orbax, `mjxvine.checkpoint`), learning_curve.png, eval/ (the final evaluation
report), lock (held while a process trains there). Signals, the lock, log truncation on
resume, write failures and the exit codes: `mjxvine.rundir`.
"""

from __future__ import annotations

import argparse
import datetime
import errno
import functools
import json
import math
import os
import signal
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jp
import numpy as np

from mjxvine import policies
from mjxvine import sac as sac_lib
from mjxvine import select as select_lib
from mjxvine import starts
from mjxvine.checkpoint import Checkpoints, restore_actor_params
from mjxvine.config import (DEFAULT_CONFIG_NAME, PACKAGED_CONFIGS, Config, add_config_args,
                            changed_keys, config_from_args, enable_compile_cache, load_config,
                            replace, resolve_config_path, to_yaml)
from mjxvine.protocol import TrainEnv
from mjxvine.rundir import (EXIT_NON_FINITE, EXIT_USAGE, EXIT_WRITE, Interrupted, RunDirBusy,
                            RunLock, StopSignals, WriteError, busy_message, clear_events,
                            exit_code, lock_holder, truncate_metrics, write_failure)
from mjxvine.trainer import (NonFiniteError, compile_key, compiled, init_members,
                             sweep_members)

# With no --config: the documented default run, shipped inside the package (a copy of
# experiments/default.yaml), so that it is found however mjxvine was installed.
DEFAULT_CONFIG = PACKAGED_CONFIGS / DEFAULT_CONFIG_NAME


@functools.lru_cache(maxsize=4)
def _start_evaluator(cfg: Config, seeds: int, env):
  sac = compiled_trainer(cfg, seeds, env)[0]
  act = starts.with_baselines(sac.act_deterministic, env.action_low, env.action_high)
  return starts.make_start_eval(env, act, cfg.train.eval_starts, seeds)


def start_evaluator(cfg: Config, seeds: int = 1):
  """The evaluation from `train.eval_starts` fresh starts per direction of a run of `cfg`
  (`mjxvine.starts`), compiled once per process: run(starts_params(actor params, policy,
  seeds), key) -> dict; policy `starts.ACTOR`, or a baseline (`starts.BASELINES`)."""
  key = compile_key(cfg)
  return _start_evaluator(replace(key, train={"eval_starts": cfg.train.eval_starts}), seeds,
                          _default_env(key))


def starts_params(actor_params, policy: int, seeds: int = 1) -> dict:
  """The parameters of `start_evaluator`'s run: which policy, for every member."""
  return {"actor": actor_params,
          "policy": jp.full((seeds,) if seeds > 1 else (), policy, jp.int32)}


@functools.lru_cache(maxsize=4)
def _default_env(cfg: Config) -> TrainEnv:
  from mjxvine.env import training_env  # the run's default; the trainer takes any env
  return training_env(cfg)


def compiled_trainer(cfg: Config, seeds: int = 1, env=None):
  """(sac, init(keys (seeds, 2)), chunk) jitted, cached per process on everything that
  shapes the compiled program (so a resume in the same process does not recompile).
  `env`: the config's vineyard (`env.training_env`) by default, or any `protocol.TrainEnv`
  (e.g. `wrappers.brax_env(...)`)."""
  key = compile_key(cfg)
  return compiled(key, seeds, _default_env(key) if env is None else env)


# ---------------------------------------------------------------------- logging
class Logger:
  """metrics.jsonl + TensorBoard (tensorboardX) + a progress line."""

  def __init__(self, run_dir: Path, total: int, start: int, enabled: bool = True,
               purge_step: int | None = None):
    """`purge_step`: on a resume, the first env step after the restored checkpoint;
    TensorBoard drops the events of the stopped run from there on."""
    self.enabled = enabled
    if not enabled:
      return
    from tensorboardX import SummaryWriter
    from tqdm import tqdm
    self.jsonl = open(run_dir / "metrics.jsonl", "a")
    self.tb = SummaryWriter(str(run_dir / "tb"), purge_step=purge_step)
    self.bar = tqdm(total=total, initial=start, unit="step", dynamic_ncols=True,
                    mininterval=2.0, file=sys.stderr)
    self.last_eval = ""

  def log(self, row: dict) -> None:
    if not self.enabled:
      return
    self.jsonl.write(json.dumps(row) + "\n")
    self.jsonl.flush()
    for k, v in row.items():
      if isinstance(v, (int, float)) and k != "env_steps" and v is not None and math.isfinite(v):
        self.tb.add_scalar(k, v, row["env_steps"])
    self.tb.flush()
    self.bar.n = row["env_steps"]
    if "eval_success_forward" in row:
      self.last_eval = (f" | eval F {row['eval_success_forward']:.2f} "
                        f"R {row['eval_success_reverse']:.2f}")
    self.bar.set_postfix_str(
        f"sps {row['sps']:.0f} ups {row['ups']:.0f} ret {_f(row['return_mean'])} "
        f"succ {_f(row['success_rate'])} eps {row['eps']:.2f} alpha {row['alpha']:.3f} "
        f"Lq {row['critic_loss']:.3g} Lpi {row['actor_loss']:.3g}{self.last_eval}",
        refresh=True)

  def close(self):
    if not self.enabled:
      return
    self.enabled = False
    self.bar.close()
    self.tb.close()
    self.jsonl.close()


def _f(x):
  return "-" if x is None else f"{x:.2f}"


def _smooth(y: np.ndarray, width: int) -> np.ndarray:
  """Moving average over the last `width` finite values (NaN where none yet)."""
  out = np.full(len(y), np.nan)
  for i in range(len(y)):
    window = y[max(0, i - width + 1):i + 1]
    window = window[np.isfinite(window)]
    if window.size:
      out[i] = window.mean()
  return out


def plot_learning_curve(run_dir: Path) -> None:
  """learning_curve.png from metrics.jsonl: training episodes (with exploration), the
  deterministic evaluations per direction, losses and the exploration schedule."""
  import matplotlib.pyplot as plt
  rows = [json.loads(l) for l in (run_dir / "metrics.jsonl").read_text().splitlines() if l]
  if not rows:
    return
  members = sorted({r.get("member", r.get("seed", 0)) for r in rows})
  fig, axes = plt.subplots(2, 3, figsize=(15, 7.5))
  axes = axes.ravel()
  width = max(1, len(rows) // len(members) // 15)
  for s in members:
    rs = [r for r in rows if r.get("member", r.get("seed", 0)) == s]
    x = np.array([r["env_steps"] for r in rs])
    col = lambda k: np.array([np.nan if r.get(k) is None else r[k] for r in rs], float)
    label = ", ".join(f"{k.split('.')[-1]} {v:g}" for k, v in rs[0].items()
                      if k.startswith("sac.")) or f"seed {rs[0].get('seed', s)}"
    if any(k.startswith("sac.") for k in rs[0]):
      label += f", seed {rs[0].get('seed', 0)}"
    colour = f"C{s % 10}"

    def curve(ax, key, lab, style="-", c=colour, smooth=True):
      y = col(key)
      if smooth and width > 1:
        ax.plot(x, y, style, color=c, alpha=0.25, lw=0.8)
        y = _smooth(y, width)
      ax.plot(x, y, style, color=c, label=lab)

    curve(axes[0], "return_mean", label)
    curve(axes[1], "success_rate", f"training ({label})")
    evaluated = np.isfinite(col("eval_success_forward"))
    for key, style, name in (("eval_success_forward", "o-", "forward"),
                             ("eval_success_reverse", "s--", "reverse")):
      if evaluated.any():
        axes[2].plot(x[evaluated], col(key)[evaluated], style, color=colour, ms=4,
                     label=f"{name} ({label})" if len(members) > 1 else name)
    if evaluated.any():
      axes[3].plot(x[evaluated], col("eval_mae_m")[evaluated], "o-", color=colour, ms=4,
                   label=label)
    learned = col("critic_loss") > 0  # 0 before learning starts: not a loss
    for ax, key in ((axes[4], "critic_loss"), (axes[5], "actor_loss")):
      y = np.where(learned, col(key), np.nan)
      ax.plot(x, y, color=colour, label=label)
    if s == members[0]:
      twin = axes[0].twinx()
      twin.plot(x, col("eps"), ":", color="0.4", label="epsilon")
      twin.plot(x, col("alpha") / max(np.nanmax(col("alpha")), 1e-12), "-.", color="0.6",
                label="alpha / max")
      twin.set_ylim(0, 1.05)
      twin.set_ylabel("epsilon, alpha / max alpha")
      twin.legend(loc="lower right", fontsize=7)
  titles = [("training episodes (with exploration): return", "episode return"),
            ("training episodes (with exploration): success", "success rate"),
            ("deterministic policy, fresh starts: success", "success rate"),
            ("deterministic policy, fresh starts: lateral MAE", "MAE (m)"),
            ("critic loss (once learning)", "loss"), ("actor loss (once learning)", "loss")]
  for ax, (title, ylabel) in zip(axes, titles):
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("env steps")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
  for ax in (axes[1], axes[2]):
    ax.set_ylim(-0.03, 1.03)
  axes[4].set_yscale("log")
  if axes[2].lines:
    axes[2].legend(fontsize=7)
  if len(members) > 1:
    axes[0].legend(fontsize=7, loc="upper left")
  fig.tight_layout()
  fig.savefig(run_dir / "learning_curve.png", dpi=100)
  plt.close(fig)


# ---------------------------------------------------------------------- the run
def _say(quiet: bool):
  return (lambda *a, **k: None) if quiet else functools.partial(print, file=sys.stderr,
                                                                 flush=True)


def _score(scores: dict) -> tuple:
  """Order of evaluations for the best checkpoint: the weaker direction's success, then
  the lower MAE."""
  return (min(scores["eval_success_forward"], scores["eval_success_reverse"]),
          -scores["eval_mae_m"])


class MemberBest:
  """Each member's best actor of a `--seeds` / sweep run, chosen by its own evaluations
  from fresh starts (`_score`), as a policy file RUN_DIR/best_members/member<k>.npz
  (`python -m mjxvine.evaluate --policy` takes it), its scores in
  RUN_DIR/best_members/scores.json. checkpoints/best follows member 0 alone."""

  def __init__(self, run_dir: Path, cfg: Config):
    self.dir, self.cfg = run_dir / "best_members", cfg
    self.json = self.dir / "scores.json"
    self.scores = json.loads(self.json.read_text()) if self.json.is_file() else {}

  def update(self, chunk: int, env_steps: int, rows: list[dict], actor) -> None:
    better = [k for k, row in enumerate(rows) if str(k) not in self.scores
              or _score(row) > _score(self.scores[str(k)])]
    if not better:
      return
    actor = _local(actor)
    for k in better:
      _export_member(self.cfg, actor, k, self.dir / f"member{k}.npz", chunk, env_steps)
      self.scores[str(k)] = {"chunk": chunk, "env_steps": env_steps,
                             **{n: v for n, v in rows[k].items() if n != "best"}}
    self.json.write_text(json.dumps(self.scores, indent=1))


def _export_member(cfg: Config, actor, k: int | None, path: Path, chunk: int,
                   env_steps: int) -> None:
  """Writes member k of the (local) actor params, stacked over members, as a policy file;
  k = None: params of a single-member run (no member axis)."""
  from mjxvine.export import export_actor, meta_from_config
  meta = {**meta_from_config(cfg), "member": 0 if k is None else k, "chunk": chunk,
          "env_steps": env_steps}
  export_actor(actor if k is None else jax.tree.map(lambda x: x[k], actor), path, meta)


def _last_row(run_dir: Path) -> dict:
  """The last row of RUN_DIR/metrics.jsonl ({} if none): that of the last member."""
  lines = (run_dir / "metrics.jsonl").read_text().splitlines() \
      if (run_dir / "metrics.jsonl").is_file() else []
  return json.loads(lines[-1]) if lines else {}


def train(cfg: Config, run_dir: Path, *, resume: bool = False, evaluate_at_end: bool = True,
          quiet: bool = False, env=None) -> dict:
  """Trains (or resumes) a run; returns the final log row of member 0 (of a run found
  complete on resume: the last row of its metrics.jsonl, `_last_row`). Trains
  `train.num_seeds` seeds times the `train.sweep` grid at once (vmap). `env` defaults to
  the config's vineyard pool; another `protocol.TrainEnv` (e.g. `wrappers.brax_env(...)`)
  trains the same way, without the vineyard evaluations.

  With the vineyard env, every `train.eval_every_chunks` chunks and at the end (with
  `evaluate_at_end` or eval_every_chunks > 0) the deterministic policy drives
  `train.eval_starts` fresh starts per direction (`mjxvine.starts`); the best of these
  evaluations (member 0) is kept as checkpoints/best (and, with several members, each
  member's own best actor as best_members/member<k>.npz: `MemberBest`), and the closing report
  (`evaluate_at_end`) evaluates that policy on the test world.

  The run holds RUN_DIR's lock throughout (`rundir.RunLock`; `rundir.RunDirBusy` if
  another process has it). A resume cuts metrics.jsonl and the TensorBoard events back to
  the restored checkpoint. SIGINT / SIGTERM end the current chunk, write a checkpoint and
  raise `rundir.Interrupted`; a failed checkpoint write raises `rundir.WriteError`. With
  several processes (`jax.distributed`) every process calls this; all of them enter the
  same collectives, process 0 alone writes logs and prints.
  """
  primary = jax.process_index() == 0
  run_dir.mkdir(parents=True, exist_ok=True)
  lock, busy = None, None
  if primary:
    try:
      lock = RunLock(run_dir).acquire()
    except RunDirBusy as e:
      busy = e
  if _max_over_processes(int(busy is not None)):  # every process refuses, or none
    raise busy or RunDirBusy(f"{run_dir} is in use (process 0 holds no lock)")
  try:
    return _train(cfg, run_dir, resume, evaluate_at_end, quiet or not primary, env, primary)
  finally:
    if lock is not None:
      lock.release()


def _max_over_processes(value: int) -> int:
  """The largest `value` over all processes: a collective that every process must enter
  (the value itself with one process)."""
  if jax.process_count() == 1:
    return value
  from jax.experimental import multihost_utils
  return int(np.max(multihost_utils.process_allgather(np.int32(value))))


def _preempted(step: int) -> bool:
  """Whether JAX's preemption service (a cluster's notice, with `jax.distributed`) asks
  every process to stop at this step (a collective; False with one process)."""
  if jax.process_count() == 1:
    return False
  from jax.experimental import multihost_utils
  try:
    return bool(multihost_utils.reached_preemption_sync_point(step))
  except RuntimeError:  # the preemption service is off
    return False


def _local(tree):
  """A replicated (possibly multi-process) pytree as numpy arrays of this process."""
  return jax.tree.map(lambda x: np.asarray(x.addressable_data(0))
                      if isinstance(x, jax.Array) else x, tree)


def _train(cfg: Config, run_dir: Path, resume: bool, evaluate_at_end: bool, quiet: bool,
           env, primary: bool) -> dict:
  say = _say(quiet)
  phase = ["setup"]  # a signal stops at once but while training (nothing to keep)
  stops = StopSignals(stop_now=lambda: phase[0] != "training", say=say)
  with stops:
    if primary:
      (run_dir / "config.yaml").write_text(to_yaml(cfg))
    members = sweep_members(cfg)
    seeds = len(members)
    vineyard = env is None
    if vineyard:
      env = _default_env(compile_key(cfg))
    sac, init_fn, chunk_fn = compiled_trainer(cfg, seeds, env)
    ts = init_members(cfg, init_fn, members)
    nbytes = sac_lib.buffer_nbytes(ts.buffer)
    ckpt = Checkpoints(run_dir, cfg.train.save_replay, clean=primary)
    ckpt.primary = primary
    steps_per_chunk = cfg.env.num_envs * cfg.train.iters_per_chunk
    total_chunks = math.ceil(cfg.train.total_env_steps / steps_per_chunk)
    chunk_index = 0
    tell = _say(not primary)  # what a resume found is said even when quiet
    if primary and getattr(ckpt, "removed", None):
      tell(f"removed {len(ckpt.removed)} partial checkpoint(s) that an interrupted or "
           f"failed save left: {', '.join(p.name for p in ckpt.removed)}")
    if resume:
      restored = ckpt.restore(ts)
      if restored is None:
        tell(f"no usable checkpoint in {run_dir}; starting afresh")
      else:
        chunk_index, ts = restored
        if chunk_index >= total_chunks:
          row = _last_row(run_dir)
          tell(f"{run_dir} is complete: {int(np.max(ts.env_steps))} env steps of "
               f"{cfg.train.total_env_steps}; raise train.total_env_steps to train on. "
               f"Its last figures: {_summary_line(row, ckpt.best_scores())}")
          return row
        tell(f"resumed {run_dir} at chunk {chunk_index} ({int(np.max(ts.env_steps))} env "
             "steps)")
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
    say(f"run {run_dir}: {seeds} seed(s) x {cfg.env.num_envs} envs, {total_chunks} chunks "
        f"of {steps_per_chunk} env steps; replay {nbytes / 2**20:.1f} MiB per seed "
        f"({nbytes / max(cfg.sac.buffer_size, 1):.0f} B/transition); device "
        f"{jax.devices()[0].device_kind} x {cfg.train.devices or jax.device_count()}"
        + (f" over {jax.process_count()} processes" if jax.process_count() > 1 else "")
        + f"; conv tower {sac_lib.describe_conv_impl(cfg.sac.conv_impl)}")
    # The evaluations from fresh starts: every eval_every_chunks chunks and at the end, or
    # only at the end when the closing report is asked for.
    start_eval = (start_evaluator(cfg, seeds)
                  if vineyard and (evaluate_at_end or cfg.train.eval_every_chunks) else None)
    eval_key = jax.random.PRNGKey(cfg.train.seed + 1)  # the same starts at every evaluation
    # read once: every process decides on the same scores (process 0 rewrites the file)
    best_scores = [ckpt.best_scores()]
    member_best = MemberBest(run_dir, cfg) if seeds > 1 and primary else None

    def evaluate_starts(ts) -> list[dict]:
      """Evaluates every member; saves the state of all members as checkpoints/best when
      member 0's scores are the best so far, and each member's actor as
      best_members/member<k>.npz when its own scores are."""
      t0 = time.time()
      out = start_eval(starts_params(ts.learner.policy_params, starts.ACTOR, seeds), eval_key)
      rows = [_member_scores(out, s) for s in range(seeds)]
      steps = int(np.max(ts.env_steps))
      best = best_scores[0]
      if best is None or _score(rows[0]) > _score(best):
        scores = {"env_steps": steps, **rows[0]}
        ckpt.save_best(chunk_index, ts, scores)
        best_scores[0] = {"chunk": chunk_index, **scores}
        rows[0]["best"] = True
      if member_best is not None:
        member_best.update(chunk_index, steps, rows, ts.learner.policy_params)
      if (cfg.train.keep_eval_policies or cfg.train.select_worlds) and primary:
        _export_member(cfg, _local(ts.learner.policy_params), 0 if seeds > 1 else None,
                       select_lib.policy_file(run_dir, steps), chunk_index, steps)
      say(f"evaluated {2 * cfg.train.eval_starts} fresh starts in {time.time() - t0:.0f} s: "
          f"{_eval_line(rows[0])}" + (" (new best)" if rows[0].get("best") else ""))
      return rows

    logger = Logger(run_dir, total_chunks * steps_per_chunk, chunk_index * steps_per_chunk,
                    enabled=primary, purge_step=restored_steps + 1 if chunk_index else None)
    last_row, t_compile, t_start, evaluated = {}, None, time.time(), -1
    every = cfg.train.eval_every_chunks
    saved, signum = chunk_index, 0
    phase[0] = "training"
    try:
      while chunk_index < total_chunks:
        if cfg.train.max_minutes and time.time() - t_start > 60 * cfg.train.max_minutes:
          say(f"train.max_minutes = {cfg.train.max_minutes} reached after chunk "
              f"{chunk_index}: stopping")
          break
        if t_compile is None:
          say("compiling the training iteration (the first chunk includes it)...")
        t0 = time.time()
        ts, m = chunk_fn(ts)
        m = jax.device_get(m)
        dt = time.time() - t0
        if t_compile is None:
          t_compile = dt
          say(f"first chunk done in {dt:.0f} s, compilation included")
        if not np.all(m["finite"]) or not all(np.all(np.isfinite(v)) for v in m.values()):
          bad = [k for k, v in m.items() if not np.all(np.isfinite(v))]
          raise NonFiniteError(
              f"non-finite {'parameters' if not np.all(m['finite']) else ', '.join(bad)} at "
              f"env step {int(np.max(ts.env_steps))} (chunk {chunk_index + 1}); the last good "
              f"checkpoint is chunk {ckpt.manager.latest_step()} in {ckpt.dir}")
        chunk_index += 1
        host = jax.device_get((ts.env_steps, ts.episodes, ts.log_episodes, ts.log_return,
                               ts.log_success, ts.log_timeout, ts.log_speed, ts.log_terms))
        evals = [{}] * seeds
        if start_eval is not None and ((every and chunk_index % every == 0) or
                                       chunk_index == total_chunks):
          evals, evaluated = evaluate_starts(ts), chunk_index
        for s in range(seeds):
          row = _row(cfg, members[s], s, chunk_index, host, m, evals[s], dt, t_compile,
                     steps_per_chunk)
          if s == 0:
            last_row = row
          logger.log(row)
        ts = ts.reset_log()
        if chunk_index % cfg.train.checkpoint_every_chunks == 0 or chunk_index == total_chunks:
          ckpt.save(chunk_index, ts)
          saved = chunk_index
        # the same decision in every process: a signal to any of them stops all
        signum = _max_over_processes(stops.requested) or (
            signal.SIGTERM if _preempted(chunk_index) else 0)
        if signum:
          break
      if saved != chunk_index:  # stopped early (a signal, train.max_minutes)
        ckpt.save(chunk_index, ts)
      phase[0] = "closing"
      if signum:
        logger.close()
        if primary:
          plot_learning_curve(run_dir)
        raise Interrupted(signum, f"stopped by {signal.Signals(signum).name} after chunk "
                          f"{chunk_index} ({int(np.max(ts.env_steps))} env steps); "
                          f"checkpoint {chunk_index} written")
      if start_eval is not None and evaluated != chunk_index:
        last_row.update(evaluate_starts(ts)[0])  # stopped early: evaluate the last policy
    finally:
      logger.close()
    if primary:
      plot_learning_curve(run_dir)
    best = best_scores[0]
    if best is not None:
      last_row.update({f"best_{k}": v for k, v in best.items()})
    selected = None
    if vineyard and cfg.train.select_worlds and primary and best is not None:
      selected = select_lib.select(cfg, run_dir, say)["selected"]
      last_row["selected_env_steps"] = selected
    if vineyard and evaluate_at_end:
      _closing_report(cfg, run_dir, sac, ckpt, ts, seeds, best, last_row, say, start_eval,
                      eval_key, primary, selected)
    return last_row


def _row(cfg: Config, member: dict, s: int, chunk_index: int, host, m: dict, evals: dict,
         dt: float, t_compile: float, steps_per_chunk: int) -> dict:
  """The metrics.jsonl row of member `s` after chunk `chunk_index`: `host` the fetched
  counters and sums of the TrainState, `m` the chunk's metrics, `dt` its seconds."""
  get = (lambda x: np.reshape(x, (-1,))[s])
  eps_done = int(get(host[2]))
  per_episode = lambda x: float(get(x) / eps_done) if eps_done else None
  row = {
      **member, "member": s,
      "chunk": chunk_index, "env_steps": int(get(host[0])),
      "episodes": int(get(host[1])),
      "return_mean": per_episode(host[3]), "success_rate": per_episode(host[4]),
      "timeout_rate": per_episode(host[5]), "v_mean": float(get(host[6])) / steps_per_chunk,
      "sps": steps_per_chunk / dt,
      "ups": cfg.train.iters_per_chunk * cfg.sac.grad_steps_per_iter / dt,
      "chunk_s": dt, "compile_s": t_compile,
      "wall": datetime.datetime.now().isoformat(timespec="seconds"),
      **evals,
  }
  row.update({k: float(get(v)) / steps_per_chunk for k, v in host[7].items()})
  row.update({k: float(get(v)) for k, v in m.items() if k != "finite"})
  return row


def _member_scores(out: dict, member: int) -> dict:
  """{"eval_<name>": float} of one member from a `start_evaluator` run's output."""
  return {f"eval_{k}": float(np.reshape(v, (-1,))[member]) for k, v in out.items()}


def _eval_line(scores: dict) -> str:
  return (f"forward {scores['eval_success_forward']:.0%}, reverse "
          f"{scores['eval_success_reverse']:.0%}, lateral MAE {scores['eval_mae_m']:.3f} m")


def _summary_line(row: dict, best: dict | None) -> str:
  text = (f"return {_f(row.get('return_mean'))}, training success "
          f"{_f(row.get('success_rate'))} (with exploration)")
  if best is not None:
    text += f"; best checkpoint (chunk {best['chunk']}): {_eval_line(best)}"
  return text


def _closing_report(cfg: Config, run_dir: Path, sac, ckpt: Checkpoints, ts, seeds: int,
                    best: dict | None, row: dict, say, start_eval, eval_key,
                    primary: bool = True, selected: int | None = None) -> None:
  """Prints the best policy's evaluation on fresh starts of the training rows beside the
  drive-straight and random baselines from the same starts, evaluates it on the test world
  (the paper's protocol, `eval.runs_after_train` runs per lane-direction, for
  information) and names the files of the run. Every process enters the restore and the
  baselines (collectives over all devices); process 0 alone runs the test world (on its
  own device) and prints. selected: the env steps of the policy chosen on validation
  worlds (RUN/selected.npz, `mjxvine.select`), which the test world then drives instead
  of checkpoints/best."""
  actor = ts.learner.policy_params
  if best is not None:
    restored = ckpt.restore(ts, best=True)
    if restored is not None:
      actor = restored[1].learner.policy_params
    say(f"\nbest policy (chunk {best['chunk']}, {best['env_steps']} env steps) from "
        f"{2 * cfg.train.eval_starts} fresh starts on the training rows: {_eval_line(best)}")
    for name, policy in starts.BASELINES.items():
      out = start_eval(starts_params(actor, policy, seeds), eval_key)
      scores = _member_scores(out, 0)
      row.update({f"{name}_{k}": v for k, v in scores.items()})
      say(f"  the same starts, {'driving straight' if name == 'straight' else name}: "
          f"{_eval_line(scores)}")
  actor = _local(actor)
  if seeds > 1:
    actor = jax.tree.map(lambda x: x[0], actor)
  runs = cfg.eval.runs_after_train
  if not primary:
    return
  which = "best checkpoint"
  if selected is not None:
    actor, _ = restore_actor_params(run_dir)  # RUN/selected.npz
    which = f"policy selected on validation worlds, {selected} env steps"
  if runs > 0:
    from mjxvine import evaluate as ev
    from mjxvine.worlds import load_test_world
    world = load_test_world(cfg.world)
    say(f"evaluating the best policy on the test world ({len(world.lanes) * 2 * runs} runs, "
        f"the paper's protocol; for information)...")
    doc, tracks = ev.run_protocol(
        cfg, "checkpoint", world, runs=runs, noise_factor=cfg.eval.noise_factor,
        policy=policies.actor_policy(sac.nets, actor, mirror=policies.averaging_mirror(cfg)),
        video=ev.video_after_train(world) if cfg.train.video else ())
    member = ", member 0" if seeds > 1 else ""
    doc["policy"] = f"{run_dir} ({which}, train.seed {cfg.train.seed}{member})"
    ev.write_results(doc, world, run_dir / "eval")
    row["eval_test_success"] = doc["overall"]["success"]
    row["eval_test_runs"] = doc["overall"]["runs"]
    say(ev.results_markdown(doc))
    if tracks:  # train.video
      say(f"filming the best policy's runs to {run_dir / 'eval' / 'videos'}/ ...")
      try:
        ev.write_videos(tracks, world, cfg, run_dir / "eval" / "videos", say=say)
      except ev.RenderError as e:  # no GL or no ffmpeg here: the run itself is fine
        say(f"no videos: {e}")
  say(f"wrote {run_dir}/: open learning_curve.png first" +
      (", then eval/trajectories.png and eval/results.md" if runs > 0 else "") +
      "; metrics.jsonl and tb/ (tensorboard --logdir) hold every chunk, checkpoints/ the "
      "last and best policies (python -m mjxvine.export --checkpoint " + f"{run_dir})")


def main(argv=None) -> int:
  """The CLI. Exit codes (`mjxvine.rundir`): 0 done, 2 a bad argument or config or a run
  directory in use, 3 a non-finite loss, 4 a failed write (disk full, ...), 130 / 143
  stopped by SIGINT / SIGTERM with a checkpoint written."""
  p = argparse.ArgumentParser(prog="python -m mjxvine.train", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  add_config_args(p, default=None)
  p.add_argument("--run-dir", default=None, help="run directory (default runs/<time>)")
  p.add_argument("--resume", default=None, metavar="RUN_DIR",
                 help="continue an interrupted run from its last checkpoint")
  p.add_argument("--seeds", type=int, default=None,
                 help="train K seeds at once (vmap); sets train.num_seeds")
  p.add_argument("--sweep", action="append", default=[], metavar="SECTION.KEY=V1,V2",
                 help="also sweep a hyper-parameter at once (vmap; repeatable: a grid); "
                 "sets train.sweep")
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
  args = p.parse_args(argv)
  enable_compile_cache()
  if args.distributed:
    _initialize_distributed(p, args)
  elif args.coordinator or args.num_processes is not None or args.process_id is not None:
    p.error("--coordinator, --num-processes and --process-id go with --distributed")
  if args.resume:
    run_dir = Path(args.resume)
    resolved = run_dir / "config.yaml"
    if not run_dir.is_dir():
      p.error(f"--resume {run_dir}: no such run directory")
    if not resolved.is_file():
      p.error(f"--resume {run_dir}: no config.yaml there (not a run directory)")
    old = config_from_args(argparse.Namespace(config=str(resolved), overrides=[]))
    cfg = config_from_args(argparse.Namespace(config=str(resolved), overrides=args.overrides))
    changed = changed_keys(old, cfg)
    free = ("train.total_env_steps", "train.max_minutes", "train.eval_every_chunks",
            "eval.runs_after_train")
    if any(c not in free for c in changed):
      p.error(f"--resume: only {', '.join(free)} may change, not {changed}")
  else:
    say = print if jax.process_index() == 0 else (lambda *a, **k: None)  # process 0 speaks
    if args.config is None:
      args.config = str(DEFAULT_CONFIG)
      say(f"config: {DEFAULT_CONFIG} (the default run, experiments/{DEFAULT_CONFIG_NAME}; "
          "--config picks another)", flush=True)
    else:
      say(f"config: {resolve_config_path(args.config)}", flush=True)
    extra = [f"train.num_seeds={args.seeds}"] if args.seeds else []
    if args.sweep:
      extra.append("train.sweep=" + "; ".join(args.sweep))
    cfg = config_from_args(args, extra)
    run_dir = Path(args.run_dir or f"runs/{datetime.datetime.now():%Y%m%d-%H%M%S}")
    if run_dir.exists() and not run_dir.is_dir():
      p.error(f"--run-dir {run_dir}: exists and is not a directory")
  # One process checks the lock here; with several, train() takes it in process 0 and every
  # process refuses together (process 0's own lock would stop the others here).
  if jax.process_count() == 1 and lock_holder(run_dir) is not None:
    print(f"error: {busy_message(run_dir)}", file=sys.stderr)
    return EXIT_USAGE
  if not args.resume and (run_dir / "checkpoints").exists():
    p.error(f"{run_dir} already holds a run: use --resume {run_dir} or another --run-dir")
  if args.resume and (args.seeds or args.sweep):
    p.error("--resume: the seeds and sweep come from the run's config.yaml")
  primary = jax.process_index() == 0
  error = functools.partial(print, file=sys.stderr, flush=True) if primary else (
      lambda *a: None)
  try:
    row = train(cfg, run_dir, resume=bool(args.resume), evaluate_at_end=not args.no_eval)
  except RunDirBusy as e:
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
        "eval_test_success", "eval_test_runs")}))
  return 0


# What a failed write of the run files (logs, config.yaml) reports in one line (exit 4).
_WRITE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EIO,
                 errno.EACCES)


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
    first = (str(e).strip().splitlines() or [type(e).__name__])[0][:200]
    p.error(f"--distributed: {first} (give --coordinator, --num-processes and "
            "--process-id, or run under SLURM / Open MPI / Kubernetes)")


if __name__ == "__main__":
  try:
    sys.exit(main())
  except KeyboardInterrupt:  # Ctrl-C before the run starts (its own handler takes over)
    print("interrupted before the run started", file=sys.stderr)
    sys.exit(exit_code(signal.SIGINT))
