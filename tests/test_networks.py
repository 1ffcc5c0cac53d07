"""Networks: the paper's exact parameter counts (docs/design.md), shapes, and the squashed Gaussian density."""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjxvine import networks as nw
from mjxvine import tower
from mjxvine.config import load_config

LOW, HIGH = np.array([0.0, -1.0], np.float32), np.array([0.5, 1.0], np.float32)


@pytest.fixture(scope="session")
def spec_nets():
  return nw.make_networks(LOW, HIGH)


def _vine_obs(batch=(1,), size=112):
  return {"depth": jnp.zeros(batch + (size, size, 1)), "state": jnp.zeros(batch + (3,))}


def test_spec_parameter_counts(spec_nets):
  actor, critic = jax.eval_shape(lambda k: nw.init_params(spec_nets, k, _vine_obs()),
                                 jax.random.PRNGKey(0))
  assert nw.num_params(actor) == 104_100
  # Twin critics: two independent critics, each 103,841 parameters.
  assert sorted(critic) == ["critic0", "critic1"]
  assert nw.num_params(critic["critic0"]) == nw.num_params(critic["critic1"]) == 103_841
  one = critic["critic0"]
  tower = one["tower"]
  assert [tower[f"conv{i}"]["kernel"].shape for i in range(4)] == [
      (3, 3, 1, 32), (3, 3, 32, 32), (3, 3, 32, 32), (3, 3, 32, 32)]


def test_tower_spatial_sizes():
  """112 (padded to 113) -> 56 -> 54 -> (pool) 27 -> 13 -> 11; 32 pooled features."""
  tower = nw.ConvTower(32)
  x = jnp.zeros((1, 112, 112, 1))
  _, state = jax.eval_shape(
      lambda k: tower.init_with_output(k, x, capture_intermediates=True),
      jax.random.PRNGKey(0))
  inter = state["intermediates"]
  sizes = [inter[f"conv{i}"]["__call__"][0].shape[1] for i in range(4)]
  assert sizes == [56, 54, 13, 11]
  assert inter["__call__"][0].shape == (1, 32)


def test_actor_critic_shapes_and_batch_dims():
  nets = nw.make_networks(LOW, HIGH, hidden=4, conv_features=2)  # small, to compile fast
  obs = _vine_obs((2, 3), 33)  # the tower works on any image size >= 33 and batch dims

  @jax.jit
  def run(key):
    a_params, c_params = nw.init_params(nets, key, obs)
    mean, log_std = nets.actor.apply({"params": a_params}, obs)
    q = nets.critic.apply({"params": c_params}, obs, jnp.zeros((2, 3, 2)))
    return c_params, mean, log_std, q

  c_params, mean, log_std, q = run(jax.random.PRNGKey(0))
  assert mean.shape == log_std.shape == (2, 3, 2)
  assert np.isfinite(np.asarray(mean)).all()
  assert q.shape == (2, 2, 3)
  # The two critics are independent (different initial parameters).
  k0, k1 = (c_params[f"critic{i}"]["dense0"]["kernel"] for i in range(2))
  assert not np.allclose(k0, k1)


def test_privileged_critics_read_the_lane_state_and_the_actor_does_not():
  nets = nw.make_networks(LOW, HIGH, hidden=8, conv_features=4)
  obs = dict(_vine_obs((2,), 41), lane=jnp.array([[0.3, -0.1, 1.2], [-0.5, 0.2, 0.4]]))
  actor, critic = nw.init_params(nets, jax.random.PRNGKey(0), obs)
  plain_actor, plain_critic = nw.init_params(nets, jax.random.PRNGKey(0), _vine_obs((2,), 41))
  # 3 more inputs to each critic's first dense layer; the actor is the same network
  assert nw.num_params(critic) == nw.num_params(plain_critic) + 2 * 3 * 8
  assert nw.num_params(actor) == nw.num_params(plain_actor)
  other = dict(obs, lane=obs["lane"] + 1.0)
  a = jnp.zeros((2, 2))
  for o in (obs, other):
    np.testing.assert_array_equal(nets.actor.apply({"params": actor}, o)[0],
                                  nets.actor.apply({"params": actor}, _vine_obs((2,), 41))[0])
  q, q_other = (nets.critic.apply({"params": critic}, o, a) for o in (obs, other))
  assert q.shape == (2, 2) and not np.allclose(q, q_other)


def test_tower_rejects_too_small_images(spec_nets):
  assert tower.tower_output_size((112, 112)) == (11, 11)  # padded to 113
  assert tower.tower_output_size((33, 40)) == (1, 2) and tower.MIN_IMAGE_SIZE == 33
  with pytest.raises(ValueError, match="too small"):
    jax.eval_shape(lambda k: nw.init_params(spec_nets, k, _vine_obs((1,), 32)),
                   jax.random.PRNGKey(0))


