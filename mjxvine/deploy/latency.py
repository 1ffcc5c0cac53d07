"""Single-decision latency of an exported policy on this CPU (numpy-only: runs on the robot).

`numpy_latency(path)` and `onnx_latency(path, threads)` time one decision through the public
APIs (`NumpyPolicy.__call__`, `InferenceSession.run`) on a random (H, W) depth image in
[0, max_depth] metres and a (3,) state, and return a dict of milliseconds (`measure`); the
command line is `python -m mjxvine.latency`. A file that is not a usable policy raises
`PolicyError` (one line), never another error.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np

from mjxvine.deploy.numpy_policy import NumpyPolicy, PolicyError, PolicyFormatError
from mjxvine.formatting import first_line


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


def _inputs(h: int, w: int, max_depth: float, seed: int,
            state_size: int = 3) -> tuple[np.ndarray, np.ndarray]:
  """A random depth image (h, w) float32 metres and state (state_size,) float32:
  [0.3, 0.1, 0.2] (v_prev m/s, w_prev rad/s, yaw rad), zeros after."""
  rng = np.random.default_rng(seed)
  depth = rng.uniform(0.0, max_depth, (h, w)).astype(np.float32)
  state = np.zeros(state_size, np.float32)
  state[:3] = [0.3, 0.1, 0.2][:state_size]
  return depth, state


def numpy_latency(path: str | Path, calls: int = 1000, seed: int = 0) -> dict:
  """`measure` of `NumpyPolicy.load(path)(depth, state)` for one (H, W) image; the
  state's entries clipped into what the policy accepts (its action box). Of a policy with
  the end-of-row detector, also `step_median_ms` (`NumpyPolicy.step`, the action and the
  end of the row) and `row_end_ms`, its cost beside the action (the two medians' gap)."""
  policy = NumpyPolicy.load(path)
  depth, state = _inputs(policy.height, policy.width, policy.max_depth, seed,
                         policy.state_size)
  state = np.clip(state, policy.state_lo, policy.state_hi)
  try:  # a policy that refuses even this input (an overflow): say which file, once
    policy(depth, state)
  except PolicyError as e:
    raise type(e)(f"{path}: {e}") from None
  out = measure(lambda: policy(depth, state), calls)
  if not policy.has_row_end:  # a file exported before the detector
    return out
  step = measure(lambda: policy.step(depth, state), calls)["median_ms"]
  return {**out, "step_median_ms": step, "row_end_ms": step - out["median_ms"]}


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
    raise PolicyFormatError(f"{path}: not a valid ONNX model ({first_line(e)})") from None
  shapes = {i.name: i.shape for i in sess.get_inputs()}
  depth_shape, state_shape = shapes.get("depth"), shapes.get("state")
  fixed = lambda dims: all(isinstance(d, int) and 1 <= d <= 4096 for d in dims)
  if not (depth_shape and state_shape and len(depth_shape) == 4 and len(state_shape) == 2 and
          fixed(depth_shape[1:3]) and fixed(state_shape[1:])):
    raise PolicyFormatError(f"{path}: not an mjxvine policy graph (inputs {shapes}: expected "
                            "depth (B, H, W, 1) and state (B, S))")
  _, h, w, _ = depth_shape
  try:
    meta = json.loads(sess.get_modelmeta().custom_metadata_map.get("mjxvine_meta", "{}"))
    max_depth = float(meta.get("max_depth_m", 5.0))
    if not 0.0 < max_depth <= 1e3:
      raise ValueError(f"max_depth_m {max_depth}")
  except Exception as e:  # noqa: BLE001 - JSON, a non-object, a non-number
    raise PolicyFormatError(f"{path}: unreadable mjxvine_meta ({first_line(e)})") from None
  depth, state = _inputs(h, w, max_depth, seed, state_shape[1])
  feed = {"depth": depth[None, :, :, None], "state": state[None]}
  if "row_memory" in shapes:  # the end-of-row detector's memory: a row's entrance
    feed["row_memory"] = np.array([[0.0, np.inf]], np.float32)
  try:  # once: a graph that does not run on its own inputs is no policy
    sess.run(["action"], feed)
  except Exception as e:  # noqa: BLE001 - onnxruntime's run errors have no public base
    raise PolicyFormatError(f"{path}: the graph does not run ({first_line(e)})") from None
  return measure(lambda: sess.run(["action"], feed), calls)
