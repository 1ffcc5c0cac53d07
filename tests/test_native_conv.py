"""The hand-written CPU conv (`mjxvine.native_conv`, conv_impl="native"): the same values
and gradients as XLA's convolution to float32 rounding, and a clear error where it is not
built."""

import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjxvine import native_conv
from mjxvine import networks as nw

needs_native = pytest.mark.skipif(not native_conv.available(),
                                  reason=f"native conv: {native_conv.unavailable_reason()}")


def _close(a, b, tol=1e-4):
  """Equal to float32 rounding, relative to the largest magnitude."""
  a, b = np.asarray(a), np.asarray(b)
  scale = max(float(np.max(np.abs(b))), 1e-6)
  np.testing.assert_allclose(a / scale, b / scale, rtol=0, atol=tol)


@needs_native
@pytest.mark.parametrize("shape, stride", [((3, 11, 9, 8, 8), 1), ((3, 11, 9, 8, 8), 2),
                                           ((2, 10, 12, 16, 16), 1), ((2, 9, 9, 4, 16), 2),
                                           ((1, 3, 3, 8, 8), 1)])
def test_conv_and_gradients_equal_xla(shape, stride):
  n, h, w, c, f = shape
  kx, kk, kg = jax.random.split(jax.random.PRNGKey(0), 3)
  x = jax.random.normal(kx, (n, h, w, c))
  k = jax.random.normal(kk, (3, 3, c, f))
  ho, wo = (h - 3) // stride + 1, (w - 3) // stride + 1
  g = jax.random.normal(kg, (n, ho, wo, f))
  y, vjp = jax.vjp(lambda a, b: native_conv.conv3x3(a, b, stride), x, k)
  y_ref, vjp_ref = jax.vjp(lambda a, b: nw.lax_conv3x3(a, b, stride), x, k)
  assert y.shape == y_ref.shape == (n, ho, wo, f)
  _close(y, y_ref)
  for got, want in zip(vjp(g), vjp_ref(g)):
    _close(got, want)


@needs_native
@pytest.mark.parametrize("features", [8, 32])  # 32: the kernel's channels do not apply
def test_tower_native_equals_xla(features):
  """The whole tower, its output and its parameters' gradient (41x41, two images)."""
  x = jax.random.uniform(jax.random.PRNGKey(1), (2, 41, 41, 1)) * 5.0
  towers = {impl: nw.ConvTower(features, 0.2, conv_impl=impl) for impl in ("xla", "native")}
  params = towers["xla"].init(jax.random.PRNGKey(2), x)
  loss = lambda impl: jax.value_and_grad(
      lambda p: jnp.sum(towers[impl].apply(p, x) ** 2))(params)
  (l_xla, g_xla), (l_nat, g_nat) = loss("xla"), loss("native")
  _close(l_nat, l_xla)
  jax.tree_util.tree_map(_close, g_nat, g_xla)


@needs_native
def test_kernel_refuses_what_it_cannot_compute():
  """The FFI handler checks its shapes itself: a kernel whose channels do not match the
  image's, or 32 output channels, is an error, not a wrong result."""
  x = jnp.ones((1, 6, 6, 8))
  for k in (jnp.ones((3, 3, 4, 8)), jnp.ones((3, 3, 8, 32))):
    with pytest.raises(Exception, match="tower conv"):
      jax.block_until_ready(native_conv._forward(x, k, 1))


def test_unavailable_is_reported():
  """Where the library is off (or cannot be built), `available()` says why and a
  "native" tower refuses with that reason rather than running something else."""
  code = ("from mjxvine import native_conv, networks as nw; import jax.numpy as jnp\n"
          "print(native_conv.available(), native_conv.unavailable_reason())\n"
          "try:\n"
          "  nw.ConvTower(8, conv_impl='native').init(__import__('jax').random.PRNGKey(0),"
          " jnp.zeros((1, 41, 41, 1)))\n"
          "except RuntimeError as e:\n"
          "  print('refused:', e)\n")
  env = dict(os.environ, MJXVINE_NATIVE_CONV="0", JAX_PLATFORMS="cpu")
  out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                       text=True, check=True, timeout=120).stdout
  assert "False disabled by MJXVINE_NATIVE_CONV=0" in out
  assert "refused: conv_impl 'native': disabled by MJXVINE_NATIVE_CONV=0" in out
