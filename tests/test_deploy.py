"""Export to .npz and the numpy-only policy: equality with flax, no jax import, bad input."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjxvine import deploy, export
from mjxvine.deploy import export as export_lib
from mjxvine import networks as nw
from mjxvine.config import Config, config_hash
from conftest import NUMPY_ONLY_PRELUDE, parse_source

H = W = 112


@pytest.fixture(scope="session")
def exported(tmp_path_factory):
  """(path, actor params, jitted flax deterministic action) of a paper-sized actor."""
  cfg = Config()
  nets = nw.make_networks_from_config(cfg)
  obs = {"depth": jnp.zeros((1, H, W, 1)), "state": jnp.zeros((1, 3))}

  @jax.jit
  def init(key):
    params, _ = nw.init_params(nets, key, obs)
    # Non-zero biases, so that the test covers them.
    return jax.tree.map(lambda x: x + 0.01 if x.ndim == 1 else x, params)

  params = init(jax.random.PRNGKey(0))
  path = export_lib.export_actor(params, tmp_path_factory.mktemp("policy") / "policy.npz",
                             export_lib.meta_from_config(cfg))
  flax_action = jax.jit(lambda p, o: nw.deterministic_action(
      nets.actor.apply({"params": p}, o)[0], nets.action_low, nets.action_high))
  return path, params, flax_action


def _inputs(batch, seed=0):
  rng = np.random.default_rng(seed)
  depth = rng.uniform(0.0, 5.0, size=(batch, H, W, 1)).astype(np.float32)
  depth[:, : H // 3] = 5.0  # some structure: far "sky" rows
  state = rng.uniform([0.0, -1.0, -np.pi], [0.5, 1.0, np.pi], size=(batch, 3)).astype(np.float32)
  return depth, state


def test_numpy_policy_matches_flax(exported):
  path, params, flax_action = exported
  policy = deploy.NumpyPolicy.load(path)
  depth, state = _inputs(5)
  expected = np.asarray(flax_action(params, {"depth": depth, "state": state}))
  assert expected[:, 0].std() > 1e-3 and expected[:, 1].std() > 1e-3  # a non-trivial test
  np.testing.assert_allclose(policy.action(depth, state), expected, atol=1e-5)
  v, w = policy(depth[..., 0], state)  # (B, H, W) works too
  np.testing.assert_allclose(np.stack([v, w], -1), expected, atol=1e-5)
  for i in range(2):  # single decisions: (H, W, 1) and (H, W) -> floats
    v, w = policy(depth[i], state[i])
    assert isinstance(v, float) and isinstance(w, float)
    np.testing.assert_allclose([v, w], expected[i], atol=1e-5)
    np.testing.assert_allclose(policy(depth[i, ..., 0], state[i]), expected[i], atol=1e-5)


def test_export_metadata(exported):
  path = exported[0]
  with np.load(path) as data:
    meta = json.loads(str(data["__meta__"]))
    assert all(data[k].dtype == np.float32 for k in data.files if k != "__meta__")
    assert "tower/conv0/kernel" in data.files and "log_std/kernel" in data.files
  assert meta["format_version"] == deploy.FORMAT_VERSION
  assert meta["image_size"] == [112, 112]
  assert meta["action_low"] == [0.0, -1.0] and meta["action_high"] == [0.5, 1.0]
  assert meta["state_layout"] == ["v_prev", "w_prev", "yaw"]
  assert meta["fovx_deg"] == 60.0 and meta["fovy_deg"] == pytest.approx(46.8)
  assert meta["config_hash"] == config_hash(Config())
  assert meta["mjxvine_version"] and meta["num_hidden"] == 2


_NO_JAX = NUMPY_ONLY_PRELUDE + textwrap.dedent("""
  import time
  import numpy as np
  from mjxvine.deploy import NumpyPolicy
  policy = NumpyPolicy.load(sys.argv[1])
  depth = np.full((112, 112), 3.0, np.float32)
  v, w = policy(depth, np.zeros(3, np.float32))
  assert 0.0 <= v <= 0.5 and -1.0 <= w <= 1.0
  for _ in range(20):
    policy(depth, np.zeros(3, np.float32))
  times = []
  for _ in range(200):
    t = time.perf_counter()
    policy(depth, np.zeros(3, np.float32))
    times.append(time.perf_counter() - t)
  loaded = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
  assert not loaded, loaded
  print(f"{v} {w} {sorted(times)[len(times) // 2] * 1e3:.3f}")
