"""Vineyard files: a block's plant rows as GeoJSON (WGS84) or CSV (local metres), read into
a `Vineyard` (`mjxvine.worlds.blocks`) and written back.

GeoJSON (RFC 7946): a FeatureCollection, one Feature per plant row, positions
[longitude, latitude] in degrees on WGS84 (a third number, the altitude, is ignored).
A row's geometry is either
  - a LineString: the row line; plants every `plant_spacing_m` (m) along it from its first
    vertex: the feature's property, else the `plant_spacing_m` argument, else the
    collection's `mjxvine.plant_spacing_m`; property `missing_plants`: the 0-based indices
    (along the row) of plants that are not there; or
  - a MultiPoint: the plants themselves, in order along the row.
Feature properties: `name` (the row's name in messages: `feature 3 ("B-12")`; features are
counted from 1 in file order), `trunk_height_m`, `canopy_width_m`, `canopy_top_m` (m, the
row's plants; absent: drawn per plant from the config's ranges); others are ignored.
The collection may carry a foreign member "mjxvine", every key optional:
  {"origin_lonlat": [lon, lat], "heading_deg": h, "offset_m": [dx, dy],
   "plant_spacing_m": s, "slope_pct": p, "cross_slope_pct": q,
   "season": "summer", "post_spacing_m": 7.2}
origin: the tangent point of the local frame (default: the centre of the rows' bounding
box); heading_deg: the rows' direction in that frame, degrees counter-clockwise from east
(default: estimated, `blocks.block_heading`); offset_m: the block frame's shift (default:
the first lane starts at x = 0, the rows centred on y = 0; within `MAX_OFFSET_M` of that);
slopes: the terrain's gradient (%) along and across the rows (arguments first, then these,
else 0). season: the block's look (`mjxvine.worlds.seasons`: classic, spring, summer,
winter, or mixed, drawn from the seed; default: the config's world.season);
post_spacing_m: its trellis line posts' spacing (m, or a [min, max] range; 0: no posts;
default: the config's). `write_geojson` writes all three of origin, heading, offset, so a
world reads back where it was, and the season and a given post spacing.

Local frame: the tangent plane at the origin (`mjxvine.worlds.geodesy`).

CSV: plant positions in a local metric frame, header `row,x_m,y_m` (any order, more
columns allowed), one plant per line: `row` a label (rows in the order first seen, plants
of a row in file order), x_m, y_m in metres. Optional columns trunk_height_m,
canopy_width_m, canopy_top_m: per plant, a row takes the mean of its plants' values (an
empty cell: not given); season and post_spacing_m: the block's, as in the "mjxvine" member
(every line that fills the cell must say the same). No origin; the heading is estimated.
`write_csv` writes a world's block frame, so reading the file back gives the same block.

Faults raise `WorldFileError`: one line naming the file, the feature (or CSV line) and
what is wrong, names and values quoted with control characters escaped. Sizes are bounded
before the work (`mjxvine.worlds.limits`): file bytes, JSON nesting, rows, plants per row
and per block, LineString vertices, plant spacing, terrain.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from mjxvine.config import WorldConfig
from mjxvine.robot_files import clean, escaped, short_repr
from mjxvine.worlds.blocks import MAX_BLOCK_M, BlockFrame, BlockLook, vineyard_from_rows
from mjxvine.worlds.geo_csv import read_csv_rows
from mjxvine.worlds.geodesy import (WGS84_A, WGS84_E2, ecef, local_to_lonlat,  # noqa: F401
                                    lonlat_to_local, tangent_plane_error_m)
# the writers, in their own module, are part of this one's interface
from mjxvine.worlds.geo_write import SIZE_KEYS, write_csv, write_geojson  # noqa: F401
from mjxvine.worlds.layout import Vineyard, WorldFileError
from mjxvine.worlds.limits import (MAX_FILE_BYTES, MAX_JSON_DEPTH, MAX_LINE_VERTICES,
                                   MAX_PLANTS, MAX_ROW_PLANTS, MAX_ROWS, MIN_PLANT_SPACING_M,
                                   json_too_deep, read_bounded)
from mjxvine.worlds.seasons import moved

PROJECTED_M = 100e3  # a "block" wider than this is coordinates in metres read as degrees
MAX_NAME_CHARS = 60  # of a row's name in a message
MAX_OFFSET_M = 10.0  # a file's offset_m may move the block this far from the default
MJXVINE_KEYS = ("origin_lonlat", "heading_deg", "offset_m", "plant_spacing_m", "slope_pct",
                "cross_slope_pct", "season", "post_spacing_m")


def read_vineyard(path, cfg: WorldConfig, *, robot_width_m: float,
                  plant_spacing_m: float | None = None, slope_pct: float | None = None,
                  cross_slope_pct: float | None = None, seed: int = 0) -> Vineyard:
  """The `Vineyard` of a vineyard file: `.geojson` (or a `.json` GeoJSON document) or
  `.csv` (module docstring). Lanes are checked for a robot `robot_width_m` (m) wide;
  `plant_spacing_m` (m): LineString rows' spacing where a feature gives none (before the
  file's own default); slopes (%): before the file's, else 0; `seed`: the drawn plant
  sizes and terrain bumps. Raises `WorldFileError` (one line: file, row, fault)."""
  path = Path(path)
  suffix = path.suffix.lower()
  if plant_spacing_m is not None:
    _spacing(plant_spacing_m, "plant spacing argument", ValueError)
  args = {"slope_pct": slope_pct, "cross_slope_pct": cross_slope_pct}
  for key, value in args.items():
    if value is not None:
      _check_slope(value, key, ValueError)
  common = dict(robot_width_m=robot_width_m, args=args, seed=seed)
  try:
    if suffix in (".geojson", ".json"):
      return _read_geojson(path, cfg, plant_spacing_m=plant_spacing_m, **common)
    if suffix == ".csv":
      return _read_csv(path, cfg, **common)
  except WorldFileError as e:  # the path too may hold a newline or an escape sequence
    raise WorldFileError(escaped(str(e))) from None
  raise WorldFileError(escaped(f"{path}: not a vineyard file: give a .geojson (rows in "
                               "WGS84 longitude, latitude) or a .csv (row,x_m,y_m in "
                               "metres)"))


def _quote(v) -> str:
  """A file's value for a message: a number as JSON writes it, else `short_repr`."""
  if v is None or isinstance(v, (bool, float)):
    return json.dumps(v)
  return short_repr(v)


