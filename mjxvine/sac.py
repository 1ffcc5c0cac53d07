"""Soft Actor-Critic (Haarnoja et al. 2018), pure-functional, with a device replay buffer.

Everything here is a pure function of pytrees, jit-able and scan-able:
  * `make_sac(nets, cfg)` -> `SAC` with `init`, `update`, `update_many`, `act`,
    `act_deterministic`;
  * losses `critic_loss`, `actor_loss`, `alpha_loss` and `polyak`;
  * the replay buffer `init_buffer` / `insert` / `sample` (`mjxvine.replay`);
  * exploration `explore_action` / `decay_eps` (docs/design.md, SAC hyper-parameters).

Bootstrapping: the target is `r + gamma * (1 - terminal) * (min_i Q'_i(s', a') - alpha
log pi(a'|s'))`; a time-out (`truncated`) is *not* terminal and bootstraps through
`next_obs`, which must be the true successor observation (before any auto-reset).
"""

from __future__ import annotations

import functools
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


class LearnerState(flax.struct.PyTreeNode):
  """All mutable learner state. Critic params hold "critic0" and "critic1".

  `policy_params` is the actor that is evaluated, kept as best and exported: the online
  `actor_params`, or their Polyak average when `sac.actor_ema_tau` > 0.
  """
  actor_params: Params
  critic_params: Params
  target_critic_params: Params
  actor_opt_state: optax.OptState
  critic_opt_state: optax.OptState
  alpha_opt_state: optax.OptState
  log_alpha: jax.Array  # () float32
  step: jax.Array  # () int32, gradient steps taken
  policy_params: Params


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
                gamma: float, keep_features: bool = False) -> tuple[jax.Array, dict]:
  """Twin-Q loss: 0.5 * sum_i wmean_b (Q_i(s, a) - y)^2. Returns (loss, {"q": (2, B),
  "target": (B,)}, plus "features": the critics' tower features of obs, with
  `keep_features`)."""
  y = critic_target(nets, actor_params, target_critic_params, alpha, batch, key, gamma)
  aux = {}
  if keep_features:
    feats = nw.twin_critic_features(nets.critic, critic_params, batch.obs)
    q = nw.twin_critic_heads(nets.critic, critic_params, feats, batch.obs, batch.action)
    aux["features"] = feats
  else:
    q = nets.critic.apply({"params": critic_params}, batch.obs, batch.action)  # (2, B)
  per_sample = 0.5 * jnp.sum((q - y[None]) ** 2, axis=0)
  return _wmean(per_sample, batch.weight), {"q": q, "target": y, **aux}


def actor_loss(actor_params: Params, critic_params: Params, alpha: jax.Array, batch: Transition,
               key: jax.Array, nets: nw.SACNetworks,
               critic_features: list | None = None) -> tuple[jax.Array, jax.Array]:
  """mean_b (alpha * log pi(a|s) - min_i Q_i(s, a)), a ~ pi(.|s) reparameterised.

  `critic_features`: the critics' tower features of obs for `critic_params` (from
  `critic_loss`), held fixed, instead of running the towers again. Returns (loss,
  log_prob (B,)).
  """
  mean, log_std = nets.actor.apply({"params": actor_params}, batch.obs)
  a, logp = nw.sample_squashed(key, mean, log_std, nets.action_low, nets.action_high)
  if critic_features is None:
    q = nets.critic.apply({"params": critic_params}, batch.obs, a)
  else:
    q = nw.twin_critic_heads(nets.critic, critic_params,
                             jax.lax.stop_gradient(critic_features), batch.obs, a)
  return jnp.mean(alpha * logp - jnp.min(q, axis=0)), logp


def alpha_loss(log_alpha: jax.Array, log_prob: jax.Array, target_entropy: float) -> jax.Array:
  """Temperature loss -mean(log_alpha * (log pi + target_entropy)), log_prob held fixed."""
  return -jnp.mean(log_alpha * jax.lax.stop_gradient(log_prob + target_entropy))


def with_hyperparams(state: LearnerState, learning_rate=None, alpha=None) -> LearnerState:
  """`state` with the actor and critic learning rate and/or the entropy temperature
  replaced (arrays shaped like the state's own: () or (members,) under a vmap)."""
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


