"""A vineyard block from its plant rows: the block frame, lanes between adjacent rows, plant
sizes and terrain, as a `Vineyard` that every command takes (docs/your-vineyard.md).

Input: plant rows in a local metric frame (m, any orientation: east/north of a tangent
plane from `mjxvine.worlds.geo`, or a CSV's own x/y). The block frame rotates them so that
the rows run along +x (the mean of the rows' start-to-end directions) and ends where the
generator's worlds do: the first lane starts at x = 0 and the block is centred on y = 0.
Rows are ordered across (by their mean y, lane k between rows k - 1 and k); each lane's
ground-truth line is the midline of its two rows over the x where both exist, smoothed
over `SMOOTH_M`, a sample every `CENTERLINE_STEP_M` of x. Lanes are driven both ways.

Faults (rows that turn back, cross, touch, run end to end or stand too close for the
robot; plants nearer than `MIN_PLANT_SPACING_M`; more rows, plants or terrain than
`mjxvine.worlds.limits` allows) raise `WorldFileError`, one line naming the rows by their
labels.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

from mjxvine.config import WorldConfig
from mjxvine.worlds.layout import (CENTERLINE_STEP_M, TERRAIN_CELL_M, TERRAIN_MARGIN_M,
                                   TRUNK_RADIUS_M, Lane, Vineyard, WorldFileError,
                                   slope_plane, terrain_bumps)
from mjxvine.worlds.limits import (MAX_PLANTS, MAX_ROW_PLANTS, MAX_ROWS, MAX_SCENERY,
                                   MAX_TERRAIN_CELLS, MIN_PLANT_SPACING_M)
from mjxvine.worlds.seasons import SHAPE_TABLES, dress

SMOOTH_M = 3.0  # moving-average window of a file lane's midline: plant jitter out, bends in
MIN_OVERLAP_M = 2.0  # adjacent rows must run side by side at least this far
LANE_MARGIN_M = 0.3  # a lane narrower than robot width + canopy + this is refused
MAX_BLOCK_M = 5000.0  # a block wider or longer than this is not one vineyard block


def block_heading(rows: Sequence[np.ndarray]) -> float:
  """The rows' direction (rad, in the input frame, in (-pi/2, pi/2]): the principal axis of
  the plants, each row centred on its own mean (a least-squares fit of parallel lines)."""
  centred = np.concatenate([r - r.mean(0) for r in rows])
  _, vecs = np.linalg.eigh(centred.T @ centred)
  d = vecs[:, -1]
  angle = float(np.arctan2(d[1], d[0]))
  return angle - np.pi if angle > np.pi / 2 else angle + np.pi if angle <= -np.pi / 2 else angle


def _rotate(xy: np.ndarray, angle: float) -> np.ndarray:
  """Points (n, 2) rotated by `angle` (rad, counter-clockwise) about the origin."""
  c, s = np.cos(angle), np.sin(angle)
  return xy @ np.array([[c, s], [-s, c]])


def _smooth(y: np.ndarray, window: int) -> np.ndarray:
  """Centred moving average over `window` samples, the window shrunk at the ends (so the
  ends stay where the rows end)."""
  if window < 2 or len(y) < 3:
    return y
  half = min(window // 2, (len(y) - 1) // 2)
  c = np.concatenate([[0.0], np.cumsum(y)])
  i = np.arange(len(y))
  h = np.minimum(np.minimum(i, len(y) - 1 - i), half)
  return (c[i + h + 1] - c[i - h]) / (2 * h + 1)


def _row_function(row: np.ndarray, label: str):
  """(x0, x1, y(x)) of a row whose plants are listed in order along it (either way);
  refuses a row that turns back (sorting by x would hide a hairpin)."""
  flip = row[-1, 0] < row[0, 0]
  x, y = (row[::-1, 0], row[::-1, 1]) if flip else (row[:, 0], row[:, 1])
  step = np.diff(x)
  if np.any(step <= 0):
    k = int(np.argmax(step <= 0)) + 1  # 0-based, in the order along +x
    k = len(x) - k if flip else k  # in the order listed
    raise WorldFileError(f"{label}: plant {k + 1} of {len(x)} is not beyond the one before "
                         "it along the rows (the row turns back, or its plants are not listed "
                         "in order): each row must run one way along the block")
  return x[0], x[-1], lambda xs: np.interp(xs, x, y)


def file_lanes(rows: list[np.ndarray], labels: list[str], min_width_m: float) -> list[Lane]:
  """The lanes between adjacent rows (block frame, rows ordered across)."""
  funcs = [_row_function(r, l) for r, l in zip(rows, labels)]
  lanes = []
  for k in range(1, len(rows)):
    (a0, a1, ya), (b0, b1, yb) = funcs[k - 1], funcs[k]
    x0, x1 = max(a0, b0), min(a1, b1)
    pair = f"{labels[k - 1]} and {labels[k]}"
    if x1 - x0 < MIN_OVERLAP_M:
      raise WorldFileError(f"{pair}: adjacent rows run side by side over {max(x1 - x0, 0):.1f}"
                           f" m (at least {MIN_OVERLAP_M} m): rows end to end are one row")
    xc = np.linspace(x0, x1, int(np.ceil((x1 - x0) / CENTERLINE_STEP_M)) + 1)
    gap = yb(xc) - ya(xc)
    if gap.min() <= 0:
      at = xc[np.argmax(gap <= 0)]  # where they first meet (not where most overlapped)
      raise WorldFileError(f"{pair}: the rows cross or touch (at {at - x0:.1f} m along them)")
    if gap.min() < min_width_m:
      raise WorldFileError(
          f"{pair}: the rows are {gap.min():.2f} m apart at the narrowest, closer than the "
          f"robot's width plus canopy and margin ({min_width_m:.2f} m)")
    mid = _smooth((ya(xc) + yb(xc)) / 2, int(round(SMOOTH_M / CENTERLINE_STEP_M)))
    line = np.stack([xc, mid], -1)
    lanes.append(Lane(k, "file", k - 1, k, line, line[-1].copy(), line[0].copy(),
                      width_m=float(np.median(gap))))
  return lanes


def plant_sizes(rng: np.random.Generator, cfg: WorldConfig, row_sizes: Sequence[dict],
                plant_row: np.ndarray, labels: Sequence[str]):
  """(trunk height, canopy top, canopy width) per plant (m): a row's given sizes, else
  drawn from the config's ranges."""
  n = len(plant_row)
  drawn = {"trunk_height_m": rng.uniform(*cfg.trunk_height_m, n),
           "canopy_top_m": rng.uniform(*cfg.canopy_top_m, n),
           "canopy_width_m": rng.uniform(*cfg.canopy_width_m, n)}
  for key, values in drawn.items():
    for j, given in enumerate(row_sizes):
      if given.get(key) is not None:
        values[plant_row == j] = float(given[key])
  trunk, top, width = (drawn[k] for k in ("trunk_height_m", "canopy_top_m", "canopy_width_m"))
  if np.any(top <= trunk):
    j = int(plant_row[np.argmax(top <= trunk)])
    raise WorldFileError(f"{labels[j]}: canopy_top_m must be above trunk_height_m")
  return trunk, top, width


