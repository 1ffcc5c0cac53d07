"""Vineyard files (`mjxvine.worlds.geo`): WGS84 <-> the tangent plane, GeoJSON and CSV
round trips of generated and file worlds, a rotated block, the example block, and every
kind of bad file refused in one line naming the file and the row. Numpy only, fast."""

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mjxvine.config import WorldConfig
from mjxvine.worlds import load_test_world
from mjxvine.worlds.blocks import BlockFrame, block_to_input, vineyard_from_rows
from mjxvine.worlds.geo import (WGS84_A, WGS84_E2, local_to_lonlat, lonlat_to_local,
                                read_vineyard, tangent_plane_error_m, write_csv, write_geojson)
from mjxvine.worlds.layout import WorldFileError

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "vineyard-block.geojson"
ORIGIN = (7.62, 44.70)
ROBOT_W = 0.43  # the Jackal
CFG = WorldConfig()


def read(path, **kw):
  return read_vineyard(path, CFG, robot_width_m=ROBOT_W, **kw)


def assert_same_lanes(a, b, atol=1e-3):
  """Same lane count, widths within 1 cm, centrelines within `atol` over common x."""
  assert len(a.lanes) == len(b.lanes)
  for la, lb in zip(a.lanes, b.lanes):
    assert abs(a.lane_width(la) - b.lane_width(lb)) < 0.01
    x0 = max(la.centerline[0, 0], lb.centerline[0, 0])
    x1 = min(la.centerline[-1, 0], lb.centerline[-1, 0])
    assert x1 - x0 > 0.9 * (la.centerline[-1, 0] - la.centerline[0, 0])
    x = np.linspace(x0, x1, 200)
    ya = np.interp(x, la.centerline[:, 0], la.centerline[:, 1])
    yb = np.interp(x, lb.centerline[:, 0], lb.centerline[:, 1])
    assert np.abs(ya - yb).max() < atol, (la.id, np.abs(ya - yb).max())


# --- WGS84 and the tangent plane --------------------------------------------------------

@pytest.mark.parametrize("origin", [ORIGIN, (0.0, 0.0), (179.99, -45.0), (10.0, 89.9)])
def test_lonlat_and_local_round_trip_over_a_5_km_block(origin):
  g = np.linspace(-5000.0, 5000.0, 41)
  xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
  lonlat = local_to_lonlat(xy, origin)
  assert np.all(np.abs(lonlat[:, 0]) <= 180) and np.all(np.abs(lonlat[:, 1]) <= 90)
  assert np.abs(lonlat_to_local(lonlat, origin) - xy).max() < 1e-6
  again = local_to_lonlat(lonlat_to_local(lonlat, origin), origin)
  dlon = (again[:, 0] - lonlat[:, 0] + 180) % 360 - 180
  metres = np.stack([dlon * np.cos(np.deg2rad(lonlat[:, 1])), again[:, 1] - lonlat[:, 1]], -1)
  assert np.abs(metres).max() * 111e3 < 1e-6
  # the origin is (0, 0); north is +y, east is +x
  np.testing.assert_allclose(lonlat_to_local([origin], origin), [[0.0, 0.0]], atol=1e-9)
  step = lonlat_to_local([[origin[0], origin[1] - 0.001]], origin)[0]
  assert step[1] < -100 and abs(step[0]) < 1e-6


@pytest.mark.parametrize("radius, measured", [(1000.0, 3.1e-6), (5000.0, 3.9e-4)])
def test_the_tangent_plane_error_of_a_block(radius, measured):
  rows = []  # rows across a disc of the radius, a point every 1/40 of a chord
  for y in np.arange(-radius, radius + 1, radius / 20):
    half = math.sqrt(max(radius ** 2 - y ** 2, 0.0))
    if half > 1:
      x = np.linspace(-half, half, 41)
      rows.append(local_to_lonlat(np.stack([x, np.full_like(x, y)], -1), ORIGIN))
  err = tangent_plane_error_m(rows, ORIGIN)
  r_min, r_max = WGS84_A * (1 - WGS84_E2), WGS84_A / math.sqrt(1 - WGS84_E2)  # of curvature
  assert 0.99 * radius ** 3 / (8 * r_max ** 2) < err < 32 / 27 * radius ** 3 / (8 * r_min ** 2)
  assert err == pytest.approx(measured, rel=0.05)  # the numbers in geo's docstring


