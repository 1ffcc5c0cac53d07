"""SAC: losses against numpy, Polyak, bootstrapping, replay buffer, exploration, learning."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjxvine import depth
from mjxvine import native
from mjxvine import networks as nw
from mjxvine import sac
from mjxvine.config import SACConfig
from mjxvine.training import schedules

LOW, HIGH = np.array([0.0, -1.0], np.float32), np.array([0.5, 1.0], np.float32)
GAMMA, ALPHA, B = 0.9, 0.3, 6


# ----------------------------------------------------------------------------------------
# Tiny vector-observation networks and a hand-written numpy reference.


@pytest.fixture(scope="session")
def tiny():
  """Tiny nets (obs 3 -> 8 -> 8), params, a fixed batch and the jitted loss functions."""
  nets = nw.make_networks(LOW, HIGH, hidden=8)
  rng = np.random.default_rng(0)
  f32 = lambda x: jnp.asarray(x, jnp.float32)
  batch = sac.Transition(
      obs=f32(rng.normal(size=(B, 3))), action=f32(rng.uniform(LOW, HIGH, size=(B, 2))),
      reward=f32(rng.normal(size=B)), terminal=f32([0, 1, 0, 0, 1, 0]),
      truncated=f32([0, 0, 1, 0, 1, 0]), next_obs=f32(rng.normal(size=(B, 3))))
  actor, critic = jax.jit(lambda k: nw.init_params(nets, k, batch.obs))(jax.random.PRNGKey(0))
  # A target that differs from the online critic.
  target = jax.tree.map(lambda x: x + 0.05 * np.sin(np.arange(x.size).reshape(x.shape)), critic)
  fns = dict(
      critic_loss=jax.jit(lambda c, t, a, b, k: sac.critic_loss(c, t, a, ALPHA, b, k, nets, GAMMA)),
      actor_loss=jax.jit(lambda a, c, b, k: sac.actor_loss(a, c, ALPHA, b, k, nets)),
      target=jax.jit(lambda a, t, b, k: sac.critic_target(nets, a, t, ALPHA, b, k, GAMMA)))
  return nets, actor, critic, target, batch, fns


def _np(tree):
  return jax.tree.map(lambda x: np.asarray(x, np.float64), tree)


def _np_torso(p, x):
  h = np.maximum(x @ p["dense0"]["kernel"] + p["dense0"]["bias"], 0)
  return np.maximum(h @ p["dense1"]["kernel"] + p["dense1"]["bias"], 0)


def _np_actor_sample(p, obs, key):
  """Reparameterised squashed sample and its log-prob, by hand. Noise from `key`."""
  h = _np_torso(p, obs)
  mean = h @ p["mean"]["kernel"] + p["mean"]["bias"]
  log_std = np.clip(h @ p["log_std"]["kernel"] + p["log_std"]["bias"], -20, 2)
  noise = np.asarray(jax.random.normal(key, mean.shape, jnp.float32), np.float64)
  u = mean + np.exp(log_std) * noise
  a = LOW + (np.tanh(u) + 1) / 2 * (HIGH - LOW)
  logp = np.sum(-0.5 * noise**2 - log_std - 0.5 * np.log(2 * np.pi), -1)
  logp -= np.sum(np.log(1 - np.tanh(u) ** 2) + np.log((HIGH - LOW) / 2), -1)
  return a, logp


def _np_q(p, obs, action):
  """(2, B) twin Q values by hand."""
  out = []
  for i in range(2):
    pi = p[f"critic{i}"]
    h = _np_torso(pi, np.concatenate([obs, action], -1))
    out.append((h @ pi["q"]["kernel"] + pi["q"]["bias"])[:, 0])
  return np.stack(out)


def _np_target(actor, target, batch, key):
  next_a, next_logp = _np_actor_sample(actor, batch.next_obs, key)
  next_v = _np_q(target, batch.next_obs, next_a).min(0) - ALPHA * next_logp
  return batch.reward + GAMMA * (1 - batch.terminal) * next_v


def test_critic_loss_matches_numpy(tiny):
  nets, actor, critic, target, batch, fns = tiny
  key = jax.random.PRNGKey(7)
  loss, aux = fns["critic_loss"](critic, target, actor, batch, key)
  a, c, t, b = _np(actor), _np(critic), _np(target), _np(batch._replace(weight=None))
  y = _np_target(a, t, b, key)
  q = _np_q(c, b.obs, b.action)
  np.testing.assert_allclose(np.asarray(aux["target"]), y, rtol=1e-5, atol=1e-5)
  np.testing.assert_allclose(np.asarray(aux["q"]), q, rtol=1e-5, atol=1e-5)
  expected = np.mean(0.5 * np.sum((q - y) ** 2, 0))
  np.testing.assert_allclose(float(loss), expected, rtol=1e-5)
  # Per-sample weights: a weighted mean (zero weight drops the sample).
  w = np.array([1, 0, 1, 1, 0, 1], np.float32)
  wloss, _ = fns["critic_loss"](critic, target, actor, batch._replace(weight=jnp.asarray(w)), key)
  expected_w = np.sum(w * 0.5 * np.sum((q - y) ** 2, 0)) / w.sum()
  np.testing.assert_allclose(float(wloss), expected_w, rtol=1e-5)


def test_actor_loss_matches_numpy(tiny):
  nets, actor, critic, _, batch, fns = tiny
  key = jax.random.PRNGKey(11)
  loss, (logp, _) = fns["actor_loss"](actor, critic, batch, key)
  a, c, b = _np(actor), _np(critic), _np(batch._replace(weight=None))
  act, np_logp = _np_actor_sample(a, b.obs, key)
  np.testing.assert_allclose(np.asarray(logp), np_logp, rtol=1e-4, atol=1e-4)
  expected = np.mean(ALPHA * np_logp - _np_q(c, b.obs, act).min(0))
  np.testing.assert_allclose(float(loss), expected, rtol=1e-4, atol=1e-5)


def test_anchor_adds_the_squared_gap_to_the_loaded_actors_action(tiny):
  """sac.anchor_weight: the actor's loss grows by w * mean_b ||tanh(mu) - tanh(mu_0)||^2,
  and its gradient pulls the actor's test-time action towards the anchor's."""
  nets, actor, critic, _, batch, _ = tiny
  key, w = jax.random.PRNGKey(11), 3.0
  anchor = jax.tree.map(lambda x: x + 0.05 * jnp.sign(x), actor)
  plain, _ = sac.actor_loss(actor, critic, ALPHA, batch, key, nets)
  loss, (_, gap) = sac.actor_loss(actor, critic, ALPHA, batch, key, nets, anchor, w)
  mean = nets.actor.apply({"params": actor}, batch.obs)[0]
  mean0 = nets.actor.apply({"params": anchor}, batch.obs)[0]
  expected_gap = np.mean(np.sum((np.tanh(mean) - np.tanh(mean0)) ** 2, -1))
  assert expected_gap > 1e-4
  np.testing.assert_allclose(float(gap), expected_gap, rtol=1e-4)
  np.testing.assert_allclose(float(loss), float(plain) + w * expected_gap, rtol=1e-4, atol=1e-6)
  # the anchor itself: no pull
  _, (_, none) = sac.actor_loss(anchor, critic, ALPHA, batch, key, nets, anchor, w)
  assert float(none) == 0.0
  # a step down the pull alone shortens the gap
  def pull(params):
    return sac.actor_loss(params, critic, ALPHA, batch, key, nets, anchor, w)[1][1]
  grads = jax.grad(pull)(actor)
  moved = jax.tree.map(lambda p, g: p - 0.01 * g, actor, grads)
  assert float(pull(moved)) < float(gap)


def test_alpha_loss_gradient_direction():
  logp = jnp.array([1.0, 3.0])  # entropy -2 < target 0: alpha must grow
  g = jax.grad(sac.alpha_loss)(jnp.float32(0.0), logp, 0.0)
  assert float(g) == pytest.approx(-2.0)
  np.testing.assert_allclose(float(sac.alpha_loss(jnp.float32(0.5), logp, -2.0)), -0.5 * 0.0)


def test_terminal_zeroes_bootstrap_truncation_does_not(tiny):
  nets, actor, _, target, batch, fns = tiny
  key = jax.random.PRNGKey(3)
  zeros = jnp.zeros(B)
  plain = fns["target"](actor, target, batch._replace(terminal=zeros, truncated=zeros), key)
  truncated = fns["target"](actor, target, batch._replace(terminal=zeros, truncated=zeros + 1),
                            key)
  terminal = fns["target"](actor, target, batch._replace(terminal=zeros + 1, truncated=zeros),
                           key)
  both = fns["target"](actor, target, batch._replace(terminal=zeros + 1, truncated=zeros + 1),
                       key)
  np.testing.assert_allclose(np.asarray(truncated), np.asarray(plain), rtol=1e-6)
  np.testing.assert_allclose(np.asarray(terminal), np.asarray(batch.reward), rtol=1e-6)
  np.testing.assert_allclose(np.asarray(both), np.asarray(batch.reward), rtol=1e-6)
  assert not np.allclose(np.asarray(plain), np.asarray(batch.reward))


def test_polyak():
  target = {"a": jnp.array([0.0, 4.0]), "b": {"c": jnp.array(8.0)}}
  online = {"a": jnp.array([4.0, 0.0]), "b": {"c": jnp.array(0.0)}}
  out = sac.polyak(target, online, 0.25)
  np.testing.assert_allclose(np.asarray(out["a"]), [1.0, 3.0])
  np.testing.assert_allclose(float(out["b"]["c"]), 6.0)


def test_update_step(tiny):
  """One jitted step with alpha tuning (fixed alpha is checked in the learning test)."""
  nets, _, _, _, batch, _ = tiny
  cfg = SACConfig(tau=0.1, auto_alpha=True, target_entropy=50.0)
  agent = sac.make_sac(nets, cfg)
  state = jax.jit(agent.init)(jax.random.PRNGKey(1), batch.obs)
  assert float(jnp.exp(state.log_alpha)) == pytest.approx(0.2)
  new, metrics = jax.jit(agent.update)(state, batch, jax.random.PRNGKey(2))
  assert int(new.step) == 1
  assert all(np.isfinite(float(v)) for v in metrics.values())
  # Target = (1 - tau) old target + tau new online critic.
  expect = jax.tree.map(lambda t, o: 0.9 * t + 0.1 * o, state.target_critic_params,
                        new.critic_params)
  jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-7),
               new.target_critic_params, expect)
  changed = lambda a, b: not all(jax.tree.leaves(jax.tree.map(np.allclose, a, b)))
  assert changed(new.actor_params, state.actor_params)
  assert changed(new.critic_params, state.critic_params)
  # Target entropy far above the policy's: alpha grows (by lr, Adam's first step).
  assert float(new.log_alpha) == pytest.approx(float(state.log_alpha) + cfg.learning_rate)


# ----------------------------------------------------------------------------------------
# Replay buffer.


def test_quantisation_round_trip():
  d = jax.random.uniform(jax.random.PRNGKey(0), (10_000,), minval=0.0, maxval=5.0)
  for dtype, bound in ((jnp.uint16, 5.0 / (2 * 65535)), (jnp.uint8, 5.0 / (2 * 255))):
    q = depth.quantize_depth(d, 5.0, dtype)
    assert q.dtype == dtype
    err = np.abs(np.asarray(depth.dequantize_depth(q, 5.0)) - np.asarray(d))
    assert err.max() <= bound * 1.001 + 1e-6
    edge = depth.dequantize_depth(depth.quantize_depth(jnp.array([-1.0, jnp.nan, 0.0, 5.0, 7.0]),
                                                   5.0, dtype), 5.0)
    np.testing.assert_allclose(np.asarray(edge), [0.0, 0.0, 0.0, 5.0, 5.0])


def _frame(value, n=2, size=4):
  return jnp.broadcast_to(jnp.asarray(value, jnp.float32)[:, None, None, None], (n, size, size, 1))


def _depth_value(t, env):
  return 0.1 * t + 0.01 * env + 0.5


def test_buffer_depth_frames_wraparound_and_truncation():
  """Frames stored once; next frame from the next row, or the side ring on truncation."""
  n = 2
  obs0 = {"depth": _frame([0.0, 0.0]), "state": jnp.zeros((n, 3))}
  buf = sac.init_buffer(obs0, 2, capacity=8, final_slots=2)  # 4 rows of 2 envs
  assert buf.num_rows == 4 and buf.capacity == 8
  terminal = {(1, 1), (2, 1)}
  truncated = {(2, 0), (3, 0), (3, 1), (2, 1)}  # (2, 1) is also terminal: no side frame
  insert = jax.jit(sac.insert)
  for t in range(5):
    env = np.arange(n)
    final = [4.5 + 0.01 * e + 0.1 * t for e in env]
    tr = sac.Transition(
        obs={"depth": _frame(_depth_value(t, env)),
             "state": jnp.asarray(np.stack([np.full(n, t), env, np.zeros(n)], -1), jnp.float32)},
        action=jnp.asarray(np.stack([np.full(n, t), env], -1), jnp.float32),
        reward=jnp.asarray(10.0 * t + env, jnp.float32),
        terminal=jnp.asarray([(t, e) in terminal for e in env], jnp.float32),
        truncated=jnp.asarray([(t, e) in truncated for e in env], jnp.float32),
        next_obs={"depth": _frame(final),  # only read where truncated
                  "state": jnp.asarray(np.stack([np.full(n, t + 1), env, np.zeros(n)], -1),
                                       jnp.float32)})
    buf = insert(buf, tr)
  assert int(sac.num_sampleable(buf)) == 6
  batch = jax.jit(sac.sample, static_argnums=2)(buf, jax.random.PRNGKey(0), 512)
  b = jax.tree.map(np.asarray, batch)
  t, env = b.obs["state"][:, 0].astype(int), b.obs["state"][:, 1].astype(int)
  assert set(zip(t, env)) == {(tt, e) for tt in (1, 2, 3) for e in (0, 1)}  # rows 1..3
  np.testing.assert_array_equal(b.next_obs["state"][:, 0], t + 1)
  np.testing.assert_array_equal(b.action[:, 0], t)
  np.testing.assert_allclose(b.reward, 10.0 * t + env)
  np.testing.assert_allclose(b.obs["depth"][:, 0, 0, 0], _depth_value(t, env), atol=1e-4)
  assert b.obs["depth"].shape == (512, 4, 4, 1) and b.obs["depth"].dtype == np.float32
  for i in range(512):
    key = (t[i], env[i])
    assert b.terminal[i] == (key in terminal) and b.truncated[i] == (key in truncated)
    nd = b.next_obs["depth"][i]
    if key == (2, 0):  # its side frame was reused by the third truncation: weight 0
      assert b.weight[i] == 0.0
      continue
    assert b.weight[i] == 1.0
    if key in truncated and key not in terminal:
      np.testing.assert_allclose(nd, 4.5 + 0.01 * env[i] + 0.1 * t[i], atol=1e-4)
    elif key not in terminal and key not in truncated:
      np.testing.assert_allclose(nd, _depth_value(t[i] + 1, env[i]), atol=1e-4)


def test_n_step_transitions_stop_at_the_end_of_an_episode():
  """`sample(..., n_step=3)` sums up to 3 discounted rewards of one episode, then
  bootstraps from the successor of its last step (the next row's frame, or the side frame
  of a truncation) with discount gamma^steps; a weight-0 step inside the window gives
  weight 0. Checked against a walk over the inserted steps."""
  n, steps, n_step, gamma = 2, 12, 3, 0.9
  obs0 = {"depth": _frame([0.0, 0.0]), "state": jnp.zeros((n, 3))}
  buf = sac.init_buffer(obs0, 2, capacity=2 * 16)
  rng = np.random.default_rng(3)
  reward = rng.normal(size=(steps, n)).astype(np.float32)
  terminal = {(3, 0), (7, 1)}
  truncated = {(5, 1), (9, 0)}
  invalid = {(6, 0)}
  insert = jax.jit(sac.insert)
  for t in range(steps):
    env = np.arange(n)
    tr = sac.Transition(
        obs={"depth": _frame(_depth_value(t, env)),
             "state": jnp.asarray(np.stack([np.full(n, t), env, np.zeros(n)], -1), jnp.float32)},
        action=jnp.zeros((n, 2)), reward=jnp.asarray(reward[t]),
        terminal=jnp.asarray([(t, e) in terminal for e in env], jnp.float32),
        truncated=jnp.asarray([(t, e) in truncated for e in env], jnp.float32),
        next_obs={"depth": _frame([3.0 + 0.01 * e + 0.1 * t for e in env]),
                  "state": jnp.asarray(np.stack([np.full(n, t + 1), env, np.zeros(n)], -1),
                                       jnp.float32)},
        weight=jnp.asarray([(t, e) not in invalid for e in env], jnp.float32))
    buf = insert(buf, tr)
  draw = jax.jit(sac.sample, static_argnums=(2, 3))
  b = jax.tree.map(np.asarray, draw(buf, jax.random.PRNGKey(0), 1024, n_step, gamma))
  t, env = b.obs["state"][:, 0].astype(int), b.obs["state"][:, 1].astype(int)
  assert set(zip(t, env)) == {(tt, e) for tt in range(steps - n_step) for e in range(n)}
  for i in range(1024):
    ret, k, ok = 0.0, 0, True
    while True:  # the reference walk
      ret += gamma ** k * reward[t[i] + k, env[i]]
      ok &= (t[i] + k, env[i]) not in invalid
      last = (t[i] + k, env[i])
      k += 1
      if last in terminal or last in truncated or k == n_step:
        break
    np.testing.assert_allclose(b.reward[i], ret, rtol=1e-5)
    np.testing.assert_allclose(b.discount[i], gamma ** k, rtol=1e-6)
    assert b.weight[i] == ok
    assert b.terminal[i] == (last in terminal) and b.truncated[i] == (last in truncated)
    assert b.next_obs["state"][i, 0] == last[0] + 1
    if last in truncated:
      np.testing.assert_allclose(b.next_obs["depth"][i], 3.0 + 0.01 * last[1] + 0.1 * last[0],
                                 atol=1e-4)
    elif last not in terminal:
      np.testing.assert_allclose(b.next_obs["depth"][i], _depth_value(last[0] + 1, last[1]),
                                 atol=1e-4)
  one = draw(buf, jax.random.PRNGKey(0), 64, 1, gamma)
  assert one.discount is None  # one step: the learner's gamma


def test_critic_target_uses_the_batch_discount(tiny):
  """An n-step batch's discount replaces gamma in the TD target."""
  nets, actor, critic, target, batch, fns = tiny
  key = jax.random.PRNGKey(7)
  y = fns["target"](actor, target, batch, key)
  discount = jnp.full(batch.reward.shape, GAMMA ** 3)
  y3 = fns["target"](actor, target, batch._replace(discount=discount), key)
  boot = (1 - np.asarray(batch.terminal)) * (np.asarray(y) - np.asarray(batch.reward)) / GAMMA
  np.testing.assert_allclose(y3, np.asarray(batch.reward) + GAMMA ** 3 * boot, rtol=1e-5,
                             atol=1e-6)


