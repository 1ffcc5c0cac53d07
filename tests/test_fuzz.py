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


# ---------------------------------------------------------------- YAML and GeoJSON, hostile
def _random_yaml(rng: np.random.Generator) -> str:
  """A YAML text of random structure: nested mappings and lists, anchors and aliases,
  merge keys, YAML 1.1 scalars (octal, sexagesimal, yes/no), long and control-character
  strings, deep nesting, or a config section with a wrong type."""
  scalars = ["010", "1:30", "yes", "0x1f", "1e999", ".nan", "'a\\x1b[31mred'", "~", "-0",
             "x" * int(rng.integers(1, 5000)), "\"line\\nbreak\"", "[1, 2", "{a: 1"]
  kind = int(rng.integers(0, 5))
  if kind == 0:  # anchors and aliases, a billion-laughs seed
    return "a: &a [x, x, x]\nb: &b [*a, *a, *a]\nc: [*b, *b, *b]\n"
  if kind == 1:  # deep nesting
    depth = int(rng.integers(10, 200))
    return "sac: " + "[" * depth + "1" + "]" * depth + "\n"
  if kind == 2:  # a known key with a surprising scalar
    key = rng.choice(["train.seed", "eval.noise_factor", "sac.auto_alpha", "env.num_envs",
                      "world.inter_row_m", "camera.width"])
    section, name = str(key).split(".")
    return f"{section}:\n  {name}: {rng.choice(scalars)}\n"
  if kind == 3:  # merge keys and unknown sections
    return "base: &base {num_envs: 4}\nenv:\n  <<: *base\n"
  return "\n".join(f"{rng.choice(['env', 'sac', 'junk', '? [1]'])}: {rng.choice(scalars)}"
                   for _ in range(int(rng.integers(1, 6)))) + "\n"


def test_hostile_yaml_configs_load_or_refuse_in_one_line(tmp_path):
  """Random hostile YAML (aliases, nesting, YAML 1.1 scalars, control characters) given as
  a config: a Config or one ConfigError line of bounded length, each within seconds."""
  import time
  from mjxvine.config import ConfigError, load_config
  rng = np.random.default_rng(7)
  path = tmp_path / "hostile.yaml"
  for _ in range(60):
    path.write_text(_random_yaml(rng))
    start = time.perf_counter()
    try:
      load_config(path)
    except ConfigError as e:
      message = str(e)
      assert "\n" not in message and "\x1b" not in message and len(message) < 1000, message
    assert time.perf_counter() - start < 5.0


def _random_geojson(rng: np.random.Generator):
  """A GeoJSON-like document with random faults: wrong types, deep nesting, huge or
  non-finite coordinates, empty or one-point rows, hostile names."""
  lon, lat = 7.62, 44.70
  pick = lambda options: options[int(rng.integers(len(options)))]
  def row(i):
    n = int(rng.integers(0, 4))
    coords = [[lon + 1e-5 * k, lat + 3e-5 * i] for k in range(n)]
    geometry = pick(["LineString", "MultiPoint", "Polygon", "Point", None])
    props = {"name": pick([f"R{i}", "a\nb", "\x1b[2J", 5, None]),
             "plant_spacing_m": pick([1.0, 0.0, -1, "x", 1e9])}
    return {"type": "Feature", "properties": props,
            "geometry": {"type": geometry, "coordinates": pick(
                [coords, [[1e308, 1e308]], [["a", "b"]], [], 3, [[[lon, lat]]]])}}
  kind = int(rng.integers(0, 4))
  if kind == 0:
    nested = 1
    for _ in range(int(rng.integers(20, 400))):
      nested = [nested]
    return {"type": "FeatureCollection", "features": nested}
  if kind == 1:
    return {"type": pick(["FeatureCollection", "Feature", 3]), "features": 7}
  return {"type": "FeatureCollection",
          "features": [row(i) for i in range(int(rng.integers(0, 6)))]}


def test_hostile_geojson_reads_or_refuses_in_one_line(tmp_path):
  """Random hostile GeoJSON documents: a Vineyard or one WorldFileError/ValueError line,
  each within seconds."""
  import time
  from mjxvine.config import WorldConfig
  from mjxvine.worlds.geo import read_vineyard
  rng = np.random.default_rng(11)
  path = tmp_path / "hostile.geojson"
  for _ in range(60):
    path.write_text(json.dumps(_random_geojson(rng), default=str))
    start = time.perf_counter()
    try:
      read_vineyard(path, WorldConfig(), robot_width_m=0.5)
    except (WorldFileError, ValueError) as e:
      message = str(e)
      assert "\n" not in message and "\x1b" not in message and len(message) < 1000, message
    assert time.perf_counter() - start < 5.0