def polyak(target: Params, online: Params, tau: float) -> Params:
  """Soft update: target <- (1 - tau) * target + tau * online, leaf by leaf."""
  return jax.tree.map(lambda t, o: (1.0 - tau) * t + tau * o, target, online)


# ----------------------------------------------------------------------------------------
# The learner.


@functools.lru_cache(maxsize=None)
def learner_compiler_options() -> dict | None:
  """XLA compiler options for the programs that take gradient steps (`jax.jit(...,
  compiler_options=...)`), or None.

  On the CPU backend, convolutions are not handed to the YNNPACK library
  (`xla_cpu_experimental_ynn_fusion_type` empty): its convolution is fast forward but
  slow for the gradient w.r.t. the kernel (an 18x18-window convolution of the conv tower),
  which dominates a gradient step; XLA's own convolution takes about half as long there
  (docs/results/cpu-update-speed.md). The same numbers to float32 rounding. None on
  accelerators, and where this jaxlib does not know the option.
  """
  if jax.default_backend() != "cpu":
    return None
  options = {"xla_cpu_experimental_ynn_fusion_type": ""}
  try:
    jax.jit(lambda x: x + 1, compiler_options=options)(jnp.zeros(()))
  except Exception:  # pylint: disable=broad-except
    return None
  return options


def learner_conv_impl(choice: str = "auto") -> str:
  """How the trainer's networks compute the conv tower (`tower.CONV_IMPLS`):
  `sac.conv_impl` where it names one; else ("auto") on the CPU backend "native" (the
  whole tower as one hand-written kernel call, `mjxvine.native`: 3-4x the gradient
  steps/s of XLA's tower for `cpu.yaml`, docs/results/cpu-update-speed.md) where it
  builds, else "shift" (the first conv as a sum of strided slices); elsewhere "xla", so
  that accelerator programs and their cost analysis are unchanged. The parameters, and
  the numbers to float32 rounding, are the same either way; evaluation and export keep
  XLA's convolution."""
  if choice != "auto":
    return choice
  if jax.default_backend() != "cpu":
    return "xla"
  from mjxvine import native  # pylint: disable=import-outside-toplevel
  return "native" if native.available() else "shift"


def resolve_conv_impl(cfg):
  """`cfg` (a `mjxvine.config.Config`) with `sac.conv_impl: auto` replaced by the tower it
  takes here (`learner_conv_impl`): what a run records in its config.yaml, so that the
  same config trains the same way, or refuses, on another machine."""
  from mjxvine.config import replace  # pylint: disable=import-outside-toplevel
  if cfg.sac.conv_impl != "auto":
    return cfg
  return replace(cfg, sac={"conv_impl": learner_conv_impl("auto")})


def describe_conv_impl(choice: str = "auto") -> str:
  """`learner_conv_impl(choice)` in words, for a run's log: "native (avx512)", or "shift
  (native: <why not>)" where auto could not take the native tower."""
  from mjxvine import native  # pylint: disable=import-outside-toplevel
  impl = learner_conv_impl(choice)
  if impl == "native":
    return f"native ({native.instruction_set()})"
  if choice == "auto" and jax.default_backend() == "cpu":
    return f"{impl} (native: {native.unavailable_reason()})"
  return impl