def test_buffer_vector_observations():
  n = 3
  buf = sac.init_buffer(jnp.zeros((n, 4)), 1, capacity=12)  # 4 rows
  assert buf.depth is None
  insert = jax.jit(sac.insert)
  for t in range(6):
    obs = jnp.tile(jnp.arange(n, dtype=jnp.float32)[:, None], (1, 4)) + 100.0 * t
    buf = insert(buf, sac.Transition(obs, jnp.full((n, 1), t, jnp.float32), jnp.zeros(n),
                                     jnp.zeros(n), jnp.zeros(n), obs + 0.5))
  b = jax.tree.map(np.asarray, jax.jit(sac.sample, static_argnums=2)(buf, jax.random.PRNGKey(1),
                                                                      256))
  t = b.action[:, 0].astype(int)
  assert set(t) == {2, 3, 4}  # after wrap-around, the newest row (t=5) waits
  np.testing.assert_allclose(b.next_obs, b.obs + 0.5)
  assert set(np.round(b.obs[:, 0] - 100.0 * t).astype(int)) == {0, 1, 2}  # the env index
  assert (b.weight == 1.0).all()


def test_buffer_bytes_per_transition():
  """1e6 transitions of 112x112 depth fit in 16 GB with uint8 frames stored once."""
  def make(dtype):
    obs = {"depth": jax.ShapeDtypeStruct((1000, 112, 112, 1), jnp.float32),
           "state": jax.ShapeDtypeStruct((1000, 3), jnp.float32)}
    return jax.eval_shape(lambda: sac.init_buffer(obs, 2, 1_000_000, depth_dtype=dtype))
  per8 = sac.buffer_nbytes(make(jnp.uint8)) / 1e6
  per16 = sac.buffer_nbytes(make(jnp.uint16)) / 1e6
  assert per8 < 13_000 and per8 * 1e6 < 16e9
  assert per16 < 26_000  # uint16: 100k-200k transitions (docs/design.md) in 2.6-5.1 GB