# --- round trips --------------------------------------------------------------------------

def test_a_generated_world_round_trips_through_geojson(tmp_path):
  world = load_test_world(CFG)
  path = write_geojson(world, tmp_path / "test world.geojson", ORIGIN)
  back = read(path)
  assert back.frame["origin_lonlat"] == list(ORIGIN) and back.frame["heading_deg"] == 0.0
  assert back.frame["offset_m"] == [0.0, 0.0] and back.frame["tangent_plane_error_m"] < 1e-8
  # the same plants, where they were (the file records heading and offset)
  assert back.plant_row.tolist() == world.plant_row.tolist()
  assert np.abs(back.plant_xy - world.plant_xy).max() < 1e-3
  np.testing.assert_allclose(np.sort(back.plant_xy, 0), np.sort(world.plant_xy, 0), atol=1e-3)
  # the lanes a file world has from these rows (midlines, median widths) ...
  direct = vineyard_from_rows(world.rows(), CFG, robot_width_m=ROBOT_W,
                              frame=BlockFrame(heading_rad=0.0))
  shift = -np.asarray(direct.frame["offset_m"])
  direct_lanes = [l.centerline + shift for l in direct.lanes]
  for lb, line in zip(back.lanes, direct_lanes):
    np.testing.assert_allclose(lb.centerline, line, atol=1e-3)
  assert_same_lanes(back, direct, atol=np.inf)
  # ... and the generated world's lanes (fifth-order fits over the same rows) within cm
  assert len(back.lanes) == len(world.lanes)
  for lb, lw in zip(back.lanes, world.lanes):
    x = lb.centerline[:, 0]
    gap = np.interp(x, lw.centerline[:, 0], lw.centerline[:, 1]) - lb.centerline[:, 1]
    assert np.abs(gap).max() < 0.06
  assert back.frame["row_names"] == [f"R{j + 1}" for j in range(world.num_rows)]


def test_a_generated_world_round_trips_through_csv(tmp_path):
  world = load_test_world(CFG)
  path = write_csv(world, tmp_path / "plants.csv")
  assert path.read_text().splitlines()[0] == "row,x_m,y_m"
  back = read(path)
  assert back.frame["origin_lonlat"] is None and back.frame["tangent_plane_error_m"] is None
  # a CSV has no heading: estimated from the rows (the curved test rows lean ~0.85 deg), so
  # the plants come back in the input (the CSV's) frame
  assert back.plant_row.tolist() == world.plant_row.tolist()
  assert np.abs(block_to_input(back, back.plant_xy) - world.plant_xy).max() < 1e-3
  direct = vineyard_from_rows(world.rows(), CFG, robot_width_m=ROBOT_W)
  assert back.frame["heading_deg"] == pytest.approx(direct.frame["heading_deg"], abs=1e-6)
  np.testing.assert_allclose(back.plant_xy, direct.plant_xy, atol=1e-3)
  assert_same_lanes(back, direct)