""")


def test_deploy_runs_without_jax(exported):
  path, params, flax_action = exported
  env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
  root = Path(__file__).resolve().parents[1]
  env["PYTHONPATH"] = os.pathsep.join([str(root), env.get("PYTHONPATH", "")])
  out = subprocess.run([sys.executable, "-c", _NO_JAX, str(path)], capture_output=True,
                       text=True, env=env, timeout=120)
  assert out.returncode == 0, out.stderr
  v, w, median_ms = (float(x) for x in out.stdout.split())
  expected = np.asarray(flax_action(params, {"depth": jnp.full((1, H, W, 1), 3.0),
                                             "state": jnp.zeros((1, 3))}))[0]
  np.testing.assert_allclose([v, w], expected, atol=1e-5)
  print(f"numpy policy: median {median_ms:.3f} ms per 112x112 decision")
  assert median_ms < 20.0  # ~1 ms on a quiet core; loose for shared CI machines


def test_bad_inputs(exported):
  policy = deploy.NumpyPolicy.load(exported[0])
  depth, state = _inputs(1)
  with pytest.raises(deploy.PolicyInputError, match="shape"):
    policy(np.zeros((64, 64)), state[0])
  with pytest.raises(deploy.PolicyInputError, match="shape"):
    policy(np.zeros((2, 112, 112, 3)), np.zeros((2, 3)))
  with pytest.raises(deploy.PolicyInputError, match="state"):
    policy(depth[0], np.zeros(4))
  with pytest.raises(deploy.PolicyInputError, match="state"):
    policy(depth, np.zeros((2, 3)))  # batch sizes differ
  with pytest.raises(deploy.PolicyInputError, match="state"):
    policy(depth[0], np.array([0.0, np.nan, 0.0]))
  bad = depth[0].copy()
  bad[10, 20] = np.nan
  bad[30, 40] = np.inf
  with pytest.raises(deploy.PolicyInputError, match="2 NaN/inf pixels.*preprocess=True"):
    policy(bad, state[0])
  # preprocess: no return (NaN, inf, 0, negative) -> the maximum range, as the simulator
  # renders a ray that hits nothing; then clip to [0, max_depth] as the sensor does.
  bad[50, 60], bad[70, 80], bad[90, 100], bad[5, 5] = 7.0, 0.0, -1.0, -np.inf
  clean = bad.copy()
  clean[10, 20] = clean[30, 40] = clean[50, 60] = clean[70, 80] = clean[90, 100] = 5.0
  clean[5, 5] = 5.0
  np.testing.assert_array_equal(policy.clean_depth(bad), clean)
  np.testing.assert_allclose(policy(bad, state[0], preprocess=True), policy(clean, state[0]),
                             atol=1e-6)
  np.testing.assert_allclose(deploy.NumpyPolicy.load(exported[0], preprocess=True)(bad, state[0]),
                             policy(clean, state[0]), atol=1e-6)
  # another value for invalid pixels, if a robot wants one
  other = deploy.NumpyPolicy.load(exported[0], preprocess=True, invalid_depth=2.5)
  assert other.clean_depth(bad)[70, 80] == 2.5 and other.clean_depth(bad)[50, 60] == 5.0
  assert other.clean_depth(bad)[10, 20] == 2.5 and bad[10, 20] != bad[10, 20]  # input kept


def _rewrite(src, dst, drop=(), meta_update=None, arrays_update=None):
  with np.load(src) as data:
    arrays = {k: data[k] for k in data.files if k not in drop}
  if meta_update is not None:
    meta = json.loads(str(arrays["__meta__"]))
    meta.update(meta_update)
    arrays["__meta__"] = np.array(json.dumps(meta))
  arrays.update(arrays_update or {})
  with open(dst, "wb") as f:
    np.savez(f, **arrays)
  return dst


def test_bad_files(exported, tmp_path):
  src = exported[0]
  err = deploy.PolicyFormatError
  with pytest.raises(err, match="no such policy file"):
    deploy.NumpyPolicy.load(tmp_path / "missing.npz")
  (tmp_path / "text.npz").write_text("not a zip")
  with pytest.raises(err, match=r"text.npz: not a valid policy file \(not an .npz archive\)"):
    deploy.NumpyPolicy.load(tmp_path / "text.npz")
  (tmp_path / "cut.npz").write_bytes(src.read_bytes()[:-200])  # a truncated download
  with pytest.raises(err, match="cut.npz: not a valid policy file"):
    deploy.NumpyPolicy.load(tmp_path / "cut.npz")
  # numpy's own error for these suggests allow_pickle=True: never for a policy file
  objects = {"dense0/kernel": np.array([{"x": 1}], dtype=object)}
  _rewrite(src, tmp_path / "objects.npz", arrays_update=objects)
  with pytest.raises(err, match=r"not a valid policy file \(dense0/kernel.npy holds pickled "
                     r"object arrays\)"):
    deploy.NumpyPolicy.load(tmp_path / "objects.npz")
  np.savez(tmp_path / "other.npz", a=np.array([{"x": 1}], dtype=object))  # never read
  with pytest.raises(err, match="no __meta__ entry: not an mjxvine policy file"):
    deploy.NumpyPolicy.load(tmp_path / "other.npz")
  with pytest.raises(err, match="format version 99"):
    deploy.NumpyPolicy.load(_rewrite(src, tmp_path / "v99.npz", meta_update={"format_version": 99}))
  with pytest.raises(err, match="lacks arrays: dense1/kernel"):
    deploy.NumpyPolicy.load(_rewrite(src, tmp_path / "partial.npz", drop=("dense1/kernel",)))
  with pytest.raises(err, match="not an mjxvine policy"):
    deploy.NumpyPolicy.load(_rewrite(src, tmp_path / "nometa.npz", drop=("__meta__",)))
  with pytest.raises(err, match="dense1/kernel has shape"):
    deploy.NumpyPolicy.load(_rewrite(src, tmp_path / "shape.npz",
                                     arrays_update={"dense1/kernel": np.zeros((3, 3))}))
  with pytest.raises(err, match="metadata"):
    deploy.NumpyPolicy.load(_rewrite(src, tmp_path / "meta.npz", meta_update={"image_size": 5}))
  assert issubclass(err, deploy.PolicyError) and issubclass(err, ValueError)


def test_reading_a_policy_file_reads_what_it_needs(exported, tmp_path):
  """read_policy_file gives every actor array (log_std too: evaluation rebuilds the actor
  from them); NumpyPolicy.load reads only __meta__ and the arrays it computes with; a
  paper-sized export is far inside the file limits (docs/deployment.md)."""
  from mjxvine.deploy import numpy_policy

  path = exported[0]
  arrays, _ = deploy.read_policy_file(path)
  with np.load(path) as data:
    assert set(arrays) == set(data.files) - {"__meta__"}
    for k, v in arrays.items():
      np.testing.assert_array_equal(v, data[k])
  assert path.stat().st_size * 100 < numpy_policy.MAX_TOTAL_BYTES
  assert max(v.nbytes for v in arrays.values()) * 100 < numpy_policy.MAX_ARRAY_BYTES
  broken = _rewrite(path, tmp_path / "log_std.npz", arrays_update={"log_std/kernel": np.array("x")})
  with pytest.raises(deploy.PolicyFormatError, match="log_std/kernel.npy of dtype <U1"):
    deploy.read_policy_file(broken)
  depth, state = _inputs(2)
  np.testing.assert_array_equal(deploy.NumpyPolicy.load(broken).action(depth, state),
                                deploy.NumpyPolicy.load(path).action(depth, state))


def test_export_cli_from_orbax_checkpoint(exported, tmp_path, capsys):
  """`python -m mjxvine.export --policy RUN_DIR` restores the latest step's actor."""
  import orbax.checkpoint as ocp

  path, params, flax_action = exported
  run = tmp_path / "run"
  ckpt = ocp.StandardCheckpointer()
  for step, scale in ((100, 0.5), (200, 1.0)):
    tree = {"learner": {"actor_params": jax.tree.map(lambda x: x * scale, params),
                        "log_alpha": jnp.float32(0.0)}, "env_steps": step}
    ckpt.save(run / "checkpoints" / str(step) / "state", tree)
  ckpt.wait_until_finished()
  export.main(["--policy", str(run), "--out", str(tmp_path / "cli.npz")])
  depth, state = _inputs(3, seed=1)
  expected = np.asarray(flax_action(params, {"depth": depth, "state": state}))
  got = deploy.NumpyPolicy.load(tmp_path / "cli.npz").action(depth, state)
  np.testing.assert_allclose(got, expected, atol=1e-5)
  (tmp_path / "empty").mkdir()
  capsys.readouterr()
  assert export.main(["--policy", str(tmp_path / "empty")]) == 2
  assert "no orbax checkpoint" in capsys.readouterr().err
  assert export.main(["--policy", str(tmp_path / "missing")]) == 2
  assert capsys.readouterr().err == f"export error: no such run directory: {tmp_path / 'missing'}\n"


