"""Vineyard and world files bounded by construction, errors that cannot break the line,
the worlds CLI's world.json read back by `--world`, and no command writing over its own
inputs. Bombs are made here, in tmp; nothing trains, nothing big is built."""

import argparse
import json
import shutil
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from mjxvine import evaluate, export
from mjxvine.atomic import OutputError, check_output
from mjxvine.config import WorldConfig, load_config
from mjxvine.worlds import WorldFileError, generate_world, load_world, world_of
from mjxvine.worlds import limits
from mjxvine.worlds.__main__ import main as worlds_main
from mjxvine.worlds.geo import local_to_lonlat, read_vineyard

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "vineyard-block.geojson"
POLICY = ROOT / "models" / "jackal.npz"
ORIGIN = (7.62, 44.70)
CFG = WorldConfig()


def _refused(path, *words, seconds=10.0, megabytes=500.0, read=None) -> str:
  """The one-line WorldFileError of reading `path`, within `seconds`, and with at most
  `megabytes` allocated at the peak (a second read, traced: tracing slows it); its
  message has `words`."""
  read = read or (lambda p: read_vineyard(p, CFG, robot_width_m=0.43))
  start = time.perf_counter()
  with pytest.raises(WorldFileError) as e:
    read(path)
  took = time.perf_counter() - start
  tracemalloc.start()
  try:
    with pytest.raises(WorldFileError):
      read(path)
    peak = tracemalloc.get_traced_memory()[1] / 2**20
  finally:
    tracemalloc.stop()
  msg = str(e.value)
  assert took < seconds and peak < megabytes, (took, peak, msg)
  assert "\n" not in msg and "\x1b" not in msg and len(msg) < 600, msg
  for word in words:
    assert word in msg, (word, msg)
  return msg


def _csv(path: Path, rows: int, plants: int, spacing: float = 0.8) -> Path:
  x = np.arange(plants) * spacing
  path.write_text("row,x_m,y_m\n" + "".join(
      f"R{j},{v:.4f},{2.5 * j}\n" for j in range(rows) for v in x))
  return path


def _geojson(path: Path, features, meta=None) -> Path:
  doc = {"type": "FeatureCollection", "features": features, **({"mjxvine": meta} if meta else {})}
  path.write_text(json.dumps(doc))
  return path


def _row(xy, kind="LineString", name=None, **props):
  return {"type": "Feature", "properties": {**({"name": name} if name is not None else {}),
                                            **props},
          "geometry": {"type": kind, "coordinates": local_to_lonlat(np.asarray(xy, float),
                                                                    ORIGIN).tolist()}}


def _line(y, length=90.0):
  return [[0.0, y], [length, y]]


# --- 1. bounded by construction ---------------------------------------------------------

def test_a_csv_of_150000_plants_is_refused_fast(tmp_path):
  path = _csv(tmp_path / "bomb.csv", rows=100, plants=1500)
  _refused(path, str(path), f"more than {limits.MAX_PLANTS} plants")


def test_a_geojson_of_2000_rows_is_refused_fast(tmp_path):
  path = _geojson(tmp_path / "rows.geojson", [_row(_line(2.5 * j)) for j in range(2000)],
                  meta={"plant_spacing_m": 1.0})
  _refused(path, "2000 plant rows", f"at most {limits.MAX_ROWS}")


def test_a_multipoint_of_200000_plants_is_refused_fast(tmp_path):
  lon = ORIGIN[0] + np.arange(200_000) * 1e-5  # ~0.8 m apart
  plants = {"type": "Feature", "properties": {}, "geometry": {
      "type": "MultiPoint", "coordinates": np.stack([lon, np.full_like(lon, ORIGIN[1])],
                                                    -1).tolist()}}
  path = _geojson(tmp_path / "points.geojson", [_row(_line(2.5), "MultiPoint"), plants])
  _refused(path, "feature 2", "200000 positions", f"at most {limits.MAX_ROW_PLANTS}")


def test_many_rows_of_plants_together_are_refused(tmp_path):
  """Rows each within the limit, more than a block's plants together (GeoJSON points and
  LineString rows alike), before a plant is made of the rest."""
  x = np.arange(9000) * 0.8
  points = [_row(np.stack([x, np.full_like(x, 2.5 * j)], -1), "MultiPoint") for j in range(6)]
  _refused(_geojson(tmp_path / "points.geojson", points), "more than 50000 plants",
           "feature 6")
  lines = [_row(_line(2.5 * j, length=4500.0)) for j in range(6)]
  _refused(_geojson(tmp_path / "lines.geojson", lines, {"plant_spacing_m": 0.5}),
           "more than 50000 plants", "feature 6")


