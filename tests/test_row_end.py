"""The end-of-row detector (`mjxvine.deploy.numpy_policy`, The end of the row): its band,
cue and memory on images made to measure; numpy, jax.numpy, `NumpyPolicy.step` and the
ONNX graph agree frame by frame; `evaluate --past-end` on the oracle."""

import json

import jax.numpy as jnp
import numpy as np
import pytest

from mjxvine import deploy
from mjxvine.config import Config, load_config, replace
from mjxvine.deploy import RowEnd, band_rows, row_cue, row_start, row_update

H = W = 41
FOVY = 46.8


def _frame(plants_left: bool, plants_right: bool, depth_m: float = 2.0, noise=None):
  """A 41x41 image: open space (5 m) above the horizon with plant columns at `depth_m` on
  the sides asked for, the ground below the horizon (near, as a camera sees it)."""
  img = np.full((H, W), 5.0, np.float32)
  if plants_left:
    img[:20, :8] = depth_m
  if plants_right:
    img[:20, -8:] = depth_m
  img[21:] = np.linspace(3.0, 0.6, H - 21)[:, None]  # the ground: never counted
  return img if noise is None else np.clip(img + noise, 0.0, 5.0)


def test_the_band_is_the_rows_above_the_axis_by_the_elevation():
  assert band_rows(H, FOVY, 3.0) == 18  # rows 0-17: centres 3.4 deg and more above the axis
  assert band_rows(H, FOVY, 1e-6) == 20  # every row above the middle one
  assert band_rows(112, FOVY, 3.0) == 49  # 56 - (r + 0.5) >= 129.4 tan 3 deg px
  share, depth = row_cue(_frame(True, True), 18, RowEnd())
  assert share == pytest.approx(16 * 18 / (18 * 41)) and depth == pytest.approx(2.0)
  share, depth = row_cue(_frame(False, False), 18, RowEnd())
  assert share == 0.0 and depth == 0.0  # the ground below the band is not a plant


def _drive(frames, speed=0.5, dt=0.1, settings=RowEnd()):
  memory, out = row_start(), []
  for img in frames:
    memory, ended = row_update(memory, *row_cue(img, 18, settings), speed, dt, settings)
    out.append(bool(ended))
  return out


def test_it_fires_once_the_last_plants_depth_and_the_margin_are_driven():
  # plants at 2 m, then open space: 2.0 + 0.25 m at 0.0625 m per frame (exact in
  # float32) = the 36th clear frame
  exact = dict(dt=0.125, settings=RowEnd(margin_m=0.25))
  ended = _drive([_frame(True, True)] * 30 + [_frame(False, False)] * 60, **exact)
  assert not any(ended[:30 + 35]) and all(ended[30 + 35:])
  # a gap in one row (the other still seen) never fires, however long
  assert not any(_drive([_frame(True, True)] * 10 + [_frame(True, False)] * 200))
  # a row never seen never ends; a robot standing still never reaches the end
  assert not any(_drive([_frame(False, False)] * 200))
  assert not any(_drive([_frame(True, True)] * 5 + [_frame(False, False)] * 200, speed=0.0))
  # a reverse command does not count as driven
  assert not any(_drive([_frame(True, True)] * 5 + [_frame(False, False)] * 200, speed=-0.5))


def test_settings_come_from_the_policy_metadata_and_bad_ones_are_refused():
  assert RowEnd.from_meta(None) == RowEnd()
  assert RowEnd.from_meta({"near_m": 2}).near_m == 2.0
  for bad in ({"near": 2.0}, {"margin_m": -1.0}, {"seen_share": float("nan")},
              {"near_m": True}, {"near_m": "3"}):
    with pytest.raises(ValueError, match="row_end"):
      RowEnd.from_meta(bad)


def _sequence(seed=0):
  """Noisy frames of a row (both sides), a one-sided gap, the row again and its end, with
  the speeds commanded."""
  rng = np.random.default_rng(seed)
  kinds = [(True, True)] * 20 + [(True, False)] * 30 + [(True, True)] * 10 + [(False, False)] * 60
  frames = np.stack([_frame(*k, depth_m=1.5 + 0.5 * rng.random(),
                            noise=rng.normal(0, 0.2, (H, W)).astype(np.float32)) for k in kinds])
  speeds = rng.uniform(0.3, 0.5, len(kinds)).astype(np.float32)
  return frames, speeds


