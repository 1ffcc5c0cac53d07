"""`python -m mjxvine.train`: SAC on the batched vineyard env, on one or many devices.

  python -m mjxvine.train --config experiments/smoke.yaml --run-dir runs/smoke
  python -m mjxvine.train --resume runs/smoke --set train.total_env_steps=20000
  python -m mjxvine.train --config experiments/fast.yaml --seeds 4
  python -m mjxvine.train --config experiments/default.yaml --sweep sac.learning_rate=2e-4,1e-3

One training iteration (N env steps with exploration, one replay insert, G gradient steps)
is one jit-compiled function; `train.iters_per_chunk` of them run under `lax.scan` (on
the CPU backend a host loop of the jitted iteration, see `_scan_chunks`); the host only
logs, checkpoints and checks for non-finite values between chunks. `--seeds K` and
`--sweep` vmap the whole training state over the members (one compiled program); envs and
replay are split over the devices (`mjxvine.parallel`).

Run directory: config.yaml (resolved), metrics.jsonl, TensorBoard events (tb/),
checkpoints/ (orbax), learning_curve.png, eval/ (the final evaluation report).
"""

from __future__ import annotations

import argparse
import datetime
import functools
import itertools
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import flax.struct
import jax
import jax.numpy as jp
import numpy as np

from mjxvine import networks as nw
from mjxvine import parallel
from mjxvine import sac as sac_lib
from mjxvine.config import (Config, add_config_args, config_from_args, load_config,
                            parse_sweep, replace, to_yaml)
from mjxvine.env import SUCCESS, VineyardEnv

DEFAULT_CONFIG = Path(__file__).resolve().parent.parent / "experiments" / "default.yaml"


class TrainState(flax.struct.PyTreeNode):
  """Everything a run carries from one iteration to the next (one seed)."""
  learner: sac_lib.LearnerState
  buffer: sac_lib.ReplayBuffer
  env_state: Any
  eps: jax.Array          # (N,) per-env exploration probability
  key: jax.Array
  env_steps: jax.Array    # () int32, summed over envs
  episodes: jax.Array     # () int32 finished episodes
  # Sums since the last log (reset by the host): finished episodes, their returns,
  # successes, gradient steps.
  log_episodes: jax.Array
  log_return: jax.Array
  log_success: jax.Array


class NonFiniteError(RuntimeError):
  """A loss or a parameter became NaN or infinite."""


