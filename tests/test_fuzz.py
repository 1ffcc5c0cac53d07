"""Damaged inputs, as random bytes, truncations and changed shapes of a policy file, a world
file and a checkpoint: each either works or raises the project's own error (a one-line
exit 2 from the command lines), and nothing is written half."""

import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from mjxvine.deploy import NumpyPolicy, PolicyError
from mjxvine.export import main as export_main
from mjxvine.worlds import WorldFileError, load_world
from mjxvine.worlds.store import TEST_WORLD_FILE

ROOT = Path(__file__).resolve().parent.parent
POLICY = ROOT / "models" / "jackal.npz"


def _variants(data: bytes, rng: np.random.Generator, count: int = 12):
  """Random bytes, truncations and single-byte flips of `data`."""
  yield b""
  yield rng.bytes(len(data))
  for cut in rng.integers(1, len(data), count // 2):
    yield data[:cut]
  for at in rng.integers(0, len(data), count // 2):
    flipped = bytearray(data)
    flipped[at] ^= 0xFF
    yield bytes(flipped)


def _npz_with(arrays: dict) -> bytes:
  buf = io.BytesIO()
  np.savez(buf, **arrays)
  return buf.getvalue()


def _policy_variants(rng):
  yield from _variants(POLICY.read_bytes(), rng)
  with np.load(POLICY) as f:
    arrays = {k: f[k] for k in f.files}
  for key in [k for k in arrays if k != "__meta__"][:4]:
    yield _npz_with({k: v for k, v in arrays.items() if k != key})             # an array gone
    yield _npz_with({**arrays, key: np.zeros(arrays[key].shape[:-1] + (3,))})   # reshaped
  meta = json.loads(str(arrays["__meta__"]))
  for key in ("image_size", "action_low", "conv_layers", "num_hidden", "format_version"):
    broken = {**meta, key: "nonsense"}
    yield _npz_with({**arrays, "__meta__": np.array(json.dumps(broken))})
  yield _npz_with({**arrays, "__meta__": np.array("{not json")})


def test_damaged_policy_files_load_or_raise_policy_errors(tmp_path, capsys):
  rng = np.random.default_rng(0)
  good = NumpyPolicy.load(POLICY)
  depth, state = np.full((good.height, good.width), 3.0), [0.2, 0.0, 0.0]
  out = tmp_path / "out.onnx"
  for i, data in enumerate(_policy_variants(rng)):
    path = tmp_path / f"policy{i}.npz"
    path.write_bytes(data)
    try:
      policy = NumpyPolicy.load(path)
      v, w = policy(depth, state)
      assert np.isfinite([v, w]).all()
    except PolicyError:
      pass
    # the converter: exit 0 with a whole graph, or 2 with one line and nothing written
    code = export_main(["--policy", str(path), "--format", "onnx", "--out", str(out)])
    err = capsys.readouterr().err
    assert code in (0, 2), err
    if code == 2:
      assert err.startswith("export error: ") and len(err.strip().splitlines()) == 1
      assert not out.exists()
    out.unlink(missing_ok=True)
  assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left


def test_damaged_world_files_load_or_raise_world_file_errors(tmp_path):
  rng = np.random.default_rng(1)
  text = TEST_WORLD_FILE.read_bytes()
  doc = json.loads(text)
  variants = list(_variants(text, rng))
  for key in ("lanes", "plant_xy", "terrain", "terrain_extent", "row_y0"):
    variants.append(json.dumps({k: v for k, v in doc.items() if k != key}).encode())
    variants.append(json.dumps({**doc, key: [[1.0, "x"]]}).encode())
  variants.append(json.dumps({**doc, "plant_xy": doc["plant_xy"][:3]}).encode())
  variants.append(json.dumps({**doc, "lanes": [{"id": 1}]}).encode())
  variants.append(json.dumps({**doc, "length_m": float("nan")}).encode())
  variants.append(json.dumps([1, 2, 3]).encode())
  for i, data in enumerate(variants):
    path = tmp_path / f"world{i}.json"
    path.write_bytes(data)
    try:
      world = load_world(path)
    except WorldFileError as e:
      assert str(path) in str(e) and "\n" not in str(e)
      continue
    assert len(world.lanes) >= 1 and np.isfinite(world.plant_xy).all()


@pytest.fixture(scope="module")
def checkpoint_run(tmp_path_factory):
  """A run directory with one orbax checkpoint of a tiny actor and its config.yaml."""
  import jax
  import jax.numpy as jnp
  import orbax.checkpoint as ocp

  from mjxvine import networks as nw
  from mjxvine.config import load_config, to_yaml
  cfg = load_config("experiments/smoke.yaml", ["camera.width=33", "camera.height=33",
                                                "sac.hidden=8", "sac.conv_features=4"])
  nets = nw.make_networks_from_config(cfg)
  obs = {"depth": jnp.zeros((1, 33, 33, 1)), "state": jnp.zeros((1, 3))}
  actor, _ = nw.init_params(nets, jax.random.PRNGKey(0), obs)
  run = tmp_path_factory.mktemp("run")
  (run / "config.yaml").write_text(to_yaml(cfg))
  with ocp.CheckpointManager(run / "checkpoints") as manager:
    manager.save(1, args=ocp.args.StandardSave({"learner": {"policy_params": actor},
                                                "state": {"00000": np.zeros(2)}}))
    manager.wait_until_finished()
  return run


def test_damaged_checkpoints_export_or_refuse_in_one_line(checkpoint_run, tmp_path, capsys):
  import shutil
  out = tmp_path / "policy.npz"
  assert export_main(["--policy", str(checkpoint_run), "--out", str(out)]) == 0
  NumpyPolicy.load(out)
  out.write_bytes(b"the previous file")
  rng = np.random.default_rng(2)
  files = sorted(p.relative_to(checkpoint_run) for p in (checkpoint_run / "checkpoints").rglob("*")
                 if p.is_file())
  for rel in files:
    for data in list(_variants((checkpoint_run / rel).read_bytes(), rng, count=2))[:3]:
      run = tmp_path / "run"
      shutil.rmtree(run, ignore_errors=True)
      shutil.copytree(checkpoint_run, run)
      (run / rel).write_bytes(data)
      code = export_main(["--policy", str(run), "--out", str(out)])
      err = capsys.readouterr().err
      assert code in (0, 2), err
      if code == 2:  # refused in one line; the previous file is intact
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
        assert out.read_bytes() == b"the previous file"
      else:
        NumpyPolicy.load(out)
        out.write_bytes(b"the previous file")
