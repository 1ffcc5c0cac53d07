"""Export a trained actor to a numpy-only .npz policy file for `mjxvine.deploy`.

    python -m mjxvine.export --checkpoint RUN_DIR [--out policy.npz] [--config FILE]

The file holds the actor's float32 arrays under their flax paths ("tower/conv0/kernel",
"dense0/bias", "mean/kernel", ...) and a JSON `__meta__` entry: format version, image
size, FOVs, max depth, depth scale, action box, state layout, network layout, config
hash and mjxvine version.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np

import mjxvine
from mjxvine import config as config_lib
from mjxvine.deploy import FORMAT_VERSION, META_KEY

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
  return {
      "image_size": [cfg.camera.height, cfg.camera.width],
      "fovx_deg": cfg.camera.fovx_deg, "fovy_deg": cfg.camera.fovy_deg,
      "max_depth_m": cfg.camera.max_depth_m, "depth_scale": 1.0 / cfg.camera.max_depth_m,
      "action_low": [0.0, -cfg.env.w_max], "action_high": [cfg.env.v_max, cfg.env.w_max],
      "control_dt": cfg.env.control_dt, "config_hash": config_lib.config_hash(cfg),
  }


def export_actor(actor_params: Any, path: str | Path, meta: dict) -> Path:
  """Writes actor params (flax "params" dict of the conv-tower actor) and meta to `path`.

  meta must give image_size [H, W], max_depth_m, action_low, action_high (lists of A
  floats) and should give depth_scale (default 1.0: the depth multiplier the actor was
  trained with), fovx_deg, fovy_deg, config_hash. format_version, mjxvine_version,
  state_layout, conv_layers and num_hidden are filled in. Returns the path written.
  """
  from mjxvine.networks import CONV_LAYERS  # imports jax: only needed when exporting

  missing = [k for k in REQUIRED_META if k not in meta]
  if missing:
    raise ValueError(f"export_actor: meta lacks {', '.join(missing)}")
  arrays = flatten_params(actor_params)
  if "tower/conv0/kernel" not in arrays:
    raise ValueError("export_actor: the actor has no conv tower (vector observations are "
                     "not exportable to the depth policy format)")
  num_hidden = sum(1 for k in arrays if re.fullmatch(r"dense\d+/kernel", k))
  full = {
      "format_version": FORMAT_VERSION, "mjxvine_version": mjxvine.__version__,
      "state_layout": list(STATE_LAYOUT), "depth_scale": 1.0,
      **{k: v for k, v in meta.items()},
      "conv_layers": [[s, p] for s, p in CONV_LAYERS], "num_hidden": num_hidden,
  }
  full["format_version"] = FORMAT_VERSION
  path = Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  with open(path, "wb") as f:  # a file object: numpy adds no ".npz" suffix
    text = json.dumps(full, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
    np.savez(f, **arrays, **{META_KEY: np.array(text)})
  return path


# ----------------------------------------------------------------------------------------
# CLI: restore the actor params from an orbax checkpoint.


def _find_checkpoint(root: Path) -> Path:
  """The orbax checkpoint item under `root`: itself, or the one with the highest step."""
  if (root / "_METADATA").is_file():
    return root
  found = [p.parent for p in root.rglob("_METADATA")]
  if not found:
    raise FileNotFoundError(f"{root}: no orbax checkpoint (no _METADATA file) inside")
  step = lambda p: tuple(int(x) for x in re.findall(r"\d+", str(p.relative_to(root))))
  return max(found, key=lambda p: (step(p), str(p)))


def _find_key(tree: Any, key: str) -> Any:
  """The first value under `key` in a nested dict (breadth first), or None."""
  level = [tree]
  while level:
    nxt = []
    for node in level:
      if isinstance(node, dict):
        if key in node:
          return node[key]
        nxt.extend(node.values())
    level = nxt
  return None


def load_actor_params(checkpoint: str | Path) -> tuple[Any, Path]:
  """Restores (as numpy) the `actor_params` entry of the latest checkpoint under a dir."""
  import jax
  import orbax.checkpoint as ocp

  item = _find_checkpoint(Path(checkpoint))
  ckpt = ocp.PyTreeCheckpointer()
  tree_meta = ckpt.metadata(item).item_metadata
  tree_meta = getattr(tree_meta, "tree", tree_meta)
  restore_args = jax.tree.map(lambda _: ocp.RestoreArgs(restore_type=np.ndarray), tree_meta)
  tree = ckpt.restore(item, args=ocp.args.PyTreeRestore(restore_args=restore_args))
  actor = _find_key(tree, "actor_params")
  if actor is None:
    raise KeyError(f"{item}: the checkpoint has no 'actor_params' entry")
  return actor, item


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(prog="python -m mjxvine.export", description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--checkpoint", required=True,
                      help="run dir or orbax checkpoint dir (the latest step is used)")
  parser.add_argument("--out", default=None, help="output .npz (default RUN_DIR/policy.npz)")
  config_lib.add_config_args(parser)
  args = parser.parse_args(argv)
  run_dir = Path(args.checkpoint)
  if args.config is None and (run_dir / "config.yaml").is_file():
    args.config = str(run_dir / "config.yaml")
  cfg = config_lib.config_from_args(args)
  try:
    actor, item = load_actor_params(run_dir)
  except (FileNotFoundError, KeyError) as e:
    raise SystemExit(f"export error: {e}") from None
  out = Path(args.out) if args.out else run_dir / "policy.npz"
  export_actor(actor, out, meta_from_config(cfg))
  print(f"wrote {out} (from {item}, config {args.config or 'defaults'})", file=sys.stderr)


if __name__ == "__main__":
  main()