@pytest.mark.parametrize("make, words", [
    (lambda p: _csv(p.with_suffix(".csv"), rows=3, plants=100, spacing=0.005),
     ['row "R0"', "plants 1 and 2 are 5 mm apart", "0.1 m"]),
    (lambda p: _geojson(p, [_row(_line(2.5 * j)) for j in range(3)], {"plant_spacing_m": 0.005}),
     ["plant_spacing_m 0.005", "0.1 m"]),
    (lambda p: _geojson(p, [_row(_line(2.5 * j), plant_spacing_m=0.05) for j in range(3)]),
     ['feature 1', "plant_spacing_m 0.05", "0.1 m"]),
])
def test_plants_5_mm_apart_are_refused(tmp_path, make, words):
  _refused(make(tmp_path / "close.geojson"), *words)


def test_a_line_of_too_many_vertices_is_refused(tmp_path):
  x = np.linspace(0.0, 90.0, limits.MAX_LINE_VERTICES + 1)
  rows = [_row(np.stack([x, np.full_like(x, 2.5 * j)], -1)) for j in range(2)]
  _refused(_geojson(tmp_path / "dense.geojson", rows, {"plant_spacing_m": 1.0}),
           f"{limits.MAX_LINE_VERTICES + 1} positions", "vertices")


def test_a_block_of_too_much_ground_is_refused_before_its_terrain(tmp_path):
  """Two rows 1 km long and 1 km apart: a 16-million-cell heightfield, 1 GB to make."""
  path = tmp_path / "far.csv"
  path.write_text("row,x_m,y_m\nA,0,0\nA,1000,0\nB,0,1000\nB,1000,1000\n")
  _refused(path, "16.3 million terrain cells", f"at most {limits.MAX_TERRAIN_CELLS / 1e6:g}",
           seconds=1.0, megabytes=50)


def test_deep_and_big_files_are_refused_before_parsing(tmp_path):
  deep = tmp_path / "deep.geojson"
  nest = "[" * 200 + "]" * 200
  deep.write_text('{"type": "FeatureCollection", "features": [], "x": ' + nest + "}")
  _refused(deep, "nested more than 16 deep", seconds=1.0)
  # brackets inside a string are text, not nesting
  shallow = tmp_path / "shallow.geojson"
  shallow.write_text(json.dumps({"type": "FeatureCollection", "features": [],
                                 "name": "[" * 100 + '\\"{'}))
  _refused(shallow, "0 plant row(s)", seconds=1.0)
  big = tmp_path / "big.csv"
  with open(big, "wb") as f:
    f.truncate(limits.MAX_FILE_BYTES + 1)  # sparse: no disk, and not read past the limit
  _refused(big, "more than 16 MiB", seconds=1.0, megabytes=40)
  huge_number = tmp_path / "number.geojson"
  huge_number.write_text('{"type": "FeatureCollection", "features": [' + "9" * 5000 + "]}")
  _refused(huge_number, "not JSON", seconds=1.0)


def test_a_world_file_bomb_is_refused_before_building(tmp_path):
  """A saved world of 60,000 plants (its build takes a minute or more): refused once read."""
  world = generate_world("train", 0, CFG).to_json()
  n = 60_000
  world.update(plant_xy=np.zeros((n, 2)).tolist(), plant_yaw=[0.0] * n, plant_row=[0] * n,
               trunk_height=[0.5] * n, canopy_half=np.ones((n, 3)).tolist(),
               canopy_z=[1.0] * n)
  path = tmp_path / "bomb.json"
  path.write_text(json.dumps(world))
  _refused(path, "60000 plants", f"at most {limits.MAX_PLANTS}", read=load_world)
  deep = tmp_path / "deep.json"
  deep.write_text("[" * 100_000 + "]" * 100_000)
  _refused(deep, "nested more than 16", read=load_world, seconds=1.0)


