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

How the learner computes the conv tower on this machine (`learner_conv_impl`: XLA's
convs, the `shift` rewrite of the first, or the `native` CPU kernel; the same parameters
and numbers to float32 rounding) and how it compiles its gradient steps
(`learner_compiler_options`, `unroll_gradient_steps`) live here, beside the tower.
"""

from __future__ import annotations

import functools
import math
from typing import Any, Callable, NamedTuple, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from mjxvine import native
from mjxvine.config import action_box, depth_input_scale, replace
from mjxvine.tower import CONV_HOOKS, CONV_IMPLS, CONV_LAYERS, MIN_IMAGE_SIZE, pad_for_tower

Obs = Any  # a dict {"depth", "state"} or a flat vector, with leading batch dims
LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0  # the actor's log-std clip (the paper's)

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


def runs_native_tower(conv_impl: str, features: int) -> bool:
  """Whether a `ConvTower` of these fields computes the whole tower as one kernel call
  (`native.tower`): "native" and features the kernel covers; else its convs are XLA's."""
  return conv_impl == "native" and native.supports_tower(features)


class ConvTower(nn.Module):
  """Depth encoder: 4 conv 3x3 (strides 2, 1, [maxpool 2], 2, 1), ReLU, global avg pool.

  Input (..., H, W, C) float32; output (..., features). The image is first padded at its
  bottom and right edges (edge values) to the next covering size (`pad_for_tower`), so
  that every pixel reaches the output. For 112x112 (padded to 113) the spatial sizes are
  113 -> 56 -> 54 -> 27 -> 13 -> 11.
  """
  features: int = 32
  depth_scale: float = 1.0  # the input is multiplied by this (e.g. 1 / max_depth)
  conv_impl: str = "xla"  # "xla" (lax.conv_general_dilated), "shift" (the first conv as
  # `conv3x3_shift`, the others XLA's) or "native" (the whole tower as `native.tower`
  # where it applies: 8, 16 or 32 features; else "shift")

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    batch_shape = x.shape[:-3]
    x = x.reshape((-1,) + x.shape[-3:]) * self.depth_scale
    if min(x.shape[-3:-1]) < MIN_IMAGE_SIZE:
      raise ValueError(f"depth image {x.shape[-3:-1]} is too small for the conv tower "
                       f"(at least {MIN_IMAGE_SIZE}x{MIN_IMAGE_SIZE})")
    x = pad_for_tower(x)
    if self.conv_impl not in CONV_IMPLS:
      raise ValueError(f"conv_impl {self.conv_impl!r}: expected one of {CONV_IMPLS}")
    if self.conv_impl == "native":
      if not native.available():
        raise RuntimeError(f"conv_impl 'native': {native.unavailable_reason()}")
      if runs_native_tower(self.conv_impl, self.features):
        params, c = [], x.shape[-1]
        for i in range(len(CONV_LAYERS)):
          params.append(_ConvParams(c, self.features, name=f"conv{i}")())
          c = self.features
        return native.tower(x, params).reshape(batch_shape + (self.features,))
    hook = CONV_HOOKS.get(self.conv_impl)
    conv = {"conv_general_dilated": hook} if hook else {}
    for i, (stride, pool) in enumerate(CONV_LAYERS):
      x = nn.Conv(self.features, (3, 3), (stride, stride), padding="VALID", name=f"conv{i}",
                  **conv)(x)
      x = nn.relu(x)
      if pool:
        x = nn.max_pool(x, (2, 2), strides=(2, 2), padding="VALID")
    x = jnp.mean(x, axis=(-3, -2))
    return x.reshape(batch_shape + (self.features,))


def _torso_input(obs: Obs, features: int, depth_scale: float, conv_impl: str,
                 extra=()) -> jax.Array:
  """Concatenates [tower(depth), state, *extra] (dict obs) or [obs, *extra] (vector)."""
  if isinstance(obs, dict):
    feats = ConvTower(features, depth_scale, conv_impl, name="tower")(obs["depth"])
    parts = [feats, obs["state"]]
  else:
    parts = [obs]
  return jnp.concatenate(parts + list(extra), axis=-1)