def _is_number(v) -> bool:
  return isinstance(v, (int, float)) and not isinstance(v, bool)


def _slope_range() -> tuple[float, float]:
  """The config's allowed range of a terrain slope (%)."""
  meta = {f.name: f.metadata for f in dataclasses.fields(WorldConfig)}["slope_pct"]
  return float(meta["lo"]), float(meta["hi"])


def _check_slope(value, name: str, error=WorldFileError, where: str = "") -> float:
  lo, hi = _slope_range()
  if not (_is_number(value) and lo <= value <= hi):
    raise error(f"{where}{name} {_quote(value)}: give a number of percent in [{lo:g}, "
                f"{hi:g}]")
  return float(value)


def _meta_field(name: str) -> dict:
  """The metadata (range, choices) of the config key world.`name`."""
  return dict({f.name: f.metadata for f in dataclasses.fields(WorldConfig)}[name])


def check_season(value, where: str) -> str:
  """A file's season (`where`: its place, for the message), else one-line WorldFileError."""
  choices = _meta_field("season")["choices"]
  if not isinstance(value, str) or value not in choices:
    raise WorldFileError(f"{where}season {_quote(value)}: one of {', '.join(choices)}")
  return value


def check_post_spacing(value, where: str) -> tuple[float, float]:
  """A file's post spacing: a number of metres or a [min, max] range (0: no posts), as
  world.post_spacing_m takes it, else one-line WorldFileError."""
  meta = _meta_field("post_spacing_m")
  pair = value if isinstance(value, list) and len(value) == 2 else [value, value]
  least = WorldConfig.MIN_POST_SPACING_M
  if not (all(_is_number(v) and math.isfinite(v) and v <= meta["hi"] for v in pair)
          and pair[0] <= pair[1] and (pair[1] == 0 or pair[0] >= least)):
    raise WorldFileError(f"{where}post_spacing_m {_quote(value)}: give metres from {least:g} "
                         f"to {meta['hi']:g} (a number or a [min, max] range), or 0 for no "
                         "posts")
  return float(pair[0]), float(pair[1])


