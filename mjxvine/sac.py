"""Soft Actor-Critic (Haarnoja et al. 2018): the losses and the update, pure functions of
pytrees, jit-able and scan-able.

  * `make_sac(nets, cfg)` -> `SAC`: `init`, `update` (one gradient step on a batch),
    `update_from` (on a replay sample), `update_many` (`sac.grad_steps_per_iter` of
    those), `act`, `act_deterministic`;
  * the losses `critic_loss`, `actor_loss`, `alpha_loss` and the target step `polyak`.
The schedules over the budget (exploration, the target critics' rate) are the trainer's
(`mjxvine.training.schedules`).

Bootstrapping: the target is `r + gamma * (1 - terminal) * (min_i Q'_i(s', a') - alpha
log pi(a'|s'))`; a time-out (`truncated`) is *not* terminal and bootstraps through
`next_obs`, which must be the true successor observation (before any auto-reset).
"""

from __future__ import annotations

import math
from typing import Any, Callable, NamedTuple

import flax.struct
import jax
import jax.numpy as jnp
import optax

from mjxvine import networks as nw
from mjxvine.config import SACConfig
# the replay buffer, part of the learner's API (`sac.init_buffer`, `sac.sample`, ...)
from mjxvine.replay import (ReplayBuffer, Transition, buffer_nbytes,  # noqa: F401
                            init_buffer, insert, num_sampleable, sample)

Params = Any
Obs = Any
Mirror = tuple[Callable, Callable]  # (mirror_obs, mirror_action) of a symmetric env


class LearnerState(flax.struct.PyTreeNode):
  """All mutable learner state. Critic params hold "critic0" and "critic1".

  `averaged_actor_params` is the Polyak average of `actor_params` at rate
  `sac.actor_ema_tau` (the learning actor itself when 0): the actor that is evaluated,
  kept as best and exported. Acting during training uses `actor_params`.
  `anchor_actor_params`: the loaded actor that `sac.anchor_weight` pulls towards (a
  frozen copy; None where the weight is 0).
  """
  actor_params: Params
  critic_params: Params
  target_critic_params: Params
  actor_opt_state: optax.OptState
  critic_opt_state: optax.OptState
  alpha_opt_state: optax.OptState
  log_alpha: jax.Array  # () float32
  step: jax.Array  # () int32, gradient steps taken
  averaged_actor_params: Params
  anchor_actor_params: Params = None


# ----------------------------------------------------------------------------------------
# Losses.


def _wmean(x: jax.Array, w: jax.Array | None) -> jax.Array:
  """Mean of x (B,) weighted by w (B,) (plain mean if w is None)."""
  if w is None:
    return jnp.mean(x)
  return jnp.sum(w * x) / jnp.maximum(jnp.sum(w), 1.0)


def critic_target(nets: nw.SACNetworks, actor_params: Params, target_critic_params: Params,
                  alpha: jax.Array, batch: Transition, key: jax.Array,
                  gamma: float) -> jax.Array:
  """Soft TD target y (B,), without gradient.

  y = r + gamma * (1 - terminal) * (min_i Q'_i(s', a') - alpha * log pi(a'|s')),
  a' ~ pi(.|s'), with batch.discount (gamma^k of an n-step transition) for gamma where
  the batch has one. Truncation does not stop bootstrapping.
  """
  mean, log_std = nets.actor.apply({"params": actor_params}, batch.next_obs)
  next_a, next_logp = nw.sample_squashed(key, mean, log_std, nets.action_low, nets.action_high)
  next_q = nets.critic.apply({"params": target_critic_params}, batch.next_obs, next_a)
  next_v = jnp.min(next_q, axis=0) - alpha * next_logp
  discount = gamma if batch.discount is None else batch.discount  # n-step: gamma^k
  y = batch.reward + discount * (1.0 - batch.terminal) * next_v
  return jax.lax.stop_gradient(y)


def critic_loss(critic_params: Params, target_critic_params: Params, actor_params: Params,
                alpha: jax.Array, batch: Transition, key: jax.Array, nets: nw.SACNetworks,
                gamma: float) -> tuple[jax.Array, dict]:
  """Twin-Q loss: 0.5 * sum_i wmean_b (Q_i(s, a) - y)^2. Returns (loss, {"q": (2, B),
  "target": (B,)})."""
  y = critic_target(nets, actor_params, target_critic_params, alpha, batch, key, gamma)
  q = nets.critic.apply({"params": critic_params}, batch.obs, batch.action)  # (2, B)
  per_sample = 0.5 * jnp.sum((q - y[None]) ** 2, axis=0)
  return _wmean(per_sample, batch.weight), {"q": q, "target": y}


