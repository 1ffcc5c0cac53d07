"""Actor and twin-critic networks of SAC (docs/design.md, SAC hyper-parameters), and the
squashed Gaussian.

Observations are either
  * a dict `{"depth": (..., H, W, 1) float32 metres, "state": (..., S) float32}`: the
    depth image goes through a conv tower (32 features) that is concatenated with the
    state vector, or
  * a flat vector `(..., D)` float32 (any brax `Env`): fed to the MLP torso directly.

Actions live in a box `[low, high]` (vineyard: v in [0, 0.5] m/s, w in [-1, 1] rad/s):
the actor outputs a Gaussian over pre-squash values `u`, and `a = low + (tanh(u) + 1) / 2
* (high - low)`.

With a 112x112 depth image and a 3-dim state the actor has exactly 104,100 parameters
and each critic 103,841 (ReLU after every conv; the mean and log-std heads are two
separate Dense(2) layers on the last hidden layer).

Mixed precision (`compute_dtype=bfloat16`): the convs and hidden layers compute in
bfloat16 on float32 parameters (flax casts them per call); the tower's pooled features,
the heads (mean, log-std, Q) and everything after them stay float32, so losses,
gradients and optimiser states are float32.
"""

from __future__ import annotations

import math
from typing import Any, Callable, NamedTuple, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from mjxvine import native
from mjxvine.config import action_box, depth_input_scale
from mjxvine.tower import (CONV_HOOKS, CONV_IMPLS, CONV_LAYERS, MIN_IMAGE_SIZE, max_pool_2x2,
                           pad_for_tower)

Obs = Any  # a dict {"depth", "state"} or a flat vector, with leading batch dims

class _ConvParams(nn.Module):
  """An `nn.Conv`'s 3x3 params, (kernel (3, 3, in_features, features), bias (features,)),
  under its names and initialisers, for a tower computed by `native.tower`."""
  in_features: int
  features: int

  @nn.compact
  def __call__(self) -> tuple[jax.Array, jax.Array]:
    kernel = self.param("kernel", nn.initializers.lecun_normal(),
                        (3, 3, self.in_features, self.features), jnp.float32)
    return kernel, self.param("bias", nn.initializers.zeros_init(), (self.features,),
                              jnp.float32)


def runs_native_tower(conv_impl: str, features: int, dtype=jnp.float32) -> bool:
  """Whether a `ConvTower` of these fields computes the whole tower as one kernel call
  (`native.tower`): "native", float32, and features the kernel covers; else its
  convs are XLA's."""
  if conv_impl != "native" or jnp.dtype(dtype) != jnp.float32:
    return False
  return native.supports_tower(features)


