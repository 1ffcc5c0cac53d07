"""ONNX export: onnxruntime equals NumpyPolicy (and flax), npz -> onnx CLI, optional import."""

import json
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjxvine import config as config_lib
from mjxvine import deploy, export
from mjxvine.deploy import export as export_lib
from mjxvine.deploy import onnx as onnx_lib
from mjxvine import networks as nw

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

H = W = 40  # small: the conv tower goes 40 -> 19 -> 17 -> 8 -> 3 -> 1


@pytest.fixture(scope="module")
def small_policy(tmp_path_factory):
  """(npz path, actor params, jitted flax deterministic action) of a 40x40 actor."""
  cfg = config_lib.replace(config_lib.Config(), camera={"height": H, "width": W})
  nets = nw.make_networks_from_config(cfg)
  obs = {"depth": jnp.zeros((1, H, W, 1)), "state": jnp.zeros((1, 3))}
  params, _ = nw.init_params(nets, jax.random.PRNGKey(1), obs)
  # Non-zero biases, and a larger mean head so that both actions vary across inputs.
  params = jax.tree.map(lambda x: x + 0.02 if x.ndim == 1 else x, params)
  params["mean"]["kernel"] = params["mean"]["kernel"] * 20.0
  path = export_lib.export_actor(params, tmp_path_factory.mktemp("onnx") / "policy.npz",
                             export_lib.meta_from_config(cfg))
  flax_action = jax.jit(lambda p, o: nw.deterministic_action(
      nets.actor.apply({"params": p}, o)[0], nets.action_low, nets.action_high))
  return path, params, flax_action


def _inputs(batch, seed=0):
  rng = np.random.default_rng(seed)
  depth = rng.uniform(0.0, 5.0, size=(batch, H, W, 1)).astype(np.float32)
  depth[:, : H // 3] = 5.0
  state = rng.uniform([0.0, -1.0, -np.pi], [0.5, 1.0, np.pi], size=(batch, 3)).astype(np.float32)
  return depth, state


def _feed(depth, state):
  """The graph's inputs: the end-of-row memory of rows' entrances beside them."""
  memory = np.tile(np.array([[0.0, np.inf]], np.float32), (len(depth), 1))
  return {"depth": depth, "state": state, "row_memory": memory}


def _session(path):
  opts = ort.SessionOptions()
  opts.intra_op_num_threads = 1
  return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


def test_onnx_matches_numpy_policy(small_policy, tmp_path):
  path, params, flax_action = small_policy
  policy = deploy.NumpyPolicy.load(path)
  onnx_path = onnx_lib.export_onnx(path, tmp_path / "policy.onnx")
  sess = _session(onnx_path)
  assert [i.name for i in sess.get_inputs()] == ["depth", "state", "row_memory"]
  assert [o.name for o in sess.get_outputs()] == ["action", "row_ended", "row_memory_out"]
  for batch, seed in ((1, 0), (1, 1), (3, 2)):
    depth, state = _inputs(batch, seed)
    (got,) = sess.run(["action"], _feed(depth, state))
    assert got.shape == (batch, 2) and got.dtype == np.float32
    np.testing.assert_allclose(got, policy.action(depth, state), atol=1e-5)
    np.testing.assert_allclose(got, np.asarray(flax_action(params, {"depth": depth,
                                                                    "state": state})), atol=1e-5)
  depth, state = _inputs(3, 3)
  (got,) = sess.run(["action"], _feed(depth, state))
  assert got[:, 0].std() > 1e-3 and got[:, 1].std() > 1e-3  # a non-trivial comparison
  assert np.all(got >= [0.0, -1.0]) and np.all(got <= [0.5, 1.0])
  model = onnx.load(str(onnx_path))
  meta = json.loads({p.key: p.value for p in model.metadata_props}[onnx_lib.ONNX_META_KEY])
  assert meta["image_size"] == [H, W] and meta["action_high"] == [0.5, 1.0]


def test_onnx_from_arrays_with_preprocess(small_policy, tmp_path):
  arrays, meta = deploy.read_policy_file(small_policy[0])
  sess = _session(onnx_lib.export_onnx((arrays, meta), tmp_path / "pre.onnx", preprocess=True))
  policy = deploy.NumpyPolicy(arrays, meta, preprocess=True)
  depth, state = _inputs(2, 4)
  depth[0, 5, 6], depth[1, 7, 8], depth[1, 9, 9] = np.nan, 9.0, -np.inf
  depth[0, 1:4, 1:30], depth[1, 20, 3], depth[1, 21, 4] = 0.0, -2.0, np.inf  # no return
  (got,) = sess.run(["action"], _feed(depth, state))
  np.testing.assert_allclose(got, policy.action(depth, state), atol=1e-5)
  clean = policy.clean_depth(depth)
  assert clean[0, 2, 10] == clean[1, 21, 4] == clean[0, 5, 6] == 5.0  # the maximum range
  np.testing.assert_allclose(got, policy.action(clean, state), atol=1e-5)
  # another value for invalid pixels: the graph and the numpy policy agree
  sess = _session(onnx_lib.export_onnx((arrays, meta), tmp_path / "pre1.onnx", preprocess=True,
                                     invalid_depth=1.0))
  (got1,) = sess.run(["action"], _feed(depth, state))
  near = deploy.NumpyPolicy(arrays, meta, preprocess=True, invalid_depth=1.0)
  np.testing.assert_allclose(got1, near.action(depth, state), atol=1e-5)
  assert np.abs(got1 - got).max() > 1e-4  # the value matters
  with pytest.raises(ValueError, match="meta"):
    onnx_lib.export_onnx(arrays, tmp_path / "x.onnx")
  with pytest.raises(deploy.PolicyFormatError, match="lacks arrays"):
    onnx_lib.export_onnx({k: v for k, v in arrays.items() if k != "mean/bias"},
                       tmp_path / "x.onnx", meta)


def test_export_cli_npz_to_onnx(small_policy, tmp_path, capsys):
  path = small_policy[0]
  out = tmp_path / "cli.onnx"
  export.main(["--policy", str(path), "--format", "onnx", "--out", str(out)])
  depth, state = _inputs(3, 5)
  (got,) = _session(out).run(["action"], _feed(depth, state))
  np.testing.assert_allclose(got, deploy.NumpyPolicy.load(path).action(depth, state), atol=1e-5)
  assert export.main(["--policy", str(path), "--out", str(tmp_path / "again.npz")]) == 2
  assert "only to --format onnx" in capsys.readouterr().err


def test_export_module_does_not_import_onnx():
  root = Path(__file__).resolve().parents[1]
  code = "import sys, mjxvine.export; assert 'onnx' not in sys.modules, 'onnx imported'"
  out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       cwd=root, timeout=60)
  assert out.returncode == 0, out.stderr


