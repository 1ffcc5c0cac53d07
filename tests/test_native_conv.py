"""The hand-written CPU tower (`mjxvine.native`, conv_impl="native"): the same values
and gradients as XLA's tower to float32 rounding, in both of its builds, the same sums
however many threads run it, and a clear error where it is not built."""

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjxvine import native
from mjxvine import networks as nw

needs_native = pytest.mark.skipif(not native.available(),
                                  reason=f"native conv: {native.unavailable_reason()}")


def _close(a, b, tol=1e-4):
  """Equal to float32 rounding, relative to the largest magnitude."""
  a, b = np.asarray(a), np.asarray(b)
  scale = max(float(np.max(np.abs(b))), 1e-6)
  np.testing.assert_allclose(a / scale, b / scale, rtol=0, atol=tol)


def _params(key, channels: int, features: int):
  keys = jax.random.split(key, 8)
  params = []
  for i in range(4):
    c = channels if i == 0 else features
    params.append((jax.random.normal(keys[2 * i], (3, 3, c, features)) / np.sqrt(9 * c),
                   0.1 * jax.random.normal(keys[2 * i + 1], (features,))))
  return params


def _tower_and_grads(tower, x, params, w):
  """Features, and the gradients of sum(features * w) w.r.t. x and params."""
  loss = lambda x, p: jnp.sum(tower(x, p) * w)
  return tower(x, params), jax.grad(loss, argnums=(0, 1))(x, params)


@needs_native
@pytest.mark.parametrize("n, size, features", [
    (3, 41, 8),    # cpu.yaml's image
    (17, 33, 8),   # more images than the gradient's runs of images, unevenly split
    (2, 49, 16),   # not a covering size: the trailing rows and columns are dropped
    (1, 41, 32),   # the paper's features
])
def test_tower_and_gradients_equal_xla(n, size, features):
  kx, kp, kw = jax.random.split(jax.random.PRNGKey(n), 3)
  x = jax.random.uniform(kx, (n, size, size, 1), maxval=2.0)
  params = _params(kp, 1, features)
  w = jax.random.normal(kw, (n, features))
  got = _tower_and_grads(jax.jit(native.tower), x, params, w)
  want = _tower_and_grads(native.xla_tower, x, params, w)
  assert got[0].shape == (n, features)
  jax.tree.map(_close, got, want)


@needs_native
def test_max_pool_ties_go_to_the_first_maximum():
  """A piecewise-constant image makes equal positive values in the pool's windows: the
  gradient goes to the first of them in row-major order, as XLA's does."""
  x = jnp.repeat(jnp.repeat(jnp.arange(4.0).reshape(1, 2, 2, 1), 21, 1), 21, 2)[:, :41, :41]
  params = [(jnp.abs(k), jnp.abs(b)) for k, b in _params(jax.random.PRNGKey(3), 1, 8)]
  w = jnp.ones((1, 8))
  jax.tree.map(_close, _tower_and_grads(jax.jit(native.tower), x, params, w),
               _tower_and_grads(native.xla_tower, x, params, w))


@needs_native
def test_the_trainer_takes_the_native_tower_on_the_cpu():
  assert nw.learner_conv_impl() == "native" == nw.learner_conv_impl("native")
  assert nw.learner_conv_impl("shift") == "shift"
  assert nw.describe_conv_impl() == f"native ({native.instruction_set()})"


@needs_native
def test_conv_tower_native_is_the_xla_tower():
  """`ConvTower(conv_impl="native")` has XLA's tower's params (names, shapes, initial
  values), and its output and gradient."""
  x = jax.random.uniform(jax.random.PRNGKey(1), (2, 41, 41, 1)) * 5.0
  towers = {impl: nw.ConvTower(8, 0.2, conv_impl=impl) for impl in ("xla", "native")}
  params = {impl: t.init(jax.random.PRNGKey(2), x) for impl, t in towers.items()}
  jax.tree.map(np.testing.assert_array_equal, params["native"], params["xla"])
  loss = lambda impl: jax.value_and_grad(
      lambda p: jnp.sum(towers[impl].apply(p, x) ** 2))(params["xla"])
  jax.tree.map(_close, loss("native"), loss("xla"))