class ConvTower(nn.Module):
  """Depth encoder: 4 conv 3x3 (strides 2, 1, [maxpool 2], 2, 1), ReLU, global avg pool.

  Input (..., H, W, C) float32; output (..., features). The image is first padded at its
  bottom and right edges (edge values) to the next covering size (`pad_for_tower`), so
  that every pixel reaches the output. For 112x112 (padded to 113) the spatial sizes are
  113 -> 56 -> 54 -> 27 -> 13 -> 11.
  """
  features: int = 32
  depth_scale: float = 1.0  # the input is multiplied by this (e.g. 1 / max_depth)
  dtype: Any = jnp.float32  # computation dtype of the convs
  conv_impl: str = "xla"  # "xla" (lax.conv_general_dilated), "dot" (im2col and a dot),
  # "shift" (the first conv as `conv3x3_shift`, the others XLA's) or "native" (the whole
  # tower as `native.tower` where it applies: float32, 8, 16 or 32 features; else
  # "shift")

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    batch_shape = x.shape[:-3]
    x = (x.reshape((-1,) + x.shape[-3:]) * self.depth_scale).astype(self.dtype)
    if min(x.shape[-3:-1]) < MIN_IMAGE_SIZE:
      raise ValueError(f"depth image {x.shape[-3:-1]} is too small for the conv tower "
                       f"(at least {MIN_IMAGE_SIZE}x{MIN_IMAGE_SIZE})")
    x = pad_for_tower(x)
    if self.conv_impl not in CONV_IMPLS:
      raise ValueError(f"conv_impl {self.conv_impl!r}: expected one of {CONV_IMPLS}")
    if self.conv_impl == "native":
      if not native.available():
        raise RuntimeError(f"conv_impl 'native': {native.unavailable_reason()}")
      if runs_native_tower(self.conv_impl, self.features, self.dtype):
        params, c = [], x.shape[-1]
        for i in range(len(CONV_LAYERS)):
          params.append(_ConvParams(c, self.features, name=f"conv{i}")())
          c = self.features
        return native.tower(x, params).reshape(batch_shape + (self.features,))
    dot = self.conv_impl == "dot"
    hook = CONV_HOOKS.get(self.conv_impl)
    conv = {"conv_general_dilated": hook} if hook else {}
    for i, (stride, pool) in enumerate(CONV_LAYERS):
      x = nn.Conv(self.features, (3, 3), (stride, stride), padding="VALID", dtype=self.dtype,
                  name=f"conv{i}", **conv)(x)
      x = nn.relu(x)
      if pool:
        x = (max_pool_2x2(x) if dot else
             nn.max_pool(x, (2, 2), strides=(2, 2), padding="VALID"))
    x = jnp.mean(x.astype(jnp.float32), axis=(-3, -2))
    return x.reshape(batch_shape + (self.features,))


def _torso_input(obs: Obs, features: int, depth_scale: float, extra=(),
                 dtype=jnp.float32, conv_impl="xla") -> jax.Array:
  """Concatenates [tower(depth), state, *extra] (dict obs) or [obs, *extra] (vector)."""
  if isinstance(obs, dict):
    feats = ConvTower(features, depth_scale, dtype, conv_impl, name="tower")(obs["depth"])
    parts = [feats, obs["state"]]
  else:
    parts = [obs]
  return jnp.concatenate(parts + list(extra), axis=-1)


class Actor(nn.Module):
  """Gaussian policy head over pre-squash actions.

  `__call__(obs) -> (mean, log_std)`, both (..., action_size); log_std is clipped to
  [log_std_min, log_std_max].
  """
  action_size: int
  hidden: Sequence[int] = (256, 256)
  conv_features: int = 32
  depth_scale: float = 1.0
  log_std_min: float = -20.0
  log_std_max: float = 2.0
  dtype: Any = jnp.float32  # computation dtype of the tower and hidden layers
  conv_impl: str = "xla"  # the tower's convs (`CONV_IMPLS`)
  mean_init_scale: float = 1.0  # the mean head's initial weights: LeCun normal x this

  @nn.compact
  def __call__(self, obs: Obs) -> tuple[jax.Array, jax.Array]:
    x = _torso_input(obs, self.conv_features, self.depth_scale, dtype=self.dtype,
                     conv_impl=self.conv_impl)
    for i, h in enumerate(self.hidden):
      x = nn.relu(nn.Dense(h, dtype=self.dtype, name=f"dense{i}")(x))
    x = x.astype(jnp.float32)
    mean = nn.Dense(self.action_size, name="mean", kernel_init=nn.initializers.variance_scaling(
        self.mean_init_scale ** 2, "fan_in", "truncated_normal"))(x)
    log_std = nn.Dense(self.action_size, name="log_std")(x)
    return mean, jnp.clip(log_std, self.log_std_min, self.log_std_max)


class Critic(nn.Module):
  """One Q network: `__call__(obs, action (..., A)) -> q (...,)`, with its own tower."""
  hidden: Sequence[int] = (256, 256)
  conv_features: int = 32
  depth_scale: float = 1.0
  dtype: Any = jnp.float32
  conv_impl: str = "xla"
  layer_norm: bool = False  # LayerNorm before each hidden ReLU (`sac.critic_layer_norm`)

  @nn.compact
  def __call__(self, obs: Obs, action: jax.Array) -> jax.Array:
    x = _torso_input(obs, self.conv_features, self.depth_scale, extra=(action,),
                     dtype=self.dtype, conv_impl=self.conv_impl)
    return _q_layers(x, self.hidden, self.dtype, self.layer_norm)