# ----------------------------------------------------------------------------------------
# Exploration.


def test_explore_action():
  n = 20_000
  low, high = jnp.asarray(LOW), jnp.asarray(HIGH)
  policy = jnp.tile(jnp.array([[0.3, 0.1]]), (n, 1))
  warm = np.asarray(schedules.explore_action(jax.random.PRNGKey(0), policy, jnp.zeros(n), low, high,
                                       True))
  assert (warm >= LOW).all() and (warm <= HIGH).all()
  np.testing.assert_allclose(warm.mean(0), (LOW + HIGH) / 2, atol=0.02)
  assert abs(np.corrcoef(warm.T)[0, 1]) < 0.05  # each dimension drawn independently
  greedy = schedules.explore_action(jax.random.PRNGKey(1), policy, jnp.zeros(n), low, high, False)
  np.testing.assert_array_equal(np.asarray(greedy), np.asarray(policy))
  mixed = np.asarray(schedules.explore_action(jax.random.PRNGKey(2), policy, jnp.full(n, 0.3), low,
                                        high, False))
  assert abs(np.mean(np.any(mixed != np.asarray(policy), -1)) - 0.3) < 0.02


def test_epsilon_schedule_is_global_over_envs():
  """Epsilon follows the fraction of the env-step budget summed over all envs: a run of 1
  env and one of 256 envs have the same epsilon at the same fraction, and the paper's
  values (1.0 * 0.992 per episode of 1500) reach the 0.05 floor at 25 % of the budget."""
  cfg = SACConfig()
  total = 1_050_000
  for n in (1, 256):
    steps = np.arange(0, total + n, n * max(1, 4096 // n))  # the iterations' counters
    eps = np.asarray(jax.vmap(lambda t: schedules.epsilon(cfg, t, total))(jnp.asarray(steps)))
    expect = np.maximum(0.992 ** (1500 * steps / total), 0.05)
    np.testing.assert_allclose(eps, expect, rtol=1e-4)
    assert eps[0] == pytest.approx(1.0) and eps[-1] == pytest.approx(0.05)
    floor_at = steps[np.argmax(eps <= 0.05 + 1e-6)] / total
    assert 0.24 < floor_at < 0.26, (n, floor_at)
  # eps_start scales the curve; eps_start = eps_min = 0: no epsilon-greedy at all
  half = SACConfig(eps_start=0.5)
  assert float(schedules.epsilon(half, 100_000, 1_000_000)) == pytest.approx(
      0.5 * 0.992 ** 150, rel=1e-4)
  assert float(schedules.epsilon(SACConfig(eps_start=0.0, eps_min=0.0), 0, total)) == 0.0


# ----------------------------------------------------------------------------------------
# Learning: a 1-D point mass that must move to a goal given in its observation.

T_TOY, N_TOY = 20, 16


def _toy_reset(key):
  """Observation [x, goal], both uniform in [-1, 1]; returns (obs (N, 2), t (N,))."""
  return jax.random.uniform(key, (N_TOY, 2), minval=-1.0, maxval=1.0), jnp.zeros(N_TOY, jnp.int32)


def _toy_step(obs, t, action):
  """x <- clip(x + 0.25 a, +-2); reward -|x - goal|; truncated after T_TOY steps."""
  x = jnp.clip(obs[:, 0] + 0.25 * action[:, 0], -2.0, 2.0)
  return obs.at[:, 0].set(x), t + 1, -jnp.abs(x - obs[:, 1]), t + 1 >= T_TOY


def _toy_return(policy, key):
  """Mean undiscounted return of `policy(obs, key) -> action` over N_TOY episodes."""
  obs, t = _toy_reset(key)
  def body(carry, k):
    obs, t = carry
    obs, t, r, _ = _toy_step(obs, t, policy(obs, k))
    return (obs, t), r
  _, rewards = jax.lax.scan(body, (obs, t), jax.random.split(key, T_TOY))
  return float(rewards.sum(0).mean())


def _train_toy(seed, iterations=500):
  """Trains SAC on the toy task; returns (learned return, random-policy return)."""
  cfg = SACConfig(learning_rate=1e-3, gamma=0.9, alpha=0.02, batch_size=64, warmup_steps=100,
                  eps_min=0.07)
  nets = nw.make_networks([-1.0], [1.0], hidden=64)
  agent = sac.make_sac(nets, cfg)
  k_env, k_init, key = jax.random.split(jax.random.PRNGKey(seed), 3)
  obs, t = _toy_reset(k_env)
  learner = agent.init(k_init, obs)
  buffer = sac.init_buffer(obs, 1, capacity=N_TOY * 1000)
  zeros = jnp.zeros(N_TOY)

  def iteration(carry, i):
    obs, t, learner, buffer, key = carry
    key, k_act, k_explore, k_reset, k_update = jax.random.split(key, 5)
    eps = schedules.epsilon(cfg, i, iterations)
    action = schedules.explore_action(k_explore, agent.act(learner.actor_params, obs, k_act), eps,
                                nets.action_low, nets.action_high, i < cfg.warmup_steps)
    next_obs, t, reward, trunc = _toy_step(obs, t, action)
    buffer = sac.insert(buffer, sac.Transition(obs, action, reward, zeros, trunc, next_obs))
    learner = jax.lax.cond(i >= 1, lambda: agent.update_many(learner, buffer, k_update)[0],
                           lambda: learner)
    reset_obs, _ = _toy_reset(k_reset)
    obs = jnp.where(trunc[:, None], reset_obs, next_obs)
    return (obs, jnp.where(trunc, 0, t), learner, buffer, key), None

  carry = (obs, t, learner, buffer, key)
  carry, _ = jax.jit(lambda c: jax.lax.scan(iteration, c, jnp.arange(iterations)))(carry)
  learner = carry[2]
  eval_key = jax.random.PRNGKey(123)
  learned = _toy_return(lambda o, k: agent.act_deterministic(learner.actor_params, o), eval_key)
  rand = _toy_return(lambda o, k: jax.random.uniform(k, (N_TOY, 1), minval=-1, maxval=1),
                     eval_key)
  assert float(jnp.exp(learner.log_alpha)) == pytest.approx(cfg.alpha)  # fixed alpha
  assert int(learner.step) == iterations - 1
  return learned, rand


def test_sac_learns_point_mass():
  learned, rand = _train_toy(0)
  assert rand < -8.0
  assert learned > -3.0, (learned, rand)


@pytest.mark.skipif(not os.environ.get("MJXVINE_SLOW_TESTS"),
                    reason="compiles a brax env (~40 s on 2 CPU cores); set MJXVINE_SLOW_TESTS=1")
def test_brax_env_smoke():
  """The learner runs on a brax Env with flat vector observations (inverted pendulum)."""
  from brax import envs

  env = envs.training.wrap(envs.get_environment("inverted_pendulum"), episode_length=5)
  n = 4
  nets = nw.make_networks(-jnp.ones(env.action_size), jnp.ones(env.action_size), hidden=16)
  agent = sac.make_sac(nets, SACConfig(batch_size=8, grad_steps_per_iter=2))
  state = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(0), n))
  learner = jax.jit(agent.init)(jax.random.PRNGKey(1), state.obs)
  buffer = sac.init_buffer(state.obs, env.action_size, 64)
  step, act, insert = jax.jit(env.step), jax.jit(agent.act), jax.jit(sac.insert)
  for i in range(6):
    action = act(learner.actor_params, state.obs, jax.random.PRNGKey(i))
    nxt = step(state, action)
    trunc = nxt.info["truncation"]
    # Brax auto-resets: nxt.obs is then the first observation of the next episode.
    buffer = insert(buffer, sac.Transition(state.obs, action, nxt.reward,
                                           nxt.done * (1 - trunc), trunc, nxt.obs))
    state = nxt
  learner, metrics = jax.jit(agent.update_many)(learner, buffer, jax.random.PRNGKey(9))
  assert int(learner.step) == 2
  assert all(np.isfinite(float(v)) for v in metrics.values())