class Actor(nn.Module):
  """Gaussian policy head over pre-squash actions.

  `__call__(obs) -> (mean, log_std)`, both (..., action_size); log_std is clipped to
  [LOG_STD_MIN, LOG_STD_MAX].
  """
  action_size: int
  hidden: Sequence[int] = (256, 256)
  conv_features: int = 32
  depth_scale: float = 1.0
  conv_impl: str = "xla"  # the tower's convs (`CONV_IMPLS`)

  @nn.compact
  def __call__(self, obs: Obs) -> tuple[jax.Array, jax.Array]:
    x = _torso_input(obs, self.conv_features, self.depth_scale, self.conv_impl)
    for i, h in enumerate(self.hidden):
      x = nn.relu(nn.Dense(h, name=f"dense{i}")(x))
    mean = nn.Dense(self.action_size, name="mean")(x)
    log_std = nn.Dense(self.action_size, name="log_std")(x)
    return mean, jnp.clip(log_std, LOG_STD_MIN, LOG_STD_MAX)


class Critic(nn.Module):
  """One Q network: `__call__(obs, action (..., A)) -> q (...,)`, with its own tower; it
  also reads obs["lane"] (..., 3) where the observation has it (`sac.privileged_critics`)."""
  hidden: Sequence[int] = (256, 256)
  conv_features: int = 32
  depth_scale: float = 1.0
  conv_impl: str = "xla"
  layer_norm: bool = False  # LayerNorm before each hidden ReLU (`sac.critic_layer_norm`)

  @nn.compact
  def __call__(self, obs: Obs, action: jax.Array) -> jax.Array:
    # obs["lane"]: the simulator's lane state, present only for privileged critics
    lane = (obs["lane"],) if isinstance(obs, dict) and "lane" in obs else ()
    x = _torso_input(obs, self.conv_features, self.depth_scale, self.conv_impl,
                     extra=lane + (action,))
    for i, h in enumerate(self.hidden):
      x = nn.Dense(h, name=f"dense{i}")(x)
      if self.layer_norm:
        x = nn.LayerNorm(name=f"norm{i}")(x)
      x = nn.relu(x)
    return nn.Dense(1, name="q")(x)[..., 0]


class TwinCritic(nn.Module):
  """`num` independent critics, params "critic0", "critic1", ...

  `__call__(obs, action) -> q (num, ...)`. (Separate modules rather than a vmap over
  stacked params: a vmapped conv becomes a grouped conv, ~8x slower on CPU.)
  """
  hidden: Sequence[int] = (256, 256)
  conv_features: int = 32
  depth_scale: float = 1.0
  num: int = 2
  conv_impl: str = "xla"
  layer_norm: bool = False

  @nn.compact
  def __call__(self, obs: Obs, action: jax.Array) -> jax.Array:
    return jnp.stack([
        Critic(self.hidden, self.conv_features, self.depth_scale, self.conv_impl,
               self.layer_norm, name=f"critic{i}")(obs, action)
        for i in range(self.num)])


class SACNetworks(NamedTuple):
  """The static parts of the agent: modules and the action box (each (A,) float32)."""
  actor: Actor
  critic: TwinCritic
  action_low: jax.Array
  action_high: jax.Array


def make_networks(action_low: Sequence[float], action_high: Sequence[float], hidden: int = 256,
                  conv_features: int = 32, depth_scale: float = 1.0, conv_impl: str = "xla",
                  critic_layer_norm: bool = False) -> SACNetworks:
  """Builds the actor and twin critic for an action box [action_low, action_high].

  `depth_scale` multiplies the depth (metres) before the first conv; the paper's
  networks are `hidden=256, conv_features=32` (two hidden layers). `conv_impl`: how the
  conv towers compute their convolutions (`CONV_IMPLS`; the same parameters either way).
  `critic_layer_norm`: LayerNorm before each hidden ReLU of the critics (not the paper's:
  it adds 4 * hidden parameters per critic).
  """
  low = jnp.asarray(action_low, jnp.float32)
  high = jnp.asarray(action_high, jnp.float32)
  if low.shape != high.shape or low.ndim != 1 or not bool(jnp.all(high > low)):
    raise ValueError(f"bad action box: low={action_low}, high={action_high}")
  hs = (hidden, hidden)
  actor = Actor(int(low.shape[0]), hs, conv_features, depth_scale, conv_impl)
  critic = TwinCritic(hs, conv_features, depth_scale, conv_impl=conv_impl,
                      layer_norm=critic_layer_norm)
  return SACNetworks(actor, critic, low, high)


