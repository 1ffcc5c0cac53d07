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
from functools import partial
from typing import Any, Callable, NamedTuple, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from mjxvine.config import action_box, depth_input_scale

Obs = Any  # a dict {"depth", "state"} or a flat vector, with leading batch dims

# Layers of the conv tower: (stride, max-pool 2x2 after it), 3x3 kernels, VALID padding.
CONV_LAYERS = ((2, False), (1, True), (2, False), (1, False))


def covering_size(n: int, layers=CONV_LAYERS) -> int:
  """The smallest input size >= n of which every pixel reaches the tower's output.

  A VALID conv of stride s drops the trailing (n - 3) % s rows, a 2x2 pool an odd last
  row: only sizes whose every layer divides evenly are covered (8k + 1 for
  `CONV_LAYERS`: 41, 65, 113).
  """
  def covers(m):
    for stride, pool in layers:
      if m < 3 or (m - 3) % stride:
        return False
      m = (m - 3) // stride + 1
      if pool:
        if m % 2:
          return False
        m //= 2
    return m >= 1
  m = n
  while not covers(m):
    m += 1
  return m


MIN_IMAGE_SIZE = covering_size(1)  # 33


def tower_pad(hw: Sequence[int]) -> tuple[int, int]:
  """(bottom, right) rows / columns by which the tower pads an (H, W) image."""
  return tuple(covering_size(int(n)) - int(n) for n in hw)


def pad_for_tower(x: jax.Array) -> jax.Array:
  """Pads (N, H, W, C) at its bottom and right by repeating the edge, up to the covering
  size (a departure from the paper's VALID tower, which never sees the last 7 columns of
  a 112- or 40-wide image). Images of a covering size pass unchanged."""
  ph, pw = tower_pad(x.shape[-3:-1])
  if not (ph or pw):
    return x
  return jnp.pad(x, ((0, 0), (0, ph), (0, pw), (0, 0)), mode="edge")


# ----------------------------------------------------------------------------------------
# The tower's convolutions as matrix multiplies (`conv_impl="dot"`, opt-in).
#
# Each 3x3 VALID conv becomes im2col (9 strided slices, concatenated on the channel axis)
# and one dot, with a hand-written gradient that is dots and slices too (never XLA's
# convolution); max pooling becomes a reshape and a max. Exact to float32 rounding. On
# XLA's CPU backend (jax 0.10) the concatenation costs more than the convolutions it
# replaces, so "dot" is never a default; it is kept for
# `python -m mjxvine.bench update --conv-impl dot`.
# `conv_impl="shift"` runs only the first conv, whose image has one channel, as
# `conv3x3_shift`: 1.25x the gradient steps/s of the trainer's CPU step for `cpu.yaml`
# (docs/results/cpu-update-speed.md). The trainer uses it on the CPU
# (`sac.learner_conv_impl`); the default of these functions is "xla".

# `conv_impl="native"` computes the whole tower as one hand-written CPU kernel call
# (`mjxvine.native_conv.tower`, XLA FFI; float32, 8, 16 or 32 features), else as "shift".

CONV_IMPLS = ("xla", "dot", "shift", "native")


def _conv3x3_taps(x: jax.Array, stride: int) -> list[jax.Array]:
  """The 9 strided slices a 3x3 VALID conv reads: (N, H, W, C) -> 9 x (N, Ho, Wo, C),
  Ho = (H - 3) // stride + 1, in (kernel row, kernel column) order."""
  n, h, w, c = x.shape
  ho, wo = (h - 3) // stride + 1, (w - 3) // stride + 1
  return [jax.lax.slice(x, (0, i, j, 0),
                        (n, i + stride * (ho - 1) + 1, j + stride * (wo - 1) + 1, c),
                        (1, stride, stride, 1))
          for i in range(3) for j in range(3)]


def im2col(x: jax.Array, stride: int) -> jax.Array:
  """3x3 VALID patches: (N, H, W, C) -> (N, Ho, Wo, 9 C), Ho = (H - 3) // stride + 1, the
  last axis ordered (kernel row, kernel column, channel) like an HWIO kernel reshaped to
  (9 C, F)."""
  return jnp.concatenate(_conv3x3_taps(x, stride), axis=-1)


def _patch_dot(p: jax.Array, kernel: jax.Array) -> jax.Array:
  """(N, Ho, Wo, 9 C) patches times an HWIO (3, 3, C, F) kernel -> (N, Ho, Wo, F)."""
  return jax.lax.dot_general(p, kernel.reshape(-1, kernel.shape[-1]),
                             (((3,), (0,)), ((), ())))


