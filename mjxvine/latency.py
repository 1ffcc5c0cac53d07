"""`python -m mjxvine.latency`: single-decision latency of an exported policy on this CPU
(numpy-only: runs on the robot).

    python -m mjxvine.latency policy.npz [--calls 1000]                  # NumpyPolicy
    python -m mjxvine.latency policy.onnx --threads 1 [--no-spinning]   # onnxruntime

Prints one JSON line: median_ms, p99_ms, mean_ms, min_ms (wall clock per call, after
warm-up calls), cpu_ms (process CPU time per call, all threads: spinning worker threads
show up here) and load_1m (the host's 1-minute load average before the run). Each call
is one decision on a random (H, W) depth image in [0, max_depth] metres and a (3,) state,
through the public API (`NumpyPolicy.__call__`, `InferenceSession.run`). The number of
BLAS threads of numpy is fixed when numpy is loaded: run with OPENBLAS_NUM_THREADS=N (or
pass --threads N with threadpoolctl installed).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from mjxvine.deploy.latency import numpy_latency, onnx_latency
from mjxvine.deploy.numpy_policy import PolicyError, set_blas_threads


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(prog="python -m mjxvine.latency", description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("policy", help="an .npz (NumpyPolicy) or .onnx (onnxruntime) file")
  parser.add_argument("--calls", type=int, default=1000, help="timed calls, >= 1")
  parser.add_argument("--threads", type=int, default=None,
                      help="onnxruntime intra-op threads (default 1); numpy: BLAS threads "
                           "via threadpoolctl, if installed")
  parser.add_argument("--no-spinning", action="store_true",
                      help="onnxruntime: worker threads sleep instead of spinning")
  parser.add_argument("--seed", type=int, default=0)
  args = parser.parse_args(argv)
  if args.calls < 1:
    parser.error(f"--calls {args.calls}: need at least 1 call")
  if args.threads is not None and args.threads < 1:
    parser.error(f"--threads {args.threads}: need at least 1 thread")
  if not Path(args.policy).is_file():
    print(f"latency error: no such policy file: {args.policy}", file=sys.stderr)
    return 2
  try:
    if args.policy.endswith(".onnx"):
      result = onnx_latency(args.policy, args.threads or 1, args.calls, args.seed,
                            not args.no_spinning)
    else:
      if args.threads is not None and not set_blas_threads(args.threads):
        parser.error("--threads with a .npz needs threadpoolctl; set OPENBLAS_NUM_THREADS")
      result = numpy_latency(args.policy, args.calls, args.seed)
  except PolicyError as e:  # an unreadable or incomplete .npz or .onnx
    print(f"latency error: {e}", file=sys.stderr)
    return 2
  print(json.dumps(result))
  return 0


if __name__ == "__main__":
  sys.exit(main())