def test_latency_onnx(small_policy, tmp_path, capsys):
  from mjxvine import latency

  onnx_path = onnx_lib.export_onnx(small_policy[0], tmp_path / "policy.onnx")
  result = latency.onnx_latency(onnx_path, threads=1, calls=5)
  assert result["calls"] == 5 and 0.0 < result["min_ms"] <= result["median_ms"]
  latency.main(["--policy", str(onnx_path), "--calls", "3", "--threads", "2", "--no-spinning"])
  assert json.loads(capsys.readouterr().out)["calls"] == 3


def test_export_cli_orbax_to_onnx(small_policy, tmp_path):
  """`--format onnx` straight from a run dir (orbax checkpoint), no .npz in between."""
  import orbax.checkpoint as ocp

  path, params, _ = small_policy
  run = tmp_path / "run"
  ckpt = ocp.StandardCheckpointer()
  ckpt.save(run / "checkpoints" / "100" / "state", {"learner": {"actor_params": params}})
  ckpt.wait_until_finished()
  export.main(["--policy", str(run), "--format", "onnx",
               "--set", f"camera.height={H}", "--set", f"camera.width={W}"])
  depth, state = _inputs(2, 6)
  (got,) = _session(run / "policy.onnx").run(["action"], _feed(depth, state))
  np.testing.assert_allclose(got, deploy.NumpyPolicy.load(path).action(depth, state), atol=1e-5)


def test_mirror_averaged_policy_is_symmetric_in_flax_numpy_and_onnx(small_policy, tmp_path):
  """`sac.mirror_average`: the action on a mirrored observation is the mirrored action,
  exactly, where the plain actor's is not; the JAX action (`networks.act_deterministic`
  with the env's mirror), NumpyPolicy and the ONNX graph agree."""
  from mjxvine.env import VineyardEnv

  path, params, _ = small_policy
  arrays, meta = deploy.read_policy_file(path)
  meta = dict(meta, mirror_average=True)
  policy, plain = deploy.NumpyPolicy(arrays, meta), deploy.NumpyPolicy(arrays, dict(meta))
  plain.mirror_average = False
  sess = _session(onnx_lib.export_onnx((arrays, meta), tmp_path / "mirror.onnx"))
  cfg = config_lib.replace(config_lib.Config(), camera={"height": H, "width": W})
  nets = nw.make_networks_from_config(cfg)
  mirror = (VineyardEnv.mirror_obs, VineyardEnv.mirror_action)
  depth, state = _inputs(3, 4)
  m_depth, m_state = depth[:, :, ::-1], state * deploy.MIRROR_STATE_SIGN
  got = policy.action(depth, state)
  np.testing.assert_allclose(policy.action(m_depth, m_state), got * [1.0, -1.0], atol=1e-6)
  asym = np.abs(plain.action(m_depth, m_state) - plain.action(depth, state) * [1.0, -1.0])
  assert asym.max() > 1e-3  # the plain actor is not symmetric: the test can fail
  np.testing.assert_allclose(got, 0.5 * (plain.action(depth, state) +
                                         plain.action(m_depth, m_state) * [1.0, -1.0]),
                             atol=1e-6)
  (onnx_got,) = sess.run(["action"], _feed(depth, state))
  np.testing.assert_allclose(onnx_got, got, atol=1e-5)
  jax_got = jax.jit(lambda p, o: nw.act_deterministic(nets, p, o, mirror))(
      params, {"depth": jnp.asarray(depth), "state": jnp.asarray(state)})
  np.testing.assert_allclose(np.asarray(jax_got), got, atol=1e-5)