class SAC(NamedTuple):
  """SAC functions closed over the networks and config (all jit-able).

  init(key, obs) -> LearnerState                       obs: example with a batch axis
  update(state, batch, key, lr_scale=1, tau=None) -> (state, metrics)  one gradient step
  update_from(state, buffer, key, lr_scale=1, tau=None) one step on cfg.batch_size samples
  update_many(state, buffer, key, lr_scale=1, tau=None) cfg.grad_steps_per_iter of those,
                                                        with keys split(key, G), metrics
                                                        averaged
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


def mirror_half(batch: Transition, key: jax.Array, mirror_obs: Callable,
                mirror_action: Callable) -> Transition:
  """`batch` with each transition replaced, with probability 1/2, by its mirror image:
  obs and next_obs through `mirror_obs`, the action through `mirror_action`; reward,
  flags and weight unchanged (`sac.mirror_augment`)."""
  flip = jax.random.bernoulli(key, 0.5, batch.reward.shape)
  def pick(x, mirrored):
    return jnp.where(flip.reshape(flip.shape + (1,) * (x.ndim - 1)), mirrored, x)
  return batch._replace(
      obs=jax.tree.map(pick, batch.obs, mirror_obs(batch.obs)),
      action=pick(batch.action, mirror_action(batch.action)),
      next_obs=jax.tree.map(pick, batch.next_obs, mirror_obs(batch.next_obs)))


def shift_depth(depth: jax.Array, key: jax.Array, pad_px: int) -> jax.Array:
  """Each image of `depth` (B, H, W, C) moved by its own random whole-pixel offset of at
  most `pad_px` along each axis, the edge values repeated into the uncovered border
  (DrQ's random shift: pad by replication, then crop back to H x W)."""
  b, h, w, c = depth.shape
  padded = jnp.pad(depth, ((0, 0), (pad_px, pad_px), (pad_px, pad_px), (0, 0)), mode="edge")
  offsets = jax.random.randint(key, (b, 2), 0, 2 * pad_px + 1)
  crop = lambda img, o: jax.lax.dynamic_slice(img, (o[0], o[1], 0), (h, w, c))
  return jax.vmap(crop)(padded, offsets)


def shift_images(batch: Transition, key: jax.Array, pad_px: int) -> Transition:
  """`batch` with obs and next_obs depth images shifted independently (`shift_depth`,
  `sac.image_shift_px`): the critics and the actor learn from views a few pixels apart,
  which regularises the conv towers (Kostrikov et al. 2020, DrQ)."""
  if not isinstance(batch.obs, dict) or "depth" not in batch.obs:
    raise ValueError("sac.image_shift_px shifts depth images: this env's observations "
                     "have none")
  k_obs, k_next = jax.random.split(key)
  return batch._replace(
      obs={**batch.obs, "depth": shift_depth(batch.obs["depth"], k_obs, pad_px)},
      next_obs={**batch.next_obs,
                "depth": shift_depth(batch.next_obs["depth"], k_next, pad_px)})


def augment(batch: Transition, k_sample: jax.Array, cfg: SACConfig,
            mirror: tuple[Callable, Callable] | None) -> Transition:
  """A sampled batch with the augmentations `cfg` asks for: the mirror image of half of
  it (`sac.mirror_augment`), then shifted depth images (`sac.image_shift_px`). Their keys
  come from the batch's sampling key `k_sample`, so that runs without them keep theirs."""
  if cfg.mirror_augment:
    # split(k_sample)[1] is also the key `sample` draws its env indices from (k_env): a
    # reuse, kept because the lanes.yaml results were measured with it
    _, k_mirror = jax.random.split(k_sample)
    batch = mirror_half(batch, k_mirror, *mirror)
  if cfg.image_shift_px:
    batch = shift_images(batch, jax.random.fold_in(k_sample, 1), cfg.image_shift_px)
  return batch


def make_sac(nets: nw.SACNetworks, cfg: SACConfig,
             shard_batch: Callable = lambda batch: batch,
             mirror: tuple[Callable, Callable] | None = None) -> SAC:
  """Builds the SAC learner for `nets` with hyper-parameters `cfg`.

  shard_batch: applied to every sampled batch; `mjxvine.training.parallel`'s `batch_constraint`
  splits it over the devices (data-parallel gradients).
  mirror: (mirror_obs, mirror_action) of a left-right symmetric env (`VineyardEnv`'s),
  needed by `cfg.mirror_augment` and `cfg.mirror_average`.

  `update_many`'s loop is fully unrolled on the CPU backend when grad_steps_per_iter <=
  16 and the towers run XLA's convolutions (XLA:CPU runs those inside a loop body ~20x
  slower, jax-ml/jax#12868), else rolled (one step compiled; the native tower, which has
  no XLA convolution, runs as fast rolled). The trainer's CPU path calls `update_many`
  once an iteration with the native tower, else `update_from` G times from the host.
  """
  # The learning rate lives in the optimiser state (inject_hyperparams), so that runs
  # vmapped over seeds can also differ in it (`mjxvine.train` sweeps).
  opt = optax.inject_hyperparams(optax.adam)(learning_rate=cfg.learning_rate)
  unroll = (jax.default_backend() == "cpu" and cfg.grad_steps_per_iter <= 16
            and not nw.native_towers(nets))
  if (cfg.mirror_augment or cfg.mirror_average) and mirror is None:
    raise ValueError("sac.mirror_augment and sac.mirror_average need an env with a mirror "
                     "image (mirror_obs, mirror_action): the vineyard's; this env has none")

  def init(key: jax.Array, obs: Obs) -> LearnerState:
    actor_params, critic_params = nw.init_params(nets, key, obs)
    log_alpha = jnp.asarray(math.log(max(cfg.alpha, 1e-8)), jnp.float32)
    return LearnerState(
        actor_params=actor_params, critic_params=critic_params,
        target_critic_params=jax.tree.map(jnp.copy, critic_params),
        actor_opt_state=opt.init(actor_params), critic_opt_state=opt.init(critic_params),
        alpha_opt_state=opt.init(log_alpha), log_alpha=log_alpha,
        step=jnp.zeros((), jnp.int32), policy_params=jax.tree.map(jnp.copy, actor_params))

  def update(state: LearnerState, batch: Transition, key: jax.Array, lr_scale=1.0, tau=None):
    """One gradient step; `lr_scale` multiplies the actor's and critics' learning rate
    (`learning_rate_scale`: Adam's step is linear in it); `tau`, the target critics' rate
    (`target_rate`), is cfg.tau when None."""
    k_critic, k_actor = jax.random.split(key)
    scaled = lambda updates: jax.tree.map(lambda u: u * lr_scale, updates)
    alpha = jnp.exp(state.log_alpha)

    reuse = cfg.reuse_critic_features
    (c_loss, c_aux), c_grads = jax.value_and_grad(critic_loss, has_aux=True)(
        state.critic_params, state.target_critic_params, state.actor_params, alpha, batch,
        k_critic, nets, cfg.gamma, reuse)
    c_updates, critic_opt_state = opt.update(c_grads, state.critic_opt_state)
    critic_params = optax.apply_updates(state.critic_params, scaled(c_updates))

    # reuse: the actor is scored by the critics of the critic loss (before their update),
    # whose tower features of obs are already computed
    (a_loss, logp), a_grads = jax.value_and_grad(actor_loss, has_aux=True)(
        state.actor_params, state.critic_params if reuse else critic_params, alpha, batch,
        k_actor, nets, c_aux.get("features"))
    a_updates, actor_opt_state = opt.update(a_grads, state.actor_opt_state)
    actor_params = optax.apply_updates(state.actor_params, scaled(a_updates))

    log_alpha, alpha_opt_state = state.log_alpha, state.alpha_opt_state
    al_loss = alpha_loss(log_alpha, logp, cfg.target_entropy)
    if cfg.auto_alpha:
      g = jax.grad(alpha_loss)(log_alpha, logp, cfg.target_entropy)
      al_updates, alpha_opt_state = opt.update(g, alpha_opt_state)
      log_alpha = optax.apply_updates(log_alpha, al_updates)

    new_state = LearnerState(
        actor_params=actor_params, critic_params=critic_params,
        target_critic_params=polyak(state.target_critic_params, critic_params,
                                    cfg.tau if tau is None else tau),
        actor_opt_state=actor_opt_state, critic_opt_state=critic_opt_state,
        alpha_opt_state=alpha_opt_state, log_alpha=log_alpha, step=state.step + 1,
        policy_params=(polyak(state.policy_params, actor_params, cfg.actor_ema_tau)
                       if cfg.actor_ema_tau > 0 else actor_params))
    metrics = {
        "critic_loss": c_loss, "actor_loss": a_loss, "alpha_loss": al_loss,
        "alpha": jnp.exp(log_alpha), "q_mean": jnp.mean(c_aux["q"]),
        "target_mean": jnp.mean(c_aux["target"]), "entropy": -jnp.mean(logp),
    }
    return new_state, metrics

  def update_from(state: LearnerState, buffer: "ReplayBuffer", key: jax.Array, lr_scale=1.0,
                  tau=None):
    k_sample, k_update = jax.random.split(key)
    batch = augment(sample(buffer, k_sample, cfg.batch_size, cfg.n_step, cfg.gamma),
                    k_sample, cfg, mirror)
    return update(state, shard_batch(batch), k_update, lr_scale, tau)

  def update_many(state: LearnerState, buffer: "ReplayBuffer", key: jax.Array, lr_scale=1.0,
                  tau=None):
    state, metrics = jax.lax.scan(lambda st, k: update_from(st, buffer, k, lr_scale, tau), state,
                                  jax.random.split(key, cfg.grad_steps_per_iter),
                                  unroll=unroll)
    return state, jax.tree.map(jnp.mean, metrics)

  make_policy = nw.make_inference_fn(nets, mirror if cfg.mirror_average else None)

  def act(actor_params: Params, obs: Obs, key: jax.Array) -> jax.Array:
    return make_policy(actor_params, deterministic=False)(obs, key)

  def act_deterministic(actor_params: Params, obs: Obs) -> jax.Array:
    return make_policy(actor_params)(obs)

  return SAC(nets, cfg, init, update, update_from, update_many, act, act_deterministic)


# ----------------------------------------------------------------------------------------
# Exploration (docs/design.md, SAC hyper-parameters).


def explore_action(key: jax.Array, policy_action: jax.Array, eps: jax.Array, low: jax.Array,
                   high: jax.Array, warmup: jax.Array | bool) -> jax.Array:
  """Warm-up / epsilon-greedy exploration on top of the SAC sample.

  policy_action (N, A); eps () or (N,) probability; low, high (A,); warmup: bool scalar
  or (N,). Where warming up, or with probability eps, the action is uniform in the box
  with each dimension drawn independently; otherwise policy_action.
  """
  k_uniform, k_coin = jax.random.split(key)
  rand = jax.random.uniform(k_uniform, policy_action.shape, policy_action.dtype, low, high)
  coin = jax.random.uniform(k_coin, policy_action.shape[:-1])
  explore = jnp.logical_or(warmup, coin < eps)
  return jnp.where(explore[..., None], rand, policy_action)


def epsilon(cfg: SACConfig, env_steps: jax.Array, total_env_steps: int) -> jax.Array:
  """Exploration probability () after `env_steps` env steps summed over all envs.

  The budget `total_env_steps` counts as `cfg.eps_budget_episodes` episodes, and epsilon
  is multiplied by `cfg.eps_decay` per such episode, floored at `cfg.eps_min`: it
  reaches the floor at the same fraction of the budget whatever the number of envs (the
  paper's 0.992 per episode over 1500 episodes: at 25 %).
  """
  episodes = cfg.eps_budget_episodes * jnp.asarray(env_steps, jnp.float32) / total_env_steps
  return jnp.maximum(cfg.eps_start * jnp.power(cfg.eps_decay, episodes), cfg.eps_min)


def learning_rate_scale(cfg: SACConfig, env_steps: jax.Array, total_env_steps) -> jax.Array:
  """The actor's and critics' learning rate () as a fraction of `cfg.learning_rate` after
  `env_steps` env steps summed over all envs: linear from 1 at the start to
  `cfg.lr_end_fraction` at `total_env_steps`, then held (1 throughout by default)."""
  done = jnp.minimum(jnp.asarray(env_steps, jnp.float32) / total_env_steps, 1.0)
  return 1.0 - (1.0 - cfg.lr_end_fraction) * done


def target_rate(cfg: SACConfig, env_steps: jax.Array, total_env_steps) -> jax.Array | float:
  """The target critics' Polyak rate after `env_steps` env steps summed over all envs:
  `cfg.tau`, then `cfg.tau_late` from `cfg.tau_late_from` x `total_env_steps` on. With
  tau_late 0 it is the Python float cfg.tau, so that runs without the switch compile as
  before."""
  if not cfg.tau_late:
    return cfg.tau
  late = jnp.asarray(env_steps, jnp.float32) >= cfg.tau_late_from * total_env_steps
  return jnp.where(late, jnp.float32(cfg.tau_late), jnp.float32(cfg.tau))