@pytest.mark.slow  # over 20 s on a 2-core CPU: the fast suite stays within 12 minutes
def test_update_many_with_depth_buffer():
  """End to end on dict observations: insert depth frames, sample, G gradient steps."""
  n, size = 2, 33  # the smallest image the tower takes
  nets = nw.make_networks(LOW, HIGH, hidden=4, conv_features=2, depth_scale=0.2)
  agent = sac.make_sac(nets, SACConfig(batch_size=4, grad_steps_per_iter=2))
  key = jax.random.PRNGKey(0)
  obs = {"depth": jax.random.uniform(key, (n, size, size, 1), maxval=5.0),
         "state": jnp.zeros((n, 3))}
  learner = jax.jit(agent.init)(key, obs)
  buffer = sac.init_buffer(obs, 2, capacity=8, depth_dtype=jnp.uint8)
  insert = jax.jit(sac.insert)
  for t in range(3):
    tr = sac.Transition(jax.tree.map(lambda x: x + 0.1 * t, obs), jnp.zeros((n, 2)),
                        jnp.ones(n), jnp.zeros(n), jnp.zeros(n), obs)
    buffer = insert(buffer, tr)
  run = jax.jit(agent.update_many)
  learner, metrics = run(learner, buffer, key)
  assert int(learner.step) == 2
  assert all(np.isfinite(float(v)) for v in metrics.values())


