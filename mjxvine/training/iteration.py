"""The trainer: SAC on any batched env (`mjxvine.episodes.TrainEnv`), as pure functions.

`make_trainer(cfg, env)` builds a `Trainer`: `init(key) -> TrainState` and `chunk(TrainState)
-> (TrainState, metrics)`, one training iteration (N env steps with exploration, one replay
insert, G gradient steps once `learning`) being one jit-compiled function and a chunk
`train.iters_per_chunk` of them under `lax.scan` (on the CPU backend a host loop of the
jitted pieces, see `scan_chunks`). `compiled(cfg, seeds, env)` jits them once per process,
vmapped over the members of a multi-seed or sweep run (`sweep_members`, `init_members`),
with envs and replay split over the devices (`mjxvine.training.parallel`). The run around
it (logs, plots, checkpoints, evaluations, resume) is `mjxvine.training.loop`.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import sys
import time
from typing import Any, Callable, NamedTuple

import flax.struct
import jax
import jax.numpy as jp
import numpy as np

from mjxvine import networks as nw
from mjxvine.training import parallel, schedules
from mjxvine import sac as sac_lib
from mjxvine.config import Config, EvalConfig, TrainConfig, parse_sweep
from mjxvine.episodes import PHYSICS, REWARD_PREFIX, SUCCESS, TIMEOUT


class TrainState(flax.struct.PyTreeNode):
  """Everything a run carries from one iteration to the next (one seed)."""
  learner: sac_lib.LearnerState
  buffer: sac_lib.ReplayBuffer
  env_state: Any
  key: jax.Array
  env_steps: jax.Array    # () int32, summed over envs
  episodes: jax.Array     # () int32 finished episodes
  budget: jax.Array       # () float32 train.total_env_steps, for the epsilon schedule
  # Sums since the last log (reset by the host): finished episodes, their returns,
  # successes and time-outs; commanded speed (m/s) and the env's named reward terms
  # ({"reward/heading": ...}, unscaled) summed over every env step.
  log_episodes: jax.Array
  log_return: jax.Array
  log_success: jax.Array
  log_timeout: jax.Array
  log_speed: jax.Array
  log_terms: dict

  def reset_log(self) -> "TrainState":
    zero = jp.zeros_like
    return self.replace(log_episodes=zero(self.log_episodes), log_return=zero(self.log_return),
                        log_success=zero(self.log_success), log_timeout=zero(self.log_timeout),
                        log_speed=zero(self.log_speed),
                        log_terms=jax.tree.map(zero, self.log_terms))


def learning(cfg: Config, env_steps, rows_written):
  """Whether the iteration that starts at `env_steps` (summed over envs), after its insert
  brought the replay to `rows_written` rows, takes gradient steps: past the warm-up, with
  a full batch sampleable. The one rule of the device (traced) and host (ints) paths."""
  n = cfg.env.num_envs
  sampleable = (jp.minimum(rows_written, cfg.sac.buffer_size // n) - 1) * n
  return (env_steps + n >= cfg.sac.warmup_steps) & (sampleable >= cfg.sac.batch_size)


class NonFiniteError(RuntimeError):
  """A loss or a parameter became NaN or infinite."""


def make_learner(cfg: Config, env, shard_batch=lambda batch: batch) -> sac_lib.SAC:
  """SAC (`mjxvine.sac.make_sac`) of the config's networks on the env's action box (the
  vineyard's [0, v_max] x [-w_max, w_max], or [-1, 1] for a brax env behind
  `wrappers.brax_env`), with the env's mirror maps when it has them."""
  nets = nw.make_networks_from_config(cfg, nw.learner_conv_impl(cfg.train.conv_impl),
                                      box=(env.action_low, env.action_high))
  mirror = ((env.mirror_obs, env.mirror_action) if hasattr(env, "mirror_obs") else None)
  return sac_lib.make_sac(nets, cfg.sac, shard_batch=shard_batch, mirror=mirror)


