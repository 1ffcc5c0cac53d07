"""`bench deploy`: single-decision latency, ms (median, p99 over `--calls` calls), of the
exported actor (random weights, the config's image size) with `NumpyPolicy` and
onnxruntime, per thread count, beside the paper's TF (2.8-6.2 ms) and TFLite
(0.63-1.96 ms) figures on the robot's CPU."""

from __future__ import annotations

import argparse
import json
import os
import sys
from importlib import metadata
from pathlib import Path

import jax
import jax.numpy as jp
import numpy as np

from mjxvine import config as config_lib
from mjxvine.bench.common import int_list, positive_int
from mjxvine.cli import seed_type


def add_deploy_args(p: argparse.ArgumentParser) -> None:
  p.add_argument("--calls", type=positive_int, default=1000,
                 help="timed single-image calls per row")
  p.add_argument("--threads", default="1,2", type=int_list,
                 help="comma-separated BLAS (numpy) / intra-op (onnxruntime) thread counts")
  p.add_argument("--seed", type=seed_type, default=0, metavar="N",
                 help="seed of the random actor weights and of the inputs of the numpy / "
                      "onnxruntime agreement check (default 0)")


def bench_deploy(args: argparse.Namespace, cfg: config_lib.Config) -> list[dict]:
  """Single-decision latency (median and p99 over `--calls` calls, one image of the
  config's size) of `NumpyPolicy` and onnxruntime on this CPU, per thread count, beside
  the paper's TF / TFLite figures. The actor has random weights of the config's sizes
  (the paper's: 104,100 parameters at 112x112). Each row runs `python -m
  mjxvine.latency` in a fresh process, so that OPENBLAS_NUM_THREADS takes effect;
  load_1m is the host's load when the row started (the machine may be shared)."""
  import subprocess  # pylint: disable=import-outside-toplevel
  import tempfile  # pylint: disable=import-outside-toplevel
  from mjxvine import deploy  # pylint: disable=import-outside-toplevel
  from mjxvine.deploy import export, onnx  # pylint: disable=import-outside-toplevel
  from mjxvine import networks  # pylint: disable=import-outside-toplevel
  h, w = cfg.camera.height, cfg.camera.width
  nets = networks.make_networks_from_config(cfg)
  obs = {"depth": jp.zeros((1, h, w, 1)), "state": jp.zeros((1, 3))}
  params, _ = networks.init_params(nets, jax.random.PRNGKey(args.seed), obs)
  common = dict(image=f"{h}x{w}", actor_params=networks.num_params(params))
  root = str(Path(__file__).resolve().parents[2])  # the repository

  def latency(path, threads, *flags):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]))
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
      env[var] = str(threads)
    cmd = [sys.executable, "-m", "mjxvine.latency", "--policy", str(path), "--calls",
           str(args.calls), *flags]
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    if out.returncode != 0:
      raise RuntimeError(f"{' '.join(cmd)} failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])

  rows = []
  with tempfile.TemporaryDirectory() as tmp:
    npz = export.export_actor(params, Path(tmp) / "policy.npz", export.meta_from_config(cfg))
    threads = [int(t) for t in args.threads.split(",")]
    for n in threads:
      rows.append(dict(impl="NumpyPolicy", threads=n, **common, **latency(npz, n)))
    try:
      import onnxruntime as ort  # pylint: disable=import-outside-toplevel
      onnx_path = onnx.export_onnx(npz, Path(tmp) / "policy.onnx")
    except ImportError as e:
      rows.append(dict(impl="onnxruntime", **common, note=f"not available ({e}); "
                       "pip install mjxvine[onnx]"))
    else:
      # Agreement of the two on a few random images (max |action difference|).
      rng = np.random.default_rng(args.seed)
      depth = rng.uniform(0.0, cfg.camera.max_depth_m, (4, h, w, 1)).astype(np.float32)
      state = rng.uniform([0.0, -1.0, -np.pi], [0.5, 1.0, np.pi], (4, 3)).astype(np.float32)
      sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
      memory = np.tile(np.array([[0.0, np.inf]], np.float32), (4, 1))  # rows' entrances
      diff = float(np.abs(sess.run(["action"], {"depth": depth, "state": state,
                                                "row_memory": memory})[0] -
                          deploy.NumpyPolicy.load(npz).action(depth, state)).max())
      version = metadata.version("onnxruntime")
      for n in threads:
        for spin in ([True, False] if n > 1 else [True]):
          flags = ["--threads", str(n)] + ([] if spin else ["--no-spinning"])
          rows.append(dict(impl=f"onnxruntime {version}", threads=n, spinning=spin, **common,
                           **latency(onnx_path, 1, *flags), max_abs_diff_vs_numpy=diff))
  # Actor inference per decision on the paper's robot CPUs (docs/design.md, Evaluation
  # protocol), ms.
  paper = {"TF (paper, robot CPU)": (2.8, 6.2), "TFLite (paper, robot CPU)": (0.63, 1.96)}
  for name, (low, high) in paper.items():
    rows.append(dict(impl=name, image="112x112", paper_low_ms=low, paper_high_ms=high))
  return rows