def _q_layers(x: jax.Array, hidden: Sequence[int], dtype: Any, layer_norm: bool) -> jax.Array:
  """A critic's layers after its torso input, called inside a module's `nn.compact` (so
  that `Critic` and `CriticHead` name their params alike): q (...,)."""
  for i, h in enumerate(hidden):
    x = nn.Dense(h, dtype=dtype, name=f"dense{i}")(x)
    if layer_norm:
      x = nn.LayerNorm(dtype=dtype, name=f"norm{i}")(x)
    x = nn.relu(x)
  return nn.Dense(1, name="q")(x.astype(jnp.float32))[..., 0]


class CriticHead(nn.Module):
  """A critic's layers after its tower: `__call__(x) -> q (...,)` on x = [features, state,
  action]. Its params are a `Critic`'s without "tower" (the same names), so that
  `twin_critic_features` and `twin_critic_heads` split one critic evaluation in two."""
  hidden: Sequence[int] = (256, 256)
  dtype: Any = jnp.float32
  layer_norm: bool = False

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    return _q_layers(x, self.hidden, self.dtype, self.layer_norm)


class TwinCritic(nn.Module):
  """`num` independent critics, params "critic0", "critic1", ...

  `__call__(obs, action) -> q (num, ...)`. (Separate modules rather than a vmap over
  stacked params: a vmapped conv becomes a grouped conv, ~8x slower on CPU.)
  """
  hidden: Sequence[int] = (256, 256)
  conv_features: int = 32
  depth_scale: float = 1.0
  num: int = 2
  dtype: Any = jnp.float32
  conv_impl: str = "xla"
  layer_norm: bool = False

  @nn.compact
  def __call__(self, obs: Obs, action: jax.Array) -> jax.Array:
    return jnp.stack([
        Critic(self.hidden, self.conv_features, self.depth_scale, self.dtype, self.conv_impl,
               self.layer_norm, name=f"critic{i}")(obs, action)
        for i in range(self.num)])


def twin_critic_features(critic: "TwinCritic", params: Any, obs: Obs) -> list[jax.Array]:
  """Each critic's tower features of `obs`, [(..., conv_features)] * num (a vector
  observation has no tower: the features are the observation itself)."""
  if not isinstance(obs, dict):
    return [obs] * critic.num
  tower = ConvTower(critic.conv_features, critic.depth_scale, critic.dtype, critic.conv_impl)
  return [tower.apply({"params": params[f"critic{i}"]["tower"]}, obs["depth"])
          for i in range(critic.num)]


def twin_critic_heads(critic: "TwinCritic", params: Any, features: list[jax.Array], obs: Obs,
                      action: jax.Array) -> jax.Array:
  """q (num, ...) from `twin_critic_features`' output: with the features of the same
  params, exactly `critic.apply({"params": params}, obs, action)`."""
  head = CriticHead(critic.hidden, critic.dtype, critic.layer_norm)
  state = [obs["state"]] if isinstance(obs, dict) else []
  return jnp.stack([
      head.apply({"params": {k: v for k, v in params[f"critic{i}"].items() if k != "tower"}},
                 jnp.concatenate([f] + state + [action], axis=-1))
      for i, f in enumerate(features)])


class SACNetworks(NamedTuple):
  """The static parts of the agent: modules and the action box (each (A,) float32)."""
  actor: Actor
  critic: TwinCritic
  action_low: jax.Array
  action_high: jax.Array