def actor_loss(actor_params: Params, critic_params: Params, alpha: jax.Array, batch: Transition,
               key: jax.Array, nets: nw.SACNetworks, anchor_params: Params = None,
               anchor_weight: float = 0.0) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
  """mean_b (alpha * log pi(a|s) - min_i Q_i(s, a)), a ~ pi(.|s) reparameterised, plus
  `anchor_weight` * mean_b ||tanh(mu(s)) - tanh(mu_0(s))||^2 (`anchor_gap`: the test-time
  actions of this actor and of the frozen `anchor_params`, each dimension scaled to
  [-1, 1]) where the weight is > 0. Returns (loss, (log_prob (B,), anchor_gap ()))."""
  mean, log_std = nets.actor.apply({"params": actor_params}, batch.obs)
  a, logp = nw.sample_squashed(key, mean, log_std, nets.action_low, nets.action_high)
  q = nets.critic.apply({"params": critic_params}, batch.obs, a)
  loss = jnp.mean(alpha * logp - jnp.min(q, axis=0))
  gap = jnp.zeros(())
  if anchor_weight > 0:
    anchor_mean, _ = nets.actor.apply({"params": anchor_params}, batch.obs)
    gap = jnp.mean(jnp.sum((jnp.tanh(mean) - jnp.tanh(anchor_mean)) ** 2, axis=-1))
    loss = loss + anchor_weight * gap
  return loss, (logp, gap)


def alpha_loss(log_alpha: jax.Array, log_prob: jax.Array, target_entropy: float) -> jax.Array:
  """Temperature loss -mean(log_alpha * (log pi + target_entropy)), log_prob held fixed."""
  return -jnp.mean(log_alpha * jax.lax.stop_gradient(log_prob + target_entropy))


def polyak(target: Params, online: Params, tau: float) -> Params:
  """Soft update: target <- (1 - tau) * target + tau * online, leaf by leaf."""
  return jax.tree.map(lambda t, o: (1.0 - tau) * t + tau * o, target, online)


# ----------------------------------------------------------------------------------------
# The learner.


def networks_optimizer(learning_rate: float) -> optax.GradientTransformation:
  """Adam for the actor and the critics. Its learning rate lives in the optimiser state
  (`inject_hyperparams`): set from `sac.learning_rate` at `init`, and per member by
  `with_hyperparams` (a vmapped sweep)."""
  return optax.inject_hyperparams(optax.adam)(learning_rate=learning_rate)


def with_hyperparams(state: LearnerState, learning_rate=None, alpha=None) -> LearnerState:
  """`state` with the actor's and critics' learning rate and/or the entropy temperature
  replaced (arrays shaped like the state's own: () or (members,) under a vmap). The
  temperature's own optimiser keeps `sac.learning_rate`."""
  if learning_rate is not None:
    def set_lr(opt_state):
      lr = jnp.broadcast_to(jnp.asarray(learning_rate, jnp.float32),
                            opt_state.hyperparams["learning_rate"].shape)
      return opt_state._replace(hyperparams={**opt_state.hyperparams, "learning_rate": lr})
    state = state.replace(actor_opt_state=set_lr(state.actor_opt_state),
                          critic_opt_state=set_lr(state.critic_opt_state))
  if alpha is not None:
    state = state.replace(log_alpha=jnp.broadcast_to(
        jnp.log(jnp.asarray(alpha, jnp.float32)), state.log_alpha.shape))
  return state


class SAC(NamedTuple):
  """SAC functions closed over the networks and config (all jit-able).

  init(key, obs) -> LearnerState                       obs: example with a batch axis
  update(state, batch, key, tau=cfg.tau) -> (state, metrics)  one gradient step
  update_from(state, buffer, key, tau=cfg.tau)         one step on cfg.batch_size samples
  update_many(state, buffer, key, tau=cfg.tau)         cfg.grad_steps_per_iter of those,
                                                       keys split(key, G), metrics averaged
  act(actor_params, obs, key) -> action (..., A)       stochastic (squashed sample)
  act_deterministic(actor_params, obs) -> (..., A)     squashed mean (test time)
  """
  nets: nw.SACNetworks
  cfg: SACConfig
  init: Callable
  update: Callable
  update_from: Callable
  update_many: Callable
  act: Callable
  act_deterministic: Callable