@needs_native
def test_kernel_refuses_what_it_cannot_compute():
  """The FFI handler checks its shapes itself: features other than 8, 16 or 32, or
  kernels whose channels do not chain, are an error, not a wrong result."""
  x = jnp.ones((1, 41, 41, 1))
  bad = [_params(jax.random.PRNGKey(0), 1, 12),
         _params(jax.random.PRNGKey(0), 2, 8)]  # the first kernel wants 2 channels
  for params in bad:
    with pytest.raises(Exception, match="tower: "):
      jax.block_until_ready(native.tower(x, params))


_RUN = textwrap.dedent("""
    import sys, jax, numpy as np
    from mjxvine import native
    x = jax.random.uniform(jax.random.PRNGKey(0), (20, 41, 41, 1), maxval=2.0)
    params = [(jax.random.normal(jax.random.PRNGKey(i), (3, 3, 1 if i == 0 else 8, 8)) / 8,
               jax.numpy.full((8,), 0.05)) for i in range(4)]
    w = jax.random.normal(jax.random.PRNGKey(9), (20, 8))
    f, g = jax.value_and_grad(lambda p: (native.tower(x, p) * w).sum())(params)
    np.savez(sys.argv[1], *jax.tree.leaves(g), f=f)
    print(native.instruction_set())
""")


@needs_native
def test_same_sums_for_any_thread_count_and_builds_agree(tmp_path):
  """One thread or three give the same bits (the gradient sums its images in fixed runs,
  whichever thread takes which); the AVX2 build equals the AVX-512 one (where this CPU
  has it) to rounding."""
  def run(name, **env):
    out = tmp_path / f"{name}.npz"
    done = subprocess.run([sys.executable, "-c", _RUN, str(out)], capture_output=True,
                          text=True, timeout=300, env=dict(os.environ, JAX_PLATFORMS="cpu",
                                                           **env))
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout.split()[-1], dict(np.load(out))
  build, one = run("one", MJXVINE_NATIVE_THREADS="1")
  _, three = run("three", MJXVINE_NATIVE_THREADS="3")
  for k in one:
    np.testing.assert_array_equal(one[k], three[k])
  if build == "avx512":
    build, avx2 = run("avx2", MJXVINE_NATIVE_CONV="avx2")
    assert build == "avx2"
    for k, v in avx2.items():
      _close(v, one[k])


def test_unavailable_is_reported():
  """Where the library is off (or cannot be built), `available()` says why, the trainer's
  default tower is "shift" and its log line says why, and a "native" tower refuses with
  that reason rather than running something else."""
  code = ("from mjxvine import native, networks as nw, sac; import jax.numpy as jnp\n"
          "print(native.available(), native.unavailable_reason())\n"
          "print('auto:', nw.learner_conv_impl(), '|', nw.describe_conv_impl())\n"
          "try:\n"
          "  nw.ConvTower(8, conv_impl='native').init(__import__('jax').random.PRNGKey(0),"
          " jnp.zeros((1, 41, 41, 1)))\n"
          "except RuntimeError as e:\n"
          "  print('refused:', e)\n")
  env = dict(os.environ, MJXVINE_NATIVE_CONV="0", JAX_PLATFORMS="cpu")
  out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                       text=True, check=True, timeout=120).stdout
  assert "False disabled by MJXVINE_NATIVE_CONV=0" in out
  assert "auto: shift | shift (native: disabled by MJXVINE_NATIVE_CONV=0)" in out
  assert "refused: conv_impl 'native': disabled by MJXVINE_NATIVE_CONV=0" in out
