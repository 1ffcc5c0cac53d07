"""Times one tower conv, its forward pass and both gradients, as XLA's convolution and as
the hand-written CPU kernel (`mjxvine.native_conv`), interleaved in one process.

  python scripts/time_tower_convs.py            # the shapes of cpu.yaml / jackal-gaps.yaml

Prints the median ms of 100 calls of each, jitted alone with the learner's compiler
options (`sac.learner_compiler_options`).
"""

import time

import jax
import numpy as np

from mjxvine import native_conv
from mjxvine.networks import lax_conv3x3
from mjxvine.sac import learner_compiler_options

# (batch, input size, in channels, out channels, stride): the towers' second and third
# convs at 41x41 with 8 and 16 features, batch 64
SHAPES = [(64, 20, 8, 8, 1), (64, 20, 16, 16, 1), (64, 9, 8, 8, 2), (64, 9, 16, 16, 2)]


def _programs(conv, x, k, g, s):
  """jitted forward, gradient w.r.t. the kernel and w.r.t. the input of `conv`."""
  opts = learner_compiler_options()
  fwd = lambda x, k: conv(x, k, s)
  dk = lambda x, k: jax.vjp(lambda k: conv(x, k, s), k)[1](g)[0]
  dx = lambda x, k: jax.vjp(lambda x: conv(x, k, s), x)[1](g)[0]
  return [jax.jit(f).lower(x, k).compile(opts) for f in (fwd, dk, dx)]


def main():
  if not native_conv.available():
    raise SystemExit(f"the native conv is not available: {native_conv.unavailable_reason()}")
  print("shape (N, H, C, F, stride) | forward | grad kernel | grad input   (ms, xla / native)")
  for n, h, c, f, s in SHAPES:
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    x = jax.random.normal(keys[0], (n, h, h, c))
    k = jax.random.normal(keys[1], (3, 3, c, f))
    ho = (h - 3) // s + 1
    g = jax.random.normal(keys[2], (n, ho, ho, f))
    progs = {name: _programs(conv, x, k, g, s)
             for name, conv in (("xla", lax_conv3x3), ("native", native_conv.conv3x3))}
    times = {name: [[] for _ in range(3)] for name in progs}
    for _ in range(100):
      for name, fns in progs.items():
        for i, fn in enumerate(fns):
          t = time.perf_counter()
          jax.block_until_ready(fn(x, k))
          times[name][i].append(time.perf_counter() - t)
    cells = [f"{np.median(times['xla'][i]) * 1e3:.3f} / {np.median(times['native'][i]) * 1e3:.3f}"
             for i in range(3)]
    print(f"{(n, h, c, f, s)} | " + " | ".join(cells))


if __name__ == "__main__":
  main()