def test_vector_observation_mlp():
  nets = nw.make_networks([-1.0], [1.0], hidden=16)
  obs = jnp.ones((5, 4))
  a_params, _ = jax.eval_shape(lambda k: nw.init_params(nets, k, obs), jax.random.PRNGKey(1))
  assert "tower" not in a_params
  mean, _ = jax.eval_shape(lambda p: nets.actor.apply({"params": p}, obs), a_params)
  assert mean.shape == (5, 1)
  # 4 -> 16 -> 16 -> 1 (+1 log-std head)
  assert nw.num_params(a_params) == (4 * 16 + 16) + (16 * 16 + 16) + 2 * (16 + 1)


def test_log_std_clipped():
  """The log-std head is clipped to the paper's [-20, 2]."""
  nets = nw.make_networks([-1.0], [1.0], hidden=4)
  obs = jax.random.normal(jax.random.PRNGKey(0), (64, 3)) * 1e4
  init_apply = lambda k: nets.actor.apply(nets.actor.init(k, obs), obs)
  _, log_std = jax.jit(init_apply)(jax.random.PRNGKey(0))
  assert (nw.LOG_STD_MIN, nw.LOG_STD_MAX) == (-20.0, 2.0)
  assert log_std.min() >= np.float32(-20.0) and log_std.max() <= np.float32(2.0)
  assert float(log_std.min()) == -20.0 and float(log_std.max()) == 2.0  # clipped both sides


def test_squashed_log_prob_change_of_variables():
  """log p(a) = log N(u) - log|det da/du|, checked against a finite-difference Jacobian."""
  rng = np.random.default_rng(0)
  low, high = jnp.asarray(LOW), jnp.asarray(HIGH)
  mean = jnp.asarray(rng.normal(size=(50, 2)), jnp.float32)
  log_std = jnp.asarray(rng.uniform(-1.5, 0.5, size=(50, 2)), jnp.float32)
  a, logp = nw.sample_squashed(jax.random.PRNGKey(3), mean, log_std, low, high)
  assert np.all(np.asarray(a) >= LOW) and np.all(np.asarray(a) <= HIGH)
  # Numerical check in float64: invert the map, differentiate it numerically.
  a64, m64, s64 = (np.asarray(x, np.float64) for x in (a, mean, jnp.exp(log_std)))
  lo, hi = LOW.astype(np.float64), HIGH.astype(np.float64)
  u = np.arctanh(2.0 * (a64 - lo) / (hi - lo) - 1.0)
  f = lambda v: lo + 0.5 * (np.tanh(v) + 1.0) * (hi - lo)
  h = 1e-6
  jac = (f(u + h) - f(u - h)) / (2 * h)  # the map is diagonal
  log_nu = np.sum(-0.5 * ((u - m64) / s64) ** 2 - np.log(s64) - 0.5 * np.log(2 * np.pi), -1)
  expected = log_nu - np.sum(np.log(jac), -1)
  np.testing.assert_allclose(np.asarray(logp), expected, rtol=1e-3, atol=2e-3)


def test_squashed_density_integrates_to_one():
  """Over a 1-D box the density of the squashed sample integrates to 1."""
  low, high = jnp.array([-2.0]), jnp.array([3.0])
  a = np.linspace(-2.0, 3.0, 200_001)[1:-1]
  u = np.arctanh(2.0 * (a + 2.0) / 5.0 - 1.0)
  logp = nw.squashed_log_prob(jnp.asarray(u[:, None], jnp.float32), jnp.array([0.3]),
                              jnp.array([-0.2]), low, high)
  total = np.trapezoid(np.exp(np.asarray(logp, np.float64)), a)
  assert abs(total - 1.0) < 1e-3


def test_deterministic_action_maps_mean_into_box():
  low, high = jnp.asarray(LOW), jnp.asarray(HIGH)
  act = nw.deterministic_action(jnp.array([[0.0, 0.0], [50.0, -50.0]]), low, high)
  np.testing.assert_allclose(np.asarray(act), [[0.25, 0.0], [0.5, -1.0]], atol=1e-6)


def test_log_prob_stable_for_saturated_tanh():
  u = jnp.array([[30.0, -30.0]])
  lp = nw.squashed_log_prob(u, jnp.zeros((1, 2)), jnp.zeros((1, 2)), jnp.asarray(LOW),
                            jnp.asarray(HIGH))
  assert np.isfinite(np.asarray(lp)).all()