def mirror_half(batch: Transition, key: jax.Array, mirror: Mirror) -> Transition:
  """`batch` with each transition replaced, with probability 1/2, by its mirror image:
  obs and next_obs through `mirror_obs`, the action through `mirror_action`; reward,
  flags and weight unchanged (`sac.mirror_augment`)."""
  mirror_obs, mirror_action = mirror
  flip = jax.random.bernoulli(key, 0.5, batch.reward.shape)
  def pick(x, mirrored):
    return jnp.where(flip.reshape(flip.shape + (1,) * (x.ndim - 1)), mirrored, x)
  return batch._replace(
      obs=jax.tree.map(pick, batch.obs, mirror_obs(batch.obs)),
      action=pick(batch.action, mirror_action(batch.action)),
      next_obs=jax.tree.map(pick, batch.next_obs, mirror_obs(batch.next_obs)))


def init_state(nets: nw.SACNetworks, cfg: SACConfig, key: jax.Array, obs: Obs) -> LearnerState:
  """A fresh LearnerState: new networks (targets and the averaged actor copies of them),
  fresh optimiser states, log_alpha = log(sac.alpha)."""
  actor_params, critic_params = nw.init_params(nets, key, obs)
  log_alpha = jnp.asarray(math.log(max(cfg.alpha, 1e-8)), jnp.float32)
  opt = networks_optimizer(cfg.learning_rate)
  return LearnerState(
      actor_params=actor_params, critic_params=critic_params,
      target_critic_params=jax.tree.map(jnp.copy, critic_params),
      actor_opt_state=opt.init(actor_params), critic_opt_state=opt.init(critic_params),
      alpha_opt_state=temperature_optimizer(cfg).init(log_alpha), log_alpha=log_alpha,
      step=jnp.zeros((), jnp.int32), averaged_actor_params=jax.tree.map(jnp.copy, actor_params),
      anchor_actor_params=(jax.tree.map(jnp.copy, actor_params) if cfg.anchor_weight > 0
                           else None))


def temperature_optimizer(cfg: SACConfig) -> optax.GradientTransformation:
  """Adam for log_alpha (`sac.auto_alpha`), at `sac.learning_rate`: its own optimiser, which
  a sweep of the networks' learning rate leaves unchanged."""
  return optax.inject_hyperparams(optax.adam)(learning_rate=cfg.learning_rate)


def _as_recorded(updates: Params, step: jax.Array) -> Params:
  """Adam's step times a run-time 1 (from the step counter, which XLA cannot fold): the
  runs on record scaled it by a learning-rate factor, and with the same multiply XLA
  fuses the update as they were trained, so that they train again bit for bit (a
  constant 1 is folded away, and the step then differs in its last bits)."""
  one = jnp.where(step >= 0, jnp.float32(1.0), jnp.float32(0.0))
  return jax.tree.map(lambda u: u * one, updates)


