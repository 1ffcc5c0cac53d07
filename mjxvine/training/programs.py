"""The compiled programs of a run, cached per process on everything that shapes them (so a
resume or a second run of the same config in one process does not recompile): the
trainer's init and chunk (`compiled_trainer`) and the evaluation from fresh starts
(`start_evaluator`)."""

from __future__ import annotations

import functools

import jax.numpy as jp

from mjxvine.config import Config, replace
from mjxvine.episodes import TrainEnv
from mjxvine.evaluation import starts
from mjxvine.training.iteration import compile_key, compiled


@functools.lru_cache(maxsize=4)
def default_env(cfg: Config) -> TrainEnv:
  """The config's vineyard pool (`env.training_env`): the run's default env."""
  from mjxvine.env import training_env  # the env's imports are heavy: only when needed
  return training_env(cfg)


def compiled_trainer(cfg: Config, seeds: int = 1, env=None):
  """(sac, init(keys (seeds, 2)), chunk) jitted. `env`: the config's vineyard
  (`default_env`) by default, or any `episodes.TrainEnv` (e.g. `wrappers.brax_env(...)`)."""
  key = compile_key(cfg)
  return compiled(key, seeds, default_env(key) if env is None else env)


@functools.lru_cache(maxsize=4)
def _start_evaluator(cfg: Config, seeds: int, env):
  sac = compiled_trainer(cfg, seeds, env)[0]
  act = starts.with_baselines(sac.act_deterministic, env.action_low, env.action_high)
  return starts.make_start_eval(env, act, cfg.train.eval_starts, seeds)


def start_evaluator(cfg: Config, seeds: int = 1):
  """The evaluation from `train.eval_starts` fresh starts per direction of a run of `cfg`
  (`mjxvine.evaluation.starts`): run(starts_params(actor params, policy, seeds), key) ->
  dict; policy `starts.ACTOR`, or a baseline (`starts.BASELINES`)."""
  key = compile_key(cfg)
  return _start_evaluator(replace(key, train={"eval_starts": cfg.train.eval_starts}), seeds,
                          default_env(key))


def starts_params(actor_params, policy: int, seeds: int = 1) -> dict:
  """The parameters of `start_evaluator`'s run: which policy, for every member."""
  return {"actor": actor_params,
          "policy": jp.full((seeds,) if seeds > 1 else (), policy, jp.int32)}