def test_a_large_real_block_fits_the_limits(tmp_path):
  """100 rows of 300 m, 2.5 m apart, a plant every 0.8 m (37,500 plants): read in seconds."""
  path = _csv(tmp_path / "large.csv", rows=100, plants=375)
  start = time.perf_counter()
  world = read_vineyard(path, CFG, robot_width_m=0.43)
  assert time.perf_counter() - start < 10
  assert len(world.plant_xy) == 37_500 and len(world.lanes) == 99
  assert world.terrain.size < limits.MAX_TERRAIN_CELLS / 3


# --- 2. names and values on one line ----------------------------------------------------

HOSTILE = "R2\n\x1b[31mred\x1b[0m\r\x07" + "x" * 500


def test_a_hostile_row_name_is_escaped_in_the_message(tmp_path):
  rows = [_row(_line(0.0), name="R1"), _row([[0.0, 2.5]], "MultiPoint", name=HOSTILE)]
  msg = _refused(_geojson(tmp_path / "names.geojson", rows), "feature 2", "1 point(s)",
                 r"R2\n\x1b[31mred")
  assert "x" * 100 not in msg  # a long name is cut
  rows = [_row(_line(0.0), name="R1"), _row(_line(2.5), name=HOSTILE, trunk_height_m="\x1b[2J")]
  _refused(_geojson(tmp_path / "value.geojson", rows, {"plant_spacing_m": 1.0}),
           r"'\x1b[2J'", "trunk_height_m")
  csv = tmp_path / "names.csv"
  csv.write_text('row,x_m,y_m\nA,0,0\nA,20,0\n"B\n\x1b[31m",0,1.0\n"B\n\x1b[31m",20,1.0\n')
  _refused(csv, r'row "B\n\x1b[31m"', "closer than the robot")
  csv.write_text('row,x_m,y_m\nA,0,0\nA,1,"\x1b[2J1"\n')
  _refused(csv, r"y_m '\x1b[2J1' is not a number")


def test_a_hostile_file_name_is_escaped_and_the_cli_says_one_line(tmp_path, capsys):
  path = tmp_path / "evil\n\x1b[31mblock.geojson"
  _geojson(path, [_row(_line(0.0))])
  _refused(path, r"evil\n\x1b[31mblock.geojson", "1 plant row(s)")
  assert worlds_main(["--world", str(path), "--out", str(tmp_path / "out")]) == 2
  err = capsys.readouterr().err
  assert len(err.strip().splitlines()) == 1 and "\x1b" not in err, err


# --- 3. worlds --out writes what --world reads ------------------------------------------

@pytest.mark.parametrize("world", ["0", str(EXAMPLE)])
def test_the_worlds_world_json_is_read_back_by_evaluate_and_view(tmp_path, capsys, world):
  """`worlds --out O`, then `evaluate --world O/world.json` / `view --world`: the same
  world, every array exact."""
  from mjxvine.view import _world as view_world
  cfg = load_config(None, ["robot.name=jackal"])
  out = tmp_path / "O"
  assert worlds_main(["--world", world, "--robot", "jackal", "--out", str(out)]) == 0
  capsys.readouterr()
  original = world_of(world, cfg)
  path = out / "world.json"
  assert json.loads(path.read_text())["robot"] == "jackal"
  for again in (world_of(str(path), cfg), view_world(str(path), cfg)):  # evaluate's, view's
    for name in ("plant_xy", "plant_row", "plant_yaw", "trunk_height", "canopy_half",
                 "canopy_z", "row_y0", "terrain"):
      np.testing.assert_array_equal(getattr(again, name), getattr(original, name))
    assert again.terrain_extent == original.terrain_extent and again.frame == original.frame
    assert (again.kind, again.seed, again.inter_row_m) == (
        original.kind, original.seed, original.inter_row_m)
    for a, b in zip(again.lanes, original.lanes):
      np.testing.assert_array_equal(a.centerline, b.centerline)
      assert again.lane_width(a) == original.lane_width(b)


def test_an_old_world_description_says_what_it_is(tmp_path):
  old = tmp_path / "world.json"
  old.write_text(json.dumps({"kind": "test", "seed": 0, "robot": "jackal", "rows": [[[0, 0]]],
                             "lanes": []}))
  with pytest.raises(WorldFileError, match="older python -m mjxvine.worlds"):
    load_world(old)


# --- 4. no output over an input ---------------------------------------------------------