def test_ros2_example_compiles(tmp_path):
  """examples/ros2_vineyard_node.py needs rclpy to run; it must at least compile."""
  import py_compile

  src = Path(__file__).resolve().parents[1] / "examples" / "ros2_vineyard_node.py"
  py_compile.compile(str(src), cfile=str(tmp_path / "node.pyc"), doraise=True)


def test_latency_numpy(exported, capsys):
  """mjxvine.latency times single decisions through the public API (a few calls here)."""
  from mjxvine import latency

  result = latency.numpy_latency(exported[0], calls=5)
  assert result["calls"] == 5 and 0.0 < result["min_ms"] <= result["median_ms"]
  assert result["median_ms"] <= result["p99_ms"]
  latency.main(["--policy", str(exported[0]), "--calls", "3"])
  assert json.loads(capsys.readouterr().out)["calls"] == 3
  assert isinstance(deploy.set_blas_threads(1), bool)


def test_yaw_input_follows_the_training_reference(exported):
  """The default policy reads the yaw relative to the row entrance (wrapped); a policy
  trained on the world yaw adds its offset; "start" without the entrance yaw is refused."""
  path = exported[0]
  policy = deploy.NumpyPolicy.load(path)
  assert policy.meta["yaw_reference"] == "start"
  assert policy.yaw_input(3.0, start_yaw=-3.0) == pytest.approx(6.0 - 2 * np.pi)
  assert policy.yaw_input(0.25, start_yaw=0.25) == 0.0
  with pytest.raises(deploy.PolicyInputError, match="start_yaw"):
    policy.yaw_input(0.1)
  arrays, meta = deploy.read_policy_file(path)
  world = deploy.NumpyPolicy(arrays, dict(meta, yaw_reference="world", yaw_offset_deg=90.0))
  assert world.yaw_input(np.pi) == pytest.approx(-np.pi / 2)