def init_state(cfg: Config, env, sac, key: jax.Array) -> TrainState:
  """A fresh TrainState of one member: N = env.num_envs envs reset, new networks, an
  empty replay, zero counters."""
  n = cfg.env.num_envs
  k_env, k_learner, k_run = jax.random.split(key, 3)
  env_state = env.reset_batch(k_env, n)
  learner = sac.init(k_learner, env_state.obs)
  buffer = sac_lib.init_buffer(env_state.obs, env.action_size, cfg.sac.buffer_size,
                               cfg.camera.max_depth_m,
                               depth_dtype=jp.dtype(cfg.sac.replay_depth_dtype))
  z, zf = jp.zeros((), jp.int32), jp.zeros((), jp.float32)
  return TrainState(learner=learner, buffer=buffer, env_state=env_state, key=k_run,
                    env_steps=z, episodes=z, budget=zf, log_episodes=z, log_return=zf,
                    log_success=z, log_timeout=z, log_speed=zf,
                    log_terms={k: zf for k in _reward_terms(env_state)})


def collect_step(cfg: Config, env, sac, ts: TrainState):
  """One env step of the N envs with exploration, inserted into the replay. Returns the
  new state, the key of this iteration's gradient steps and whether they are due."""
  n = cfg.env.num_envs
  key, k_act, k_explore, k_update = jax.random.split(ts.key, 4)
  obs = ts.env_state.obs
  policy_action = sac.act(ts.learner.actor_params, obs, k_act)
  # a loaded agent (train.init_from) warms the replay up with its own driving
  in_warmup = (ts.env_steps < cfg.sac.warmup_steps) if not cfg.train.init_from else False
  eps = schedules.epsilon(cfg.sac, ts.env_steps, ts.budget)
  action = schedules.explore_action(k_explore, policy_action, eps, env.action_low,
                                  env.action_high, in_warmup)
  env_state, final_obs = env.step_batch(ts.env_state, action)
  done = env_state.done > 0
  truncated = done & (env_state.info["truncation"] > 0)
  outcome = env_state.info["last_outcome"]
  # A physics reset's successor is the restored old state: nothing to learn from.
  weight = jp.where(done & (outcome == PHYSICS), 0.0, 1.0)
  tr = sac_lib.Transition(obs=obs, action=action,
                          reward=env_state.reward * cfg.sac.reward_scale,
                          terminal=(done & ~truncated).astype(jp.float32),
                          truncated=truncated.astype(jp.float32), next_obs=final_obs,
                          weight=weight)
  buffer = sac_lib.insert(ts.buffer, tr)
  learn = learning(cfg, ts.env_steps, buffer.rows_written)
  ts = ts.replace(
      buffer=buffer, env_state=env_state, key=key,
      env_steps=ts.env_steps + n, episodes=ts.episodes + done.sum(),
      log_episodes=ts.log_episodes + done.sum(),
      log_return=ts.log_return + jp.sum(jp.where(done, env_state.info["last_return"], 0.0)),
      log_success=ts.log_success + jp.sum(done & (outcome == SUCCESS)),
      log_timeout=ts.log_timeout + jp.sum(done & (outcome == TIMEOUT)),
      log_speed=ts.log_speed + jp.sum(action[:, 0]),
      log_terms={k: v + jp.sum(env_state.metrics[k]) for k, v in ts.log_terms.items()})
  return ts, k_update, learn


class Trainer(NamedTuple):
  """The pieces of one training iteration (N env steps, one replay insert, then, once
  `learning`, G = sac.grad_steps_per_iter gradient steps), as pure functions:

  init(key) -> TrainState                 a fresh member
  chunk(ts) -> (ts, metrics)              `train.iters_per_chunk` iterations, one program
  collect(ts) -> (ts, k_update, learn)    the env step and the replay insert
  learn_step(ts, key) -> (ts, metrics)    one gradient step (key: one of split(k_update, G))
  learn_steps(ts, k_update) -> (ts, m)    the G gradient steps in one program
  summarize(ts, metrics) -> (ts, m)       a chunk's metrics from its iterations'
  The host path (`compiled` on the CPU) calls collect, then learn_step(s), then summarize.
  """
  sac: sac_lib.SAC
  init: Callable
  chunk: Callable
  collect: Callable
  learn_step: Callable
  learn_steps: Callable
  summarize: Callable