def _read_text(path: Path) -> str:
  """The file's text (UTF-8, a byte-order mark dropped; at most `MAX_FILE_BYTES`), else
  one-line WorldFileError."""
  data = read_bounded(path, MAX_FILE_BYTES, WorldFileError, "vineyard file")
  try:
    return data.decode("utf-8-sig")
  except UnicodeDecodeError as e:
    raise WorldFileError(f"{path}: not UTF-8 text (byte 0x{data[e.start]:02x} at offset "
                         f"{e.start})") from None


def _frame(world: Vineyard, names_by_label: dict, fmt: str, error_m) -> Vineyard:
  """`world` with the file's format, row names (block order) and plane error in its frame."""
  world.frame["format"] = fmt
  world.frame["row_names"] = [names_by_label[l] for l in world.frame["rows"]]
  world.frame["tangent_plane_error_m"] = error_m
  return world


def _from_rows(path: Path, rows, cfg, frame: BlockFrame, **kw) -> Vineyard:
  """`blocks.vineyard_from_rows`, `frame`'s source the file, its messages prefixed with
  the file."""
  try:
    return vineyard_from_rows(rows, cfg, frame=frame._replace(source=str(path)), **kw)
  except WorldFileError as e:
    msg = str(e)
    raise WorldFileError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None


def _read_geojson(path: Path, cfg: WorldConfig, *, robot_width_m, plant_spacing_m, args,
                  seed) -> Vineyard:
  doc = _parse_json(path, _read_text(path))
  if not isinstance(doc, dict) or "type" not in doc:
    raise WorldFileError(f"{path}: JSON but not GeoJSON (no \"type\" member): a vineyard file "
                         "is a GeoJSON FeatureCollection, one Feature per plant row")
  if doc["type"] != "FeatureCollection":
    raise WorldFileError(f"{path}: a GeoJSON {short_repr(doc['type'])}, not a "
                         "FeatureCollection: give one Feature per plant row")
  features = doc.get("features")
  if not isinstance(features, list):
    raise WorldFileError(f"{path}: the FeatureCollection's \"features\" is not a list")
  meta = _meta(path, doc.get("mjxvine"))
  if len(features) < 2:
    raise WorldFileError(f"{path}: {len(features)} plant row(s) (features); a lane needs two "
                         "rows side by side")
  if len(features) > MAX_ROWS:
    raise WorldFileError(f"{path}: {len(features)} plant rows (features); a block has at most "
                         f"{MAX_ROWS}")
  default_spacing = plant_spacing_m if plant_spacing_m is not None else meta.get(
      "plant_spacing_m")
  parsed, points = [], 0
  for i, f in enumerate(features):  # MultiPoint plants counted before any is made
    parsed.append(_feature(path, i + 1, f))
    points += len(parsed[-1]["lonlat"]) if parsed[-1]["kind"] == "MultiPoint" else 0
    if points > MAX_PLANTS:
      raise WorldFileError(f"{path}: more than {MAX_PLANTS} plants by {parsed[-1]['label']}; "
                           f"a block has at most {MAX_PLANTS}")
  labels = [p["label"] for p in parsed]
  coords = [p["lonlat"] for p in parsed]

  allpts = np.concatenate(coords)
  origin = meta.get("origin_lonlat")
  if origin is None:  # the bounding box's centre, longitudes unwrapped across 180
    rel = (allpts[:, 0] - allpts[0, 0] + 180.0) % 360.0 - 180.0
    lon = allpts[0, 0] + (rel.min() + rel.max()) / 2
    origin = ((lon + 180.0) % 360.0 - 180.0, (allpts[:, 1].min() + allpts[:, 1].max()) / 2)
  far = float(np.linalg.norm(ecef(allpts) - ecef(origin), axis=1).max())
  local = [lonlat_to_local(c, origin) for c in coords]
  span = np.concatenate(local).max(0) - np.concatenate(local).min(0)
  if "origin_lonlat" in meta and far > MAX_BLOCK_M:
    raise WorldFileError(f"{path}: mjxvine.origin_lonlat lies {far / 1000:.1f} km from the "
                         f"farthest plant; put it within {MAX_BLOCK_M / 1000:g} km of the block")
  if span.max() > PROJECTED_M:  # (the default origin is among the points: the plane holds)
    raise WorldFileError(
        f"{path}: the rows span {span[0] / 1000:.0f} x {span[1] / 1000:.0f} km: looks like "
        "projected metres; GeoJSON needs WGS84 longitude, latitude in degrees")
  if span.max() > MAX_BLOCK_M:
    raise WorldFileError(
        f"{path}: the rows span {span[0] / 1000:.1f} x {span[1] / 1000:.1f} km (east x north),"
        f" more than one vineyard block (at most {MAX_BLOCK_M / 1000:g} km across)")

  rows = _row_plants(path, parsed, local, default_spacing)
  error_m = tangent_plane_error_m(coords, origin)
  heading = meta.get("heading_deg")
  slopes = {k: v if v is not None else meta.get(k, 0.0) for k, v in args.items()}
  frame = BlockFrame(origin_lonlat=origin,
                     heading_rad=None if heading is None else math.radians(heading), **slopes)
  world = _from_rows(path, rows, cfg, frame, robot_width_m=robot_width_m, labels=labels,
                     seed=seed, row_sizes=[p["sizes"] for p in parsed],
                     look=BlockLook(meta.get("season"), meta.get("post_spacing_m")))
  if "offset_m" in meta:
    world = _shifted(path, world, meta["offset_m"])
  return _frame(world, {p["label"]: p["name"] for p in parsed}, "geojson", error_m)