def make_networks_from_config(cfg, conv_impl: str = "xla", box=None) -> SACNetworks:
  """The networks of a `mjxvine.config.Config`.

  Action box `box` = (low, high), by default the vineyard's `config.action_box`; depth
  scaled by `config.depth_input_scale` so that the tower sees [0, 1]; sizes from `cfg.sac`.
  """
  return make_networks(
      *(action_box(cfg) if box is None else box), hidden=cfg.sac.hidden,
      conv_features=cfg.sac.conv_features, depth_scale=depth_input_scale(cfg),
      conv_impl=conv_impl, critic_layer_norm=cfg.sac.critic_layer_norm)


# ----------------------------------------------------------------------------------------
# How the learner computes the tower on this machine.


def native_towers(nets: SACNetworks) -> bool:
  """Whether the towers of `nets` run as the native kernel, with no XLA convolution (which
  XLA:CPU runs far slower inside a loop body, jax-ml/jax#12868)."""
  return runs_native_tower(nets.actor.conv_impl, nets.actor.conv_features)


def unroll_gradient_steps(nets: SACNetworks, grad_steps: int) -> bool:
  """Whether a loop of `grad_steps` gradient steps is unrolled: on the CPU backend, up to
  16 steps of towers with XLA's convolutions (which XLA:CPU runs ~20x slower inside a
  loop body, jax-ml/jax#12868); rolled elsewhere (one step compiled; the native tower,
  which has no XLA convolution, runs as fast rolled)."""
  return jax.default_backend() == "cpu" and grad_steps <= 16 and not native_towers(nets)


@functools.lru_cache(maxsize=None)
def learner_compiler_options() -> dict | None:
  """XLA compiler options for the programs that take gradient steps (`jax.jit(...,
  compiler_options=...)`), or None.

  On the CPU backend, convolutions are not handed to the YNNPACK library
  (`xla_cpu_experimental_ynn_fusion_type` empty): its convolution is fast forward but
  slow for the gradient w.r.t. the kernel (an 18x18-window convolution of the conv tower),
  which dominates a gradient step; XLA's own convolution takes about half as long there.
  The same numbers to float32 rounding. None on accelerators, and where this jaxlib does
  not know the option.
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
  `train.conv_impl` where it names one; else ("auto") on the CPU backend "native" (the
  whole tower as one hand-written kernel call, `mjxvine.native`: 3-4x the gradient
  steps/s of XLA's tower for `cpu.yaml`) where it builds, else "shift" (the first conv as
  a sum of strided slices); elsewhere "xla", so that accelerator programs and their cost
  analysis are unchanged. Evaluation and export keep XLA's convolution."""
  if choice != "auto":
    return choice
  if jax.default_backend() != "cpu":
    return "xla"
  return "native" if native.available() else "shift"


def resolve_conv_impl(cfg):
  """`cfg` (a `mjxvine.config.Config`) with `train.conv_impl: auto` replaced by the tower
  it takes here (`learner_conv_impl`): what a run records in its config.yaml, so that the
  same config trains the same way, or refuses, on another machine."""
  if cfg.train.conv_impl != "auto":
    return cfg
  return replace(cfg, train={"conv_impl": learner_conv_impl("auto")})


def describe_conv_impl(choice: str = "auto") -> str:
  """`learner_conv_impl(choice)` in words, for a run's log: "native (avx512)", or "shift
  (native: <why not>)" where auto could not take the native tower."""
  impl = learner_conv_impl(choice)
  if impl == "native":
    return f"native ({native.instruction_set()})"
  if choice == "auto" and jax.default_backend() == "cpu":
    return f"{impl} (native: {native.unavailable_reason()})"
  return impl


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

