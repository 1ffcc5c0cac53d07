"""A policy file's actor as an ONNX graph (opset 17; `pip install mjxvine[onnx]`).

The graph takes depth (B, H, W, 1) float32 metres and state (B, 3) and outputs action
(B, 2): the same deterministic action as `NumpyPolicy`, box mapping and depth scaling
included. onnx is imported only when a graph is built.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from mjxvine import atomic
from mjxvine.deploy.numpy_policy import (META_KEY, MIRROR_ACTION_SIGN, MIRROR_STATE_SIGN,
                                         NumpyPolicy, RowEnd, band_rows, read_policy_file)

ONNX_OPSET = 17
ONNX_META_KEY = "mjxvine_meta"


def policy_source(source: Any, meta: dict | None) -> tuple[dict[str, np.ndarray], dict]:
  """(arrays, meta) from an .npz path or from (arrays, meta), validated by NumpyPolicy."""
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


class _Graph:
  """The nodes and initialisers of the graph being built, each output named once."""

  def __init__(self):
    from onnx import helper, numpy_helper
    self.helper, self.numpy_helper = helper, numpy_helper
    self.inits, self.nodes = [], []

  def const(self, name: str, value) -> str:
    self.inits.append(self.numpy_helper.from_array(np.ascontiguousarray(value), name))
    return name

  def node(self, op: str, inputs: list[str], name: str, **attrs) -> str:
    self.nodes.append(self.helper.make_node(op, inputs, [name], name=name, **attrs))
    return name


def _clean_depth(g: _Graph, x: str, meta: dict, invalid_depth: float | None) -> str:
  """`NumpyPolicy.clean_depth`: NaN, inf and <= 0 -> invalid_depth, then a clip to
  [0, max_depth_m]."""
  top = float(meta["max_depth_m"])
  zero, top_c = g.const("zero", np.float32(0.0)), g.const("max_depth", np.float32(top))
  fill = g.const("invalid_depth", np.float32(top if invalid_depth is None else invalid_depth))
  bad = g.node("Or", [g.node("IsNaN", [x], "is_nan"), g.node("IsInf", [x], "is_inf")],
               "not_finite")
  bad = g.node("Or", [bad, g.node("LessOrEqual", [x, zero], "no_return")], "invalid")
  x = g.node("Where", [bad, fill, x], "depth_valid")
  return g.node("Clip", [x, zero, top_c], "depth_clipped")


def _with_mirror(g: _Graph, x: str, state: str) -> tuple[str, str]:
  """One batch of the inputs and their mirror images (columns reversed, state signs)."""
  flipped = g.node("Slice", [x, g.const("last", np.array([-1], np.int64)),
                             g.const("before_first", np.array([-(1 << 62)], np.int64)),
                             g.const("width_axis", np.array([3], np.int64)),
                             g.const("step_back", np.array([-1], np.int64))], "mirrored")
  x = g.node("Concat", [x, flipped], "with_mirror", axis=0)
  state_sign = g.const("state_sign", MIRROR_STATE_SIGN)
  state = g.node("Concat", [state, g.node("Mul", [state, state_sign], "state_mirrored")],
                 "states", axis=0)
  return x, state


def _tower(g: _Graph, x: str, arrays: dict, meta: dict) -> str:
  """The conv tower on (B, 1, H, W): edge padding, convs with ReLUs and the max pool, the
  global mean -> (B, F). The depth scale is folded into the first kernel."""
  ph, pw = (int(v) for v in meta.get("tower_pad", (0, 0)))
  if ph or pw:  # repeat the bottom rows / right columns, as the tower was trained
    x = g.node("Pad", [x, g.const("tower_pad", np.array([0, 0, 0, 0, 0, 0, ph, pw], np.int64))],
               "padded", mode="edge")
  for i, (stride, pool) in enumerate((int(s), bool(p)) for s, p in meta["conv_layers"]):
    k = arrays[f"tower/conv{i}/kernel"].astype(np.float32)  # (3, 3, C, F)
    if i == 0:
      k = k * np.float32(meta.get("depth_scale", 1.0))
    x = g.node("Conv", [x, g.const(f"conv{i}_w", k.transpose(3, 2, 0, 1)),
                        g.const(f"conv{i}_b", arrays[f"tower/conv{i}/bias"])], f"conv{i}",
               kernel_shape=[3, 3], strides=[stride, stride])
    x = g.node("Relu", [x], f"conv{i}_relu")
    if pool:
      x = g.node("MaxPool", [x], f"conv{i}_pool", kernel_shape=[2, 2], strides=[2, 2])
  return g.node("Flatten", [g.node("GlobalAveragePool", [x], "avg_pool")], "features", axis=1)


def _action(g: _Graph, x: str, arrays: dict, meta: dict, mirror: bool) -> str:
  """The MLP torso on the (B, F + S) torso input, the mean head, tanh onto the action box;
  with `mirror`, the mean of the action and the mirrored action on the mirror image."""
  low = np.asarray(meta["action_low"], np.float32)
  high = np.asarray(meta["action_high"], np.float32)
  for i in range(int(meta["num_hidden"])):
    x = g.node("Gemm", [x, g.const(f"dense{i}_w", arrays[f"dense{i}/kernel"]),
                        g.const(f"dense{i}_b", arrays[f"dense{i}/bias"])], f"dense{i}")
    x = g.node("Relu", [x], f"dense{i}_relu")
  x = g.node("Gemm", [x, g.const("mean_w", arrays["mean/kernel"]),
                      g.const("mean_b", arrays["mean/bias"])], "mean")
  # low + (tanh(u) + 1) / 2 (high - low) = tanh(u) (high - low) / 2 + (high + low) / 2
  x = g.node("Mul", [g.node("Tanh", [x], "tanh"), g.const("half_range", (high - low) / 2)],
             "scaled")
  x = g.node("Add", [x, g.const("mid", (high + low) / 2)], "actions" if mirror else "action")
  if not mirror:
    return x
  g.nodes.append(g.helper.make_node("Split", [x], ["action_direct", "action_of_mirror"],
                                    name="split", axis=0))
  x = g.node("Add", ["action_direct", g.node("Mul", [
      "action_of_mirror", g.const("action_sign", MIRROR_ACTION_SIGN)], "action_mirrored")],
             "action_sum")
  return g.node("Mul", [x, g.const("half", np.float32(0.5))], "action")


def _row_end(g: _Graph, depth: str, state: str, meta: dict, state_layout: list) -> None:
  """`NumpyPolicy.step`'s end-of-row detector (`row_cue`, `row_update`) on depth (B, H, W,
  1) m, the state (its v_prev) and the memory input row_memory (B, 2) [driven m, last
  depth m] ([0, inf] at a row's entrance): outputs row_ended (B,) bool and
  row_memory_out (B, 2), the next frame's row_memory."""
  s = RowEnd.from_meta(meta.get("row_end"))
  h, w = (int(v) for v in meta["image_size"])
  rows = band_rows(h, float(meta["fovy_deg"]), s.min_elevation_deg)
  f32 = lambda name, v: g.const(name, np.float32(v))
  i64 = lambda name, v: g.const(name, np.asarray(v, np.int64))
  band = g.node("Slice", [depth, i64("band_start", [0]), i64("band_end", [rows]),
                          i64("band_axis", [1])], "row_band")
  plant = g.node("Less", [band, f32("row_near", s.near_m)], "row_plant")
  axes = i64("row_axes", [1, 2, 3])
  count = g.node("ReduceSum", [g.node("Cast", [plant], "row_plant_f", to=1), axes],
                 "row_count", keepdims=0)
  share = g.node("Div", [count, f32("row_band_size", rows * w)], "row_share")
  total = g.node("ReduceSum", [g.node("Where", [plant, band, f32("row_zero", 0.0)],
                                      "row_plant_depth"), axes], "row_depth_sum", keepdims=0)
  mean = g.node("Div", [total, g.node("Max", [count, f32("row_one", 1.0)], "row_count1")],
                "row_mean_depth")
  column = lambda x, i, name: g.node("Squeeze", [g.node(  # (B, 1) -> (B,)
      "Gather", [x, i64(f"{name}_index", [i])], f"{name}_1", axis=1), i64(f"{name}_axis", [1])],
      name)
  v = column(state, state_layout.index("v_prev"), "row_v")
  seen = g.node("Greater", [share, f32("row_seen_share", s.seen_share)], "row_seen")
  step = g.node("Mul", [g.node("Max", [v, "row_zero"], "row_v_forward"),
                        f32("row_dt", float(meta["control_dt"]))], "row_step")
  driven = g.node("Where", [seen, "row_zero", g.node("Add", [
      column("row_memory", 0, "row_driven_in"), step], "row_driven_more")], "row_driven")
  last = g.node("Where", [seen, mean, column("row_memory", 1, "row_last_in")], "row_last")
  far = g.node("GreaterOrEqual", [driven, g.node("Add", [last, f32("row_margin", s.margin_m)],
                                                "row_needed")], "row_far")
  g.node("And", [g.node("Not", [seen], "row_unseen"), far], "row_ended")
  unsq = lambda x: g.node("Unsqueeze", [x, i64(f"{x}_axis", [1])], f"{x}_col")
  g.node("Concat", [unsq(driven), unsq(last)], "row_memory_out", axis=1)


def onnx_model(arrays: dict[str, np.ndarray], meta: dict, preprocess: bool = False,
               invalid_depth: float | None = None):
  """The actor's deterministic action as an `onnx.ModelProto` (opset 17).

  Inputs: depth (B, H, W, 1) float32 metres, state (B, S) float32, and row_memory (B, 2)
  float32, the end-of-row detector's memory (`row_memory_out` of the last frame; [0, inf]
  at a row's entrance). Outputs: action (B, A)
  float32 in the action box, as `NumpyPolicy.action`; row_ended (B,) bool and
  row_memory_out (B, 2), the memory to feed back with the next frame, as
  `NumpyPolicy.step` (files without control_dt, fovy_deg or v_prev: the action alone).
  The depth scale is folded into the first conv kernel. preprocess=True puts `NumpyPolicy.clean_depth` in front: NaN, inf and
  readings <= 0 (no return) -> `invalid_depth` (None: max_depth_m, what the simulator
  shows), then a clip to [0, max_depth]; otherwise inputs must be finite.
  """
  import onnx
  from onnx import TensorProto, helper

  h, w = (int(v) for v in meta["image_size"])
  actions = len(meta["action_low"])
  state_size = arrays["dense0/kernel"].shape[0] - arrays["tower/conv0/kernel"].shape[-1]
  g = _Graph()
  x = _clean_depth(g, "depth", meta, invalid_depth) if preprocess else "depth"
  policy = NumpyPolicy(arrays, meta)
  row_end = policy.has_row_end
  if row_end:
    _row_end(g, x, "state", meta, policy.state_layout)
  # (B, H, W, 1) -> (B, 1, H, W): a reshape, since there is one channel.
  x = g.node("Reshape", [x, g.const("nchw_shape", np.array([-1, 1, h, w], np.int64))], "nchw")
  mirror = bool(meta.get("mirror_average", False))
  x, state = _with_mirror(g, x, "state") if mirror else (x, "state")
  x = g.node("Concat", [_tower(g, x, arrays, meta), state], "torso", axis=1)
  _action(g, x, arrays, meta, mirror)
  graph = helper.make_graph(
      g.nodes, "mjxvine_actor",
      [helper.make_tensor_value_info("depth", TensorProto.FLOAT, ["batch", h, w, 1]),
       helper.make_tensor_value_info("state", TensorProto.FLOAT, ["batch", state_size])]
      + ([helper.make_tensor_value_info("row_memory", TensorProto.FLOAT, ["batch", 2])]
         if row_end else []),
      [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", actions])]
      + ([helper.make_tensor_value_info("row_ended", TensorProto.BOOL, ["batch"]),
          helper.make_tensor_value_info("row_memory_out", TensorProto.FLOAT, ["batch", 2])]
         if row_end else []),
      initializer=g.inits)
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

  source: an .npz policy file (from `mjxvine.deploy.export.export_actor`), or its arrays
  {"tower/conv0/kernel": ...} with `meta` (the full metadata, as `actor_arrays` returns), or
  an (arrays, meta) tuple. The metadata is stored as JSON under the model property
  "mjxvine_meta". preprocess, invalid_depth: see `onnx_model`.
  """
  import onnx

  arrays, meta = policy_source(source, meta)
  model = onnx_model(arrays, meta, preprocess, invalid_depth)
  path = Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  with atomic.atomic_path(path) as tmp:  # a failed write keeps the previous file
    onnx.save(model, str(tmp))
  return path