@pytest.mark.slow  # over 20 s on a 2-core CPU: the fast suite stays within 12 minutes
def test_learning_rate_lives_in_the_state_and_vmaps(tiny):
  """`with_hyperparams` sets the learning rate per vmapped member: lr 0 leaves the
  networks unchanged, and a member's step size scales with its own rate."""
  nets, _, _, _, batch, _ = tiny
  agent = sac.make_sac(nets, SACConfig())
  keys = jax.random.split(jax.random.PRNGKey(1), 3)
  states = jax.vmap(agent.init, (0, None))(keys[:1].repeat(3, 0), batch.obs)
  states = sac.with_hyperparams(states, learning_rate=np.array([0.0, 1e-4, 1e-3]),
                                alpha=np.array([0.1, 0.2, 0.3]))
  np.testing.assert_allclose(np.exp(states.log_alpha), [0.1, 0.2, 0.3], rtol=1e-6)
  new, _ = jax.jit(jax.vmap(agent.update, (0, None, None)))(states, batch,
                                                            jax.random.PRNGKey(2))
  step = [max(float(np.max(np.abs(a[i] - b[i]))) for a, b in
              zip(jax.tree.leaves(new.actor_params), jax.tree.leaves(states.actor_params)))
          for i in range(3)]
  assert step[0] == 0.0
  # Adam's first step is ~lr per parameter
  assert step[1] == pytest.approx(1e-4, rel=0.05) and step[2] == pytest.approx(1e-3, rel=0.05)