@partial(jax.custom_vjp, nondiff_argnums=(2,))
def conv3x3_dot(x: jax.Array, kernel: jax.Array, stride: int) -> jax.Array:
  """A 3x3 VALID conv, NHWC x HWIO -> NHWC, as im2col and one dot: x (N, H, W, C),
  kernel (3, 3, C, F) -> (N, Ho, Wo, F). Equal to `lax.conv_general_dilated` to rounding;
  its gradient is dots and slices as well (never XLA's convolution)."""
  return _patch_dot(im2col(x, stride), kernel)


def _conv3x3_dot_fwd(x, kernel, stride):
  return conv3x3_dot(x, kernel, stride), (x, kernel)


def _conv3x3_dot_bwd(stride, res, dy):
  x, kernel = res
  _, h, w, _ = x.shape
  _, ho, wo, f = dy.shape
  # d kernel: patches^T dy, one dot contracting over N * Ho * Wo (the patches are rebuilt
  # from x rather than kept: slices are cheap, a 9x larger residual is not).
  p = im2col(x, stride).reshape(-1, kernel.shape[0] * kernel.shape[1] * kernel.shape[2])
  dk = jax.lax.dot_general(p, dy.reshape(-1, f), (((0,), (0,)), ((), ())))
  # d x: the transposed conv, i.e. a stride-1 conv of dy (dilated by the stride and padded
  # by 2, plus the rows and columns the strided conv skipped) with the flipped kernel.
  eh, ew = h - (stride * (ho - 1) + 3), w - (stride * (wo - 1) + 3)
  zero = jnp.zeros((), dy.dtype)
  dyp = jax.lax.pad(dy, zero, ((0, 0, 0), (2, 2 + eh, stride - 1), (2, 2 + ew, stride - 1),
                               (0, 0, 0)))
  dx = _patch_dot(im2col(dyp, 1), jnp.flip(kernel, (0, 1)).transpose(0, 1, 3, 2))
  return dx.astype(x.dtype), dk.reshape(kernel.shape).astype(kernel.dtype)


conv3x3_dot.defvjp(_conv3x3_dot_fwd, _conv3x3_dot_bwd)


def _is_tower_conv(rhs, window_strides, padding, lhs_dilation, rhs_dilation,
                   feature_group_count) -> bool:
  """Whether `lax.conv_general_dilated`'s arguments (as `nn.Conv` passes them) are one of
  the tower's convs: a 3x3 kernel, VALID, equal strides, no dilation or groups."""
  return (rhs.shape[:2] == (3, 3) and padding == "VALID" and len(set(window_strides)) == 1
          and all(d == 1 for d in (lhs_dilation or ()) + (rhs_dilation or ()))
          and feature_group_count == 1)


def _dot_conv_general_dilated(lhs, rhs, window_strides, padding, lhs_dilation=None,
                              rhs_dilation=None, dimension_numbers=None,
                              feature_group_count=1, precision=None, **_):
  """`lax.conv_general_dilated`'s signature (as `nn.Conv` calls it) for the tower's convs
  only: 3x3 kernels, VALID, equal strides, NHWC, no dilation or groups."""
  del dimension_numbers, precision  # nn.Conv passes NHWC / HWIO, default precision
  if not _is_tower_conv(rhs, window_strides, padding, lhs_dilation, rhs_dilation,
                        feature_group_count):
    raise NotImplementedError("conv3x3_dot: 3x3 VALID convs with equal strides only")
  return conv3x3_dot(lhs, rhs, int(window_strides[0]))


def lax_conv3x3(x: jax.Array, kernel: jax.Array, stride: int) -> jax.Array:
  """XLA's 3x3 VALID conv, x (N, H, W, C) x kernel (3, 3, C, F) -> (N, Ho, Wo, F): the
  reference the tower's other formulations equal, and their fallback."""
  return jax.lax.conv_general_dilated(x, kernel, (stride, stride), "VALID",
                                      dimension_numbers=("NHWC", "HWIO", "NHWC"))