def test_a_file_world_round_trips_with_its_names_and_sizes(tmp_path):
  doc = json.loads(EXAMPLE.read_text())
  doc["features"][2]["properties"].update(trunk_height_m=0.7, canopy_width_m=0.45,
                                          canopy_top_m=1.8)
  src = tmp_path / "block.geojson"
  src.write_text(json.dumps(doc))
  world = read(src)
  r3 = world.frame["row_names"].index("R3")
  np.testing.assert_allclose(world.trunk_height[world.plant_row == r3], 0.7)

  again = read(write_geojson(world, tmp_path / "again.geojson"))
  assert again.frame["row_names"] == world.frame["row_names"]
  for key in ("origin_lonlat", "heading_deg", "offset_m"):
    np.testing.assert_allclose(again.frame[key], world.frame[key], atol=1e-9)
  assert np.abs(again.plant_xy - world.plant_xy).max() < 1e-3
  assert_same_lanes(again, world)
  m = again.plant_row == r3
  np.testing.assert_allclose(again.trunk_height[m], 0.7)
  np.testing.assert_allclose(2 * again.canopy_half[m, :2], 0.45)
  np.testing.assert_allclose((again.canopy_z + again.canopy_half[:, 2])[m], 1.8)

  text = write_csv(world, tmp_path / "block.csv").read_text()
  assert text.splitlines()[0] == "row,x_m,y_m,trunk_height_m,canopy_width_m,canopy_top_m"
  csv_world = read(tmp_path / "block.csv")
  assert abs(csv_world.frame["heading_deg"]) < 1e-6  # the block frame already
  assert np.abs(csv_world.plant_xy - world.plant_xy).max() < 1e-3
  assert_same_lanes(csv_world, world)
  np.testing.assert_allclose(csv_world.trunk_height[csv_world.plant_row == r3], 0.7)


def test_a_rotated_block_gives_lanes_along_x_of_the_same_widths(tmp_path):
  world = load_test_world(CFG)
  a = np.deg2rad(37.0)  # rows 37 degrees from east (north of east)
  rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
  features = [{"type": "Feature", "properties": {"name": f"B-{j + 1}"},
               "geometry": {"type": "MultiPoint", "coordinates": local_to_lonlat(
                   (r + [30.0, -12.0]) @ rot.T, ORIGIN).tolist()}}
              for j, r in enumerate(world.rows())]
  path = tmp_path / "rotated.geojson"
  path.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
  back = read(path)
  direct = vineyard_from_rows(world.rows(), CFG, robot_width_m=ROBOT_W)  # heading estimated
  # (north at the reader's origin, the rows' centre 40 m east of ORIGIN, is turned by
  # 3.6e-4 deg: the meridians converge)
  assert back.frame["heading_deg"] == pytest.approx(37.0 + direct.frame["heading_deg"],
                                                    abs=1e-3)
  assert back.frame["tangent_plane_error_m"] < 1e-9
  # the block frame does not depend on where the rows lie or which way they run
  np.testing.assert_allclose(back.plant_xy, direct.plant_xy, atol=1e-3)
  assert_same_lanes(back, direct)
  for lane in back.lanes:
    assert np.all(np.diff(lane.centerline[:, 0]) > 0)
  # lane 1 is straight: along +x but for the curved rows' lean of the block (0.85 deg)
  x, y = back.lanes[0].centerline.T
  slope, icept = np.polyfit(x, y, 1)
  assert abs(slope) < np.tan(np.deg2rad(1.5)) and np.abs(y - slope * x - icept).max() < 0.05
  assert x[-1] - x[0] > 22
  assert min(l.centerline[0, 0] for l in back.lanes) == pytest.approx(0.0, abs=1e-9)


# --- the example --------------------------------------------------------------------------

def test_the_example_block_is_what_the_script_writes_and_reads(tmp_path):
  out = tmp_path / "block.geojson"
  env = dict(os.environ, PYTHONPATH=str(ROOT))
  run = subprocess.run([sys.executable, str(ROOT / "scripts" / "example_block.py"), str(out)],
                       capture_output=True, text=True, env=env, timeout=120)
  assert run.returncode == 0, run.stderr
  assert out.read_bytes() == EXAMPLE.read_bytes()
  assert "lane 8:" in run.stdout
  doc = json.loads(EXAMPLE.read_text())
  assert doc["mjxvine"] == {"plant_spacing_m": 1.0}
  world = read(EXAMPLE)
  assert world.num_rows == 9 and len(world.lanes) == 8
  # 20 degrees east of north is 70 degrees from east
  assert world.frame["heading_deg"] == pytest.approx(70.0, abs=0.5)
  lengths = [l.centerline[-1, 0] - l.centerline[0, 0] for l in world.lanes]
  assert min(lengths) > 80 and 2 < max(lengths) - min(lengths) < 6
  np.testing.assert_allclose([world.lane_width(l) for l in world.lanes], 2.4, atol=0.05)
  assert world.spacing_m == pytest.approx(1.0)
  assert sorted(world.frame["row_names"]) == sorted(f"R{j}" for j in range(1, 10))


