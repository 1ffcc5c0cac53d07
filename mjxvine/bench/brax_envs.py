"""`bench brax`: brax's own SAC and mjxvine's SAC with one schedule on the
vector-observation vineyard task (`VectorObsEnv`), both scored by brax's `Evaluator`:
success rate against env steps and training seconds, and the env steps and wall-clock to
a common success rate (`--target`) as ratios (brax / mjxvine)."""

from __future__ import annotations

import argparse
import contextlib
import time
from pathlib import Path

import jax
import jax.numpy as jp

from mjxvine import config as config_lib
from mjxvine.bench.common import EXPERIMENTS, positive_int, size


def add_brax_args(p: argparse.ArgumentParser) -> None:
  p.add_argument("--steps", type=positive_int, default=20_000, help="env steps per learner")
  p.add_argument("--evals", type=positive_int, default=10, help="evaluations along the way")
  p.add_argument("--eval-envs", type=positive_int, default=64, help="episodes per evaluation")
  p.add_argument("--pool", default="8x8", type=size,
                 help="depth average-pooled to HxW cells")
  p.add_argument("--target", type=float, default=0.5,
                 help="success rate whose env steps and wall-clock are compared")
  p.set_defaults(config=str(EXPERIMENTS / "compare.yaml"))


def bench_brax(args: argparse.Namespace, cfg: config_lib.Config) -> list[dict]:
  """brax's SAC (`brax.training.agents.sac`) and mjxvine's SAC side by side on the same
  vineyard task, with the same schedule (envs, batch, gradient steps per env step,
  learning rate, gamma, tau, replay, warm-up, reward scale, automatic temperature), both
  evaluated by brax's own `Evaluator` (deterministic policy, `--eval-envs` episodes).

  brax's SAC takes vector observations only, so both learn on `VectorObsEnv`: the depth
  image average-pooled to `--pool` cells plus the state (the paper's conv tower cannot
  be given to brax's SAC). Each row is one evaluation: env steps, training wall-clock
  (compilation included, evaluation excluded) and success rate."""
  import tempfile  # pylint: disable=import-outside-toplevel
  from brax import envs as brax_envs  # pylint: disable=import-outside-toplevel
  from brax.training.acting import Evaluator  # pylint: disable=import-outside-toplevel
  from brax.training.agents.sac import train as brax_sac  # pylint: disable=import-outside-toplevel
  from mjxvine import wrappers  # pylint: disable=import-outside-toplevel
  from mjxvine.env import VectorObsEnv  # pylint: disable=import-outside-toplevel
  from mjxvine.rundir import checkpoints as checkpoint  # pylint: disable=import-outside-toplevel
  from mjxvine.evaluation import policies  # pylint: disable=import-outside-toplevel
  from mjxvine.training import loop, programs  # pylint: disable=import-outside-toplevel

  pool = tuple(int(x) for x in args.pool.split("x"))
  venv = VectorObsEnv(cfg, pool)
  c, length, n = cfg.sac, cfg.env.max_steps, cfg.env.num_envs
  per_eval = args.steps // args.evals
  rows: list[dict] = []

  # brax: progress_fn runs after each evaluation; "training/walltime" is brax's own clock
  # of its training epochs (compilation included, evaluation excluded).
  def progress(step, metrics):
    rows.append(dict(learner="brax.sac", env_steps=int(step),
                     train_s=float(metrics.get("training/walltime", 0.0)),
                     success=float(metrics["eval/episode_success"]),
                     episode_return=float(metrics["eval/episode_reward"])))

  with brax_jax_compat():
    brax_sac.train(
        environment=venv, num_timesteps=args.steps, episode_length=length, num_envs=n,
        num_eval_envs=args.eval_envs, learning_rate=c.learning_rate, discounting=c.gamma,
        seed=cfg.train.seed, batch_size=c.batch_size, num_evals=args.evals + 1,
        reward_scaling=c.reward_scale, tau=c.tau, min_replay_size=c.warmup_steps,
        max_replay_size=c.buffer_size, grad_updates_per_step=c.grad_steps_per_iter,
        deterministic_eval=True, progress_fn=progress)

  # mjxvine: the same setting through wrappers.brax_env, evaluated by the same Evaluator.
  ours = config_lib.replace(
      cfg, sac={"auto_alpha": True, "alpha": 1.0, "target_entropy": -1.0, "eps_start": 0.0,
                "eps_min": 0.0},
      train={"iters_per_chunk": max(1, per_eval // n // 4)})
  adapter = wrappers.brax_env(venv, length)
  sac, _, _ = programs.compiled_trainer(ours, env=adapter)
  evaluator = Evaluator(
      brax_envs.training.wrap(venv, episode_length=length),
      lambda params: policies.actor_policy(sac.nets, params, brax=True),
      num_eval_envs=args.eval_envs, episode_length=length, action_repeat=1,
      key=jax.random.PRNGKey(cfg.train.seed + 1))
  run = Path(tempfile.mkdtemp(prefix="bench-brax-"))
  template = programs.compiled_trainer(ours, env=adapter)[1](
      jax.random.split(jax.random.PRNGKey(cfg.train.seed), 1))
  train_s = 0.0
  for k in range(args.evals + 1):
    steps = max(k * per_eval, 1)
    t = time.perf_counter()
    if k:
      loop.train(config_lib.replace(ours, train={"total_env_steps": steps}), run,
                      resume=k > 1, evaluate_at_end=False, quiet=True, env=adapter)
    train_s += time.perf_counter() - t
    restored = checkpoint.Checkpoints(run, False).restore(template) if k else None
    state = restored[1] if restored else template
    m = evaluator.run_evaluation(state.learner.averaged_actor_params, training_metrics={})
    rows.append(dict(learner="mjxvine.sac", env_steps=int(state.env_steps), train_s=train_s,
                     success=float(m["eval/episode_success"]),
                     episode_return=float(m["eval/episode_reward"])))
  return rows, {"summary": brax_summary(rows, args.target), "target_success": args.target}


@contextlib.contextmanager
def brax_jax_compat():
  """brax 0.14's SAC still calls `jax.device_put_replicated`, which JAX 0.10 removed;
  provide its replacement (a leading device axis, as `jax.pmap` expects) while it runs."""
  if "device_put_replicated" in vars(jax):
    yield
    return

  def device_put_replicated(x, devices):
    return jax.tree.map(lambda a: jax.device_put(jp.stack([jp.asarray(a)] * len(devices))), x)

  jax.device_put_replicated = device_put_replicated
  try:
    yield
  finally:
    del jax.device_put_replicated


def brax_summary(rows: list[dict], target: float) -> dict:
  """Env steps and training seconds each learner took to first reach `target` success,
  and mjxvine's speed-up (brax / mjxvine) where both did."""
  out = {}
  for name in ("brax.sac", "mjxvine.sac"):
    hit = [r for r in rows if r["learner"] == name and r["success"] >= target]
    out[name] = dict(env_steps=hit[0]["env_steps"], train_s=hit[0]["train_s"]) if hit else None
  if out["brax.sac"] and out["mjxvine.sac"]:
    out["wall_clock_ratio"] = out["brax.sac"]["train_s"] / max(out["mjxvine.sac"]["train_s"], 1e-9)
    out["env_steps_ratio"] = out["brax.sac"]["env_steps"] / max(out["mjxvine.sac"]["env_steps"], 1)
  return out