def test_target_rate_switches_to_tau_late_and_moves_the_target_critics_by_it(tiny):
  """`tau_late`: the target critics' rate is tau before `TAU_LATE_FROM` of the budget and
  tau_late from there on (off by default: cfg.tau, a Python float); an update's target
  critics move by the rate it is given."""
  total = 16_000
  late = SACConfig(tau=0.005, tau_late=0.001)
  assert schedules.TAU_LATE_FROM == 0.25  # where epsilon reaches its floor
  assert schedules.target_rate(SACConfig(tau=0.005), 15_000, total) == 0.005
  assert float(schedules.target_rate(late, 3_999, total)) == pytest.approx(0.005)
  assert float(schedules.target_rate(late, 4_000, total)) == pytest.approx(0.001)
  assert float(schedules.target_rate(late, 2 * total, total)) == pytest.approx(0.001)
  nets, _, _, _, batch, _ = tiny
  agent = sac.make_sac(nets, SACConfig(learning_rate=1e-2))
  state = jax.jit(agent.init)(jax.random.PRNGKey(1), batch.obs)
  # a target apart from the critics, so that the Polyak step is not zero
  state = state.replace(target_critic_params=jax.tree.map(jnp.zeros_like,
                                                          state.target_critic_params))
  update = jax.jit(agent.update)
  for tau in (0.001, 0.25):
    new, _ = update(state, batch, jax.random.PRNGKey(2), jnp.float32(tau))
    for t, c in zip(jax.tree.leaves(new.target_critic_params),
                    jax.tree.leaves(new.critic_params)):
      np.testing.assert_allclose(t, tau * c, rtol=1e-5, atol=1e-9)


