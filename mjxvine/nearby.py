"""Fixed-size sets of the static points (plants) of a pool of worlds near a query point, so
that the env step's cost follows what is near the robot, not the vineyard's size.

A uniform xy grid over the points of every world; each world's points sorted by cell,
row-major (y, then x). The cells within `reach` of a query point make `wy` grid rows of
`wx` cells; in the sorted order each such row of cells is one contiguous run, and no run
is longer than `span` (the largest count in `wx` adjacent cells of any world, found when
the index is built). A query reads `wy` runs of `span` entries: `wy * span` ids, a number
fixed by the layout's density, never by its extent. The cell height is chosen to make it
smallest; when it would not be smaller than the point count, a query returns every point.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jp
import numpy as np

CELL_X_M = 0.5  # cell width along x (m): a run's slack, up to 2 cells beyond 2 * reach
BAND_FRACTIONS = (0.25, 0.5, 1.0, 2.0, 4.0)  # cell heights tried, as fractions of reach
MARGIN_M = 0.01  # added to every reach: float32 rounding of the cell arithmetic


@dataclasses.dataclass(frozen=True, eq=False)
class NearbyIndex:
  """Which of a world's `count` points lie within `reach` (m) of a point in x and y.

  `near(world, xy)` returns `size` ids (int32, ascending): a superset of the ids of the
  points within `reach` in both x and y (a square, so a disc too), padded with `count`
  (no point). Static numbers describe the grid (origin and cell (x, y) m, shape (ny, nx),
  window (wy, wx) cells, span); `order` (Wd, N + span) holds each world's point ids sorted
  by cell, padded with `count`, and `start` (Wd, ny * nx + 1) the first entry of each cell.
  `order` is None where every query returns all points (`everything`).
  """
  count: int
  reach: float
  origin: tuple[float, float]
  cell: tuple[float, float]
  shape: tuple[int, int]
  window: tuple[int, int]
  span: int
  order: jax.Array | None
  start: jax.Array | None

  @property
  def everything(self) -> bool:
    """Whether a query returns every point (no grid would read fewer)."""
    return self.order is None

  @property
  def size(self) -> int:
    """Ids per query (static)."""
    return self.count if self.everything else self.window[0] * self.span

  @staticmethod
  def build(xy: np.ndarray, keep: np.ndarray, reach: float) -> "NearbyIndex":
    """Index of points xy (Wd, P, 2) m of a pool of worlds; `keep` (Wd, P) bool: points
    that a query may return (the others never can be near: parked plant slots)."""
    xy, keep = np.asarray(xy, np.float64), np.asarray(keep, bool)
    count, reach = xy.shape[1], float(reach) + MARGIN_M
    full = NearbyIndex(count, reach, (0.0, 0.0), (1.0, 1.0), (1, 1), (1, 1), count, None,
                       None)
    if not keep.any():
      return full
    pts = xy[keep]
    origin = (float(pts[:, 0].min()), float(pts[:, 1].min()))
    best = min((_layout(xy, keep, origin, (CELL_X_M, f * reach), reach)
                for f in BAND_FRACTIONS), key=lambda g: g[0])
    size, cell, shape, window, span, order, start = best
    if size >= count:
      return full
    return NearbyIndex(count, reach, origin, cell, shape, window, span,
                       jp.asarray(order), jp.asarray(start))

  def near(self, world, xy: jax.Array) -> jax.Array:
    """Ids (size,) int32, ascending, of world `world`'s points within `reach` of xy (2,)
    in x and y, and `count` in the unused entries."""
    if self.everything:
      return jp.arange(self.count, dtype=jp.int32)
    (ny, nx), (wy, wx) = self.shape, self.window
    ix = jp.floor((xy[0] - self.reach - self.origin[0]) / self.cell[0]).astype(jp.int32)
    iy = jp.floor((xy[1] - self.reach - self.origin[1]) / self.cell[1]).astype(jp.int32)
    ix, iy = jp.clip(ix, 0, nx - wx), jp.clip(iy, 0, ny - wy)
    first = (iy + jp.arange(wy)) * nx + ix  # (wy,) first cell of each run
    lo, hi = self.start[world, first], self.start[world, first + wx]
    at = lo[:, None] + jp.arange(self.span)  # (wy, span) within the padded order
    ids = jp.where(at < hi[:, None], self.order[world, at], self.count)
    return jp.sort(ids.reshape(-1))  # the points' own order: lax.top_k breaks ties by it


def _layout(xy, keep, origin, cell, reach):
  """(ids per query, cell, shape, window, span, order (Wd, N + span), start
  (Wd, cells + 1)) of the grid with cells `cell` (x, y) m."""
  pts = xy[keep]
  nx = int(math.floor((pts[:, 0].max() - origin[0]) / cell[0])) + 1
  ny = int(math.floor((pts[:, 1].max() - origin[1]) / cell[1])) + 1
  # a query's cells run from floor((q - reach) / c) to floor((q + reach) / c): at most
  wx, wy = (min(n, math.ceil(2 * reach / c) + 1) for n, c in ((nx, cell[0]), (ny, cell[1])))
  ix = np.clip(np.floor((xy[..., 0] - origin[0]) / cell[0]), 0, nx - 1).astype(np.int64)
  iy = np.clip(np.floor((xy[..., 1] - origin[1]) / cell[1]), 0, ny - 1).astype(np.int64)
  cellid = np.where(keep, iy * nx + ix, ny * nx)  # points never returned sort last
  worlds, points = keep.shape
  counts = np.stack([np.bincount(c[k], minlength=ny * nx) for c, k in zip(cellid, keep)])
  start = np.concatenate([np.zeros((worlds, 1), np.int64), np.cumsum(counts, 1)], 1)
  first = np.arange(ny)[:, None] * nx + np.arange(nx - wx + 1)  # every run a query reads
  span = int((start[:, first + wx] - start[:, first]).max())
  order = np.full((worlds, points + span), points, np.int32)
  for w in range(worlds):
    order[w, :keep[w].sum()] = np.argsort(cellid[w], kind="stable")[:keep[w].sum()]
  return wy * span, cell, (ny, nx), (wy, wx), span, order, start.astype(np.int32)