def make_networks(action_low: Sequence[float], action_high: Sequence[float], hidden: int = 256,
                  conv_features: int = 32, depth_scale: float = 1.0,
                  log_std_min: float = -20.0, log_std_max: float = 2.0,
                  compute_dtype: str = "float32", conv_impl: str = "xla",
                  critic_layer_norm: bool = False,
                  actor_mean_init_scale: float = 1.0) -> SACNetworks:
  """Builds the actor and twin critic for an action box [action_low, action_high].

  `depth_scale` multiplies the depth (metres) before the first conv; the paper's
  networks are `hidden=256, conv_features=32` (two hidden layers). `compute_dtype`: "float32"
  or "bfloat16" (mixed precision, see the module docstring). `conv_impl`: how the conv
  towers compute their convolutions (`CONV_IMPLS`; the same parameters either way).
  `critic_layer_norm`: LayerNorm before each hidden ReLU of the critics (not the paper's:
  it adds 4 * hidden parameters per critic). `actor_mean_init_scale` scales the initial
  weights of the actor's mean head (1: flax's LeCun normal).
  """
  dtype = jnp.dtype(compute_dtype)
  low = jnp.asarray(action_low, jnp.float32)
  high = jnp.asarray(action_high, jnp.float32)
  if low.shape != high.shape or low.ndim != 1 or not bool(jnp.all(high > low)):
    raise ValueError(f"bad action box: low={action_low}, high={action_high}")
  hs = (hidden, hidden)
  actor = Actor(int(low.shape[0]), hs, conv_features, depth_scale, log_std_min, log_std_max,
                dtype, conv_impl, actor_mean_init_scale)
  critic = TwinCritic(hs, conv_features, depth_scale, dtype=dtype, conv_impl=conv_impl,
                      layer_norm=critic_layer_norm)
  return SACNetworks(actor, critic, low, high)


def native_towers(nets: SACNetworks) -> bool:
  """Whether the towers of `nets` run as the native kernel, with no XLA convolution (which
  XLA:CPU runs far slower inside a loop body, jax-ml/jax#12868)."""
  return runs_native_tower(nets.actor.conv_impl, nets.actor.conv_features, nets.actor.dtype)


def make_networks_from_config(cfg, conv_impl: str = "xla", box=None) -> SACNetworks:
  """The networks of a `mjxvine.config.Config`.

  Action box `box` = (low, high), by default the vineyard's `config.action_box`; depth
  scaled by `config.depth_input_scale` so that the tower sees [0, 1]; sizes and log-std
  bounds from `cfg.sac`.
  """
  return make_networks(
      *(action_box(cfg) if box is None else box), hidden=cfg.sac.hidden,
      conv_features=cfg.sac.conv_features, depth_scale=depth_input_scale(cfg),
      log_std_min=cfg.sac.log_std_min, log_std_max=cfg.sac.log_std_max,
      compute_dtype=cfg.sac.compute_dtype, conv_impl=conv_impl,
      critic_layer_norm=cfg.sac.critic_layer_norm,
      actor_mean_init_scale=cfg.sac.actor_mean_init_scale)


def init_params(nets: SACNetworks, key: jax.Array, obs: Obs) -> tuple[Any, Any]:
  """Initialises (actor_params, critic_params) from an example observation (any batch)."""
  k1, k2 = jax.random.split(key)
  act = jnp.zeros(jax.tree.leaves(obs)[0].shape[:_batch_ndim(obs)] + nets.action_low.shape)
  return nets.actor.init(k1, obs)["params"], nets.critic.init(k2, obs, act)["params"]


def _batch_ndim(obs: Obs) -> int:
  """Number of leading batch dims of an observation (depth has 3 trailing dims)."""
  if isinstance(obs, dict):
    return obs["state"].ndim - 1
  return obs.ndim - 1


def num_params(params: Any) -> int:
  """Total number of scalars in a params pytree."""
  return sum(int(math.prod(x.shape)) for x in jax.tree.leaves(params))


# ----------------------------------------------------------------------------------------
# Tanh-squashed Gaussian mapped onto the action box.