def _parse_json(path: Path, text: str):
  """The JSON document of `text` (nesting bounded before parsing), else one-line
  WorldFileError."""
  if json_too_deep(text, MAX_JSON_DEPTH):
    raise WorldFileError(f"{path}: JSON nested more than {MAX_JSON_DEPTH} deep (arrays and "
                         "objects inside each other); GeoJSON rows need 6")
  try:
    doc = json.loads(text)
  except json.JSONDecodeError as e:
    raise WorldFileError(f"{path}: not JSON ({e.msg} at line {e.lineno} column "
                         f"{e.colno})") from None
  except RecursionError:
    raise WorldFileError(f"{path}: not JSON (nested too deeply)") from None
  except ValueError as e:  # a number of thousands of digits
    raise WorldFileError(f"{path}: not JSON ({clean(str(e), 80)})") from None
  return doc


def _row_plants(path: Path, parsed: list[dict], local: list[np.ndarray],
                default_spacing: float | None) -> list[np.ndarray]:
  """The plants (n, 2), local m, of each checked feature (`_feature`; `local`: its
  positions in the tangent plane): a LineString's along its line, a MultiPoint's as given;
  the block's plants counted as they are made."""
  rows, plants = [], 0
  for p, xy in zip(parsed, local):
    if p["kind"] == "LineString":
      spacing = p["spacing"] if p["spacing"] is not None else default_spacing
      if spacing is None:
        raise WorldFileError(
            f"{path}: {p['label']}: a LineString row needs plant_spacing_m (m): give it as "
            "the feature's property, the file's mjxvine.plant_spacing_m or the "
            "plant-spacing argument")
      rows.append(_plant_line(path, p, xy, spacing))
    else:
      rows.append(xy)
    plants += len(rows[-1])
    if plants > MAX_PLANTS:
      raise WorldFileError(f"{path}: more than {MAX_PLANTS} plants by {p['label']}; a block "
                           f"has at most {MAX_PLANTS}")
  return rows


