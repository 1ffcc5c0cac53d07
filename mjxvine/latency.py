"""`python -m mjxvine.latency`: single-decision latency of an exported policy on this CPU
(numpy-only: runs on the robot).

    python -m mjxvine.latency --policy policy.npz [--calls 1000]                # NumpyPolicy
    python -m mjxvine.latency --policy policy.onnx --threads 1 [--no-spinning] # onnxruntime

Prints one JSON line: median_ms, p99_ms, mean_ms, min_ms (wall clock per call, after
warm-up calls), cpu_ms (process CPU time per call, all threads: spinning worker threads
show up here) and load_1m (the host's 1-minute load average before the run). Each call
is one decision on a random (H, W) depth image in [0, max_depth] metres and a (3,) state,
through the public API (`NumpyPolicy.__call__`, `InferenceSession.run`). --threads N
limits numpy's BLAS to N threads (threadpoolctl, a dependency of mjxvine) or sets
onnxruntime's intra-op threads.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from mjxvine.cli import CommandParser, int_range, seed_type
from mjxvine.deploy.latency import numpy_latency, onnx_latency
from mjxvine.deploy.numpy_policy import PolicyError, set_blas_threads


# A million calls of a ~1 ms policy time for about 17 minutes (and keep 8 MB of times);
# more threads than any robot's CPU has cores measure only the oversubscription.
MAX_CALLS = 1_000_000
MAX_THREADS = 256


def parser() -> argparse.ArgumentParser:
  """The command line's flags."""
  p = CommandParser(prog="python -m mjxvine.latency", description=__doc__)
  p.add_argument("--policy", required=True, metavar="FILE",
                 help="an exported policy file: .npz (NumpyPolicy) or .onnx (onnxruntime)")
  p.add_argument("--calls", type=int_range(1, MAX_CALLS), default=1000,
                 help=f"timed calls, 1-{MAX_CALLS} (default 1000)")
  p.add_argument("--threads", type=int_range(1, MAX_THREADS), default=None, metavar="N",
                 help=f"1-{MAX_THREADS}; onnxruntime: intra-op threads (default 1); .npz: "
                      "numpy's BLAS threads (default: as numpy started, OPENBLAS_NUM_THREADS)")
  p.add_argument("--no-spinning", action="store_true",
                 help="onnxruntime: worker threads sleep instead of spinning")
  p.add_argument("--seed", type=seed_type, default=0, metavar="N",
                 help="seed of the random depth images and states the policy is called on "
                      "(default 0)")
  return p


def main(argv=None) -> int:
  """The CLI: one JSON line; 2 a bad argument or policy file (one line)."""
  p = parser()
  args = p.parse_args(argv)  # --calls and --threads are range-checked here
  if not Path(args.policy).is_file():
    print(f"latency error: no such policy file: {args.policy}", file=sys.stderr)
    return 2
  try:
    if args.policy.endswith(".onnx"):
      result = onnx_latency(args.policy, args.threads or 1, args.calls, args.seed,
                            not args.no_spinning)
    else:
      if args.threads is not None and not set_blas_threads(args.threads):
        p.error("--threads with a .npz needs threadpoolctl (pip install threadpoolctl); "
                "or set OPENBLAS_NUM_THREADS=N")
      result = numpy_latency(args.policy, args.calls, args.seed)
  except PolicyError as e:  # an unreadable or incomplete .npz or .onnx
    print(f"latency error: {e}", file=sys.stderr)
    return 2
  print(json.dumps(result))
  return 0


if __name__ == "__main__":
  from mjxvine.atomic import command_main
  # SIGINT / SIGTERM: 130 / 143 in one line, the outputs of the unfinished set removed
  command_main(main)