def test_deploy_is_one_python_3_8_file_that_needs_only_numpy(exported, tmp_path):
  """mjxvine/deploy/numpy_policy.py parses as Python 3.8 and, copied alone onto a robot
  (as mjxvine_deploy.py), runs the policy with jax, flax, mujoco and mjxvine unimportable."""
  import ast
  import shutil

  from mjxvine.deploy import numpy_policy

  src = Path(numpy_policy.__file__)  # the file itself, not the package's __init__
  tree = parse_source(src.read_text(), feature_version=(3, 8))
  imported = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import)
              for a in n.names}
  imported |= {n.module.split(".")[0] for n in ast.walk(tree)
               if isinstance(n, ast.ImportFrom) and n.module}
  # numpy, and threadpoolctl where it is installed (`set_blas_threads`, optional)
  assert imported - set(sys.stdlib_module_names) - {"__future__"} == {"numpy",
                                                                      "threadpoolctl"}
  shutil.copy(src, tmp_path / "mjxvine_deploy.py")
  code = _NO_JAX.replace("from mjxvine.deploy import", "from mjxvine_deploy import").replace(
      '"orbax")', '"orbax", "mjxvine")')
  env = dict(os.environ, OPENBLAS_NUM_THREADS="1", PYTHONPATH=str(tmp_path))
  out = subprocess.run([sys.executable, "-c", code, str(exported[0])], capture_output=True,
                       text=True, env=env, timeout=120, cwd=tmp_path)
  assert out.returncode == 0, out.stderr
  assert "from mjxvine_deploy import" in code and '"mjxvine")' in code


def test_fov_window():
  """The columns (rows) of a wider camera inside the policy's field of view."""
  # 640 px, fx 320: a 90 deg camera; 60 deg is +-320 tan(30 deg) = +-184.75 px around cx
  assert deploy.fov_window(640, 320.0, 320.0, 60.0) == (135, 505)
  assert deploy.fov_window(640, 320.0, 300.0, 60.0) == (115, 485)  # off-centre cx
  assert deploy.fov_window(640, 320.0, 320.0, 120.0) == (0, 640)  # narrower: all of it
