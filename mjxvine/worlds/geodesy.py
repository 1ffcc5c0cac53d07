"""WGS84 longitude/latitude and the local tangent plane (east, north, metres).

Local frame: the tangent plane at the origin on the WGS84 ellipsoid (a = 6378137 m,
f = 1/298.257223563): geodetic -> ECEF -> ENU, exact, the up component dropped; x east,
y north, metres. Positions are taken on the ellipsoid (altitude 0). Its error against the
true 3-D distances (ECEF chords; `tangent_plane_error_m`, kept in
`world.frame["tangent_plane_error_m"]`) is r^3 / (8 R^2) between the origin and a point r
from it (R the Earth's radius of curvature there), at most 32/27 of that between any two
points within r: measured (tests/test_vineyard_files.py, rows across a disc at lat 44.7)
3.1e-6 m over a block of radius 1 km and 3.9e-4 m over 5 km, far under a plant's
jitter. Dropping the altitude h matters more, if still little: a block at h is
(1 + h / R) larger than on the ellipsoid, 4.7e-5 per 300 m (4 mm over a 90 m row).
"""

from __future__ import annotations

import numpy as np

WGS84_A = 6378137.0  # semi-major axis (m)
WGS84_F = 1 / 298.257223563  # flattening
WGS84_E2 = WGS84_F * (2 - WGS84_F)  # first eccentricity squared


def ecef(lonlat) -> np.ndarray:
  """Points (..., 2) of longitude, latitude (degrees) on the ellipsoid as ECEF (..., 3), m."""
  lonlat = np.asarray(lonlat, np.float64)
  lon, lat = np.deg2rad(lonlat[..., 0]), np.deg2rad(lonlat[..., 1])
  n = WGS84_A / np.sqrt(1 - WGS84_E2 * np.sin(lat) ** 2)  # prime vertical radius
  return np.stack([n * np.cos(lat) * np.cos(lon), n * np.cos(lat) * np.sin(lon),
                   n * (1 - WGS84_E2) * np.sin(lat)], -1)


def _enu_axes(origin) -> np.ndarray:
  """(3, 3): the unit east, north and up vectors (rows, ECEF) at `origin` (lon, lat deg)."""
  lon, lat = np.deg2rad(np.asarray(origin, np.float64))
  sl, cl, sp, cp = np.sin(lon), np.cos(lon), np.sin(lat), np.cos(lat)
  return np.array([[-sl, cl, 0.0], [-sp * cl, -sp * sl, cp], [cp * cl, cp * sl, sp]])


def _geodetic(xyz: np.ndarray) -> np.ndarray:
  """ECEF points (n, 3), m, as (n, 3) longitude, latitude (degrees), ellipsoidal height
  (m). Fixed-point iteration on the latitude: converges to 1e-15 rad within a few steps
  for points near the surface."""
  x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
  p = np.hypot(x, y)
  lat = np.arctan2(z, p * (1 - WGS84_E2))
  for _ in range(20):
    s = np.sin(lat)
    root = np.sqrt(1 - WGS84_E2 * s ** 2)
    h = p * np.cos(lat) + z * s - WGS84_A * root  # exact for any latitude, poles too
    n = WGS84_A / root
    new = np.arctan2(z, p * (1 - WGS84_E2 * n / (n + h)))
    done = np.max(np.abs(new - lat), initial=0.0) < 1e-15
    lat = new
    if done:
      break
  s = np.sin(lat)
  h = p * np.cos(lat) + z * s - WGS84_A * np.sqrt(1 - WGS84_E2 * s ** 2)
  return np.stack([np.rad2deg(np.arctan2(y, x)), np.rad2deg(lat), h], -1)


def lonlat_to_local(lonlat, origin) -> np.ndarray:
  """Points (n, 2) of longitude, latitude (degrees, WGS84, on the ellipsoid) as (n, 2)
  east, north (m) in the tangent plane at `origin` (lon, lat degrees)."""
  d = ecef(np.asarray(lonlat, np.float64).reshape(-1, 2)) - ecef(origin)
  return d @ _enu_axes(origin)[:2].T


def local_to_lonlat(xy, origin) -> np.ndarray:
  """The inverse of `lonlat_to_local`: east, north (n, 2), m, in the tangent plane at
  `origin` as (n, 2) longitude, latitude (degrees) of the points of the ellipsoid below
  or above them (the up component solved for; round trip well under 1e-6 m within 5 km)."""
  xy = np.asarray(xy, np.float64).reshape(-1, 2)
  axes, o = _enu_axes(origin), ecef(origin)
  up = -(xy ** 2).sum(1) / (2 * WGS84_A)  # the sphere's drop: a close first guess
  for _ in range(20):
    geo = _geodetic(o + xy @ axes[:2] + up[:, None] * axes[2])
    # the height is measured along the local normal, within r / R of the origin's up
    up = up - geo[:, 2]
    if np.max(np.abs(geo[:, 2]), initial=0.0) < 1e-10:
      break
  lon = (geo[:, 0] + 180.0) % 360.0 - 180.0
  return np.stack([lon, geo[:, 1]], -1)


def tangent_plane_error_m(rows_lonlat, origin) -> float:
  """The largest difference (m) between a distance in the tangent plane at `origin` and
  the true 3-D (ECEF chord) distance, over the pairs (origin, each point) and (consecutive
  points of each row). `rows_lonlat`: one (n, 2) array of longitude, latitude (degrees),
  taken as one row, or a sequence of them (rows)."""
  if isinstance(rows_lonlat, np.ndarray) and rows_lonlat.ndim == 2:
    rows_lonlat = [rows_lonlat]
  o = ecef(origin)
  worst = 0.0
  for row in rows_lonlat:
    row = np.asarray(row, np.float64).reshape(-1, 2)
    plane, true = lonlat_to_local(row, origin), ecef(row)
    err = np.abs(np.linalg.norm(plane, axis=1) - np.linalg.norm(true - o, axis=1))
    steps = np.abs(np.linalg.norm(np.diff(plane, axis=0), axis=1)
                   - np.linalg.norm(np.diff(true, axis=0), axis=1))
    worst = max(worst, float(err.max(initial=0.0)), float(steps.max(initial=0.0)))
  return worst


# --- reading ------------------------------------------------------------------------------