# --- bad files ----------------------------------------------------------------------------

def _line(length=30.0, y=0.0, x0=0.0, bend=0.0):
  """A straight (or bent) LineString row in local metres: (n, 2) vertices."""
  x = np.linspace(x0, x0 + length, 7)
  return np.stack([x, y + bend * np.sin(np.pi * (x - x0) / length) ** 2], -1)


def _feature(xy, name=None, kind="LineString", **props):
  """A row feature: vertices or plants `xy` (local m), or `kind` a whole geometry."""
  if isinstance(kind, dict):
    geom = kind
  else:
    geom = {"type": kind, "coordinates": local_to_lonlat(xy, ORIGIN).tolist()}
  return {"type": "Feature", "properties": {**({"name": name} if name else {}), **props},
          "geometry": geom}


def _block(*features, meta={"plant_spacing_m": 1.0}):
  doc = {"type": "FeatureCollection", "features": list(features)}
  if meta is not None:
    doc["mjxvine"] = meta
  return doc


def _good(n=3, **kw):
  return [_feature(_line(y=2.4 * j), f"R{j + 1}", **kw) for j in range(n)]


def _replace(k, feature, n=3):
  rows = _good(n)
  rows[k] = feature
  return _block(*rows)


def _raw_coords(coords, kind="LineString"):
  return {"type": "Feature", "properties": {"name": "R2"},
          "geometry": {"type": kind, "coordinates": coords}}


