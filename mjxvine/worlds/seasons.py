"""What a vineyard looks like by season (docs/environment.md, Seasons): trellis posts,
cordons, canopy lobes, shoots and lane-floor tufts around a world's plant rows, in numpy.

`dress(world, cfg)` gives `world` the look of its season (`world.season` of the config; a
vineyard file may name its own):
- classic: the world as it is, a trunk and one canopy ellipsoid per plant (the paper's);
- spring: trunks up to the cordon, the cordon along the row, a few small lobes on it;
- summer: trunks up to the cordon, a wall of canopy lobes from the cordon to the canopy's
  top, shoots hanging into the lanes;
- winter: bare trunks up to the cordon and the cordon;
- mixed: each world one of spring, summer and winter, drawn from its seed.
Every season but classic adds the trellis posts (line posts every `post_spacing_m` along
a row, anchor posts beyond both ends) and the lane floor's tufts (`tuft_density_per_m2`).
The trunks of those seasons reach the cordon, at `cordon_height_m` (drawn per row).

All of it is drawn from its own random stream, (seed, kind, `STREAM`), beside the
layout's: a world's rows, plants, gaps and terrain are the same in every season, and the
same (world, config) gives the same dressing bit for bit. Heights are above the ground at
each shape's (x, y); `mjxvine.worlds.build` puts them on the terrain.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from mjxvine.config import WorldConfig

SEASONS = ("classic", "spring", "summer", "winter")  # what a world's plants look like
DRAWN_SEASONS = ("spring", "summer", "winter")  # those that `mixed` draws from
SHAPE_TABLES = ("cordons", "lobes", "shoots", "tufts")  # (n, 10) tables of a `Vineyard`
SCENERY_FIELDS = ("season", "post_xy", "post_height", "post_radius", *SHAPE_TABLES)
REALISM_KEYS = ("season", "post_spacing_m", "post_height_m", "cordon_height_m",
                "canopy_lobes", "shoots_per_plant", "shoot_reach_m", "tuft_density_per_m2")

STREAM = 3  # the dressing's random stream: [seed, kind, STREAM] (the layout's: [seed, kind])
KIND_STREAM = {"train": 0, "test": 1, "file": 2}

# Trellis (docs/environment.md, Seasons, for the sources): line posts about 8 cm across,
# anchor (end) posts 10-15 cm, the anchor half a plant spacing beyond the row's end plant.
LINE_POST_RADIUS_M = 0.04
ANCHOR_POST_RADIUS_M = 0.06
ANCHOR_GAP_SPACINGS = 0.5
CORDON_RADIUS_M = 0.035  # a cordon arm, 6-8 cm across
# Canopy: summer lobes span the canopy's height by these fractions (semi-axis up) and the
# plant spacing by these over the lobe count (semi-axis along the row); spring lobes are
# small, just above the cordon.
SUMMER_LOBE_UP = (0.3, 0.5)
SUMMER_LOBE_ALONG = (0.7, 1.1)
SUMMER_LOBE_ACROSS = (0.7, 1.0)  # of the canopy's half width
SPRING_LOBE_M = ((0.05, 0.12), (0.04, 0.09), (0.05, 0.12))  # semi-axes along, across, up
SPRING_LOBE_RISE_M = (0.05, 0.3)  # lobe centre above the cordon
# Shoots: thin ellipsoids (a shoot with its leaves, as a depth camera sees it) from inside
# the canopy's side, down into the lane at this angle below the horizontal.
SHOOT_RADIUS_M = 0.03
SHOOT_DROOP_DEG = (15.0, 60.0)
SHOOT_BASE_UP = (0.5, 0.95)  # base height, fraction of the canopy from the cordon up
# Tufts: ellipsoids centred on the ground (a dome of their semi-axis up shows).
TUFT_HALF_M = (0.04, 0.12)
TUFT_HEIGHT_M = (0.03, 0.12)
TUFT_ROW_CLEARANCE_M = 0.15  # tufts keep this far from the row lines
MIN_CANOPY_M = 0.1  # a canopy is at least this tall above the cordon


def classic_config(cfg: WorldConfig) -> WorldConfig:
  """`cfg` with the realism keys at their defaults: the config of the classic layout that
  every season of `cfg` dresses."""
  defaults = WorldConfig()
  return dataclasses.replace(cfg, **{k: getattr(defaults, k) for k in REALISM_KEYS})


def dress(world, cfg: WorldConfig, *, season: str | None = None,
          post_spacing_m: tuple[float, float] | None = None,
          given_trunks: np.ndarray | None = None):
  """`world` (a classic `layout.Vineyard`) dressed for `season` (default `cfg.season`;
  `mixed` draws one), posts every `post_spacing_m` (range, m; default the config's);
  `given_trunks` (P,) bool: plants whose trunk height a vineyard file gave (kept as the
  cordon's height there). A classic season, or a world already dressed (a saved one),
  returns `world` itself."""
  season = cfg.season if season is None else season
  if season == "classic" or world.season != "classic":
    return world
  rng = np.random.default_rng([world.seed, KIND_STREAM[world.kind], STREAM])
  if season == "mixed":
    season = DRAWN_SEASONS[int(rng.integers(len(DRAWN_SEASONS)))]
  if season not in DRAWN_SEASONS:
    raise ValueError(f"season {season!r}: one of {', '.join(SEASONS)} or mixed")
  heading, spacing = row_directions(world)
  cordon = rng.uniform(*cfg.cordon_height_m, world.num_rows)[world.plant_row]
  if given_trunks is not None:
    cordon = np.where(given_trunks, world.trunk_height, cordon)
  top = np.maximum(world.canopy_z + world.canopy_half[:, 2], cordon + MIN_CANOPY_M)
  width = 2 * world.canopy_half[:, 0]
  half = world.canopy_half.copy()
  half[:, 2] = (top - cordon) / 2
  post_xy, post_radius = posts(world, rng, cfg.post_spacing_m if post_spacing_m is None
                               else post_spacing_m)
  post_height = rng.uniform(*cfg.post_height_m, len(post_xy))
  empty = np.zeros((0, 10))
  cordons = _cordons(world, heading, spacing, cordon) if season != "summer" else empty
  if season == "summer":
    lobes = _summer_lobes(world, rng, cfg, heading, spacing, cordon, top, width)
    shoots = _shoots(world, rng, cfg, heading, spacing, cordon, top, width)
  elif season == "spring":
    lobes, shoots = _spring_lobes(world, rng, cfg, heading, spacing, cordon), empty
  else:
    lobes = shoots = empty
  return dataclasses.replace(
      world, season=season, trunk_height=cordon, canopy_half=half,
      canopy_z=(top + cordon) / 2, post_xy=post_xy, post_height=post_height,
      post_radius=post_radius, cordons=cordons, lobes=lobes, shoots=shoots,
      tufts=tufts(world, rng, cfg.tuft_density_per_m2))


def moved(world, offset) -> dict:
  """The scenery fields of `world` moved by `offset` (2,) m in x, y (for
  `dataclasses.replace`)."""
  d = np.asarray(offset, np.float64)
  out = {"post_xy": world.post_xy + d}
  for name in SHAPE_TABLES:
    table = getattr(world, name).copy()
    table[:, :2] += d
    out[name] = table
  return out


def row_directions(world) -> tuple[np.ndarray, np.ndarray]:
  """Per plant (P,): its row's direction (rad; central differences of the row's plants
  in order along x) and its spacing (m; the shorter of its gaps to its row neighbours: a
  wide gap beside it is missing plants)."""
  n = len(world.plant_xy)
  heading, spacing = np.zeros(n), np.full(n, float(world.spacing_m))
  for ids in _row_order(world):
    if len(ids) < 2:
      continue
    p = world.plant_xy[ids]
    d = np.gradient(p, axis=0)
    heading[ids] = np.arctan2(d[:, 1], d[:, 0])
    gaps = np.linalg.norm(np.diff(p, axis=0), axis=1)
    spacing[ids] = np.minimum(np.concatenate([gaps[:1], gaps]), np.concatenate([gaps, gaps[-1:]]))
  return heading, spacing


def _row_order(world) -> list[np.ndarray]:
  """Plant ids of each row, in order along x."""
  out = []
  for j in range(world.num_rows):
    ids = np.flatnonzero(world.plant_row == j)
    out.append(ids[np.argsort(world.plant_xy[ids, 0], kind="stable")])
  return out


def posts(world, rng: np.random.Generator, spacing_m) -> tuple[np.ndarray, np.ndarray]:
  """Trellis posts of every row: (Q, 2) positions and (Q,) radii (m). Anchor posts
  `ANCHOR_GAP_SPACINGS` plant spacings beyond both end plants, on the row's line; line
  posts every s (drawn from `spacing_m` once per world) of the row's length from its
  first anchor, each midway between the two plants around it (never on a trunk), none
  within s / 2 of the far anchor. None where `spacing_m` is [0, 0]."""
  if spacing_m[1] <= 0:
    return np.zeros((0, 2)), np.zeros(0)
  step = float(rng.uniform(*spacing_m))
  gap = ANCHOR_GAP_SPACINGS * world.spacing_m
  xy, radius = [], []
  for ids in _row_order(world):
    p = world.plant_xy[ids]
    if len(p) < 2:
      continue
    first, last = p[1] - p[0], p[-1] - p[-2]
    xy += [p[0] - gap * first / np.linalg.norm(first), p[-1] + gap * last / np.linalg.norm(last)]
    radius += [ANCHOR_POST_RADIUS_M] * 2
    along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    at = np.arange(1, int((along[-1] + 2 * gap) / step) + 1) * step - gap
    at = at[(at > 0) & (at < along[-1]) & (at < along[-1] + gap - step / 2)]
    bay = np.unique(np.searchsorted(along, at, side="right") - 1)
    xy += list((p[bay] + p[bay + 1]) / 2)
    radius += [LINE_POST_RADIUS_M] * len(bay)
  return np.asarray(xy, np.float64).reshape(-1, 2), np.asarray(radius, np.float64)


def _table(xy, z, size, quat) -> np.ndarray:
  """Shape table rows (n, 10): [x, y, z, size (3), quat (4)]."""
  return np.concatenate([np.asarray(xy).reshape(-1, 2), np.asarray(z).reshape(-1, 1),
                         np.asarray(size).reshape(-1, 3), np.asarray(quat).reshape(-1, 4)], 1)


def yaw_pitch_quat(yaw, pitch) -> np.ndarray:
  """Quaternions (n, 4) [w, x, y, z] of a yaw about z (rad) after a pitch about the
  body's y (rad; positive turns +x down)."""
  cy, sy = np.cos(np.asarray(yaw) / 2), np.sin(np.asarray(yaw) / 2)
  cp, sp = np.cos(np.asarray(pitch) / 2), np.sin(np.asarray(pitch) / 2)
  return np.stack(np.broadcast_arrays(cy * cp, -sy * sp, cy * sp, sy * cp), -1)


def _along_across(world, plant, heading, along, across) -> np.ndarray:
  """Points (n, 2) at `along` / `across` (m) from plants `plant` in their rows' frame."""
  c, s = np.cos(heading[plant]), np.sin(heading[plant])
  return world.plant_xy[plant] + np.stack([along * c - across * s, along * s + across * c], -1)


def _cordons(world, heading, spacing, cordon) -> np.ndarray:
  """A cylinder per plant along its row at the cordon's height, spanning its spacing."""
  n = len(world.plant_xy)
  size = np.stack([np.full(n, CORDON_RADIUS_M), spacing / 2, np.zeros(n)], -1)
  return _table(world.plant_xy, cordon, size, yaw_pitch_quat(heading, np.pi / 2))


def _per_plant(rng: np.random.Generator, counts: tuple[int, int], n: int):
  """(plant id, index within the plant, count of the plant) of a count drawn per plant."""
  k = rng.integers(counts[0], counts[1] + 1, n)
  plant = np.repeat(np.arange(n), k)
  index = np.arange(len(plant)) - np.repeat(np.cumsum(k) - k, k)
  return plant, index, k[plant]


def _summer_lobes(world, rng, cfg: WorldConfig, heading, spacing, cordon, top, width):
  """`canopy_lobes` ellipsoids per plant, spread along its spacing (stratified), each a
  fraction of the canopy's height tall, from the cordon to the canopy's top: a wall."""
  plant, m, k = _per_plant(rng, cfg.canopy_lobes, len(world.plant_xy))
  n = len(plant)
  s, tall = spacing[plant], (top - cordon)[plant]
  along = ((m + rng.uniform(0.2, 0.8, n)) / k - 0.5) * s
  across = width[plant] * rng.uniform(-0.1, 0.1, n)
  up = tall * rng.uniform(*SUMMER_LOBE_UP, n)
  size = np.stack([s / k * rng.uniform(*SUMMER_LOBE_ALONG, n),
                   width[plant] / 2 * rng.uniform(*SUMMER_LOBE_ACROSS, n), up], -1)
  z = cordon[plant] + up + (tall - 2 * up) * rng.uniform(0, 1, n)
  yaw = heading[plant] + rng.uniform(-0.2, 0.2, n)
  return _table(_along_across(world, plant, heading, along, across), z, size,
                yaw_pitch_quat(yaw, 0.0))


def _spring_lobes(world, rng, cfg: WorldConfig, heading, spacing, cordon):
  """`canopy_lobes` small ellipsoids per plant just above the cordon, anywhere along its
  spacing: the first leaves."""
  plant, _, _ = _per_plant(rng, cfg.canopy_lobes, len(world.plant_xy))
  n = len(plant)
  along = rng.uniform(-0.5, 0.5, n) * spacing[plant]
  across = rng.uniform(-0.05, 0.05, n)
  size = np.stack([rng.uniform(*r, n) for r in SPRING_LOBE_M], -1)
  z = cordon[plant] + rng.uniform(*SPRING_LOBE_RISE_M, n)
  yaw = heading[plant] + rng.uniform(-0.5, 0.5, n)
  return _table(_along_across(world, plant, heading, along, across), z, size,
                yaw_pitch_quat(yaw, 0.0))


def _shoots(world, rng, cfg: WorldConfig, heading, spacing, cordon, top, width):
  """`shoots_per_plant` thin ellipsoids per plant from inside the canopy's side (either
  side) out and down, `shoot_reach_m` beyond the side: shoots before hedging."""
  plant, _, _ = _per_plant(rng, cfg.shoots_per_plant, len(world.plant_xy))
  n = len(plant)
  side = rng.choice([-1.0, 1.0], n)
  along = rng.uniform(-0.5, 0.5, n) * spacing[plant]
  base = cordon[plant] + (top - cordon)[plant] * rng.uniform(*SHOOT_BASE_UP, n)
  start = width[plant] / 4  # inside the canopy: no seam at its side
  out = width[plant] / 2 - start + rng.uniform(*cfg.shoot_reach_m, n)
  droop = np.deg2rad(rng.uniform(*SHOOT_DROOP_DEG, n))
  length = out / np.cos(droop)
  xy = _along_across(world, plant, heading, along, side * (start + out / 2))
  z = base - length / 2 * np.sin(droop)
  size = np.stack([length / 2, np.full(n, SHOOT_RADIUS_M), np.full(n, SHOOT_RADIUS_M)], -1)
  return _table(xy, z, size, yaw_pitch_quat(heading[plant] + side * np.pi / 2, droop))


def tufts(world, rng: np.random.Generator, density_per_m2: float) -> np.ndarray:
  """Grass and weed tufts on every lane's floor: a Poisson number of `density_per_m2` per
  m^2 of the lane (its length times its width less `TUFT_ROW_CLEARANCE_M` each side),
  uniform over it, each an ellipsoid centred on the ground, yawed at random."""
  parts = []
  for lane in world.lanes if density_per_m2 > 0 else ():
    line = lane.centerline
    half = world.lane_width(lane) / 2 - TUFT_ROW_CLEARANCE_M
    length = line[-1, 0] - line[0, 0]
    if half <= 0 or length <= 0:
      continue
    n = int(rng.poisson(density_per_m2 * length * 2 * half))
    x = rng.uniform(line[0, 0], line[-1, 0], n)
    y = np.interp(x, line[:, 0], line[:, 1]) + rng.uniform(-half, half, n)
    size = np.concatenate([rng.uniform(*TUFT_HALF_M, (n, 2)),
                           rng.uniform(*TUFT_HEIGHT_M, (n, 1))], 1)
    parts.append(_table(np.stack([x, y], -1), np.zeros(n), size,
                        yaw_pitch_quat(rng.uniform(-np.pi, np.pi, n), 0.0)))
  return np.concatenate(parts) if parts else np.zeros((0, 10))
