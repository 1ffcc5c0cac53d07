"""Run by tests/test_parallel.py in a fresh process with 4 host CPU devices (the XLA flag
must be set before JAX starts): trains one chunk on 1 device and on 4 devices and prints
a JSON comparison. The chunk's last iteration is the first gradient step."""

import os

os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                           " --xla_force_host_platform_device_count=4")

import json  # noqa: E402
import sys  # noqa: E402

import jax  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import PartitionSpec as P  # noqa: E402

from mjxvine.training import iteration, parallel, programs  # noqa: E402

# chunks as one lax.scan program, as on accelerators (the CPU's own path is a host loop)
iteration.scan_chunks = lambda: True
from mjxvine.config import load_config  # noqa: E402

OVERRIDES = ["camera.width=36", "camera.height=36", "env.num_envs=4", "env.max_steps=8",
             "sac.batch_size=16", "sac.buffer_size=256", "sac.warmup_steps=20",
             "sac.hidden=16", "sac.conv_features=4", "train.iters_per_chunk=5",
             "world.pool_size=2", "world.train_length_m=6"]


def config(devices: int):
  return load_config("experiments/smoke.yaml", OVERRIDES + [f"train.devices={devices}"])


def one_chunk(devices: int):
  _, init_fn, chunk_fn = programs.compiled_trainer(config(devices))
  ts = init_fn(jax.random.split(jax.random.PRNGKey(0), 1))
  ts, metrics = chunk_fn(ts)
  return ts, jax.device_get(metrics)


def main():
  out = {"devices": jax.device_count()}
  (ts1, m1), (ts4, m4) = one_chunk(1), one_chunk(4)
  out["depth_split_on_env_axis"] = ts4.buffer.depth.sharding.spec == P(None, "env")
  out["env_devices"] = len(ts4.env_state.obs["depth"].sharding.device_set)
  out["metric_keys_equal"] = sorted(m1) == sorted(m4)
  out["critic_loss"] = [float(m1["critic_loss"]), float(m4["critic_loss"])]
  out["finite"] = bool(all(np.all(np.isfinite(v)) for m in (m1, m4) for v in m.values()))
  # One update from the same learner state and replay: once on 1 device,
  # once with the replay split over 4 and the batch split (gradients all-reduced).
  sac1 = programs.compiled_trainer(config(1))[0]
  sac4 = programs.compiled_trainer(config(4))[0]
  key = jax.random.PRNGKey(5)
  on4 = jax.device_put(ts1, parallel.train_state_sharding(ts1, parallel.make_mesh(4)))
  (up1, u1), (up4, u4) = (jax.jit(s.update_many)(t.learner, t.buffer, key)
                          for s, t in ((sac1, ts1), (sac4, on4)))
  out["update_critic_loss"] = [float(u1["critic_loss"]), float(u4["critic_loss"])]
  p1 = jax.tree.leaves(jax.device_get(up1))
  p4 = jax.tree.leaves(jax.device_get(up4))
  diffs = np.concatenate([np.abs(np.asarray(a, np.float64) - b).ravel()
                          for a, b in zip(p1, p4) if np.size(a)])
  # Adam's first step moves each parameter by about lr * sign(gradient): parameters whose
  # gradient is ~0 may flip sign with the summation order, all others must agree.
  out["param_diff_frac"] = float(np.mean(diffs > 1e-3 * 2e-4))
  out["max_param_diff"] = float(diffs.max())
  # A ray that grazes a geom's edge may hit on one layout and miss on the other, so the
  # depth images are compared pixel by pixel, the rest of the observation as a whole.
  depth_diff = np.abs(np.asarray(ts1.env_state.obs["depth"]) -
                      np.asarray(ts4.env_state.obs["depth"]))
  out["depth_frac_differ"] = float(np.mean(depth_diff > 1e-3))
  out["state_obs_max_diff"] = float(np.max(np.abs(np.asarray(ts1.env_state.obs["state"]) -
                                                  np.asarray(ts4.env_state.obs["state"]))))
  out["updates"] = [int(ts1.learner.step), int(ts4.learner.step)]
  json.dump(out, sys.stdout)


if __name__ == "__main__":
  main()