G = ".geojson"
BAD = {
    # name: (suffix, content: bytes, str or a GeoJSON dict; words the message must contain)
    "not utf-8": (G, b'{"type": "Feature\xff"}', ["not UTF-8"]),
    "not json": (G, '{"type": "FeatureCollection", features: []}', ["not JSON", "line 1"]),
    "json, no type": (G, {"features": []}, ["not GeoJSON", '"type"']),
    "not a collection": (G, {"type": "Feature", "geometry": None, "properties": {}},
                         ["'Feature'", "not a FeatureCollection"]),
    "no geometry": (G, _replace(1, {"type": "Feature", "properties": {"name": "R2"},
                                    "geometry": None}), ['feature 2 ("R2")', "no geometry"]),
    "polygon": (G, _replace(1, _feature(None, "R2", kind={"type": "Polygon", "coordinates": [
        [[7.62, 44.7], [7.621, 44.7], [7.621, 44.701], [7.62, 44.7]]]})),
                ['feature 2 ("R2")', "Polygon", "LineString", "MultiPoint"]),
    "text coordinates": (G, _replace(1, _raw_coords([[7.62, 44.7], ["7.621", 44.7]])),
                         ['feature 2 ("R2")', "coordinates[1]", "pair of numbers"]),
    "nan": (G, json.dumps(_replace(1, _raw_coords([[7.62, 44.7], [float("nan"), 44.7]]))),
            ['feature 2 ("R2")', "coordinates[1]", "not finite"]),
    "longitude": (G, _replace(1, _raw_coords([[190.0, 44.7], [190.001, 44.7]])),
                  ['feature 2 ("R2")', "longitude 190", "[-180, 180]"]),
    "latitude": (G, _replace(1, _raw_coords([[100.0, 95.0], [100.0, 95.001]])),
                 ['feature 2 ("R2")', "latitude 95", "[-90, 90]"]),
    "swapped": (G, _replace(1, _raw_coords([[-35.3, 149.1], [-35.301, 149.1]])),
                ['feature 2 ("R2")', "swapped?"]),
    "metres": (G, _replace(1, _raw_coords([[395000.0, 4950000.0], [395000.0, 4950090.0]])),
               ['feature 2 ("R2")', "[395000, 49500", "looks like projected metres",
                "WGS84 longitude, latitude"]),
    "local metres as degrees": (G, _block(*[_raw_coords([[0.0, 2.4 * j], [90.0, 2.4 * j]])
                                            for j in range(3)]),
                                ["looks like projected metres", "WGS84 longitude, latitude"]),
    "one row": (G, _block(*_good(1)), ["1 plant row(s)"]),
    "one point": (G, _replace(1, _feature(_line(y=2.4)[:1], "R2", kind="MultiPoint")),
                  ['feature 2 ("R2")', "1 point(s)", "at least 2"]),
    "no spacing": (G, _block(*_good(), meta=None), ["feature 1 (\"R1\")", "plant_spacing_m"]),
    "zero spacing": (G, _replace(1, _feature(_line(y=2.4), "R2", plant_spacing_m=0)),
                     ['feature 2 ("R2")', "plant_spacing_m 0", "positive"]),
    "negative default spacing": (G, _block(*_good(), meta={"plant_spacing_m": -1.0}),
                                 ["mjxvine", "plant_spacing_m -1.0", "positive"]),
    "missing not integers": (G, _replace(1, _feature(_line(y=2.4), "R2",
                                                     missing_plants=["3", 4.5])),
                             ['feature 2 ("R2")', "missing_plants", "whole numbers"]),
    "missing out of range": (G, _replace(1, _feature(_line(y=2.4), "R2", missing_plants=[31])),
                             ['feature 2 ("R2")', "index 31 out of range", "0 to 30"]),
    "missing all but one": (G, _replace(1, _feature(_line(y=2.4), "R2",
                                                    missing_plants=list(range(30)))),
                            ['feature 2 ("R2")', "1 plant(s) left"]),
    "rows cross": (G, _block(_feature(_line(), "R1"), _feature(
        np.array([[0.0, 2.4], [30.0, -2.4]]), "R2"), _feature(_line(y=4.8, length=30), "R3")),
                   ['feature 1 ("R1") and feature 2 ("R2")', "cross or touch (at 15."]),
    "rows too close": (G, _replace(1, _feature(_line(y=0.9), "R2")),
                       ['feature 1 ("R1") and feature 2 ("R2")', "closer than the robot"]),
    "end to end": (G, _block(_feature(_line(), "R1"), _feature(_line(x0=32.0), "R2")),
                   ['feature 1 ("R1") and feature 2 ("R2")', "side by side"]),
    "hairpin": (G, _replace(1, _feature(np.concatenate([_line(y=2.4), _line(y=3.6)[::-1]]),
                                        "R2", kind="MultiPoint")),
                ['feature 2 ("R2")', "turns back"]),
    "many km": (G, _block(*[_feature(_line(length=8000.0, y=2.4 * j), f"R{j + 1}")
                            for j in range(3)], meta={"plant_spacing_m": 10.0}),
                ["8.0 x", "km", "more than one vineyard block"]),
    "unknown member key": (G, _block(*_good(), meta={"plant_spacing": 1.0}),
                           ["mjxvine", "unknown key(s) plant_spacing"]),
    "bad origin": (G, _block(*_good(), meta={"plant_spacing_m": 1.0, "origin_lonlat": [7.6]}),
                   ["mjxvine.origin_lonlat", "pair of numbers"]),
    "far origin": (G, _block(*_good(), meta={"plant_spacing_m": 1.0,
                                             "origin_lonlat": [7.7, 44.7]}),
                   ["mjxvine.origin_lonlat lies 6.3 km"]),
    "far offset": (G, _block(*_good(), meta={"plant_spacing_m": 1.0, "offset_m": [50.0, 0.0]}),
                   ["mjxvine.offset_m moves the block"]),
    "geometry without type": (G, _replace(1, _feature(None, "R2", kind={"coordinates": []})),
                              ['feature 2 ("R2")', 'geometry has no "type"']),
    "csv nul": (".csv", "row,x_m,y_m\nR1,0\x00,0\n", ["line 2", "x_m", "is not a number"]),
    "csv not utf-8": (".csv", b"row,x_m,y_m\nR\xe91,0,0\n", ["not UTF-8"]),
    "empty csv": (".csv", "\n  \n", ["empty", "row,x_m,y_m"]),
    "csv header": (".csv", "row;x;y\nR1;0;0\n", ["line 1", "has no row, x_m, y_m", "';'"]),
    "csv no plants": (".csv", "row,x_m,y_m\n", ["no plants"]),
    "csv text value": (".csv", "row,x_m,y_m\nR1,0,0\nR1,1,0\nR1,2,abc\n",
                       ["line 4", "y_m 'abc' is not a number"]),
    "csv nan": (".csv", "row,x_m,y_m\nR1,0,0\nR1,nan,0\n", ["line 3", "not a finite number"]),
    "csv fields": (".csv", "row,x_m,y_m\nR1,0,0\nR1,1\n", ["line 3", "2 fields"]),
    "csv one row": (".csv", "row,x_m,y_m\nR1,0,0\nR1,1,0\n", ["1 plant row(s)"]),
    "csv one plant": (".csv", "row,x_m,y_m\nR1,0,0\nR1,9,0\nR2,0,2.4\n",
                      ['row "R2"', "1 plant(s)"]),
    "csv degrees": (".csv", "row,x_m,y_m\nR1,7.62,44.7\nR1,7.621,44.7\nR2,7.62,44.70002\n"
                            "R2,7.621,44.70002\n", ["degrees?", "metres"]),
    "csv too close": (".csv", "row,x_m,y_m\nA,0,0\nA,20,0\nB,0,1.0\nB,20,1.0\n",
                      ['row "A" and row "B"', "closer than the robot"]),
    "csv many km": (".csv", "row,x_m,y_m\nA,0,0\nA,9000,0\nB,0,2.4\nB,9000,2.4\n",
                    ["spans 9.0 x", "km"]),
    "csv size": (".csv", "row,x_m,y_m,trunk_height_m\nA,0,0,0.7\nA,20,0,-1\n",
                 ["line 3", "trunk_height_m -1", "positive"]),
    "other suffix": (".txt", "row,x_m,y_m\n", ["not a vineyard file", ".geojson", ".csv"]),
}