def _meta(path: Path, m) -> dict:
  """The collection's "mjxvine" member, checked: {key: value} of the keys it gives."""
  if m is None:
    return {}
  if not isinstance(m, dict):
    raise WorldFileError(f"{path}: the \"mjxvine\" member must be an object with any of "
                         f"{', '.join(MJXVINE_KEYS)}")
  unknown = sorted(set(m) - set(MJXVINE_KEYS))
  if unknown:
    raise WorldFileError(f"{path}: mjxvine member: unknown key(s) {', '.join(unknown)} (known: "
                         f"{', '.join(MJXVINE_KEYS)})")
  out = {}
  where = f"{path}: mjxvine."
  for key in ("origin_lonlat", "offset_m"):
    if key in m:
      v = m[key]
      if not (isinstance(v, list) and len(v) == 2 and all(_is_number(x) and math.isfinite(x)
                                                           for x in v)):
        raise WorldFileError(f"{where}{key} must be a pair of numbers, got {_quote(v)}")
      out[key] = (float(v[0]), float(v[1]))
  if "origin_lonlat" in out:
    lon, lat = out["origin_lonlat"]
    if not (-180 <= lon <= 180 and -90 <= lat <= 90):
      raise WorldFileError(f"{where}origin_lonlat [{lon:g}, {lat:g}] is not a [longitude, "
                           "latitude] in degrees")
  if "heading_deg" in m:
    if not (_is_number(m["heading_deg"]) and math.isfinite(m["heading_deg"])):
      raise WorldFileError(f"{where}heading_deg must be a number (degrees from east), got "
                           f"{_quote(m['heading_deg'])}")
    out["heading_deg"] = float(m["heading_deg"])
  if "plant_spacing_m" in m:
    out["plant_spacing_m"] = _spacing(m["plant_spacing_m"], where.rstrip("."))
  for key in ("slope_pct", "cross_slope_pct"):
    if key in m:
      out[key] = _check_slope(m[key], key, where=where[:-1] + ": ")
  if "season" in m:
    out["season"] = check_season(m["season"], where)
  if "post_spacing_m" in m:
    out["post_spacing_m"] = check_post_spacing(m["post_spacing_m"], where)
  return out


def _spacing(v, where: str, error=WorldFileError) -> float:
  if not (_is_number(v) and math.isfinite(v) and v > 0):
    raise error(f"{where}: plant_spacing_m {_quote(v)}: give a positive number of metres")
  if v < MIN_PLANT_SPACING_M:
    raise error(f"{where}: plant_spacing_m {v:g}: plants nearer than {MIN_PLANT_SPACING_M:g} m "
                "are not vines (the spacing is in metres)")
  return float(v)


