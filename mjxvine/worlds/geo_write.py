"""Vineyards written as vineyard files (`mjxvine.worlds.geo` reads them back): GeoJSON in
WGS84 at a given origin, or CSV in the block frame (m)."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Sequence

import numpy as np

from mjxvine import atomic
from mjxvine.worlds.blocks import block_to_input
from mjxvine.worlds.geodesy import local_to_lonlat
from mjxvine.worlds.layout import Vineyard

GEOJSON_DECIMALS = 10  # degrees, about 0.01 mm: a written world reads back well under 1 mm
SIZE_KEYS = ("trunk_height_m", "canopy_width_m", "canopy_top_m")


def _row_names(world: Vineyard) -> list[str]:
  """A unique name per plant row (block order): the file's names, else R1, R2, ..."""
  given = (world.frame or {}).get("row_names") or [None] * world.num_rows
  names = [n if n else f"R{j + 1}" for j, n in enumerate(given)]
  return names if len(set(names)) == len(names) else [f"R{j + 1}" for j in range(len(names))]


def _row_sizes(world: Vineyard, j: int) -> dict:
  """The sizes (m) that every plant of row j shares (a file world's per-row sizes), to
  write back; a size drawn per plant (generated worlds) is not written."""
  m = world.plant_row == j
  top = world.canopy_z[m] + world.canopy_half[m, 2]
  values = {"trunk_height_m": world.trunk_height[m], "canopy_width_m": 2 * world.canopy_half[m, 0],
            "canopy_top_m": top}
  round_ = world.canopy_half[m, 0] == world.canopy_half[m, 1]
  return {k: round(float(v.mean()), 6) for k, v in values.items()
          if np.ptp(v) < 1e-9 and (k != "canopy_width_m" or round_.all())}


def write_geojson(world: Vineyard, path, origin_lonlat: Sequence[float] | None = None) -> Path:
  """Writes `world`'s plants as GeoJSON, one MultiPoint feature per row (block order), at
  `origin_lonlat` (lon, lat degrees; default: the world's own origin, for a file world),
  atomically. The "mjxvine" member records origin, heading and offset, so that
  `read_vineyard` puts the plants where they were (a generated world: heading 0, offset 0:
  its frame is the block frame). Per-row sizes that every plant of a row shares are kept."""
  frame = world.frame or {}
  origin = origin_lonlat if origin_lonlat is not None else frame.get("origin_lonlat")
  if origin is None:
    raise ValueError("write_geojson: this world has no origin; give origin_lonlat (lon, lat)")
  lon, lat = (float(v) for v in origin)
  if not (-180 <= lon <= 180 and -90 <= lat <= 90):
    raise ValueError(f"write_geojson: origin ({lon:g}, {lat:g}) is not a (longitude, latitude)"
                     " in degrees")
  if world.frame:
    local = block_to_input(world, world.plant_xy)
    heading, offset = float(frame["heading_deg"]), [float(v) for v in frame["offset_m"]]
  else:
    local, heading, offset = world.plant_xy, 0.0, [0.0, 0.0]
  lonlat = np.round(local_to_lonlat(local, (lon, lat)), GEOJSON_DECIMALS)
  meta = {"origin_lonlat": [lon, lat], "heading_deg": heading, "offset_m": offset}
  for key in ("slope_pct", "cross_slope_pct"):
    if frame.get(key):
      meta[key] = float(frame[key])
  meta.update(_block_look(world))
  features = []
  for j, name in enumerate(_row_names(world)):
    features.append(json.dumps({
        "type": "Feature", "properties": {"name": name, **_row_sizes(world, j)},
        "geometry": {"type": "MultiPoint",
                     "coordinates": lonlat[world.plant_row == j].tolist()}}))
  text = ('{"type": "FeatureCollection",\n "mjxvine": ' + json.dumps(meta)
          + ',\n "features": [\n  ' + ",\n  ".join(features) + "\n]}\n")
  return atomic.write_text(path, text)


def _block_look(world: Vineyard) -> dict:
  """The season (unless classic) and the post spacing a file gave (`Vineyard.frame`) of
  `world`, as a vineyard file says them."""
  out = {} if world.season == "classic" else {"season": world.season}
  spacing = (world.frame or {}).get("post_spacing_m")
  if spacing is not None:
    out["post_spacing_m"] = spacing[0] if spacing[0] == spacing[1] else list(spacing)
  return out


def write_csv(world: Vineyard, path) -> Path:
  """Writes `world`'s plants as a CSV (row,x_m,y_m in the world's block frame, m, to 1 µm;
  size columns where rows share sizes; the season and a given post spacing on the first
  line), atomically; `read_vineyard` reads it back as the same block."""
  names = _row_names(world)
  sizes = [_row_sizes(world, j) for j in range(world.num_rows)]
  extra = [k for k in SIZE_KEYS if any(k in s for s in sizes)]
  look = _block_look(world)
  if isinstance(look.get("post_spacing_m"), list):  # (a cell holds one number)
    del look["post_spacing_m"]
  out = io.StringIO()
  w = csv.writer(out, lineterminator="\n")
  w.writerow(["row", "x_m", "y_m", *extra, *look])
  for i, ((x, y), j) in enumerate(zip(world.plant_xy, world.plant_row)):
    w.writerow([names[j], f"{x:.6f}", f"{y:.6f}", *(sizes[j].get(k, "") for k in extra),
                *(look.values() if i == 0 else [""] * len(look))])
  return atomic.write_text(path, out.getvalue())
