"""What the benchmarks share: the machine they ran on (`environment`), the table and JSON
of their rows (`write_results`), timing of compiled programs (seconds per call, compile
seconds, XLA's flop and byte counts; several programs in turn), the argparse types of
their flags, and the env setup of `bench physics` and `bench env`."""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from importlib import metadata
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jp
import numpy as np

from mjxvine import atomic
from mjxvine.formatting import fmt_value

# The repository's experiments/ folder: default configs of `bench train` and `bench brax`.
EXPERIMENTS = Path(__file__).resolve().parents[2] / "experiments"


# ------------------------------------------------------------------ results

def environment() -> dict:
  """Device, backend, versions and host load: what a benchmark number depends on."""
  versions = {}
  for pkg in ("jax", "jaxlib", "mujoco", "mujoco-mjx", "brax", "flax", "numpy"):
    try:
      versions[pkg] = metadata.version(pkg)
    except metadata.PackageNotFoundError:
      pass
  dev = jax.devices()[0]
  kind = getattr(dev, "device_kind", "")
  if dev.platform == "cpu":
    try:
      with open("/proc/cpuinfo") as f:
        kind = next(l.split(":", 1)[1].strip() for l in f if l.startswith("model name"))
    except (OSError, StopIteration):
      kind = platform.processor() or kind
  return dict(device=f"{dev.platform}: {kind}",
              devices=len(jax.devices()), backend=jax.default_backend(), versions=versions,
              python=platform.python_version(), host=platform.node(), cpus=os.cpu_count(),
              load_avg=os.getloadavg() if hasattr(os, "getloadavg") else None,
              time=time.strftime("%Y-%m-%dT%H:%M:%S"))


def write_results(name: str, rows: list[dict], out: str | None = None, **extra) -> dict:
  """Prints `rows` as a table and, if `out` is given, writes them with `environment()`."""
  env = environment()
  result = dict(benchmark=name, **env, **extra, rows=rows)
  print(f"# {name}: {env['device']} ({env['backend']}), jax {env['versions'].get('jax')}, "
        f"mujoco {env['versions'].get('mujoco')}, load {env['load_avg']}")
  if rows:
    keys = list(dict.fromkeys(k for r in rows for k in r))
    cells = [[fmt_value(r.get(k, "")) for k in keys] for r in rows]
    widths = [max(len(k), *(len(c[i]) for c in cells)) for i, k in enumerate(keys)]
    print("  ".join(k.rjust(w) for k, w in zip(keys, widths)))
    for c in cells:
      print("  ".join(v.rjust(w) for v, w in zip(c, widths)))
  for k, v in extra.items():
    print(f"{k}: {v}")
  if out:
    atomic.write_text(out, json.dumps(result, indent=1, default=json_default))
    print(f"wrote {out}")
  return result


def json_default(o):
  """`json.dump`'s `default`: numpy scalars and arrays as Python numbers and lists."""
  if isinstance(o, (np.generic,)):
    return o.item()
  if isinstance(o, np.ndarray):
    return o.tolist()
  raise TypeError(type(o))


# ------------------------------------------------------------------ timing

def cost_analysis(compiled) -> dict:
  """XLA's own count of a compiled program's work: {"flops", "bytes_accessed"} per call
  (None where the backend gives none). It does not depend on the machine's load."""
  cost = compiled.cost_analysis()
  if isinstance(cost, (list, tuple)):  # older jax: one dict per device program
    cost = cost[0] if cost else {}
  cost = cost or {}
  get = lambda k: float(cost[k]) if k in cost else None
  return {"flops": get("flops"), "bytes_accessed": get("bytes accessed")}


def time_compiled(fn: Callable, *args, min_time: float = 1.0, min_reps: int = 3) -> dict:
  """Steady-state seconds per call of a compiled `fn(*args)`: median, best, median CPU
  seconds, over at least `min_reps` calls and `min_time` seconds (after one warm-up)."""
  jax.block_until_ready(fn(*args))  # warm-up
  times, cpu, start = [], [], time.perf_counter()
  while len(times) < min_reps or time.perf_counter() - start < min_time:
    t, c = time.perf_counter(), time.process_time()
    jax.block_until_ready(fn(*args))
    times.append(time.perf_counter() - t)
    cpu.append(time.process_time() - c)
  return dict(call_s=float(np.median(times)), best_s=float(np.min(times)),
              cpu_s=float(np.median(cpu)), reps=len(times))