def make_trainer(cfg: Config, env, shard_batch=lambda batch: batch):
  """Returns (sac, init(key) -> TrainState, chunk(TrainState) -> (TrainState, metrics),
  iteration(TrainState, None) -> (TrainState, metrics), summarize). `shard_batch`: see
  `mjxvine.sac.make_sac` (data parallelism over devices)."""
  n = cfg.env.num_envs
  # The action box comes from the env: the vineyard's [0, v_max] x [-w_max, w_max], or
  # [-1, 1] for a brax env behind `BraxAdapter`.
  nets = nw.make_networks(env.action_low, env.action_high, hidden=cfg.sac.hidden,
                          conv_features=cfg.sac.conv_features,
                          depth_scale=1.0 / cfg.camera.max_depth_m,
                          log_std_min=cfg.sac.log_std_min, log_std_max=cfg.sac.log_std_max)
  sac = sac_lib.make_sac(nets, cfg.sac, shard_batch=shard_batch)
  warmup = cfg.sac.warmup_steps

  def init(key: jax.Array) -> TrainState:
    k_env, k_learner, k_run = jax.random.split(key, 3)
    env_state = env.reset_batch(k_env, n)
    learner = sac.init(k_learner, env_state.obs)
    buffer = sac_lib.init_buffer(env_state.obs, env.action_size, cfg.sac.buffer_size,
                                 cfg.camera.max_depth_m,
                                 depth_dtype=jp.dtype(cfg.sac.replay_depth_dtype))
    z = jp.zeros((), jp.int32)
    return TrainState(learner=learner, buffer=buffer, env_state=env_state,
                      eps=jp.full((n,), cfg.sac.eps_start, jp.float32), key=k_run,
                      env_steps=z, episodes=z, log_episodes=z, log_return=jp.zeros(()),
                      log_success=z)

  def iteration(ts: TrainState, _, learn_now: bool | None = None):
    """One iteration. `learn_now` None decides on device (lax.cond); True/False is a
    static decision made by the host (the CPU path: XLA runs convolutions inside a
    conditional or loop body slowly on CPU)."""
    key, k_act, k_explore, k_update = jax.random.split(ts.key, 4)
    obs = ts.env_state.obs
    policy_action = sac.act(ts.learner.actor_params, obs, k_act)
    in_warmup = ts.env_steps < warmup
    action = sac_lib.explore_action(k_explore, policy_action, ts.eps, env.action_low,
                                    env.action_high, in_warmup)
    env_state, final_obs = env.step_batch(ts.env_state, action)
    done = env_state.done > 0
    truncated = done & (env_state.info["truncation"] > 0)
    tr = sac_lib.Transition(obs=obs, action=action,
                            reward=env_state.reward * cfg.sac.reward_scale,
                            terminal=(done & ~truncated).astype(jp.float32),
                            truncated=truncated.astype(jp.float32), next_obs=final_obs)
    buffer = sac_lib.insert(ts.buffer, tr)
    learn = (ts.env_steps + n >= warmup) & (sac_lib.num_sampleable(buffer) >= cfg.sac.batch_size)
    if learn_now is None:
      learner, metrics = jax.lax.cond(
          learn, lambda: sac.update_many(ts.learner, buffer, k_update),
          lambda: (ts.learner, _zero_metrics(sac, ts.learner, buffer, k_update)))
    elif learn_now:
      learner, metrics = sac.update_many(ts.learner, buffer, k_update)
    else:
      learner, metrics = ts.learner, _zero_metrics(sac, ts.learner, buffer, k_update)
      learn = jp.zeros((), bool)
    metrics["learning"] = learn.astype(jp.float32)
    success = done & (env_state.info["last_outcome"] == SUCCESS)
    ts = ts.replace(
        learner=learner, buffer=buffer, env_state=env_state, key=key,
        eps=sac_lib.decay_eps(ts.eps, done, cfg.sac.eps_decay, cfg.sac.eps_min),
        env_steps=ts.env_steps + n, episodes=ts.episodes + done.sum(),
        log_episodes=ts.log_episodes + done.sum(),
        log_return=ts.log_return + jp.sum(jp.where(done, env_state.info["last_return"], 0.0)),
        log_success=ts.log_success + success.sum())
    return ts, metrics

  def summarize(ts: TrainState, metrics: dict):
    """Chunk metrics: losses averaged over the iterations that learned."""
    metrics = dict(metrics)
    learning = metrics.pop("learning")
    w = learning / jp.maximum(learning.sum(), 1.0)
    out = {k: jp.sum(v * w) for k, v in metrics.items()}
    out["eps"] = jp.mean(ts.eps)
    out["alpha"] = jp.exp(ts.learner.log_alpha)
    out["finite"] = _all_finite(ts.learner)
    return ts, out

  def chunk(ts: TrainState):
    return summarize(*jax.lax.scan(iteration, ts, None, cfg.train.iters_per_chunk))

  return sac, init, chunk, iteration, summarize


def _scan_chunks(cfg: Config) -> bool:
  """Whether a chunk runs as one `lax.scan` program. On XLA's CPU backend convolutions
  inside a loop run ~20-100x slower (jax-ml/jax#12868), so there the host loops over the
  jitted iteration instead; accelerators scan."""
  if cfg.train.chunk_loop == "auto":
    return jax.default_backend() != "cpu"
  return cfg.train.chunk_loop == "scan"


