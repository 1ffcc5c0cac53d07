"""Single-decision latency of an exported policy on this CPU (numpy-only: runs on the robot).

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
import os
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np

from mjxvine.deploy import NumpyPolicy, PolicyError, PolicyFormatError, set_blas_threads


def measure(fn: Callable[[], object], calls: int = 1000, warmup: int = 50) -> dict:
  """Wall-clock ms per call of fn() over `calls` calls: median, p99, mean, min; CPU ms."""
  for _ in range(warmup):
    fn()
  times = np.empty(calls)
  load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
  cpu = time.process_time()
  for i in range(calls):
    t = time.perf_counter()
    fn()
    times[i] = time.perf_counter() - t
  cpu = time.process_time() - cpu
  times *= 1e3
  return dict(median_ms=float(np.median(times)), p99_ms=float(np.percentile(times, 99)),
              mean_ms=float(times.mean()), min_ms=float(times.min()),
              cpu_ms=1e3 * cpu / calls, calls=calls, load_1m=load)


def _inputs(h: int, w: int, max_depth: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
  """A random depth image (h, w) float32 metres and state (3,) float32."""
  rng = np.random.default_rng(seed)
  depth = rng.uniform(0.0, max_depth, (h, w)).astype(np.float32)
  state = np.array([0.3, 0.1, 0.2], np.float32)
  return depth, state


def numpy_latency(path: str | Path, calls: int = 1000, seed: int = 0) -> dict:
  """`measure` of `NumpyPolicy.load(path)(depth, state)` for one (H, W) image."""
  policy = NumpyPolicy.load(path)
  depth, state = _inputs(policy.height, policy.width, policy.max_depth, seed)
  return measure(lambda: policy(depth, state), calls)


def onnx_latency(path: str | Path, threads: int = 1, calls: int = 1000, seed: int = 0,
                 spinning: bool = True) -> dict:
  """`measure` of an onnxruntime session (CPU, `threads` intra-op threads, sequential
  execution, all graph optimisations) on a (1, H, W, 1) image and (1, 3) state."""
  import onnxruntime as ort

  opts = ort.SessionOptions()
  opts.intra_op_num_threads = threads
  opts.inter_op_num_threads = 1
  opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
  opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
  opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
  try:
    sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
  except Exception as e:  # noqa: BLE001 - onnxruntime's load errors have no public base
    raise PolicyFormatError(f"{path}: not a valid ONNX model ({str(e).splitlines()[0][:160]})"
                            ) from None
  _, h, w, _ = sess.get_inputs()[0].shape
  meta = json.loads(sess.get_modelmeta().custom_metadata_map.get("mjxvine_meta", "{}"))
  depth, state = _inputs(h, w, float(meta.get("max_depth_m", 5.0)), seed)
  feed = {"depth": depth[None, :, :, None], "state": state[None]}
  return measure(lambda: sess.run(["action"], feed), calls)


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
