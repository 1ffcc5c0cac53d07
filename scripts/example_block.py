"""Writes the example vineyard block, examples/vineyard-block.geojson (deterministic):

  python scripts/example_block.py examples/vineyard-block.geojson

Nine rows (eight lanes) 2.4 m apart in Piedmont (near lon 7.62, lat 44.70), running 20
degrees east of north, plants every 1.0 m (the file's `mjxvine.plant_spacing_m`; no origin
or heading: the reader estimates them). The southern headland is slanted, so the rows
start 0.45 m further north each and run 91.5 to 87.9 m; rows R6-R9 bend east by up to
0.1-0.4 m over their northern half; a few plants are missing. Rows are LineStrings, a
vertex every 5 m where they bend, coordinates to 8 decimals (about 1 mm). Prints the
lanes the reader finds (for a robot 0.43 m wide, the Jackal).
"""

import json
import sys
from pathlib import Path

import numpy as np

from mjxvine import atomic
from mjxvine.config import WorldConfig
from mjxvine.worlds.geo import local_to_lonlat, read_vineyard

ORIGIN = (7.62, 44.70)  # lon, lat (deg): the tangent point of the layout below
AZIMUTH_DEG = 20.0  # the rows' direction, clockwise from north
INTER_ROW_M = 2.4
END_M = 91.5  # the rows' northern ends, along the rows from the first row's start
HEADLAND_STEP_M = 0.45  # each row starts this much further along: the slanted edge
BEND_M = (0.0, 0.0, 0.0, 0.0, 0.0, 0.1, 0.25, 0.4, 0.4)  # eastward bend per row
MISSING = {"R2": [23], "R4": [51, 52], "R7": [12], "R9": [70]}  # 0-based plant indices


def row_vertices(j: int) -> np.ndarray:
  """Row j's vertices (n, 2): along the rows, across them (m, east-ish positive)."""
  start = j * HEADLAND_STEP_M
  u = np.array([start, END_M]) if BEND_M[j] == 0 else np.append(
      np.arange(start, END_M, 5.0), END_M)
  t = np.clip((u - END_M / 2) / (END_M / 2), 0.0, 1.0)  # the bend starts halfway
  v = j * INTER_ROW_M + BEND_M[j] * (1 - np.cos(np.pi * t)) / 2
  return np.stack([u, v], -1)


def block() -> dict:
  """The GeoJSON document of the block."""
  a = np.deg2rad(AZIMUTH_DEG)
  along, across = np.array([np.sin(a), np.cos(a)]), np.array([np.cos(a), -np.sin(a)])
  rows = [row_vertices(j) for j in range(len(BEND_M))]
  centre = np.concatenate(rows).mean(0)
  features = []
  for j, uv in enumerate(rows):
    east_north = (uv[:, :1] - centre[0]) * along + (uv[:, 1:] - centre[1]) * across
    lonlat = np.round(local_to_lonlat(east_north, ORIGIN), 8)
    name = f"R{j + 1}"
    props = {"name": name, "variety": "Nebbiolo"}
    if name in MISSING:
      props["missing_plants"] = MISSING[name]
    features.append({"type": "Feature", "properties": props,
                     "geometry": {"type": "LineString", "coordinates": lonlat.tolist()}})
  return {"type": "FeatureCollection", "mjxvine": {"plant_spacing_m": 1.0},
          "features": features}


def main(argv: list[str]) -> int:
  if len(argv) != 1:
    print(__doc__, file=sys.stderr)
    return 2
  doc = block()
  text = ('{"type": "FeatureCollection",\n "mjxvine": ' + json.dumps(doc["mjxvine"])
          + ',\n "features": [\n  ' + ",\n  ".join(json.dumps(f) for f in doc["features"])
          + "\n]}\n")
  path = atomic.write_text(Path(argv[0]), text)
  world = read_vineyard(path, WorldConfig(), robot_width_m=0.43)
  print(f"{path}: {world.num_rows} rows, {len(world.plant_xy)} plants, heading "
        f"{world.frame['heading_deg']:.2f} deg from east, origin {world.frame['origin_lonlat']}")
  for lane in world.lanes:
    length = lane.centerline[-1, 0] - lane.centerline[0, 0]
    print(f"  lane {lane.id}: {length:.1f} m long, {world.lane_width(lane):.2f} m wide")
  return 0


if __name__ == "__main__":
  sys.exit(main(sys.argv[1:]))
