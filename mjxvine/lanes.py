"""The lanes of a pool of worlds as arrays for the jit-compiled env (`mjxvine.env`), and the
lane frame at a point: nearest centreline sample, tangent, lateral offset (m)."""

from __future__ import annotations

from typing import Sequence

import jax
import jax.numpy as jp
import numpy as np

from mjxvine.angles import wrap
from mjxvine.worlds import Vineyard

LANE_DIST_SCALE_M = 10.0  # `LaneTable.lane_state`'s distance to the row's end is in these
MIRROR_LANE_SIGN = (-1.0, -1.0, 1.0)  # `LaneTable.lane_state` mirrored left-right

REFERENCE_ROW_M = 24.0  # the paper's test rows, which its protocol drives in 700 steps


def lane_steps(max_steps: int, length_m: float) -> int:
  """The episode limit (control steps) on a lane `length_m` long (its x extent): `max_steps`
  for rows up to 24 m, in proportion beyond (the paper's 700 steps per 24 m make 2917 for
  a 100 m row: the same 0.34 m/s)."""
  return max(int(max_steps), int(np.ceil(max_steps * length_m / REFERENCE_ROW_M - 1e-6)))


class LaneTable:
  """Lanes of every pool world, padded to common counts: centerlines (Wd, L, K, 2) m (a lane
  of fewer samples repeats its last one), samples per lane (Wd, L), the x extent of each
  lane (Wd, L) m, lane widths (Wd, L) m and lane counts (Wd,).

  `uniform`: every lane has the same samples and x extent (generated pools): then
  `length_m` and `samples` are static numbers too (`static_length_m`, `static_samples`).
  `max_steps` (Wd, L): each lane's episode limit (`lane_steps` of `max_steps`), static
  (`static_max_steps`) where every lane has the same."""

  def __init__(self, worlds: Sequence[Vineyard], max_steps: int = 700):
    num = max(len(w.lanes) for w in worlds)
    k = max(len(l.centerline) for w in worlds for l in w.lanes)
    lines = np.zeros((len(worlds), num, k, 2), np.float32)
    samples = np.zeros((len(worlds), num), np.int32)
    length = np.zeros((len(worlds), num), np.float64)
    width = np.zeros((len(worlds), num), np.float64)
    for i, w in enumerate(worlds):
      for j in range(num):
        lane = w.lanes[min(j, len(w.lanes) - 1)]  # padding lanes repeat the last one
        n = len(lane.centerline)
        lines[i, j, :n] = lane.centerline
        lines[i, j, n:] = lane.centerline[-1]
        samples[i, j] = n
        length[i, j] = lane.centerline[-1, 0] - lane.centerline[0, 0]
        width[i, j] = w.lane_width(lane)
    self.centerline = jp.asarray(lines)
    self.count = jp.asarray([len(w.lanes) for w in worlds], jp.int32)
    self.samples = jp.asarray(samples)
    self.length_m = jp.asarray(length, jp.float32)
    self.width_m = jp.asarray(width, jp.float32)
    lengths = {l.centerline[-1, 0] - l.centerline[0, 0] for w in worlds for l in w.lanes}
    self.uniform = bool(np.all(samples == k)) and len({round(x, 9) for x in lengths}) == 1
    # generated pools: their row length (a lane's x extent is exactly it)
    self.static_length_m = float(length.flat[0]) if self.uniform else None
    self.static_samples = k if self.uniform else None
    limits = np.vectorize(lambda x: lane_steps(max_steps, x))(length).astype(np.int32)
    self.max_steps = jp.asarray(limits)
    self.static_max_steps = int(limits.flat[0]) if np.all(limits == limits.flat[0]) else None

  def steps_limit(self, world, lane):
    """The episode limit (control steps) of lane `lane` of pool world `world`."""
    if self.static_max_steps is not None:
      return self.static_max_steps
    return self.max_steps[world, lane]

  def lane(self, world, lane):
    """(centerline (K, 2), samples, x extent m, width m) of lane `lane` (0-based) of pool
    world `world`; samples and extent static where `uniform`."""
    if self.uniform:
      return (self.centerline[world, lane], self.static_samples, self.static_length_m,
              self.width_m[world, lane])
    return (self.centerline[world, lane], self.samples[world, lane],
            self.length_m[world, lane], self.width_m[world, lane])

  def lane_state(self, pose: dict, xy: jax.Array, yaw: jax.Array) -> jax.Array:
    """(3,) float32, what privileged critics read (`sac.privileged_critics`), never the
    actor: [lateral offset / half lane width, heading error (rad) against the lane's
    tangent, distance to the row's end / 10 m] of a robot at `xy` (m), `yaw` (rad) on the
    episode's lane (`pose`: world, lane, direction, eor)."""
    line, k, _, width = self.lane(pose["world"], pose["lane"])
    _, tangent, lateral, _ = lane_frame(line, xy, pose["direction"], k)
    heading_err = wrap(yaw - jp.arctan2(tangent[1], tangent[0]))
    dist = jp.linalg.norm(xy - pose["eor"])
    return jp.stack([lateral / (width / 2), heading_err, dist / LANE_DIST_SCALE_M]
                    ).astype(jp.float32)


def lane_frame(line: jax.Array, p: jax.Array, direction: jax.Array, samples=None):
  """Nearest centerline sample to p (2,) and the lane frame there for a travel direction.
  `samples`: how many of `line`'s samples are the lane's (default all; the rest repeat the
  last one, so the nearest is never past it).

  Returns (index, tangent (2,) in the travel direction, lateral offset m (left +),
  along-lane coordinate of p m).
  """
  i = jp.argmin(jp.sum((line - p) ** 2, -1))
  k = line.shape[0] if samples is None else samples
  a, b = line[jp.clip(i - 1, 0, k - 2)], line[jp.clip(i + 1, 1, k - 1)]
  t = (b - a) / (jp.linalg.norm(b - a) + 1e-9) * direction
  rel = p - line[i]
  lateral = t[0] * rel[1] - t[1] * rel[0]
  return i, t, lateral, rel @ t


def point_ahead(line: jax.Array, index: jax.Array, direction: jax.Array,
                samples: int, count=None) -> jax.Array:
  """The centerline sample `samples` samples after `index` in the travel direction (2,),
  clipped to the lane's ends (past the EoR it stays at the last sample); `count`: the
  lane's own samples of `line` (default all)."""
  ahead = jp.where(direction > 0, samples, -samples)
  last = line.shape[0] - 1 if count is None else count - 1
  return line[jp.clip(index + ahead, 0, last)]
