"""Export a trained actor to a numpy-only .npz policy file for `mjxvine.deploy`, or ONNX.

    python -m mjxvine.export --checkpoint RUN_DIR [--out policy.npz] [--config FILE]
    python -m mjxvine.export --checkpoint RUN_DIR --which last      # not the best checkpoint
    python -m mjxvine.export --checkpoint RUN_DIR --format onnx [--out policy.onnx]
    python -m mjxvine.export --checkpoint policy.npz --format onnx   # convert a policy file

A run's checkpoint is RUN_DIR/checkpoints/best/<step>/ (the best one; --which best, the
default) or the newest RUN_DIR/checkpoints/<step>/ (--which last); a run without a best
checkpoint gives its last one (`mjxvine.checkpoint`). The run's config.yaml gives the
metadata; --config FILE and --set only override it, and not what the networks were
trained for (image size, depth range, network sizes, action box: `mjxvine.runs`). Of a
run that trained several members (--seeds, sweeps), --member K picks one (default: the
one checkpoints/best follows, member 0).

The file holds the actor's float32 arrays under their flax paths ("tower/conv0/kernel",
"dense0/bias", "mean/kernel", ...) and a JSON `__meta__` entry: format version, image
size, FOVs, max depth, depth scale, action box, state layout, network layout, config
hash, the whole training config and mjxvine version.

The ONNX graph (`export_onnx`, opset 17; `pip install mjxvine[onnx]`) takes depth (B, H,
W, 1) float32 metres and state (B, 3) and outputs action (B, 2): the same deterministic
action as `NumpyPolicy`, box mapping and depth scaling included. onnx is imported only
when ONNX is exported.
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
from mjxvine.checkpoint import WHICH, restore_actor_params, run_dir_of
from mjxvine.deploy import FORMAT_VERSION, META_KEY, MIRROR_ACTION_SIGN, MIRROR_STATE_SIGN
from mjxvine.runs import policy_config

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
      # the IMU yaw plus yaw_offset_deg (both wrapped to [-pi, pi)); NumpyPolicy.yaw_input
      "yaw_reference": cfg.env.yaw_reference, "yaw_offset_deg": cfg.env.yaw_offset_deg,
      # the action is the mean of the actor's on the image and its mirror (sac.mirror_average)
      "mirror_average": cfg.sac.mirror_average,
      # the whole training config: `evaluate --policy FILE.npz` then evaluates as the run
      # does (world, episode limit, env options); the robot needs none of it
      "config": config_lib.to_dict(cfg),
  }


def actor_arrays(actor_params: Any, meta: dict) -> tuple[dict[str, np.ndarray], dict]:
  """(arrays, full meta) of the policy file of actor params; see `export_actor`."""
  from mjxvine.networks import CONV_LAYERS, tower_pad  # imports jax: only when exporting

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
  with open(path, "wb") as f:  # a file object: numpy adds no ".npz" suffix
    np.savez(f, **arrays, **{META_KEY: np.array(json.dumps(full))})
  return path


# ----------------------------------------------------------------------------------------
# ONNX (optional: needs the `onnx` package, imported only here)

ONNX_OPSET = 17
ONNX_META_KEY = "mjxvine_meta"


def _policy_source(source: Any, meta: dict | None) -> tuple[dict[str, np.ndarray], dict]:
  """(arrays, meta) from an .npz path or from (arrays, meta), validated by NumpyPolicy."""
  from mjxvine.deploy import NumpyPolicy, read_policy_file

  if isinstance(source, (str, Path)):
    arrays, meta = read_policy_file(source)
  else:
    if isinstance(source, tuple):
      source, meta = source
    if meta is None:
      raise ValueError("export_onnx: arrays need their meta")
    arrays = {k: np.asarray(v, np.float32) for k, v in source.items() if k != META_KEY}
  NumpyPolicy(arrays, meta)  # raises PolicyFormatError on missing or misshapen arrays
  return arrays, meta


def onnx_model(arrays: dict[str, np.ndarray], meta: dict, preprocess: bool = False,
               invalid_depth: float | None = None):
  """The actor's deterministic action as an `onnx.ModelProto` (opset 17).

  Inputs: depth (B, H, W, 1) float32 metres, state (B, S) float32. Output: action (B, A)
  float32 in the action box, as `NumpyPolicy.action`. The depth scale is folded into the
  first conv kernel. preprocess=True puts `NumpyPolicy.clean_depth` in front: NaN, inf and
  readings <= 0 (no return) -> `invalid_depth` (None: max_depth_m, what the simulator
  shows), then a clip to [0, max_depth]; otherwise inputs must be finite.
  """
  import onnx
  from onnx import TensorProto, helper, numpy_helper

  h, w = (int(v) for v in meta["image_size"])
  layers = [(int(st), bool(pl)) for st, pl in meta["conv_layers"]]
  low = np.asarray(meta["action_low"], np.float32)
  high = np.asarray(meta["action_high"], np.float32)
  state_size = arrays["dense0/kernel"].shape[0] - arrays["tower/conv0/kernel"].shape[-1]
  inits, nodes = [], []

  def const(name, value):
    inits.append(numpy_helper.from_array(np.ascontiguousarray(value), name))
    return name

  def node(op, inputs, name, **attrs):
    nodes.append(helper.make_node(op, inputs, [name], name=name, **attrs))
    return name

  x = "depth"
  if preprocess:
    top = float(meta["max_depth_m"])
    zero, top_c = const("zero", np.float32(0.0)), const("max_depth", np.float32(top))
    fill = const("invalid_depth", np.float32(top if invalid_depth is None else invalid_depth))
    bad = node("Or", [node("IsNaN", [x], "is_nan"), node("IsInf", [x], "is_inf")], "not_finite")
    bad = node("Or", [bad, node("LessOrEqual", [x, zero], "no_return")], "invalid")
    x = node("Where", [bad, fill, x], "depth_valid")
    x = node("Clip", [x, zero, top_c], "depth_clipped")
  # (B, H, W, 1) -> (B, 1, H, W): a reshape, since there is one channel.
  x = node("Reshape", [x, const("nchw_shape", np.array([-1, 1, h, w], np.int64))], "nchw")
  state = "state"
  mirror = bool(meta.get("mirror_average", False))
  if mirror:  # one batch of the inputs and their mirror images: columns reversed
    flipped = node("Slice", [x, const("last", np.array([-1], np.int64)),
                             const("before_first", np.array([-(1 << 62)], np.int64)),
                             const("width_axis", np.array([3], np.int64)),
                             const("step_back", np.array([-1], np.int64))], "mirrored")
    x = node("Concat", [x, flipped], "with_mirror", axis=0)
    state_sign = const("state_sign", MIRROR_STATE_SIGN)
    state = node("Concat", [state, node("Mul", [state, state_sign], "state_mirrored")],
                 "states", axis=0)
  ph, pw = (int(v) for v in meta.get("tower_pad", (0, 0)))
  if ph or pw:  # repeat the bottom rows / right columns, as the tower was trained
    x = node("Pad", [x, const("tower_pad", np.array([0, 0, 0, 0, 0, 0, ph, pw], np.int64))],
             "padded", mode="edge")
  for i, (stride, pool) in enumerate(layers):
    k = arrays[f"tower/conv{i}/kernel"].astype(np.float32)  # (3, 3, C, F)
    if i == 0:
      k = k * np.float32(meta.get("depth_scale", 1.0))
    x = node("Conv", [x, const(f"conv{i}_w", k.transpose(3, 2, 0, 1)),
                      const(f"conv{i}_b", arrays[f"tower/conv{i}/bias"])], f"conv{i}",
             kernel_shape=[3, 3], strides=[stride, stride])
    x = node("Relu", [x], f"conv{i}_relu")
    if pool:
      x = node("MaxPool", [x], f"conv{i}_pool", kernel_shape=[2, 2], strides=[2, 2])
  x = node("Flatten", [node("GlobalAveragePool", [x], "avg_pool")], "features", axis=1)
  x = node("Concat", [x, state], "torso", axis=1)
  for i in range(int(meta["num_hidden"])):
    x = node("Gemm", [x, const(f"dense{i}_w", arrays[f"dense{i}/kernel"]),
                      const(f"dense{i}_b", arrays[f"dense{i}/bias"])], f"dense{i}")
    x = node("Relu", [x], f"dense{i}_relu")
  x = node("Gemm", [x, const("mean_w", arrays["mean/kernel"]),
                    const("mean_b", arrays["mean/bias"])], "mean")
  # low + (tanh(u) + 1) / 2 (high - low) = tanh(u) (high - low) / 2 + (high + low) / 2
  x = node("Mul", [node("Tanh", [x], "tanh"), const("half_range", (high - low) / 2)], "scaled")
  x = node("Add", [x, const("mid", (high + low) / 2)], "actions" if mirror else "action")
  if mirror:  # the mean of the action and the mirrored action on the mirror image
    nodes.append(helper.make_node("Split", [x], ["action_direct", "action_of_mirror"],
                                  name="split", axis=0))
    x = node("Add", ["action_direct", node("Mul", ["action_of_mirror",
                                                   const("action_sign", MIRROR_ACTION_SIGN)],
                                           "action_mirrored")], "action_sum")
    node("Mul", [x, const("half", np.float32(0.5))], "action")
  graph = helper.make_graph(
      nodes, "mjxvine_actor",
      [helper.make_tensor_value_info("depth", TensorProto.FLOAT, ["batch", h, w, 1]),
       helper.make_tensor_value_info("state", TensorProto.FLOAT, ["batch", state_size])],
      [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", len(low)])],
      initializer=inits)
  model = helper.make_model(graph, producer_name="mjxvine",
                            producer_version=str(meta.get("mjxvine_version", "")),
                            opset_imports=[helper.make_opsetid("", ONNX_OPSET)], ir_version=8,
                            doc_string="mjxvine actor: depth (B,H,W,1) m, state (B,S) -> "
                                       "deterministic action (B,A) in the action box")
  helper.set_model_props(model, {ONNX_META_KEY: json.dumps(meta)})
  onnx.checker.check_model(model, full_check=True)
  return model


def export_onnx(source: Any, path: str | Path, meta: dict | None = None,
                preprocess: bool = False, invalid_depth: float | None = None) -> Path:
  """Writes the ONNX graph of a policy to `path` and returns it.

  source: an .npz policy file (from `export_actor`), or its arrays {"tower/conv0/kernel":
  ...} with `meta` (the full metadata, as `actor_arrays` returns), or an (arrays, meta)
  tuple. The metadata is stored as JSON under the model property "mjxvine_meta".
  preprocess, invalid_depth: see `onnx_model`.
  """
  import onnx

  arrays, meta = _policy_source(source, meta)
  model = onnx_model(arrays, meta, preprocess, invalid_depth)
  path = Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  onnx.save(model, str(path))
  return path


# ----------------------------------------------------------------------------------------
# CLI: a run's checkpoint (`mjxvine.checkpoint`) or an .npz -> a policy file


def _fail(message: str) -> int:
  """One line on stderr; the exit status of usage and input errors (argparse's)."""
  print(f"export error: {message}", file=sys.stderr)
  return 2


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(prog="python -m mjxvine.export", description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--checkpoint", required=True,
                      help="run dir, its checkpoints/ dir or one orbax checkpoint step (see "
                           "--which); with --format onnx also an exported .npz policy file")
  parser.add_argument("--which", choices=WHICH, default="best",
                      help="which checkpoint of a run: best (the highest step under "
                           "RUN/checkpoints/best/; the last step when the run has none) or "
                           "last (the newest step under RUN/checkpoints/). Default: best")
  parser.add_argument("--format", choices=("npz", "onnx"), default="npz",
                      help="npz (numpy-only mjxvine.deploy) or onnx (needs the onnx package)")
  parser.add_argument("--out", default=None,
                      help="output file (default RUN_DIR/policy.npz or RUN_DIR/policy.onnx; "
                           "for an .npz input, the same name with .onnx)")
  parser.add_argument("--member", type=int, default=None,
                      help="of a run that trained several members (--seeds, sweeps): which "
                           "one to export (default: the one checkpoints/best follows, "
                           "member 0)")
  parser.add_argument("--preprocess", action="store_true",
                      help="onnx: in the graph, map invalid depth (NaN, inf, <= 0) to the "
                           "maximum range (or --invalid-depth) and clip to [0, max_depth]")
  parser.add_argument("--invalid-depth", type=float, default=None, metavar="M",
                      help="with --preprocess: what invalid pixels become, metres (default: "
                           "the camera's max_depth_m, as the simulator renders no return)")
  config_lib.add_config_args(parser)
  args = parser.parse_args(argv)
  if args.invalid_depth is not None and not args.preprocess:
    parser.error("--invalid-depth: give --preprocess too")
  src = Path(args.checkpoint)
  if src.is_file():
    if args.format != "onnx":
      return _fail(f"{src} is a file; an .npz policy converts only to --format onnx")
    out = Path(args.out) if args.out else src.with_suffix(".onnx")
    try:
      export_onnx(src, out, preprocess=args.preprocess, invalid_depth=args.invalid_depth)
    except ValueError as e:  # PolicyFormatError
      return _fail(str(e))
    print(f"wrote {out} (from {src})", file=sys.stderr)
    return 0
  if not src.exists():
    return _fail(f"no such {'policy file' if src.suffix == '.npz' else 'run directory'}: {src}")
  try:
    actor, item = restore_actor_params(src, args.which, args.member)
    # the run's own config.yaml (image size, FOVs, action box); --config/--set override
    cfg, source = policy_config(src, args.config, args.overrides, args.which)
  except config_lib.ConfigError as e:
    print(f"config error: {e}", file=sys.stderr)
    return 2
  except (FileNotFoundError, KeyError, ValueError) as e:  # no, or a damaged, checkpoint
    return _fail(e.args[0] if e.args else str(e))  # a KeyError's str() is quoted
  run_dir = run_dir_of(item)
  out = Path(args.out) if args.out else (run_dir or src) / f"policy.{args.format}"
  try:
    if args.format == "onnx":
      export_onnx(actor_arrays(actor, meta_from_config(cfg)), out, preprocess=args.preprocess,
                  invalid_depth=args.invalid_depth)
    else:
      export_actor(actor, out, meta_from_config(cfg))
  except ValueError as e:  # no conv tower, or arrays that do not fit the metadata
    return _fail(f"{item}: {e}")
  print(f"wrote {out} (from {item}, config {source})", file=sys.stderr)
  return 0


if __name__ == "__main__":
  sys.exit(main())