def test_averaged_actor_is_the_actor_or_its_polyak_average(tiny):
  """`averaged_actor_params` (evaluated and exported) follow the learning actor by default, and
  with `actor_ema_tau` move that fraction of the way towards it every step."""
  nets, _, _, _, batch, _ = tiny
  for tau in (0.0, 0.25):
    agent = sac.make_sac(nets, SACConfig(learning_rate=1e-2, actor_ema_tau=tau))
    state = jax.jit(agent.init)(jax.random.PRNGKey(1), batch.obs)
    new, _ = jax.jit(agent.update)(state, batch, jax.random.PRNGKey(2))
    expect = new.actor_params if tau == 0 else jax.tree.map(
        lambda e, a: (1 - tau) * e + tau * a, state.averaged_actor_params, new.actor_params)
    jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-8),
                 new.averaged_actor_params, expect)
    moved = max(float(np.max(np.abs(a - b))) for a, b in zip(
        jax.tree.leaves(new.averaged_actor_params), jax.tree.leaves(state.averaged_actor_params)))
    assert moved > 0.0


def test_mirror_half_flips_whole_transitions():
  """`mirror_half` replaces about half of the transitions by their mirror image, each one
  whole (obs, action and next_obs together) and its reward and flags untouched; the
  learner refuses `mirror_augment` without a mirror."""
  from mjxvine.env import VineyardEnv
  n = 256
  keys = jax.random.split(jax.random.PRNGKey(4), 4)
  obs = lambda k: {"depth": jax.random.uniform(k, (n, 6, 5, 1)),
                   "state": jax.random.normal(k, (n, 3))}
  batch = sac.Transition(
      obs=obs(keys[0]), action=jax.random.uniform(keys[1], (n, 2), minval=-1.0),
      reward=jnp.arange(n, dtype=jnp.float32), terminal=jnp.zeros(n), truncated=jnp.zeros(n),
      next_obs=obs(keys[2]), weight=jnp.ones(n))
  out = sac.mirror_half(batch, keys[3], (VineyardEnv.mirror_obs, VineyardEnv.mirror_action))
  flipped = np.asarray(out.action[:, 1] != batch.action[:, 1])
  assert 0.35 < flipped.mean() < 0.65
  mirrored = sac.Transition(*jax.tree.map(
      lambda x, m: np.where(flipped.reshape((n,) + (1,) * (x.ndim - 1)), m, x),
      tuple(batch), (VineyardEnv.mirror_obs(batch.obs),
                     VineyardEnv.mirror_action(batch.action), batch.reward, batch.terminal,
                     batch.truncated, VineyardEnv.mirror_obs(batch.next_obs), batch.weight,
                     batch.discount)))
  jax.tree.map(np.testing.assert_array_equal, tuple(out), tuple(mirrored))
  np.testing.assert_array_equal(out.obs["depth"][flipped][:, :, ::-1],
                                batch.obs["depth"][flipped])
  nets = nw.make_networks(LOW, HIGH, hidden=8)
  for key in ("mirror_augment", "mirror_average"):
    with pytest.raises(ValueError, match=key):
      sac.make_sac(nets, SACConfig(**{key: True}))