def _feature(path: Path, number: int, f) -> dict:
  """A feature checked: {label, name, kind, lonlat (n, 2), spacing, missing, sizes}."""
  label = f"feature {number}"
  if not isinstance(f, dict) or f.get("type") != "Feature":
    raise WorldFileError(f"{path}: {label} is not a GeoJSON Feature")
  props = f.get("properties")
  if props is None:
    props = {}
  if not isinstance(props, dict):
    raise WorldFileError(f"{path}: {label}: \"properties\" must be an object or null")
  name = props.get("name")
  name = None if name is None else str(name)
  if name is not None:  # escaped: a name is one line of a message, whatever it holds
    label = f'{label} ("{clean(name, MAX_NAME_CHARS)}")'
  where = f"{path}: {label}"
  geom = f.get("geometry")
  if geom is None:
    raise WorldFileError(f"{where}: has no geometry; a row is a LineString (the row line) or "
                         "a MultiPoint (its plants)")
  kind = geom.get("type") if isinstance(geom, dict) else None
  if kind not in ("LineString", "MultiPoint"):
    what = f"is a {kind}" if isinstance(kind, str) else "has no \"type\""
    raise WorldFileError(f"{where}: geometry {what}; a row is a LineString (the row line) or a "
                         "MultiPoint (its plants)")
  coords = geom.get("coordinates")
  if not isinstance(coords, list):
    raise WorldFileError(f"{where}: the geometry has no list of coordinates")
  most, what = ((MAX_LINE_VERTICES, "vertices of a row line") if kind == "LineString" else
                (MAX_ROW_PLANTS, "plants of a row"))
  if len(coords) > most:
    raise WorldFileError(f"{where}: {len(coords)} positions; at most {most} {what}")
  lonlat = np.zeros((len(coords), 2))
  for i, pos in enumerate(coords):
    if not (isinstance(pos, list) and len(pos) in (2, 3) and all(map(_is_number, pos))):
      raise WorldFileError(f"{where}: coordinates[{i}] {_quote(pos)} is not a "
                           "[longitude, latitude] pair of numbers")
    if not all(math.isfinite(v) for v in pos):
      raise WorldFileError(f"{where}: coordinates[{i}] {_quote(pos)} is not finite")
    lonlat[i] = pos[:2]
  _check_lonlat(where, lonlat)
  if len(lonlat) < 2:
    raise WorldFileError(f"{where}: {len(lonlat)} point(s); a row needs at least 2")
  spacing = props.get("plant_spacing_m")
  if spacing is not None:
    spacing = _spacing(spacing, where)
  missing = props.get("missing_plants")
  if missing is not None and kind == "MultiPoint":
    raise WorldFileError(f"{where}: missing_plants is for LineString rows; a MultiPoint lists "
                         "the plants that are there")
  if missing is not None and not (isinstance(missing, list) and all(
      isinstance(k, int) and not isinstance(k, bool) for k in missing)):
    raise WorldFileError(f"{where}: missing_plants must be a list of whole numbers (0-based "
                         f"plant indices along the row), got {_quote(missing)}")
  sizes = {}
  for key in SIZE_KEYS:
    v = props.get(key)
    if v is not None:
      if not (_is_number(v) and math.isfinite(v) and v > 0):
        raise WorldFileError(f"{where}: {key} {_quote(v)}: give a positive number of "
                             "metres")
      sizes[key] = float(v)
  return {"label": label, "name": name, "kind": kind, "lonlat": lonlat, "spacing": spacing,
          "missing": missing or [], "sizes": sizes}


def _check_lonlat(where: str, lonlat: np.ndarray) -> None:
  """Refuses positions that are not WGS84 degrees, saying what they look like instead."""
  lon, lat = lonlat[:, 0], lonlat[:, 1]
  if np.any(np.abs(lonlat) > 360):
    v = lonlat[np.argmax(np.abs(lonlat).max(1))]
    raise WorldFileError(f"{where}: [{v[0]:.10g}, {v[1]:.10g}] looks like projected metres; "
                         "GeoJSON needs WGS84 longitude, latitude in degrees")
  if np.any(np.abs(lat) > 90) and np.all(np.abs(lon) <= 90):
    v = lonlat[np.argmax(np.abs(lat))]
    raise WorldFileError(f"{where}: latitude {v[1]:.8g} outside [-90, 90] (at [{v[0]:.8g}, "
                         f"{v[1]:.8g}]): longitude and latitude swapped? GeoJSON positions are "
                         "[longitude, latitude]")
  for values, name, bound in ((lon, "longitude", 180), (lat, "latitude", 90)):
    if np.any(np.abs(values) > bound):
      v = values[np.argmax(np.abs(values))]
      raise WorldFileError(f"{where}: {name} {v:.8g} outside [-{bound}, {bound}] degrees")


