"""Times the conv tower alone, forward and forward + gradient w.r.t. its params, as each
`conv_impl` computes it (xla, shift, native), interleaved in one process.

  python scripts/time_tower.py                       # 41x41, batch 64, 8 and 16 features
  python scripts/time_tower.py --size 113 --batch 256 --features 32   # the paper's

Prints the median ms of `--calls` calls of each, jitted alone with the learner's compiler
options (`networks.learner_compiler_options`), and the native build (`avx2` or `avx512`).
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from mjxvine import native
from mjxvine import networks as nw
from mjxvine.networks import learner_compiler_options

IMPLS = ("xla", "shift", "native")


def _programs(impl: str, features: int, x: jax.Array, w: jax.Array):
  """(params, jitted forward, jitted gradient) of a tower as `impl` computes it."""
  tower = nw.ConvTower(features, 0.2, conv_impl=impl)
  params = tower.init(jax.random.PRNGKey(1), x)
  loss = lambda p, x: jnp.sum(tower.apply(p, x) * w)
  opts = learner_compiler_options()
  return (params, jax.jit(tower.apply).lower(params, x).compile(opts),
          jax.jit(jax.grad(loss)).lower(params, x).compile(opts))


def main():
  p = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
  p.add_argument("--size", type=int, default=41, help="image height and width (pixels)")
  p.add_argument("--batch", type=int, default=64)
  p.add_argument("--features", type=int, nargs="+", default=[8, 16])
  p.add_argument("--calls", type=int, default=100)
  args = p.parse_args()
  impls = IMPLS if native.available() else IMPLS[:2]
  print(f"native: {native.instruction_set() if native.available() else native.unavailable_reason()}")
  print(f"tower {args.size}x{args.size}, batch {args.batch}: median ms of {args.calls} calls "
        f"(forward | forward + gradient), {' / '.join(impls)}")
  for f in args.features:
    x = jax.random.uniform(jax.random.PRNGKey(0), (args.batch, args.size, args.size, 1),
                           maxval=5.0)
    w = jax.random.normal(jax.random.PRNGKey(2), (args.batch, f))
    progs = {impl: _programs(impl, f, x, w) for impl in impls}
    times = {impl: ([], []) for impl in impls}
    for _ in range(args.calls):
      for impl, (params, fwd, grad) in progs.items():
        for fn, out in zip((fwd, grad), times[impl]):
          t = time.perf_counter()
          jax.block_until_ready(fn(params, x))
          out.append(time.perf_counter() - t)
    cells = [" / ".join(f"{np.median(times[impl][i]) * 1e3:.3f}" for impl in impls)
             for i in range(2)]
    print(f"{f:3d} features | {cells[0]} | {cells[1]}")


if __name__ == "__main__":
  main()