class BlockLook(NamedTuple):
  """What a vineyard file says of its block's look: its `season` and the spacing of its
  trellis line posts (`post_spacing_m`, a range in m); None: the config's."""
  season: str | None = None
  post_spacing_m: tuple[float, float] | None = None


class BlockFrame(NamedTuple):
  """Where a block's rows come from and how it lies, as `Vineyard.frame` keeps it: `source`
  (the file, in messages; "" for none), `origin_lonlat` (the local frame's tangent point,
  degrees; None: no geographic frame), `heading_rad` (the rows' direction in the local
  frame; None: estimated, `block_heading`), and the terrain's gradient (%) along
  (`slope_pct`) and across (`cross_slope_pct`) the rows, on top of the config's bumps."""
  source: str = ""
  origin_lonlat: tuple[float, float] | None = None
  heading_rad: float | None = None
  slope_pct: float = 0.0
  cross_slope_pct: float = 0.0


def vineyard_from_rows(rows: Sequence[np.ndarray], cfg: WorldConfig, *, robot_width_m: float,
                       labels: Sequence[str] | None = None,
                       row_sizes: Sequence[dict] | None = None, seed: int = 0,
                       frame: BlockFrame = BlockFrame(), look: BlockLook = BlockLook()
                       ) -> Vineyard:
  """The `Vineyard` of plant rows given as (n_j, 2) arrays of plant positions (m) in a
  local metric frame, at least two rows of at least two plants, lying as `frame` says
  (`BlockFrame`: source, origin, heading, slopes).

  row_sizes: optional per-row plant sizes (m), a dict per row with any of
  "trunk_height_m", "canopy_width_m", "canopy_top_m"; what a row does not give is drawn
  per plant from the config's ranges with `seed`. The frame (origin, heading, offset,
  slopes) is kept in `Vineyard.frame`. `look` (`BlockLook`): the block's own season and
  post spacing, before the config's (`seasons.dress`; a row's trunk height is its cordon's
  there); a given spacing is kept in the frame too."""
  source, origin_lonlat, heading_rad, slope_pct, cross_slope_pct = frame
  labels = list(labels or [f"row {j + 1}" for j in range(len(rows))])
  rows = [np.asarray(r, np.float64).reshape(-1, 2) for r in rows]
  block = source or "the block"
  _check_rows(block, rows, labels)
  heading = block_heading(rows) if heading_rad is None else heading_rad
  rows = [_rotate(r, -heading) for r in rows]
  _check_terrain(block, np.concatenate(rows))
  order = np.argsort([r[:, 1].mean() for r in rows], kind="stable")
  rows, labels = [rows[i] for i in order], [labels[i] for i in order]
  row_sizes = [dict((row_sizes or [{}] * len(order))[i]) for i in order]
  min_width = robot_width_m + cfg.canopy_width_m[1] + LANE_MARGIN_M
  lanes = file_lanes(rows, labels, min_width)
  # shift: the first lane's start at x = 0, the rows' mean y at 0
  offset = -np.array([min(l.centerline[0, 0] for l in lanes),
                      np.concatenate(rows)[:, 1].mean()])
  rows = [r + offset for r in rows]
  lanes = [Lane(l.id, l.shape, l.left_row, l.right_row, l.centerline + offset,
                l.eor_forward + offset, l.eor_reverse + offset, l.width_m) for l in lanes]

  plant_xy = np.concatenate(rows)
  plant_row = np.concatenate([np.full(len(r), j) for j, r in enumerate(rows)])
  n = len(plant_xy)
  rng = np.random.default_rng([seed, 2])
  trunk, top, width = plant_sizes(rng, cfg, row_sizes, plant_row, labels)
  canopy_half = np.stack([width / 2, width / 2, (top - trunk) / 2], -1)
  spacing = float(np.median(np.concatenate([np.linalg.norm(np.diff(r, axis=0), axis=1)
                                            for r in rows])))
  widths = np.array([l.width_m for l in lanes])
  m = TERRAIN_MARGIN_M
  lo, hi = plant_xy.min(0), plant_xy.max(0)
  extent = (float(lo[0] - m), float(hi[0] + m), float(lo[1] - m), float(hi[1] + m))
  terrain = terrain_bumps(rng, extent)
  if slope_pct or cross_slope_pct:
    terrain = terrain + slope_plane(terrain.shape, extent, slope_pct, cross_slope_pct)
  world = Vineyard(
      kind="file", seed=int(seed), inter_row_m=float(np.median(widths)), spacing_m=spacing,
      length_m=float(max(l.centerline[-1, 0] for l in lanes)),
      row_y0=np.array([r[:, 1].mean() for r in rows]), plant_xy=plant_xy,
      plant_yaw=rng.uniform(-np.pi, np.pi, n), plant_row=plant_row, trunk_height=trunk,
      trunk_radius=TRUNK_RADIUS_M, canopy_half=canopy_half, canopy_z=(top + trunk) / 2,
      lanes=tuple(lanes), terrain=terrain, terrain_extent=extent,
      frame={"source": source, "origin_lonlat": None if origin_lonlat is None else
             [float(v) for v in origin_lonlat], "heading_deg": float(np.rad2deg(heading)),
             "offset_m": offset.tolist(), "rows": labels,
             "slope_pct": float(slope_pct), "cross_slope_pct": float(cross_slope_pct),
             **({} if look.post_spacing_m is None else
                {"post_spacing_m": [float(v) for v in look.post_spacing_m]})})
  given = np.array([s.get("trunk_height_m") is not None for s in row_sizes], bool)
  world = dress(world, cfg, season=look.season, post_spacing_m=look.post_spacing_m,
                given_trunks=given[plant_row])
  shapes = len(world.post_xy) + sum(len(getattr(world, k)) for k in SHAPE_TABLES)
  if shapes > MAX_SCENERY:
    raise WorldFileError(f"{block}: {world.season} puts {shapes} posts and shapes on it; a "
                         f"block has at most {MAX_SCENERY} (a smaller block, fewer tufts)")
  return world