@functools.lru_cache(maxsize=4)
def _compiled(cfg: Config, seeds: int, env=None):
  env = VineyardEnv(cfg) if env is None else env
  mesh = parallel.make_mesh(cfg.train.devices)
  parallel.check_divisible(mesh, cfg.env.num_envs, cfg.sac.batch_size)
  sac, init, chunk, iteration, summarize = make_trainer(
      cfg, env, parallel.batch_constraint(mesh, seeds))
  batch = (lambda f: f) if seeds == 1 else jax.vmap
  init_one = (lambda k: init(k[0])) if seeds == 1 else jax.vmap(init)
  keys = jax.ShapeDtypeStruct((seeds, 2), jp.uint32)
  shard = parallel.train_state_sharding(jax.eval_shape(init_one, keys), mesh, seeds)
  init_fn = jax.jit(init_one, out_shardings=shard)
  # Donating the state lets XLA update the replay buffer in place instead of copying it;
  # pinning its sharding keeps envs and replay rows on their devices between calls.
  jit_state = functools.partial(jax.jit, donate_argnums=0, out_shardings=(shard, None))
  if _scan_chunks(cfg):
    return sac, init_fn, jit_state(batch(chunk))
  step_fns = {learn: jit_state(batch(functools.partial(iteration, learn_now=learn)))
              for learn in (False, True)}
  summarize_fn = jax.jit(batch(summarize))
  n = cfg.env.num_envs

  def host_chunk(ts):
    rows = []
    steps = int(np.max(jax.device_get(ts.env_steps)))
    for _ in range(cfg.train.iters_per_chunk):
      # the same rule as on device: past the warm-up, and a full batch in the replay
      inserted = steps // n + 1
      sampleable = (min(inserted, cfg.sac.buffer_size // n) - 1) * n
      learn = steps + n >= cfg.sac.warmup_steps and sampleable >= cfg.sac.batch_size
      ts, m = step_fns[learn](ts, None)
      steps += n
      rows.append(m)
    # iterations axis after the seeds axis, if any
    stacked = jax.tree.map(lambda *x: jp.stack(x, axis=0 if seeds == 1 else 1), *rows)
    return summarize_fn(ts, stacked)

  return sac, init_fn, host_chunk


def compiled_trainer(cfg: Config, seeds: int = 1, env=None):
  """(sac, init(keys (seeds, 2)), chunk) jitted, cached per process on everything that
  shapes the compiled program (so a resume in the same process does not recompile).
  `env`: the config's `VineyardEnv` by default, or e.g. a `BraxAdapter`."""
  return _compiled(replace(cfg, train={"total_env_steps": 1, "checkpoint_every_chunks": 1,
                                       "save_replay": False, "sweep": "", "num_seeds": 1,
                                       "max_minutes": 0.0},
                           eval={"runs_after_train": 0}), seeds, env)


def _zero_metrics(sac, learner, buffer, key):
  shapes = jax.eval_shape(lambda: sac.update_many(learner, buffer, key)[1])
  return jax.tree.map(lambda s: jp.zeros(s.shape, s.dtype), shapes)


def _all_finite(tree) -> jax.Array:
  leaves = [jp.all(jp.isfinite(x)) for x in jax.tree.leaves(tree)
            if jp.issubdtype(x.dtype, jp.floating)]
  return jp.all(jp.stack(leaves))


# ---------------------------------------------------------------------- checkpoints
class Checkpoints:
  """Orbax checkpoints of the TrainState under RUN_DIR/checkpoints/<step>, written
  atomically (orbax finalises a step only once complete). Restoring falls back to the
  previous step, with a message, when the newest is corrupt or partial."""

  def __init__(self, run_dir: Path, save_replay: bool, keep: int = 3):
    import orbax.checkpoint as ocp
    self.ocp = ocp
    self.dir = (run_dir / "checkpoints").resolve()
    self.save_replay = save_replay
    self.manager = ocp.CheckpointManager(
        self.dir, options=ocp.CheckpointManagerOptions(max_to_keep=keep, create=True))

  def _payload(self, ts) -> dict:
    """{"learner": LearnerState, "state": {index: array}}: the learner keeps its field
    names (`mjxvine.export` finds `actor_params` there); the rest is flattened, because
    orbax cannot store the zero-size arrays of MJX data."""
    rest = ts.replace(learner=None, buffer=None if not self.save_replay else ts.buffer)
    leaves = jax.tree.leaves(rest)
    return {"learner": ts.learner,
            "state": {f"{i:05d}": x for i, x in enumerate(leaves) if x.size > 0}}

  def _unpayload(self, payload: dict, template):
    rest = template.replace(learner=None,
                            buffer=None if not self.save_replay else template.buffer)
    leaves, treedef = jax.tree.flatten(rest)
    leaves = [payload["state"].get(f"{i:05d}", x) for i, x in enumerate(leaves)]
    ts = jax.tree.unflatten(treedef, leaves).replace(learner=payload["learner"])
    return ts if self.save_replay else ts.replace(buffer=template.buffer)

  def save(self, step: int, ts) -> None:
    self.manager.save(step, args=self.ocp.args.StandardSave(self._payload(ts)))
    self.manager.wait_until_finished()

  def restore(self, template):
    """(step, TrainState) of the latest good checkpoint, restored onto `template` (a fresh
    TrainState of the same config), or None."""
    abstract = jax.tree.map(
        lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding),
        self._payload(template))
    for step in sorted(self.manager.all_steps(), reverse=True):
      try:
        payload = self.manager.restore(step, args=self.ocp.args.StandardRestore(abstract))
      except Exception as e:  # noqa: BLE001 - any failure means this step is unusable
        print(f"checkpoint {step} is corrupt or partial ({type(e).__name__}: "
              f"{str(e).splitlines()[0][:120]}); trying the previous one", file=sys.stderr)
        continue
      return step, self._unpayload(payload, template)
    return None


# ---------------------------------------------------------------------- logging
class Logger:
  """metrics.jsonl + TensorBoard (tensorboardX) + a progress line."""

  def __init__(self, run_dir: Path, total: int, start: int, enabled: bool = True):
    self.enabled = enabled
    if not enabled:
      return
    from tensorboardX import SummaryWriter
    from tqdm import tqdm
    self.jsonl = open(run_dir / "metrics.jsonl", "a")
    self.tb = SummaryWriter(str(run_dir / "tb"))
    self.bar = tqdm(total=total, initial=start, unit="step", dynamic_ncols=True,
                    mininterval=2.0, file=sys.stderr)

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
    self.bar.set_postfix_str(
        f"sps {row['sps']:.0f} ups {row['ups']:.0f} ret {_f(row['return_mean'])} "
        f"succ {_f(row['success_rate'])} eps {row['eps']:.2f} alpha {row['alpha']:.3f} "
        f"Lq {row['critic_loss']:.3g} Lpi {row['actor_loss']:.3g}", refresh=True)

  def close(self):
    if not self.enabled:
      return
    self.bar.close()
    self.tb.close()
    self.jsonl.close()


def _f(x):
  return "-" if x is None else f"{x:.2f}"


def plot_learning_curve(run_dir: Path) -> None:
  """learning_curve.png from metrics.jsonl: return, success rate and losses."""
  import matplotlib.pyplot as plt
  rows = [json.loads(l) for l in (run_dir / "metrics.jsonl").read_text().splitlines() if l]
  if not rows:
    return
  members = sorted({r.get("member", r.get("seed", 0)) for r in rows})
  fig, axes = plt.subplots(1, 3, figsize=(14, 3.6))
  for s in members:
    rs = [r for r in rows if r.get("member", r.get("seed", 0)) == s]
    x = [r["env_steps"] for r in rs]
    label = ", ".join(f"{k.split('.')[-1]} {v:g}" for k, v in rs[0].items()
                      if k.startswith("sac.")) or f"seed {rs[0].get('seed', s)}"
    if any(k.startswith("sac.") for k in rs[0]):
      label += f", seed {rs[0].get('seed', 0)}"
    for ax, key in zip(axes, ("return_mean", "success_rate", "critic_loss")):
      ax.plot(x, [np.nan if r[key] is None else r[key] for r in rs], label=label)
  for ax, title in zip(axes, ("episode return", "success rate", "critic loss")):
    ax.set_title(title)
    ax.set_xlabel("env steps")
  axes[2].set_yscale("log")
  if len(members) > 1:
    axes[0].legend(fontsize=7)
  fig.tight_layout()
  fig.savefig(run_dir / "learning_curve.png", dpi=110)
  plt.close(fig)


# ---------------------------------------------------------------------- the run
def sweep_members(cfg: Config) -> list[dict]:
  """The runs trained at once: every combination of `train.sweep`'s values, each with
  `train.num_seeds` seeds. One dict per member: {"seed": i, "sac.learning_rate": ...}."""
  grid = parse_sweep(cfg.train.sweep)
  combos = [dict(zip(grid, values)) for values in itertools.product(*grid.values())]
  return [{"seed": s, **combo} for combo in combos for s in range(cfg.train.num_seeds)]


def init_members(cfg: Config, init_fn, members: list[dict]):
  """The initial TrainState of every member (a leading members axis if more than one):
  member seeds share keys across sweep values, so a sweep compares like with like."""
  keys = jax.random.split(jax.random.PRNGKey(cfg.train.seed), cfg.train.num_seeds)
  ts = init_fn(keys[np.array([m["seed"] for m in members])])
  values = lambda k: (np.array([m[k] for m in members], np.float32)
                      if k in members[0] else None)
  lr, alpha = values("sac.learning_rate"), values("sac.alpha")
  if lr is None and alpha is None:
    return ts
  learner = sac_lib.with_hyperparams(ts.learner, learning_rate=lr, alpha=alpha)
  return ts.replace(learner=jax.device_put(learner, jax.tree.map(lambda x: x.sharding,
                                                                  ts.learner)))


def train(cfg: Config, run_dir: Path, *, resume: bool = False, evaluate_at_end: bool = True,
          quiet: bool = False, env=None) -> dict:
  """Trains (or resumes) a run; returns the final log row of member 0. Trains
  `train.num_seeds` seeds times the `train.sweep` grid at once (vmap). `env` defaults to
  the config's vineyard pool; another env (a `BraxAdapter`) trains the same way, without
  the vineyard evaluation at the end."""
  run_dir.mkdir(parents=True, exist_ok=True)
  (run_dir / "config.yaml").write_text(to_yaml(cfg))
  members = sweep_members(cfg)
  seeds = len(members)
  sac, init_fn, chunk_fn = compiled_trainer(cfg, seeds, env)
  evaluate_at_end = evaluate_at_end and env is None
  ts = init_members(cfg, init_fn, members)
  nbytes = sac_lib.buffer_nbytes(ts.buffer)
  ckpt = Checkpoints(run_dir, cfg.train.save_replay)
  chunk_index = 0
  if resume:
    restored = ckpt.restore(ts)
    if restored is None:
      print(f"no usable checkpoint in {run_dir}; starting afresh", file=sys.stderr)
    else:
      chunk_index, ts = restored
      print(f"resumed {run_dir} at chunk {chunk_index} "
            f"({int(np.max(ts.env_steps))} env steps)", file=sys.stderr)
  steps_per_chunk = cfg.env.num_envs * cfg.train.iters_per_chunk
  total_chunks = math.ceil(cfg.train.total_env_steps / steps_per_chunk)
  if not quiet:
    print(f"run {run_dir}: {seeds} seed(s) x {cfg.env.num_envs} envs, {total_chunks} chunks of "
          f"{steps_per_chunk} env steps; replay {nbytes / 2**20:.1f} MiB per seed "
          f"({nbytes / max(cfg.sac.buffer_size, 1):.0f} B/transition); device "
          f"{jax.devices()[0].device_kind} x {cfg.train.devices or jax.device_count()}",
          file=sys.stderr)
  # Multi-host: every process runs the same program; process 0 writes logs and reports.
  primary = jax.process_index() == 0
  logger = Logger(run_dir, total_chunks * steps_per_chunk, chunk_index * steps_per_chunk,
                  enabled=primary)
  last_row, t_compile, t_start = {}, None, time.time()
  try:
    while chunk_index < total_chunks:
      if cfg.train.max_minutes and time.time() - t_start > 60 * cfg.train.max_minutes:
        print(f"train.max_minutes = {cfg.train.max_minutes} reached after chunk "
              f"{chunk_index}: stopping", file=sys.stderr)
        if ckpt.manager.latest_step() != chunk_index:
          ckpt.save(chunk_index, ts)
        break
      t0 = time.time()
      ts, m = chunk_fn(ts)
      m = jax.device_get(m)
      dt = time.time() - t0
      if t_compile is None:
        t_compile = dt
      if not np.all(m["finite"]) or not all(np.all(np.isfinite(v)) for v in m.values()):
        bad = [k for k, v in m.items() if not np.all(np.isfinite(v))]
        raise NonFiniteError(
            f"non-finite {'parameters' if not np.all(m['finite']) else ', '.join(bad)} at "
            f"env step {int(np.max(ts.env_steps))} (chunk {chunk_index + 1}); the last good "
            f"checkpoint is chunk {ckpt.manager.latest_step()} in {ckpt.dir}")
      chunk_index += 1
      host = jax.device_get((ts.env_steps, ts.episodes, ts.log_episodes, ts.log_return,
                             ts.log_success))
      for s in range(seeds):
        get = (lambda x: np.reshape(x, (-1,))[s])
        eps_done = int(get(host[2]))
        row = {
            **members[s], "member": s,
            "chunk": chunk_index, "env_steps": int(get(host[0])),
            "episodes": int(get(host[1])),
            "return_mean": float(get(host[3]) / eps_done) if eps_done else None,
            "success_rate": float(get(host[4]) / eps_done) if eps_done else None,
            "sps": steps_per_chunk / dt,
            "ups": cfg.train.iters_per_chunk * cfg.sac.grad_steps_per_iter / dt,
            "chunk_s": dt, "compile_s": t_compile,
            "wall": datetime.datetime.now().isoformat(timespec="seconds"),
        }
        row.update({k: float(get(v)) for k, v in m.items() if k != "finite"})
        if s == 0:
          last_row = row
        logger.log(row)
      ts = ts.replace(log_episodes=jp.zeros_like(ts.log_episodes),
                      log_return=jp.zeros_like(ts.log_return),
                      log_success=jp.zeros_like(ts.log_success))
      if chunk_index % cfg.train.checkpoint_every_chunks == 0 or chunk_index == total_chunks:
        ckpt.save(chunk_index, ts)
  finally:
    logger.close()
  if not primary:
    return last_row
  plot_learning_curve(run_dir)
  if evaluate_at_end and cfg.eval.runs_after_train > 0:
    from mjxvine import evaluate as ev
    from mjxvine.worlds import load_test_world
    world = load_test_world(cfg.world)
    actor = jax.tree.map(lambda x: x[0], ts.learner.actor_params) if seeds > 1 else \
        ts.learner.actor_params
    doc = ev.evaluate(cfg, "checkpoint", world, runs=cfg.eval.runs_after_train,
                      noise_factor=cfg.eval.noise_factor,
                      policy=_actor_policy(sac, actor))
    doc["policy"] = f"{run_dir} (seed 0)"
    ev.write_results(doc, world, run_dir / "eval")
    last_row["eval_success"] = doc["overall"]["success"]
    last_row["eval_runs"] = doc["overall"]["runs"]
    if not quiet:
      print(ev.results_markdown(doc), file=sys.stderr)
  return last_row


def _actor_policy(sac, actor_params):
  def policy(state, key):
    del key
    return sac.act_deterministic(actor_params, state.obs)
  return policy


def main(argv=None) -> int:
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
  p.add_argument("--distributed", action="store_true",
                 help="multi-host: call jax.distributed.initialize() (coordinator, process "
                 "count and id from the cluster environment) and train over every host's "
                 "devices")
  args = p.parse_args(argv)
  if args.distributed:
    jax.distributed.initialize()
  if args.resume:
    run_dir = Path(args.resume)
    resolved = run_dir / "config.yaml"
    if not resolved.is_file():
      raise SystemExit(f"--resume {run_dir}: no config.yaml there (not a run directory)")
    old = load_config(resolved)
    cfg = config_from_args(argparse.Namespace(config=str(resolved), overrides=args.overrides))
    changed = [f"{s}.{k}" for s in ("world", "robot", "camera", "env", "sac", "train", "eval")
               for k, v in vars(getattr(cfg, s)).items() if getattr(getattr(old, s), k) != v]
    if any(c not in ("train.total_env_steps", "train.max_minutes", "eval.runs_after_train")
           for c in changed):
      raise SystemExit(f"--resume: only train.total_env_steps may change, not {changed}")
  else:
    if args.config is None and DEFAULT_CONFIG.is_file():
      args.config = str(DEFAULT_CONFIG)
    extra = [f"train.num_seeds={args.seeds}"] if args.seeds else []
    if args.sweep:
      extra.append("train.sweep=" + "; ".join(args.sweep))
    cfg = config_from_args(args, extra)
    run_dir = Path(args.run_dir or f"runs/{datetime.datetime.now():%Y%m%d-%H%M%S}")
    if (run_dir / "checkpoints").exists():
      raise SystemExit(f"{run_dir} already holds a run: use --resume {run_dir} or another "
                       "--run-dir")
  if args.resume and (args.seeds or args.sweep):
    raise SystemExit("--resume: the seeds and sweep come from the run's config.yaml")
  try:
    row = train(cfg, run_dir, resume=bool(args.resume), evaluate_at_end=not args.no_eval)
  except NonFiniteError as e:
    print(f"error: {e}", file=sys.stderr)
    return 3
  print(json.dumps({k: row.get(k) for k in ("env_steps", "episodes", "return_mean",
                                            "success_rate", "sps", "eval_success")}))
  return 0


if __name__ == "__main__":
  sys.exit(main())