def _exit(main, argv, capsys, *words):
  try:
    code = main(argv)
  except SystemExit as e:
    code = e.code
  err = capsys.readouterr().err.strip()
  assert code == 2 and len(err.splitlines()) == 1, err
  for word in words:
    assert word in err, err


def test_export_never_writes_over_its_input_nor_under_another_format(tmp_path, capsys):
  policy = tmp_path / "p.npz"
  shutil.copy(POLICY, policy)
  before = policy.read_bytes()
  _exit(export.main, ["--policy", str(policy), "--format", "onnx", "--out", str(policy)],
        capsys, f"--out {policy}", ".npz name, but --format onnx")
  link = tmp_path / "link.onnx"
  link.symlink_to(policy)
  _exit(export.main, ["--policy", str(policy), "--out", str(link)], capsys,
        "is the --policy file")
  _exit(export.main, ["--policy", str(policy), "--format", "npz", "--out",
                      str(tmp_path / "x.onnx")], capsys, ".onnx name, but --format npz")
  _exit(export.main, ["--policy", str(policy), "--format", "onnx", "--out",
                      str(tmp_path / "x.bin")], capsys, "give a .npz or .onnx file name")
  assert policy.read_bytes() == before
  assert sorted(p.name for p in tmp_path.iterdir()) == ["link.onnx", "p.npz"]
  run = tmp_path / "run"
  (run / "checkpoints").mkdir(parents=True)
  (run / "config.yaml").write_text("seed: 0\n")
  shutil.copy(POLICY, run / "selected.npz")
  for out in (run / "config.yaml", run / "selected.npz", run / "checkpoints" / "x.npz"):
    _exit(export.main, ["--policy", str(run), "--out", str(out)], capsys)
  _exit(export.main, ["--policy", str(run), "--out", str(run / "selected.npz")], capsys,
        "inside the run directory of --policy", f"or {run / 'policy.npz'}")
  assert (run / "config.yaml").read_text() == "seed: 0\n"
  assert (run / "selected.npz").read_bytes() == before


def test_the_output_check_allows_a_commands_own_outputs_only(tmp_path):
  run = tmp_path / "run"
  (run / "checkpoints" / "best").mkdir(parents=True)
  inputs = [(run, "the run directory of --policy")]
  own = [run / "policy.npz"]
  check_output(run / "policy.npz", "--out", inputs=inputs, own=own)
  check_output(tmp_path / "elsewhere.npz", "--out", inputs=inputs, own=own)
  for out in (run / "config.yaml", run / "checkpoints" / "best" / "1", run / "new.npz"):
    with pytest.raises(OutputError, match="inside the run directory"):
      check_output(out, "--out", inputs=inputs, own=own)
  # an input by another spelling: ../ and links
  with pytest.raises(OutputError, match="inside"):
    check_output(tmp_path / "x" / ".." / "run" / "a.npz", "--out", inputs=inputs)


def test_evaluate_and_worlds_never_write_over_their_inputs(tmp_path, capsys):
  out = tmp_path / "O"
  assert worlds_main(["--world", "0", "--out", str(out)]) == 0
  capsys.readouterr()
  world = out / "world.json"
  before = world.read_bytes()
  _exit(worlds_main, ["--world", str(world), "--out", str(out)], capsys,
        "would write world.json over the --world file")
  _exit(evaluate.main, ["--policy", "oracle", "--world", str(world), "--out", str(world)],
        capsys, "is the --world file")
  _exit(evaluate.main, ["--policy", str(POLICY), "--out", str(POLICY)], capsys,
        "is the --policy file")
  assert world.read_bytes() == before

  def check(policy, world, out, config=None):
    args = argparse.Namespace(policy=str(policy), world=world and str(world), config=config,
                              robot=None)
    check_output(out, "--out", directory=True, inputs=evaluate._inputs(args),
                 writes=evaluate.WRITES)
  check("oracle", world, out)  # evaluate --world O/world.json --out O: nothing over it
  results = out / "results.json"
  results.write_text("{}")
  with pytest.raises(OutputError, match="would write results.json over the --world file"):
    check("oracle", results, out)
  run = tmp_path / "run"
  (run / "checkpoints").mkdir(parents=True)
  for inside in (run, run / "eval", run / "checkpoints" / "9"):
    with pytest.raises(OutputError, match="inside the run directory of --policy"):
      check(run / "checkpoints", None, inside)
