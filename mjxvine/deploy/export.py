"""A trained actor as a numpy-only .npz policy file for `mjxvine.deploy.NumpyPolicy`.

`export_actor(actor_params, path, meta_from_config(cfg))` writes one; the command line that
exports a run's checkpoint is `python -m mjxvine.export`, the ONNX graph `mjxvine.deploy.onnx`.

The file holds the actor's float32 arrays under their flax paths ("tower/conv0/kernel",
"dense0/bias", "mean/kernel", ...) and a JSON `__meta__` entry: format version, image
size, FOVs, max depth, depth scale, action box, state layout, network layout, config
hash, the whole training config and mjxvine version.
"""

from __future__ import annotations

import json
import re
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

import mjxvine
from mjxvine import atomic
from mjxvine import config as config_lib
from mjxvine.deploy.numpy_policy import FORMAT_VERSION, META_KEY, RowEnd

STATE_LAYOUT = ("v_prev", "w_prev", "yaw")
REQUIRED_META = ("image_size", "max_depth_m", "action_low", "action_high")


def flatten_params(params: Any, prefix: str = "") -> dict[str, np.ndarray]:
  """Nested dict of arrays -> {"a/b/c": float32 array}."""
  out = {}
  for k, v in params.items():
    name = f"{prefix}{k}"
    if isinstance(v, dict) or hasattr(v, "items"):
      out.update(flatten_params(v, name + "/"))
    else:
      out[name] = np.asarray(v, np.float32)
  return out


def meta_from_config(cfg: config_lib.Config) -> dict:
  """The metadata of a vineyard actor built by `networks.make_networks_from_config(cfg)`."""
  low, high = config_lib.action_box(cfg)
  return {
      "image_size": [cfg.camera.height, cfg.camera.width],
      "fovx_deg": cfg.camera.fovx_deg, "fovy_deg": cfg.camera.fovy_deg,
      "max_depth_m": cfg.camera.max_depth_m, "depth_scale": config_lib.depth_input_scale(cfg),
      "action_low": low, "action_high": high,
      "control_dt": cfg.env.control_dt, "config_hash": config_lib.config_hash(cfg),
      # the state's yaw: "start", the IMU yaw minus the yaw at the row entrance; "world",
      # the IMU yaw itself (both wrapped to [-pi, pi)); NumpyPolicy.yaw_input
      "yaw_reference": cfg.env.yaw_reference,
      # the action is the mean of the actor's on the image and its mirror (sac.mirror_average)
      "mirror_average": cfg.sac.mirror_average,
      # the end-of-row detector's settings (NumpyPolicy.step, numpy_policy.RowEnd)
      "row_end": RowEnd()._asdict(),
      # the whole training config: `evaluate --policy FILE.npz` then evaluates as the run
      # does (world, episode limit, env options); the robot needs none of it
      "config": config_lib.to_dict(cfg),
  }


def actor_arrays(actor_params: Any, meta: dict) -> tuple[dict[str, np.ndarray], dict]:
  """(arrays, full meta) of the policy file of actor params; see `export_actor`."""
  from mjxvine.tower import CONV_LAYERS, tower_pad  # imports jax: only when exporting

  missing = [k for k in REQUIRED_META if k not in meta]
  if missing:
    raise ValueError(f"export_actor: meta lacks {', '.join(missing)}")
  arrays = flatten_params(actor_params)
  if "tower/conv0/kernel" not in arrays:
    raise ValueError("export_actor: the actor has no conv tower (vector observations are "
                     "not exportable to the depth policy format)")
  num_hidden = sum(1 for k in arrays if re.fullmatch(r"dense\d+/kernel", k))
  full = {
      "mjxvine_version": mjxvine.__version__, "state_layout": list(STATE_LAYOUT),
      "depth_scale": 1.0, **meta,  # meta may set these, not the format below
      "format_version": FORMAT_VERSION,
      "conv_layers": [[s, p] for s, p in CONV_LAYERS], "num_hidden": num_hidden,
  }
  if "image_size" in full:  # the tower's edge padding (bottom, right), as it was trained
    full["tower_pad"] = list(tower_pad(full["image_size"]))
  # numpy scalars/arrays in meta -> plain JSON values
  full = json.loads(json.dumps(full, default=lambda o: o.tolist() if hasattr(o, "tolist")
                               else str(o)))
  return arrays, full


def export_actor(actor_params: Any, path: str | Path, meta: dict) -> Path:
  """Writes actor params (flax "params" dict of the conv-tower actor) and meta to `path`.

  meta must give image_size [H, W], max_depth_m, action_low, action_high (lists of A
  floats) and should give depth_scale (default 1.0: the depth multiplier the actor was
  trained with), fovx_deg, fovy_deg, config_hash. format_version, mjxvine_version,
  state_layout, conv_layers and num_hidden are filled in. Returns the path written.
  """
  arrays, full = actor_arrays(actor_params, meta)
  path = Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  with atomic.atomic_path(path) as tmp:  # a failed write keeps the previous file
    write_npz(tmp, {**arrays, META_KEY: np.array(json.dumps(full))})
  return path


def write_npz(path: str | Path, arrays: dict[str, np.ndarray]) -> None:
  """`np.savez` with a fixed timestamp on every entry (numpy stamps the current time), so
  that the same arrays give the same bytes: the same training command gives the same
  policy file. `np.load` reads it as any .npz."""
  with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf:
    for name, value in arrays.items():
      info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
      with zf.open(info, "w", force_zip64=True) as f:
        np.lib.format.write_array(f, np.asanyarray(value), allow_pickle=False)


def check_actor_fits(actor_params: Any, cfg: config_lib.Config) -> None:
  """Raises ValueError, naming the arrays, when actor params (one member's flax "params")
  do not have the shapes of the actor that `cfg` builds (image size, `sac.hidden`,
  `sac.conv_features`, the action box): a checkpoint of another config."""
  import jax
  import jax.numpy as jnp

  from mjxvine import networks as nw
  nets = nw.make_networks_from_config(cfg)
  obs = {"depth": jnp.zeros((1, cfg.camera.height, cfg.camera.width, 1), jnp.float32),
         "state": jnp.zeros((1, 3), jnp.float32)}
  abstract = jax.eval_shape(lambda k: nw.init_params(nets, k, obs)[0], jax.random.PRNGKey(0))
  want = {"/".join(str(getattr(p, "key", p)) for p in path): tuple(leaf.shape)
          for path, leaf in jax.tree_util.tree_leaves_with_path(abstract)}
  got = {k: np.shape(v) for k, v in flatten_params(actor_params).items()}
  bad = [f"{k} {got.get(k, 'missing')} (the config's {v})"
         for k, v in want.items() if got.get(k) != v]
  bad += [f"{k} (not in the config's actor)" for k in got if k not in want]
  if bad:
    raise ValueError(f"the checkpoint's actor does not fit the config: {'; '.join(bad[:3])}"
                     + (f"; and {len(bad) - 3} more" if len(bad) > 3 else ""))