def compile_call(fn: Callable, *args) -> tuple[Callable, dict]:
  """A jitted `fn` compiled for `args`, and {"compile_s", "flops", "bytes_accessed"}."""
  t = time.perf_counter()
  fn = fn.lower(*args).compile()
  return fn, dict(compile_s=time.perf_counter() - t, **cost_analysis(fn))


def time_call(fn: Callable, *args, min_time: float = 1.0, min_reps: int = 3) -> dict:
  """Compile time, steady-state seconds per call (`time_compiled`) and XLA's cost analysis
  (flops, bytes accessed per call) of a jitted `fn(*args)`."""
  fn, info = compile_call(fn, *args)
  return dict(compile_s=info["compile_s"], **time_compiled(fn, *args, min_time=min_time,
                                                           min_reps=min_reps),
              flops=info["flops"], bytes_accessed=info["bytes_accessed"])


def time_alternating(calls: list[tuple[Callable, tuple]], rounds: int = 10) -> list[dict]:
  """Steady-state seconds per call of compiled programs `calls` [(fn, args)], called in
  turn (A, B, A, B, ...: a load on the machine that comes and goes falls on all alike),
  `rounds` times after one warm-up each. Per program: median, best and median CPU
  seconds, and `ratio`, the median over rounds of its time over the first program's in
  the same round (1 for the first)."""
  for fn, args in calls:
    jax.block_until_ready(fn(*args))
  wall = np.zeros((rounds, len(calls)))
  cpu = np.zeros_like(wall)
  for r in range(rounds):
    for i, (fn, args) in enumerate(calls):
      t, c = time.perf_counter(), time.process_time()
      jax.block_until_ready(fn(*args))
      wall[r, i], cpu[r, i] = time.perf_counter() - t, time.process_time() - c
  return [dict(call_s=float(np.median(wall[:, i])), best_s=float(wall[:, i].min()),
               cpu_s=float(np.median(cpu[:, i])), reps=rounds,
               ratio=float(np.median(wall[:, i] / wall[:, 0])))
          for i in range(len(calls))]


def per(cost: float | None, count: float | None) -> float | None:
  """`cost / count`, None where XLA gave no count (either)."""
  return None if cost is None or count is None else cost / count


# ------------------------------------------------------------------ argparse types
# A bad value is a usage error (exit status 2, one line), not a traceback halfway through
# a benchmark. Lists stay text: the benchmarks split them.

def positive_int(text: str) -> int:
  """A positive integer ("16")."""
  try:
    value = int(text)
  except ValueError:
    value = 0
  if value < 1:
    raise argparse.ArgumentTypeError(f"{text!r}: expected a positive integer")
  return value


def int_list(text: str) -> str:
  """Comma-separated positive integers ("1,16,64")."""
  for item in text.split(","):
    positive_int(item)
  return text


def size(text: str) -> str:
  """HxW of positive integers ("112x112")."""
  parts = text.lower().split("x")
  if len(parts) != 2:
    raise argparse.ArgumentTypeError(f"{text!r}: expected HxW, e.g. 112x112")
  for part in parts:
    positive_int(part)
  return text


def size_list(text: str) -> str:
  """Comma-separated HxW sizes ("112x112,64x64")."""
  for item in text.split(","):
    size(item)
  return text


# ------------------------------------------------------------------ env counts

def add_env_count_args(p: argparse.ArgumentParser) -> None:
  """The flags of `bench physics` and `bench env`: env counts, steps per call, baseline."""
  p.add_argument("--sizes", default=None, type=int_list,
                 help="comma-separated env counts (default 1,16,64,256, plus "
                      "1024,4096,16384 on an accelerator)")
  p.add_argument("--steps", type=positive_int, default=10,
                 help="control steps per timed call")
  p.add_argument("--no-baseline", dest="baseline", action="store_false",
                 help="skip the Python loop over mujoco.mj_step (physics) baseline")


def env_counts(args: argparse.Namespace) -> list[int]:
  """The env counts of `--sizes`, or the defaults of this backend."""
  if args.sizes:
    return [int(x) for x in args.sizes.split(",")]
  return [1, 16, 64, 256] + ([1024, 4096, 16384] if jax.default_backend() != "cpu" else [])


def env_setup(cfg, n: int, worlds=None):
  """(training env of `cfg` (on `worlds`, default the config's pool), its reset state for
  `n` envs, one constant action per env)."""
  from mjxvine.env import training_env  # pylint: disable=import-outside-toplevel
  env = training_env(cfg, worlds)
  state = jax.jit(lambda k: env.reset_batch(k, n))(jax.random.PRNGKey(0))
  action = jp.tile(jp.array([[0.3, 0.1]], jp.float32), (n, 1))
  return env, state, action