def _check_rows(block: str, rows: list[np.ndarray], labels: list[str]) -> None:
  """Refuses rows (input frame, m) beyond the block's limits: row, plant and per-row counts,
  finite positions, plant spacing and the block's span; `block` names it in messages."""
  if len(rows) < 2:
    raise WorldFileError(f"{block}: {len(rows)} plant row(s); a lane needs two rows side by "
                         "side")
  if len(rows) > MAX_ROWS:
    raise WorldFileError(f"{block}: {len(rows)} plant rows; a block has at most {MAX_ROWS}")
  total = sum(len(r) for r in rows)
  if total > MAX_PLANTS:
    raise WorldFileError(f"{block}: {total} plants; a block has at most {MAX_PLANTS}")
  for r, label in zip(rows, labels):
    if len(r) < 2:
      raise WorldFileError(f"{label}: {len(r)} plant(s); a row needs at least 2")
    if len(r) > MAX_ROW_PLANTS:
      raise WorldFileError(f"{label}: {len(r)} plants; a row has at most {MAX_ROW_PLANTS}")
    if not np.all(np.isfinite(r)):
      raise WorldFileError(f"{label}: a position is not a finite number")
    gaps = np.linalg.norm(np.diff(r, axis=0), axis=1)
    if gaps.min() < MIN_PLANT_SPACING_M:
      k = int(np.argmax(gaps < MIN_PLANT_SPACING_M))  # the first such pair
      raise WorldFileError(
          f"{label}: plants {k + 1} and {k + 2} are {gaps[k] * 1000:.0f} mm apart; plants of "
          f"a row nearer than {MIN_PLANT_SPACING_M:g} m are not vines (positions in metres?)")
  allxy = np.concatenate(rows)
  span = allxy.max(0) - allxy.min(0)
  if span.max() > MAX_BLOCK_M:
    raise WorldFileError(
        f"{block}: spans {span[0] / 1000:.1f} x {span[1] / 1000:.1f} km; a vineyard block is "
        f"at most {MAX_BLOCK_M / 1000:g} km across (swapped or projected coordinates?)")


def _check_terrain(block: str, xy: np.ndarray) -> None:
  """Refuses a block whose terrain (the plants' box in the block frame and its margins)
  would have more than `MAX_TERRAIN_CELLS` heightfield cells, before it is made."""
  size = xy.max(0) - xy.min(0) + 2 * TERRAIN_MARGIN_M
  cells = np.prod(np.round(size / TERRAIN_CELL_M) + 1)
  if cells > MAX_TERRAIN_CELLS:
    raise WorldFileError(
        f"{block}: its ground, {size[0]:.0f} x {size[1]:.0f} m with the margins, is "
        f"{cells / 1e6:.1f} million terrain cells of {TERRAIN_CELL_M:g} m; a block has at most "
        f"{MAX_TERRAIN_CELLS / 1e6:g} million ({MAX_TERRAIN_CELLS * TERRAIN_CELL_M ** 2 / 1e4:g}"
        " ha)")


def block_to_input(world: Vineyard, xy: np.ndarray) -> np.ndarray:
  """Block-frame points (n, 2) back in the input's local frame (m)."""
  f = world.frame
  return _rotate(np.asarray(xy) - f["offset_m"], np.deg2rad(f["heading_deg"]))
