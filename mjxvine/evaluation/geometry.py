"""Lane geometry in numpy, for the evaluation's metrics and videos: distances and signed
offsets of points to a lane's centreline, arc lengths and how far a run got along a lane.

A centreline is a polyline `line` (k, 2) of x, y points (m) from the lane's start
(forward, "F") to its end; reverse runs ("R") travel it from line[-1]. These are the
closest points on the polyline's segments; the env's JAX lane frame
(`mjxvine.env.lane_frame`) uses the nearest sample, which agrees within the sampling's
curvature error (tests/test_geometry.py).
"""

from __future__ import annotations

import numpy as np


def _closest(points: np.ndarray, line: np.ndarray):
  """For points (n, 2) and the polyline `line` (k, 2): the distances (n,) (m) to the line,
  the index (n,) of the closest segment and the fraction (n,) along it."""
  a, b = line[:-1], line[1:]
  ab = b - a
  t = np.clip(np.einsum("nkd,kd->nk", points[:, None] - a, ab) / np.sum(ab * ab, -1), 0, 1)
  dist = np.linalg.norm(points[:, None] - (a + t[..., None] * ab), axis=-1)
  seg = np.argmin(dist, axis=1)
  rows = np.arange(len(points))
  return dist[rows, seg], seg, t[rows, seg]


def distance_to_line(points: np.ndarray, line: np.ndarray) -> np.ndarray:
  """Distance (m) of each point (n, 2) to the polyline `line` (k, 2): (n,)."""
  return _closest(points, line)[0]


def arc_length(line: np.ndarray) -> float:
  """Length (m) of the polyline `line` (k, 2)."""
  return float(np.linalg.norm(np.diff(line, axis=0), axis=1).sum())


def along_line(points: np.ndarray, line: np.ndarray) -> np.ndarray:
  """Arc-length coordinate (m, from line[0]) of the closest point of `line` (k, 2) to each
  point (n, 2): (n,), in [0, arc_length(line)]."""
  _, seg, t = _closest(points, line)
  lengths = np.linalg.norm(np.diff(line, axis=0), axis=1)
  return np.concatenate([[0.0], np.cumsum(lengths)])[seg] + t * lengths[seg]


def lane_progress(xy: np.ndarray, line: np.ndarray, direction: str) -> float:
  """How far (m) a trajectory xy (n, 2) got along the lane centreline `line` (k, 2), from
  the lane's start in its travel direction ("F": from line[0], "R": from line[-1]): the
  along-lane coordinate of its furthest point, in [0, arc_length(line)]."""
  if len(xy) == 0:
    return 0.0
  s = along_line(xy, line)
  return float(s.max() if direction == "F" else arc_length(line) - s.min())


def trajectory_errors(xy: np.ndarray, line: np.ndarray) -> np.ndarray:
  """Distances (m) to the ground-truth line (k, 2) of the points of the trajectory xy
  (n, 2) inside the row (their x within the line's x extent): (m,), m <= n."""
  inside = (xy[:, 0] >= line[0, 0]) & (xy[:, 0] <= line[-1, 0])
  return distance_to_line(xy[inside], line) if inside.any() else np.zeros(0)


def signed_offsets(points: np.ndarray, line: np.ndarray, direction: str) -> np.ndarray:
  """Lateral offset (m) of points (n, 2) from the polyline `line` (k, 2), positive on the
  left of the travel direction ("F": along the line, "R": against it): (n,)."""
  dist, seg, _ = _closest(points, line)
  tangent = line[seg + 1] - line[seg]
  rel = points - line[seg]
  side = np.sign(tangent[:, 0] * rel[:, 1] - tangent[:, 1] * rel[:, 0])
  return dist * side * (1.0 if direction == "F" else -1.0)