@partial(jax.custom_vjp, nondiff_argnums=(2,))
def conv3x3_shift(x: jax.Array, kernel: jax.Array, stride: int) -> jax.Array:
  """A 3x3 VALID conv of a one-channel image as the sum of its 9 strided slices, each
  times one row of the kernel: x (N, H, W, 1), kernel (3, 3, 1, F) -> (N, Ho, Wo, F).

  One elementwise fusion, about 5x faster forward than XLA's convolution on the CPU for
  the tower's first conv; its gradient is XLA's convolution's (JAX's own derivative of
  the sum is slower). Equal to `lax.conv_general_dilated` to float32 rounding."""
  y = 0.0
  for k, tap in enumerate(_conv3x3_taps(x, stride)):
    y = y + tap * kernel[k // 3, k % 3, 0]
  return y.astype(x.dtype)


def _conv3x3_shift_fwd(x, kernel, stride):
  return conv3x3_shift(x, kernel, stride), (x, kernel)


def _conv3x3_shift_bwd(stride, res, dy):
  x, kernel = res
  return jax.vjp(lambda a, b: lax_conv3x3(a, b, stride), x, kernel)[1](dy)


conv3x3_shift.defvjp(_conv3x3_shift_fwd, _conv3x3_shift_bwd)


def _shift_conv_general_dilated(lhs, rhs, window_strides, padding, lhs_dilation=None,
                                rhs_dilation=None, dimension_numbers=None,
                                feature_group_count=1, precision=None, **kw):
  """`lax.conv_general_dilated`'s signature (as `nn.Conv` calls it): `conv3x3_shift` for
  a one-channel 3x3 VALID conv with equal strides (the tower's first), else XLA's."""
  if rhs.shape[2] == 1 and _is_tower_conv(rhs, window_strides, padding, lhs_dilation,
                                           rhs_dilation, feature_group_count):
    return conv3x3_shift(lhs, rhs, int(window_strides[0]))
  return jax.lax.conv_general_dilated(lhs, rhs, window_strides, padding, lhs_dilation,
                                      rhs_dilation, dimension_numbers, feature_group_count,
                                      precision=precision, **kw)


# what `nn.Conv` calls instead of `lax.conv_general_dilated`, per `conv_impl` ("xla": none)
# ("native": where `native_conv.tower` does not compute the tower, as "shift")
_CONV_HOOKS = {"dot": _dot_conv_general_dilated, "shift": _shift_conv_general_dilated,
               "native": _shift_conv_general_dilated}


def max_pool_2x2(x: jax.Array) -> jax.Array:
  """2x2 max pool, stride 2, VALID, of (N, H, W, C) -> (N, H // 2, W // 2, C) as a reshape
  and a max. Its gradient goes, like XLA's reduce_window / select_and_scatter, to the
  first maximum of each window in row-major order (also where several are equal)."""
  n, h, w, c = x.shape
  x = x[:, :h // 2 * 2, :w // 2 * 2].reshape(n, h // 2, 2, w // 2, 2, c)
  a, b, d, e = x[:, :, 0, :, 0], x[:, :, 0, :, 1], x[:, :, 1, :, 0], x[:, :, 1, :, 1]
  m = jax.lax.stop_gradient(jnp.maximum(jnp.maximum(a, b), jnp.maximum(d, e)))
  return jnp.where(a == m, a, jnp.where(b == m, b, jnp.where(d == m, d, e)))


class _ConvParams(nn.Module):
  """An `nn.Conv`'s 3x3 params, (kernel (3, 3, in_features, features), bias (features,)),
  under its names and initialisers, for a tower computed by `native_conv.tower`."""
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
  (`native_conv.tower`): "native", float32, and features the kernel covers; else its
  convs are XLA's."""
  if conv_impl != "native" or jnp.dtype(dtype) != jnp.float32:
    return False
  from mjxvine import native_conv  # pylint: disable=import-outside-toplevel
  return native_conv.supports_tower(features)


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
  # tower as `native_conv.tower` where it applies: float32, 8, 16 or 32 features; else
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
      from mjxvine import native_conv
      if not native_conv.available():
        raise RuntimeError(f"conv_impl 'native': {native_conv.unavailable_reason()}")
      if runs_native_tower(self.conv_impl, self.features, self.dtype):
        params, c = [], x.shape[-1]
        for i in range(len(CONV_LAYERS)):
          params.append(_ConvParams(c, self.features, name=f"conv{i}")())
          c = self.features
        return native_conv.tower(x, params).reshape(batch_shape + (self.features,))
    dot = self.conv_impl == "dot"
    hook = _CONV_HOOKS.get(self.conv_impl)
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


def tower_output_size(hw: Sequence[int]) -> tuple[int, ...]:
  """Spatial size after the last conv for an image of size hw (after `pad_for_tower`)."""
  out = []
  for n in hw:
    n = covering_size(n)
    for stride, pool in CONV_LAYERS:
      n = (n - 3) // stride + 1
      n = n // 2 if pool else n
    out.append(n)
  return tuple(out)


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

  @nn.compact
  def __call__(self, obs: Obs) -> tuple[jax.Array, jax.Array]:
    x = _torso_input(obs, self.conv_features, self.depth_scale, dtype=self.dtype,
                     conv_impl=self.conv_impl)
    for i, h in enumerate(self.hidden):
      x = nn.relu(nn.Dense(h, dtype=self.dtype, name=f"dense{i}")(x))
    x = x.astype(jnp.float32)
    mean = nn.Dense(self.action_size, name="mean")(x)
    log_std = nn.Dense(self.action_size, name="log_std")(x)
    return mean, jnp.clip(log_std, self.log_std_min, self.log_std_max)


class Critic(nn.Module):
  """One Q network: `__call__(obs, action (..., A)) -> q (...,)`, with its own tower."""
  hidden: Sequence[int] = (256, 256)
  conv_features: int = 32
  depth_scale: float = 1.0
  dtype: Any = jnp.float32
  conv_impl: str = "xla"

  @nn.compact
  def __call__(self, obs: Obs, action: jax.Array) -> jax.Array:
    x = _torso_input(obs, self.conv_features, self.depth_scale, extra=(action,),
                     dtype=self.dtype, conv_impl=self.conv_impl)
    for i, h in enumerate(self.hidden):
      x = nn.relu(nn.Dense(h, dtype=self.dtype, name=f"dense{i}")(x))
    return nn.Dense(1, name="q")(x.astype(jnp.float32))[..., 0]


class CriticHead(nn.Module):
  """A critic's layers after its tower: `__call__(x) -> q (...,)` on x = [features, state,
  action]. Its params are a `Critic`'s without "tower" (the same names), so that
  `twin_critic_features` and `twin_critic_heads` split one critic evaluation in two."""
  hidden: Sequence[int] = (256, 256)
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    for i, h in enumerate(self.hidden):
      x = nn.relu(nn.Dense(h, dtype=self.dtype, name=f"dense{i}")(x))
    return nn.Dense(1, name="q")(x.astype(jnp.float32))[..., 0]


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

  @nn.compact
  def __call__(self, obs: Obs, action: jax.Array) -> jax.Array:
    return jnp.stack([
        Critic(self.hidden, self.conv_features, self.depth_scale, self.dtype, self.conv_impl,
               name=f"critic{i}")(obs, action)
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
  head = CriticHead(critic.hidden, critic.dtype)
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
                  compute_dtype: str = "float32", conv_impl: str = "xla") -> SACNetworks:
  """Builds the actor and twin critic for an action box [action_low, action_high].

  `depth_scale` multiplies the depth (metres) before the first conv; the paper's
  networks are `hidden=256, conv_features=32` (two hidden layers). `compute_dtype`: "float32"
  or "bfloat16" (mixed precision, see the module docstring). `conv_impl`: how the conv
  towers compute their convolutions (`CONV_IMPLS`; the same parameters either way).
  """
  dtype = jnp.dtype(compute_dtype)
  low = jnp.asarray(action_low, jnp.float32)
  high = jnp.asarray(action_high, jnp.float32)
  if low.shape != high.shape or low.ndim != 1 or not bool(jnp.all(high > low)):
    raise ValueError(f"bad action box: low={action_low}, high={action_high}")
  hs = (hidden, hidden)
  actor = Actor(int(low.shape[0]), hs, conv_features, depth_scale, log_std_min, log_std_max,
                dtype, conv_impl)
  critic = TwinCritic(hs, conv_features, depth_scale, dtype=dtype, conv_impl=conv_impl)
  return SACNetworks(actor, critic, low, high)


def native_towers(nets: SACNetworks) -> bool:
  """Whether the towers of `nets` run as the native kernel, with no XLA convolution (which
  XLA:CPU runs far slower inside a loop body, jax-ml/jax#12868)."""
  return runs_native_tower(nets.actor.conv_impl, nets.actor.conv_features, nets.actor.dtype)


def make_networks_from_config(cfg, conv_impl: str = "xla") -> SACNetworks:
  """The vineyard networks of a `mjxvine.config.Config`.

  Action box `config.action_box`; depth scaled by `config.depth_input_scale` so that the
  tower sees [0, 1]; sizes and log-std bounds from `cfg.sac`.
  """
  return make_networks(
      *action_box(cfg), hidden=cfg.sac.hidden,
      conv_features=cfg.sac.conv_features, depth_scale=depth_input_scale(cfg),
      log_std_min=cfg.sac.log_std_min, log_std_max=cfg.sac.log_std_max,
      compute_dtype=cfg.sac.compute_dtype, conv_impl=conv_impl)


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