def make_trainer(cfg: Config, env, shard_batch=lambda batch: batch) -> Trainer:
  """The `Trainer` of `cfg` on `env`. `shard_batch`: see `mjxvine.sac.make_sac` (data
  parallelism over devices)."""
  sac = make_learner(cfg, env, shard_batch)
  init = functools.partial(init_state, cfg, env, sac)
  collect = functools.partial(collect_step, cfg, env, sac)

  def tau(ts: TrainState):
    """This iteration's target-critic rate (`schedules.target_rate`)."""
    return schedules.target_rate(cfg.sac, ts.env_steps, ts.budget)

  def learn_step(ts: TrainState, key: jax.Array):
    learner, metrics = sac.update_from(ts.learner, ts.buffer, key, tau(ts))
    return ts.replace(learner=learner), metrics

  def learn_steps(ts: TrainState, k_update: jax.Array):
    learner, metrics = sac.update_many(ts.learner, ts.buffer, k_update, tau(ts))
    return ts.replace(learner=learner), metrics

  def iteration(ts: TrainState, _):
    """collect, then G gradient steps if due (lax.cond): the device path."""
    ts, k_update, learn = collect(ts)
    learner, metrics = jax.lax.cond(
        learn, lambda: sac.update_many(ts.learner, ts.buffer, k_update, tau(ts)),
        lambda: (ts.learner, _zero_metrics(sac, ts.learner, ts.buffer, k_update)))
    metrics["learning"] = learn.astype(jp.float32)
    return ts.replace(learner=learner), metrics

  def summarize(ts: TrainState, metrics: dict):
    """Chunk metrics: losses averaged over the iterations that learned."""
    metrics = dict(metrics)
    learning = metrics.pop("learning")
    w = learning / jp.maximum(learning.sum(), 1.0)
    out = {k: jp.sum(v * w) for k, v in metrics.items()}
    out["eps"] = schedules.epsilon(cfg.sac, ts.env_steps, ts.budget)
    out["tau"] = jp.asarray(tau(ts), jp.float32)
    out["alpha"] = jp.exp(ts.learner.log_alpha)
    out["finite"] = _all_finite(ts.learner)
    return ts, out

  def chunk(ts: TrainState):
    return summarize(*jax.lax.scan(iteration, ts, None, cfg.train.iters_per_chunk))

  return Trainer(sac, init, chunk, collect, learn_step, learn_steps, summarize)


def scan_chunks() -> bool:
  """Whether a chunk runs as one `lax.scan` program. On XLA's CPU backend convolutions
  inside a loop run ~20-100x slower (jax-ml/jax#12868), so there the host loops over the
  jitted iteration instead; accelerators scan."""
  return jax.default_backend() != "cpu"