def test_numpy_and_jax_agree_frame_by_frame():
  frames, speeds = _sequence()
  settings = RowEnd()
  numpy_out = []
  memory = row_start()
  for img, v in zip(frames, speeds):
    memory, ended = row_update(memory, *row_cue(img, 18, settings), v, 0.1, settings)
    numpy_out.append(bool(ended))
  share, depth = row_cue(jnp.asarray(frames), 18, settings, xp=jnp)
  from mjxvine.evaluation.past_end import Detector
  jax_out = Detector(settings, 18, 0.1).ended(np.asarray(share)[:, None],
                                              np.asarray(depth)[:, None], speeds[:, None])
  assert jax_out[:, 0].tolist() == numpy_out
  assert 1 <= numpy_out.index(True) - 60 <= 60 and not any(numpy_out[:60])


@pytest.fixture(scope="module")
def policy_file(tmp_path_factory):
  import jax
  from mjxvine import networks as nw
  from mjxvine.deploy import export as export_lib
  cfg = replace(Config(), camera={"height": H, "width": W})
  nets = nw.make_networks_from_config(cfg)
  params, _ = nw.init_params(nets, jax.random.PRNGKey(2), {"depth": jnp.zeros((1, H, W, 1)),
                                                           "state": jnp.zeros((1, 3))})
  return export_lib.export_actor(params, tmp_path_factory.mktemp("row_end") / "p.npz",
                                 export_lib.meta_from_config(cfg))


def test_numpy_policy_step_and_the_onnx_graph_agree(policy_file, tmp_path):
  ort = pytest.importorskip("onnxruntime")
  from mjxvine.deploy import onnx as onnx_lib
  policy = deploy.NumpyPolicy.load(policy_file)
  assert policy.row_end == RowEnd()  # written into the file's metadata by the export
  sess = ort.InferenceSession(str(onnx_lib.export_onnx(policy_file, tmp_path / "p.onnx")),
                              providers=["CPUExecutionProvider"])
  assert [o.name for o in sess.get_outputs()] == ["action", "row_ended", "row_memory_out"]
  frames, speeds = _sequence(1)
  memory = np.array([[0.0, np.inf]], np.float32)
  steps, graph = [], []
  for img, v in zip(frames, speeds):
    state = np.array([v, 0.1, 0.2], np.float32)
    action, ended = policy.step(img, state)
    steps.append(ended)
    got = sess.run(None, {"depth": img[None, :, :, None], "state": state[None],
                          "row_memory": memory})
    memory = got[2]
    graph.append(bool(got[1][0]))
    np.testing.assert_allclose(got[0][0], action, atol=1e-5)
  assert graph == steps and any(steps) and not any(steps[:60])
  policy.reset_row()  # a new row: the memory is forgotten
  assert policy.step(frames[-1], np.array([0.5, 0.0, 0.0], np.float32))[1] is False
  with pytest.raises(deploy.PolicyInputError, match="one robot"):
    policy.step(frames[:2], np.zeros((2, 3), np.float32))


def test_evaluate_past_end_reports_where_the_oracle_stopped(tmp_path):
  from mjxvine.evaluation.rollout import PolicySource, Protocol, run_protocol
  from mjxvine.worlds import load_test_world
  cfg = load_config(None, ["camera.width=41", "camera.height=41"])
  world = load_test_world(cfg.world)
  doc, _ = run_protocol(cfg, PolicySource("oracle"), world,
                        Protocol(1, 1.0, lanes=[1], past_end=True))
  section = doc["row_end"]
  assert section["runs"] == 2 and set(section["rows"]) == {"1F", "1R"}
  assert section["false_stops"] == 0 and section["missed"] == 0
  assert section["stopped_within_1m"] == 2
  assert all(abs(s) <= 1.0 for s in section["stops_m"])
  json.dumps(doc)  # the results file takes it as it is
  from mjxvine.evaluation.report import results_markdown
  assert "## The end of the row" in results_markdown({**doc, "wall_s": 1.0})