def _plant_line(path: Path, p: dict, xy: np.ndarray, spacing: float) -> np.ndarray:
  """The plants (n, 2), m, of a LineString row (vertices `xy`, local m): every `spacing`
  along the polyline from its first vertex, `p["missing"]` left out."""
  where = f"{path}: {p['label']}"
  seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
  keep = np.concatenate([[True], seg > 1e-9])  # repeated vertices add no length
  xy, seg = xy[keep], seg[seg > 1e-9]
  if len(xy) < 2:
    raise WorldFileError(f"{where}: all its vertices are one point; a row needs at least 2")
  s = np.concatenate([[0.0], np.cumsum(seg)])
  count = int(np.floor(s[-1] / spacing + 1e-9)) + 1  # a plant at the end if it falls there
  if count > MAX_ROW_PLANTS:
    raise WorldFileError(f"{where}: plant_spacing_m {spacing:g} puts {count} plants along "
                         f"{s[-1]:.0f} m (at most {MAX_ROW_PLANTS} a row); the spacing is in "
                         "metres")
  at = np.arange(count) * spacing
  plants = np.stack([np.interp(at, s, xy[:, 0]), np.interp(at, s, xy[:, 1])], -1)
  bad = [k for k in p["missing"] if not 0 <= k < count]
  if bad:
    raise WorldFileError(f"{where}: missing_plants index {bad[0]} out of range: the row has "
                         f"{count} plants (0 to {count - 1}) at {spacing:g} m along {s[-1]:.1f} m")
  kept = np.setdiff1d(np.arange(count), p["missing"])
  if len(kept) < 2:
    raise WorldFileError(f"{where}: {len(kept)} plant(s) left ({count} every {spacing:g} m "
                         f"along {s[-1]:.1f} m, {count - len(kept)} missing); a row needs at "
                         "least 2")
  return plants[kept]


def _shifted(path: Path, world: Vineyard, offset) -> Vineyard:
  """`world` moved so that its block frame has the file's `offset` (m) (`write_geojson`
  records it, so a world reads back where it was, not re-centred on its plants)."""
  d = np.asarray(offset, np.float64) - np.asarray(world.frame["offset_m"])
  if np.abs(d).max() > MAX_OFFSET_M:
    raise WorldFileError(f"{path}: mjxvine.offset_m moves the block {np.abs(d).max():.1f} m "
                         f"from where its first lane starts at x = 0 (at most {MAX_OFFSET_M:g} m)")
  lanes = tuple(dataclasses.replace(l, centerline=l.centerline + d, eor_forward=l.eor_forward + d,
                                    eor_reverse=l.eor_reverse + d) for l in world.lanes)
  x0, x1, y0, y1 = world.terrain_extent  # the terrain moves with the plants
  return dataclasses.replace(
      world, plant_xy=world.plant_xy + d, row_y0=world.row_y0 + d[1], lanes=lanes,
      terrain_extent=(x0 + d[0], x1 + d[0], y0 + d[1], y1 + d[1]),
      frame=dict(world.frame, offset_m=[float(v) for v in offset]), **moved(world, d))


def _read_csv(path: Path, cfg: WorldConfig, *, robot_width_m, args, seed) -> Vineyard:
  rows, sizes, block = read_csv_rows(path, _read_text(path))
  if not rows:
    raise WorldFileError(f"{path}: a header but no plants")
  plants = np.concatenate([np.asarray(r) for r in rows.values()])
  span = plants.max(0) - plants.min(0)
  if len(rows) >= 2 and span.max() < 1.0:
    raise WorldFileError(f"{path}: the plants span {span[0]:.2g} x {span[1]:.2g} m: degrees? a "
                         "CSV takes metres (x_m, y_m); longitude, latitude go in a GeoJSON file")
  labels = []
  for k in rows:  # escaped, shortened, and still one label per row
    label = f'row "{clean(k, MAX_NAME_CHARS)}"'
    labels.append(label if label not in labels else f"{label} ({len(labels) + 1})")
  slopes = {k: v if v is not None else 0.0 for k, v in args.items()}
  world = _from_rows(path, [np.asarray(r) for r in rows.values()], cfg, BlockFrame(**slopes),
                     robot_width_m=robot_width_m, labels=labels, seed=seed,
                     row_sizes=[{k: float(np.mean(v)) for k, v in sizes[r].items()}
                                for r in rows], look=_csv_block(path, block))
  return _frame(world, dict(zip(labels, rows)), "csv", None)


def _csv_block(path: Path, block: dict) -> BlockLook:
  """The season and post spacing a CSV's columns give ({key: (line, value)}), checked."""
  checks = {"season": check_season, "post_spacing_m": check_post_spacing}
  return BlockLook(**{key: checks[key](value, f"{path}: line {line}: ")
                      for key, (line, value) in block.items()})