def test_critic_layer_norm_adds_norms_to_the_critics_alone():
  """`sac.critic_layer_norm`: each critic gains a LayerNorm per hidden layer (4 * hidden
  parameters), the actor is unchanged."""
  obs = {"depth": jax.random.uniform(jax.random.PRNGKey(0), (3, 36, 36, 1)),
         "state": jnp.ones((3, 3))}
  action = jnp.full((3, 2), 0.2)
  counts = {}
  for norm in (False, True):
    nets = nw.make_networks(LOW, HIGH, hidden=16, conv_features=4, critic_layer_norm=norm)
    actor, critic = nw.init_params(nets, jax.random.PRNGKey(1), obs)
    counts[norm] = (nw.num_params(actor), nw.num_params(critic["critic0"]))
    assert np.all(np.isfinite(nets.critic.apply({"params": critic}, obs, action)))
  assert counts[True][0] == counts[False][0]
  assert counts[True][1] == counts[False][1] + 4 * 16
  assert "norm0" in critic["critic0"] and "norm1" in critic["critic0"]


@pytest.mark.parametrize("conv_impl, features", [
    ("xla", 4), ("shift", 4),
    pytest.param("native", 8, marks=pytest.mark.skipif(
        not native.available(), reason="the native conv is not built here"))])
def test_cpu_learner_gives_the_same_losses_and_gradients(conv_impl, features):
  """A fixed depth batch: the critic and actor losses and their gradients compiled with
  `learner_compiler_options()` (the trainer's) and with the tower computed as `conv_impl`
  are those of XLA's convolution compiled with XLA's default options, to float32 rounding
  (the tower alone: tests/test_networks.py, tests/test_native_conv.py)."""
  size, b = 33, 4
  keys = jax.random.split(jax.random.PRNGKey(0), 4)
  obs = lambda k: {"depth": jax.random.uniform(k, (b, size, size, 1), maxval=5.0),
                   "state": jax.random.normal(k, (b, 3))}
  batch = sac.Transition(obs(keys[0]), jax.random.uniform(keys[1], (b, 2)), jnp.ones(b),
                         jnp.zeros(b), jnp.zeros(b), obs(keys[2]))

  def losses(options, impl):
    nets = nw.make_networks(LOW, HIGH, hidden=8, conv_features=features, depth_scale=0.2,
                            conv_impl=impl)
    actor, critic = nw.init_params(nets, keys[3], batch.obs)
    target = jax.tree.map(lambda x: 0.9 * x, critic)

    def run(actor, critic, target):
      c = jax.value_and_grad(sac.critic_loss, has_aux=True)(
          critic, target, actor, ALPHA, batch, keys[0], nets, GAMMA)
      a = jax.value_and_grad(sac.actor_loss, has_aux=True)(
          actor, critic, ALPHA, batch, keys[1], nets)
      return c[0][0], c[1], a[0][0], a[1]
    return jax.jit(run, compiler_options=options)(actor, critic, target)

  ref, out = losses(None, "xla"), losses(nw.learner_compiler_options(), conv_impl)
  for x, y in zip(jax.tree.leaves(out), jax.tree.leaves(ref)):
    np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-5 * float(jnp.max(jnp.abs(y))))


@pytest.mark.skipif(not native.available(), reason="the native conv is not built here")
def test_update_many_with_the_native_tower_is_one_rolled_loop_of_update_from():
  """With the native tower (no XLA convolution) `update_many` keeps its G steps in one
  rolled loop, which the trainer's CPU path calls once an iteration instead of G calls
  of `update_from`, and gives what those G calls give (keys split(key, G)) to float32
  rounding."""
  n, size, g = 2, 33, 3
  nets = nw.make_networks(LOW, HIGH, hidden=8, conv_features=8, depth_scale=0.2,
                          conv_impl="native")
  assert nw.native_towers(nets)
  assert not nw.native_towers(nw.make_networks(LOW, HIGH, conv_features=8, conv_impl="shift"))
  assert not nw.native_towers(nw.make_networks(LOW, HIGH, conv_features=4, conv_impl="native"))
  agent = sac.make_sac(nets, SACConfig(batch_size=4, grad_steps_per_iter=g))
  key = jax.random.PRNGKey(0)
  obs = {"depth": jax.random.uniform(key, (n, size, size, 1), maxval=5.0),
         "state": jax.random.normal(key, (n, 3))}
  learner = jax.jit(agent.init)(key, obs)
  buffer = sac.init_buffer(obs, 2, capacity=8, depth_dtype=jnp.uint8)
  for t in range(4):
    buffer = sac.insert(buffer, sac.Transition(
        jax.tree.map(lambda x: x + 0.1 * t, obs), jnp.full((n, 2), 0.1 * t), jnp.ones(n),
        jnp.zeros(n), jnp.zeros(n), obs))
  options = nw.learner_compiler_options()
  grads = lambda fn: fn.lower(learner, buffer, key).as_text().count("@mjxvine_tower_grad")
  one, many = (jax.jit(f, compiler_options=options)
               for f in (agent.update_from, agent.update_many))
  assert grads(many) == grads(one) > 0  # one step's tower calls, in a loop body
  stepped = learner
  for k in jax.random.split(key, g):
    stepped, _ = one(stepped, buffer, k)
  looped, metrics = many(learner, buffer, key)
  assert int(looped.step) == g and all(np.isfinite(float(v)) for v in metrics.values())
  for x, y in zip(jax.tree.leaves(looped), jax.tree.leaves(stepped)):
    np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6)