@pytest.mark.parametrize("kind", sorted(BAD))
def test_a_bad_file_is_refused_in_one_line(tmp_path, kind):
  suffix, content, words = BAD[kind]
  path = tmp_path / f"{kind.replace(' ', '-').replace(',', '')}-block{suffix}"
  if isinstance(content, dict):
    content = json.dumps(content)
  path.write_bytes(content if isinstance(content, bytes) else content.encode())
  with pytest.raises(WorldFileError) as e:
    read(path)
  msg = str(e.value)
  assert "\n" not in msg and msg.startswith(str(path)), msg
  for word in words:
    assert word in msg, (word, msg)


def test_an_unreadable_file_is_refused_in_one_line(tmp_path):
  for path in (tmp_path / "missing.geojson", tmp_path / "folder.csv"):
    if path.suffix == ".csv":
      path.mkdir()
    with pytest.raises(WorldFileError, match="cannot be read") as e:
      read(path)
    assert "\n" not in str(e.value) and str(path) in str(e.value)


def test_the_spacing_argument_and_the_files_defaults(tmp_path):
  path = tmp_path / "block.geojson"
  path.write_text(json.dumps(_block(*_good(), meta={"plant_spacing_m": 1.0, "slope_pct": 4.0})))
  assert read(path).spacing_m == pytest.approx(1.0)
  world = read(path, plant_spacing_m=1.5, slope_pct=-2.0)  # arguments before the file's
  assert world.spacing_m == pytest.approx(1.5) and world.frame["slope_pct"] == -2.0
  assert read(path).frame["slope_pct"] == 4.0
  rows = _good()
  rows[0]["properties"]["plant_spacing_m"] = 0.75  # a feature's own spacing comes first
  path.write_text(json.dumps(_block(*rows, meta=None)))
  world = read(path, plant_spacing_m=1.5)
  assert np.diff(world.rows()[0][:, 0]).mean() == pytest.approx(0.75)
  assert np.diff(world.rows()[1][:, 0]).mean() == pytest.approx(1.5)
  rows[1]["properties"]["missing_plants"] = [0, 5, 5]
  path.write_text(json.dumps(_block(*rows, meta=None)))
  assert len(read(path, plant_spacing_m=1.5).rows()[1]) == 21 - 2