def gradient_step(nets: nw.SACNetworks, cfg: SACConfig, state: LearnerState, batch: Transition,
                  key: jax.Array, tau) -> tuple[LearnerState, dict]:
  """One gradient step of the critics, then the actor (scored by the updated critics),
  then the temperature (`sac.auto_alpha`); the target critics move at rate `tau`, the
  averaged actor at `sac.actor_ema_tau`. Returns (state, metrics of the step)."""
  opt = networks_optimizer(cfg.learning_rate)  # the rate itself is in the states
  k_critic, k_actor = jax.random.split(key)
  alpha = jnp.exp(state.log_alpha)
  (c_loss, c_aux), c_grads = jax.value_and_grad(critic_loss, has_aux=True)(
      state.critic_params, state.target_critic_params, state.actor_params, alpha, batch,
      k_critic, nets, cfg.gamma)
  c_updates, critic_opt_state = opt.update(c_grads, state.critic_opt_state)
  critic_params = optax.apply_updates(state.critic_params, _as_recorded(c_updates, state.step))

  (a_loss, (logp, anchor_gap)), a_grads = jax.value_and_grad(actor_loss, has_aux=True)(
      state.actor_params, critic_params, alpha, batch, k_actor, nets,
      state.anchor_actor_params, cfg.anchor_weight)
  a_updates, actor_opt_state = opt.update(a_grads, state.actor_opt_state)
  actor_params = optax.apply_updates(state.actor_params, _as_recorded(a_updates, state.step))

  log_alpha, alpha_opt_state = state.log_alpha, state.alpha_opt_state
  al_loss = alpha_loss(log_alpha, logp, cfg.target_entropy)
  if cfg.auto_alpha:
    g = jax.grad(alpha_loss)(log_alpha, logp, cfg.target_entropy)
    al_updates, alpha_opt_state = temperature_optimizer(cfg).update(g, alpha_opt_state)
    log_alpha = optax.apply_updates(log_alpha, al_updates)

  averaged = (polyak(state.averaged_actor_params, actor_params, cfg.actor_ema_tau)
              if cfg.actor_ema_tau > 0 else actor_params)
  new_state = LearnerState(
      actor_params=actor_params, critic_params=critic_params,
      target_critic_params=polyak(state.target_critic_params, critic_params, tau),
      actor_opt_state=actor_opt_state, critic_opt_state=critic_opt_state,
      alpha_opt_state=alpha_opt_state, log_alpha=log_alpha, step=state.step + 1,
      averaged_actor_params=averaged, anchor_actor_params=state.anchor_actor_params)
  metrics = {
      "critic_loss": c_loss, "actor_loss": a_loss, "alpha_loss": al_loss,
      "alpha": jnp.exp(log_alpha), "q_mean": jnp.mean(c_aux["q"]),
      "target_mean": jnp.mean(c_aux["target"]), "entropy": -jnp.mean(logp),
  }
  if cfg.anchor_weight > 0:
    metrics["anchor_gap"] = anchor_gap
  return new_state, metrics


def make_sac(nets: nw.SACNetworks, cfg: SACConfig,
             shard_batch: Callable = lambda batch: batch, mirror: Mirror | None = None) -> SAC:
  """Builds the SAC learner for `nets` with hyper-parameters `cfg`.

  shard_batch: applied to every sampled batch; `mjxvine.training.parallel`'s
  `batch_constraint` splits it over the devices (data-parallel gradients).
  mirror: (mirror_obs, mirror_action) of a left-right symmetric env (`VineyardEnv`'s),
  needed by `cfg.mirror_augment` and `cfg.mirror_average`.
  `update_many`'s loop is unrolled where `networks.unroll_gradient_steps` says.
  """
  if (cfg.mirror_augment or cfg.mirror_average) and mirror is None:
    raise ValueError("sac.mirror_augment and sac.mirror_average need an env with a mirror "
                     "image (mirror_obs, mirror_action): the vineyard's; this env has none")
  unroll = nw.unroll_gradient_steps(nets, cfg.grad_steps_per_iter)

  def update(state: LearnerState, batch: Transition, key: jax.Array, tau=cfg.tau):
    return gradient_step(nets, cfg, state, batch, key, tau)

  def update_from(state: LearnerState, buffer: ReplayBuffer, key: jax.Array, tau=cfg.tau):
    k_sample, k_update = jax.random.split(key)
    batch = sample(buffer, k_sample, cfg.batch_size, cfg.n_step, cfg.gamma)
    if cfg.mirror_augment:
      # split(k_sample)[1] is also the key `sample` draws its env indices from: a reuse,
      # kept so that the recorded runs train again bit for bit
      batch = mirror_half(batch, jax.random.split(k_sample)[1], mirror)
    return update(state, shard_batch(batch), k_update, tau)

  def update_many(state: LearnerState, buffer: ReplayBuffer, key: jax.Array, tau=cfg.tau):
    state, metrics = jax.lax.scan(lambda st, k: update_from(st, buffer, k, tau), state,
                                  jax.random.split(key, cfg.grad_steps_per_iter),
                                  unroll=unroll)
    return state, jax.tree.map(jnp.mean, metrics)

  make_policy = nw.make_inference_fn(nets, mirror if cfg.mirror_average else None)
  return SAC(nets, cfg, lambda key, obs: init_state(nets, cfg, key, obs), update,
             update_from, update_many,
             lambda actor_params, obs, key: make_policy(actor_params, False)(obs, key),
             lambda actor_params, obs: make_policy(actor_params)(obs))