def _input_reach(hw):
  """|d tower / d pixel| summed over random images and features: (H, W) numpy."""
  tower = nw.ConvTower(features=4)
  x = jax.random.uniform(jax.random.PRNGKey(0), (3,) + tuple(hw) + (1,))
  params = tower.init(jax.random.PRNGKey(1), x)
  grad = jax.grad(lambda x: jnp.sum(tower.apply(params, x) ** 2))(x)
  return np.abs(np.asarray(grad)).sum(axis=(0, 3))


def test_covering_sizes():
  assert [tower.covering_size(n) for n in (33, 40, 41, 64, 65, 112, 113)] == [
      33, 41, 41, 65, 65, 113, 113]
  assert tower.tower_pad((40, 40)) == (1, 1) and tower.tower_pad((41, 112)) == (0, 1)
  # an image of a covering size goes through unchanged; others repeat their last row/column
  x = jnp.arange(40 * 41, dtype=jnp.float32).reshape(1, 40, 41, 1)
  padded = tower.pad_for_tower(x)
  assert padded.shape == (1, 41, 41, 1)
  np.testing.assert_array_equal(padded[0, 40], x[0, 39])
  assert tower.pad_for_tower(padded) is padded


# compare.yaml feeds brax's SAC vector observations (the depth pooled to 8x8): no tower.
@pytest.mark.parametrize("config_file", sorted(
    p.name for p in (Path(__file__).parent.parent / "experiments").glob("*.yaml")
    if p.name != "compare.yaml"))
def test_tower_sees_every_pixel_of_each_config(config_file):
  """Every row and column of each committed config's depth image reaches the tower's
  output (a non-zero gradient), at the config's own image size."""
  cfg = load_config(Path(__file__).parent.parent / "experiments" / config_file)
  reach = _input_reach((cfg.camera.height, cfg.camera.width))
  assert (reach.sum(axis=0) > 0).all(), f"{config_file}: columns without gradient"
  assert (reach.sum(axis=1) > 0).all(), f"{config_file}: rows without gradient"


@pytest.mark.parametrize("stride", [1, 2])
def test_conv3x3_shift_matches_lax_conv_values_and_gradients(stride):
  """The one-channel conv as a sum of 9 strided slices equals XLA's convolution in values
  and gradients (w.r.t. the image and the kernel) to float32 rounding, also for sizes a
  strided conv does not cover evenly."""
  conv, channels = tower.conv3x3_shift, 1
  kx, kk, kd = jax.random.split(jax.random.PRNGKey(0), 3)
  x = jax.random.normal(kx, (2, 12, 11, channels))
  kernel = jax.random.normal(kk, (3, 3, channels, 4))
  ref = lambda x, k: jax.lax.conv_general_dilated(
      x, k, (stride, stride), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC"))
  ours = lambda x, k: conv(x, k, stride)
  y_ref, y = jax.jit(ref)(x, kernel), jax.jit(ours)(x, kernel)
  assert y.shape == y_ref.shape
  np.testing.assert_allclose(y, y_ref, rtol=1e-5, atol=1e-5)
  dy = jax.random.normal(kd, y.shape)
  grads = lambda f: jax.jit(lambda x, k: jax.vjp(f, x, k)[1](dy))(x, kernel)
  for g, g_ref in zip(grads(ours), grads(ref)):
    np.testing.assert_allclose(g, g_ref, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("image, impl", [("random", "shift"), ("constant", "shift")])
def test_other_tower_impls_match_the_xla_tower(image, impl):
  """`conv_impl="shift"` gives the tower's features and gradients (params and input) of
  the XLA tower; on a constant image, whose max-pool windows tie, the gradient goes to
  the same pixel."""
  x = (jax.random.uniform(jax.random.PRNGKey(1), (3, 40, 40, 1), maxval=5.0)
       if image == "random" else jnp.full((3, 40, 40, 1), 2.0))
  towers = [nw.ConvTower(4, 0.2, conv_impl=i) for i in ("xla", impl)]
  params = towers[0].init(jax.random.PRNGKey(0), x)
  params = jax.tree.map(lambda p: p + 0.1, params)  # nonzero biases
  loss = lambda t: jax.jit(jax.value_and_grad(
      lambda p, x: jnp.sum(jnp.sin(t.apply(p, x)) ** 2), argnums=(0, 1)))
  (v_ref, g_ref), (v, g) = (loss(t)(params, x) for t in towers)
  np.testing.assert_allclose(v, v_ref, rtol=1e-5)
  # float32 sums of terms up to max|b| in another order: small entries of a gradient
  # (cancellations) differ by a few 1e-6 of the largest one, more on some CPUs' kernels
  for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(g_ref)):
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5 * float(jnp.max(jnp.abs(b))))