@pytest.mark.parametrize("kind", sorted(BAD))
def test_the_command_lines_refuse_a_bad_file_in_one_line_and_write_nothing(tmp_path, kind,
                                                                            capsys):
  from mjxvine.evaluate import main as evaluate_main
  from mjxvine.worlds.__main__ import main as worlds_main
  suffix, content, _ = BAD[kind]
  path = tmp_path / f"block{suffix}"
  if isinstance(content, dict):
    content = json.dumps(content)
  path.write_bytes(content if isinstance(content, bytes) else content.encode())
  for run, argv in ((worlds_main, ["--world", str(path)]),
                    (evaluate_main, ["--policy", "oracle", "--world", str(path)])):
    out = tmp_path / "out"
    assert run([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err and str(path) in err, err
    assert not out.exists()  # nothing written, not even the folder


def test_the_worlds_command_writes_a_block(tmp_path, capsys):
  from mjxvine.worlds.__main__ import main as worlds_main
  assert worlds_main(["--world", str(EXAMPLE), "--out", str(tmp_path / "block")]) == 0
  printed = capsys.readouterr().out
  assert "8 lanes, inter-row 2.40 m" in printed and "lane 8: 90.5 m long, 2.40 m wide" in printed
  doc = json.loads((tmp_path / "block" / "world.json").read_text())
  assert doc["frame"]["source"].endswith("vineyard-block.geojson") and len(doc["lanes"]) == 8
  assert (tmp_path / "block" / "world.png").stat().st_size > 50_000


def test_the_vineyard_results_page_is_its_records():
  """Every figure of docs/results/vineyards.md's tables is read from its record."""
  page = (ROOT / "docs" / "results" / "vineyards.md").read_text()
  grid = json.loads((ROOT / "docs/results/vineyards/rows.json").read_text())["grid"]
  for v in grid.values():
    gap = f"{v['inter_row_m']:.1f}"
    line = next(l for l in page.splitlines() if l.startswith(f"| {gap} m |"))
    cells = [c.strip() for c in line.strip("|").split("|")][1:]
    slopes = sorted({g["slope_pct"] for g in grid.values()})
    assert cells[slopes.index(v["slope_pct"])] == (
        f"{v['success']}/{v['runs']} ({v['mae_m_rows']:.3f})"), line
  block = json.loads((ROOT / "docs/results/vineyards/block-results.json").read_text())
  o = block["overall"]
  assert f"| {o['success']}/{o['runs']} to the end of the row |" in page
  assert f"| {o['mae_m_rows']:.3f} m (RMSE {o['rmse_m_rows']:.3f} m) |" in page
  worst = max(block["rows"], key=lambda r: r["mae_m"])
  assert f"worst row | {worst['lane']}{worst['direction']}: MAE {worst['mae_m']:.3f} m" in page
  assert f"{o['v_mean_rows']:.3f} m/s" in page


def test_train_refuses_a_bad_train_file_before_making_anything(tmp_path, capsys):
  from mjxvine.train import main as train_main
  bad = tmp_path / "block.geojson"
  bad.write_text('{"type": "Feature"}')
  run = tmp_path / "run"
  for path in (bad, tmp_path / "missing.geojson"):
    with pytest.raises(SystemExit) as e:
      train_main(["--config", "experiments/smoke.yaml", "--out", str(run),
                  "--set", f"world.train_files={path}"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "world.train_files" in err or str(path) in err, err
    assert not run.exists()