@functools.lru_cache(maxsize=4)
def compiled(cfg: Config, seeds: int, env):
  mesh = parallel.make_mesh(cfg.train.devices)
  parallel.check_divisible(mesh, cfg.env.num_envs, cfg.sac.batch_size)
  trainer = make_trainer(cfg, env, parallel.batch_constraint(mesh, seeds))
  sac = trainer.sac
  batch = (lambda f: f) if seeds == 1 else jax.vmap
  init_one = (lambda k: trainer.init(k[0])) if seeds == 1 else jax.vmap(trainer.init)
  keys = jax.ShapeDtypeStruct((seeds, 2), jp.uint32)
  abstract = jax.eval_shape(init_one, keys)
  shard = parallel.train_state_sharding(abstract, mesh, seeds)
  init_fn = jax.jit(init_one, out_shardings=shard)
  # Donating the state lets XLA update the replay buffer in place instead of copying it;
  # pinning its sharding keeps envs and replay rows on their devices between calls.
  jit_state = lambda f, outs, **kw: jax.jit(f, donate_argnums=0,
                                            out_shardings=(shard, *outs), **kw)
  # the programs with gradient steps: on the CPU without YNNPACK's convolutions
  learner_options = dict(compiler_options=nw.learner_compiler_options())
  if scan_chunks():
    return sac, init_fn, jit_state(batch(trainer.chunk), (None,), **learner_options)
  # The host path: the env step and the gradient steps are separate programs, so each is
  # compiled once. The G gradient steps of an iteration are one call of a loop where the
  # towers are the native kernel; else G calls of one step (no XLA convolution in a loop
  # body), at the cost of a dispatch, and the state's arguments parsed, per step.
  g = cfg.sac.grad_steps_per_iter
  one_call = nw.native_towers(sac.nets)
  collect_fn = jit_state(batch(trainer.collect), (None, None))
  learn_fn = jit_state(batch(trainer.learn_steps if one_call else trainer.learn_step), (None,),
                       **learner_options)
  split_fn = jax.jit(batch(lambda k: jax.random.split(k, g)))
  summarize_fn = jax.jit(batch(trainer.summarize))
  lead = () if seeds == 1 else (seeds,)
  metric_shapes = jax.eval_shape(batch(trainer.learn_step), abstract,
                                 jax.ShapeDtypeStruct(lead + (2,), jp.uint32))[1]
  idle = {k: jp.zeros(v.shape, v.dtype) for k, v in metric_shapes.items()}
  idle["learning"] = jp.zeros(lead)
  n = cfg.env.num_envs
  called = set()  # the programs called once (compiled): their first call is "compile"

  def host_chunk(ts, profile=None):
    """One chunk on the host path. With `profile` (`training.profile.Profile`) each call
    is timed to the end of its work and added to "compile" (a program's first call),
    "collection" or "gradient_steps" (the loop adds the host's bookkeeping around them)."""

    def call(phase: str, program, *args):
      t0, first = time.perf_counter(), id(program) not in called
      called.add(id(program))
      if profile is None:  # asynchronous, untimed
        return program(*args)
      out = jax.block_until_ready(program(*args))
      profile.add("compile" if first else phase, time.perf_counter() - t0)
      return out

    rows = []
    steps, written = (int(np.max(x)) for x in jax.device_get((ts.env_steps,
                                                              ts.buffer.rows_written)))
    for _ in range(cfg.train.iters_per_chunk):
      written += 1
      learn = bool(learning(cfg, steps, written))
      ts, k_update, _ = call("collection", collect_fn, ts)
      steps += n
      if not learn:
        rows.append(idle)
        continue
      if id(learn_fn) not in called and jax.process_index() == 0:  # process 0 alone prints
        print(f"learning starts at env step {steps - n}: compiling the gradient step...",
              file=sys.stderr, flush=True)
      if one_call:
        ts, m = call("gradient_steps", learn_fn, ts, k_update)
        rows.append({**m, "learning": jp.ones(lead)})
        continue
      keys = split_fn(k_update)
      for i in range(g):
        ts, m = call("gradient_steps", learn_fn, ts, keys[i] if seeds == 1 else keys[:, i])
        rows.append({**m, "learning": jp.ones(lead)})
    # iterations axis after the seeds axis, if any
    stacked = jax.tree.map(lambda *x: jp.stack(x, axis=0 if seeds == 1 else 1), *rows)
    return summarize_fn(ts, stacked)

  return sac, init_fn, host_chunk


# The train.* keys that shape the compiled program; every other train.* key, and eval.*,
# is read only by what runs around the compiled chunks (budget, files, evaluations, choice).
PROGRAM_TRAIN_KEYS = ("iters_per_chunk", "devices", "conv_impl", "init_from")


def compile_key(cfg: Config) -> Config:
  """`cfg` as far as it shapes the compiled program: the world, robot, camera, env and sac
  sections, `PROGRAM_TRAIN_KEYS` of train (with the conv tower `train.conv_impl: auto`
  takes here: the same program either way); train's other keys and eval at defaults."""
  cfg = nw.resolve_conv_impl(cfg)
  return dataclasses.replace(
      cfg, train=TrainConfig(**{k: getattr(cfg.train, k) for k in PROGRAM_TRAIN_KEYS}),
      eval=EvalConfig())


def _reward_terms(env_state) -> list[str]:
  """The env's named reward terms ("reward/<term>" metrics), if it has any."""
  return sorted(k for k in env_state.metrics if k.startswith(REWARD_PREFIX))


def _zero_metrics(sac, learner, buffer, key):
  shapes = jax.eval_shape(lambda: sac.update_many(learner, buffer, key)[1])
  return jax.tree.map(lambda s: jp.zeros(s.shape, s.dtype), shapes)


def _all_finite(tree) -> jax.Array:
  leaves = [jp.all(jp.isfinite(x)) for x in jax.tree.leaves(tree)
            if jp.issubdtype(x.dtype, jp.floating)]
  return jp.all(jp.stack(leaves))


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