def squash(u: jax.Array, low: jax.Array, high: jax.Array) -> jax.Array:
  """Maps pre-squash u (..., A) into the box: low + (tanh(u) + 1) / 2 * (high - low)."""
  return low + 0.5 * (jnp.tanh(u) + 1.0) * (high - low)


def _log_det_squash(u: jax.Array, low: jax.Array, high: jax.Array) -> jax.Array:
  """log |d squash / du| summed over the action dims: (..., A) -> (...)."""
  # log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)), stable for large |u|.
  log_dtanh = 2.0 * (math.log(2.0) - u - jax.nn.softplus(-2.0 * u))
  return jnp.sum(log_dtanh + jnp.log(0.5 * (high - low)), axis=-1)


def gaussian_log_prob(u: jax.Array, mean: jax.Array, log_std: jax.Array) -> jax.Array:
  """log N(u; mean, exp(log_std)^2) of a diagonal Gaussian, summed over the last axis."""
  z = (u - mean) * jnp.exp(-log_std)
  return jnp.sum(-0.5 * z * z - log_std - 0.5 * math.log(2.0 * math.pi), axis=-1)


def squashed_log_prob(u: jax.Array, mean: jax.Array, log_std: jax.Array, low: jax.Array,
                      high: jax.Array) -> jax.Array:
  """Log-density (w.r.t. the action box) of `squash(u)`, u drawn from N(mean, std): (...)."""
  return gaussian_log_prob(u, mean, log_std) - _log_det_squash(u, low, high)


def sample_squashed(key: jax.Array, mean: jax.Array, log_std: jax.Array, low: jax.Array,
                    high: jax.Array) -> tuple[jax.Array, jax.Array]:
  """Reparameterised sample. Returns (action (..., A) in the box, log_prob (...))."""
  u = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape, mean.dtype)
  return squash(u, low, high), squashed_log_prob(u, mean, log_std, low, high)


def deterministic_action(mean: jax.Array, low: jax.Array, high: jax.Array) -> jax.Array:
  """The test-time action: the squashed, box-mapped mean (..., A)."""
  return squash(mean, low, high)


def act_deterministic(nets: SACNetworks, actor_params: Any, obs: Obs,
                      mirror: tuple[Callable, Callable] | None = None) -> jax.Array:
  """The actor's test-time action (..., A) for `obs` (any leading batch dims).

  mirror: (mirror_obs, mirror_action) of a left-right symmetric task (`sac.mirror_average`):
  the action is then the mean of the action on `obs` and the mirrored action on the
  mirrored `obs`, so that mirrored observations get exactly mirrored actions.
  """
  def act(o):
    mean, _ = nets.actor.apply({"params": actor_params}, o)
    return deterministic_action(mean, nets.action_low, nets.action_high)

  if mirror is None:
    return act(obs)
  mirror_obs, mirror_action = mirror
  return 0.5 * (act(obs) + mirror_action(act(mirror_obs(obs))))


def make_inference_fn(nets: SACNetworks, mirror: tuple[Callable, Callable] | None = None):
  """The one maker of the actor's action, as brax's `make_inference_fn`:
  `make_policy(actor_params, deterministic=True) -> policy(obs, key) -> action (..., A)`.

  deterministic: the test-time action (`act_deterministic`, mirror-averaged with `mirror`);
  else a sample of the squashed Gaussian (exploration; `mirror` does not apply). Training,
  evaluation, videos and the exported policies (`mjxvine.deploy`, tested equal) all act
  through it."""
  def make_policy(actor_params: Any, deterministic: bool = True) -> Callable:
    def policy(obs: Obs, key: jax.Array | None = None) -> jax.Array:
      if deterministic:
        return act_deterministic(nets, actor_params, obs, mirror)
      mean, log_std = nets.actor.apply({"params": actor_params}, obs)
      return sample_squashed(key, mean, log_std, nets.action_low, nets.action_high)[0]
    return policy
  return make_policy

