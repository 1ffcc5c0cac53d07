"""Procedural vineyard layouts (docs/design.md, World layout): plant rows, lanes and
terrain, in numpy.

Frame: rows run along +x from x = 0 to x = length; row j lies near y = j * inter_row,
shifted so that the vineyard is centred on y = 0. A lane is the strip between two
adjacent plant rows; lane k (1-based, as in the paper's test figure) lies between rows
k - 1 and k. Its forward End of Row (EoR) is at the +x end, its reverse EoR at x = 0.

Everything is drawn from one `numpy.random.Generator` seeded by `seed`, so the same
(kind, seed, config) gives the same world bit for bit.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from mjxvine.config import WorldConfig
from mjxvine.robot_files import escaped, short_repr
from mjxvine.worlds.seasons import SCENERY_FIELDS, SEASONS, SHAPE_TABLES, dress

TEST_LANE_SHAPES = ("straight", "straight", "hybrid", "curved", "curved")
CENTERLINE_STEP_M = 0.25  # sampling of lane centerlines
TRUNK_RADIUS_M = 0.04  # every trunk's radius (m)
CURVE_AMPLITUDE_M = 0.7  # lateral wander of curved rows (m)
JITTER_FRAC = 0.1  # plant position jitter, a fraction of the spacing (triangular)


@dataclasses.dataclass(frozen=True)
class Lane:
  """A lane between two plant rows. `centerline` is (K, 2) metres, ordered along +x, one
  sample every `CENTERLINE_STEP_M` of x or less. `width_m`: the distance between its two
  rows (m; None: the world's `inter_row_m`, as in generated worlds)."""
  id: int
  shape: str
  left_row: int
  right_row: int
  centerline: np.ndarray
  eor_forward: np.ndarray  # (2,) the +x end of the centerline
  eor_reverse: np.ndarray  # (2,) the x = 0 end
  width_m: float | None = None


@dataclasses.dataclass(frozen=True)
class Vineyard:
  """One generated world. Plant arrays are (P,) or (P, k) over the plants that exist.
  (In every season but classic the trunks reach the cordon and the canopy arrays are the
  envelope of the canopy lobes, from the cordon to the canopy's top.)

  plant_xy: (P, 2) m; plant_yaw: (P,) rad; plant_row: (P,) int; trunk_height: (P,) m;
  canopy_half: (P, 3) ellipsoid semi-axes (m); canopy_z: (P,) canopy centre height (m).
  terrain: (nrow, ncol) heights in metres over the rectangle `terrain_extent`
  (xmin, xmax, ymin, ymax), row-major in y then x, as MuJoCo's heightfield stores it.
  """
  kind: str
  seed: int
  inter_row_m: float
  spacing_m: float
  length_m: float
  row_y0: np.ndarray           # (R,) nominal y of each row at its straight part
  plant_xy: np.ndarray
  plant_yaw: np.ndarray
  plant_row: np.ndarray
  trunk_height: np.ndarray
  trunk_radius: float
  canopy_half: np.ndarray
  canopy_z: np.ndarray
  lanes: tuple[Lane, ...]
  terrain: np.ndarray
  terrain_extent: tuple[float, float, float, float]
  # A world read from a vineyard file (`mjxvine.worlds.blocks`): where the block frame lies
  # in the file's frame (origin, heading, source); None for generated worlds.
  frame: dict | None = None
  # What the vineyard looks like (`mjxvine.worlds.seasons`); a "classic" world has only
  # the plants above. Posts: (Q, 2) m, (Q,) height above the ground (m), (Q,) radius (m).
  # Shape tables: (n, 10) rows [x, y, z above the ground at (x, y), MuJoCo geom size (3),
  # quaternion (4)], all in m: cordons (cylinders along the rows), canopy lobes and shoots
  # (ellipsoids), tufts (ellipsoids on the lane floor).
  season: str = "classic"
  post_xy: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 2)))
  post_height: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
  post_radius: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
  cordons: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 10)))
  lobes: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 10)))
  shoots: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 10)))
  tufts: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 10)))

  @property
  def num_rows(self) -> int:
    return len(self.row_y0)

  def rows(self) -> list[np.ndarray]:
    """Plant positions per plant row, (n_j, 2) each, gaps absent."""
    return [self.plant_xy[self.plant_row == j] for j in range(self.num_rows)]

  def to_json(self, robot: str | None = None) -> dict:
    """The world file's document (`save_world`; the worlds CLI's world.json), which
    `load_world` (so `--world FILE.json` of every command) reads back: every field, arrays
    as lists, exact; each lane's width (m) written out. `robot`: the robot the CLI built
    world.xml for, a note that `load_world` passes over."""
    d = {"kind": self.kind, "seed": int(self.seed), **({"robot": robot} if robot else {})}
    for f in dataclasses.fields(self):
      v = getattr(self, f.name)
      if f.name == "lanes":
        v = [{g.name: getattr(l, g.name) for g in dataclasses.fields(l)}
             | {"width_m": self.lane_width(l)} for l in v]
        v = [{k: (x.tolist() if isinstance(x, np.ndarray) else x) for k, x in l.items()}
             for l in v]
      elif f.name == "frame" and v is None:
        continue
      elif f.name in SCENERY_FIELDS and (v == "classic" if f.name == "season" else not len(v)):
        continue  # (a classic world's file is as it always was)
      d[f.name] = v.tolist() if isinstance(v, np.ndarray) else v
    return d

  def lane_width(self, lane: Lane) -> float:
    """The distance (m) between the two rows of `lane`."""
    return self.inter_row_m if lane.width_m is None else float(lane.width_m)


def _row_offsets(kind: str, num_rows: int, length: float, amplitude: float):
  """Lateral offset functions y_j(x) - y_j(0) of each row, for x in [0, length].

  Test world (6 rows): rows 0-2 straight; row 3 hybrid, H(x) = 0 for x < L/2 then a smooth
  half-cosine rise to A at x = L; rows 4-5 curved, H(x) + A sin^2(pi x / L). Lane 3 (rows
  2-3) is then straight-then-curved, lanes 4-5 curved (wander ~A), lanes 1-2 straight, and
  no lane is ever narrower than the drawn inter-row distance. Each shape is smooth enough
  for the fifth-order ground-truth fit (docs/design.md, Evaluation protocol).
  """
  def straight(x):
    return np.zeros_like(x)

  def hybrid(x):
    t = np.clip((x - length / 2) / (length / 2), 0.0, 1.0)
    return amplitude * (1 - np.cos(np.pi * t)) / 2

  def curved(x):
    return hybrid(x) + amplitude * np.sin(np.pi * x / length) ** 2

  if kind == "train":
    return [straight] * num_rows
  return [straight, straight, straight, hybrid, curved, curved]


def _varied_offsets(rng: np.random.Generator, num_rows: int, length: float,
                    amplitude: float):
  """Row offsets of a `train_layout: varied` train world: the test world's shapes,
  recombined per world. A bend that every row shares (straight, hybrid, sine or curved,
  either side, amplitude in [0, A]) keeps the lanes' width; on top of it each lane is,
  with probability 1/2, widened by a hybrid or sine bump of its far row (the widenings
  together at most A), as lanes 3 and 4 of the test world are. So rows stay within the
  terrain of `world_extent` and no lane is narrower than the drawn inter-row distance.
  """
  def shape(name, start):
    def f(x):
      t = np.clip((x - start) / (length - start), 0.0, 1.0)
      rise = (1 - np.cos(np.pi * t)) / 2  # 0 before `start`, smooth to 1 at the end
      sine = np.sin(np.pi * x / length) ** 2
      return {"straight": 0 * x, "hybrid": rise, "sine": sine, "curved": rise + sine}[name]
    return f

  names = ("straight", "hybrid", "sine", "curved")
  bend = shape(names[rng.integers(4)], rng.uniform(0.3, 0.7) * length)
  bend_a = rng.uniform(0.0, amplitude) * rng.choice([-1.0, 1.0])
  widen = [(shape(names[rng.integers(1, 3)], rng.uniform(0.3, 0.7) * length),
            rng.uniform(0.0, amplitude) * (rng.uniform() < 0.5))
           for _ in range(num_rows - 1)]
  total = sum(a for _, a in widen)
  scale = min(1.0, amplitude / total) if total > 0 else 0.0
  def row(j):
    return lambda x: bend_a * bend(x) + sum(scale * a * f(x) for f, a in widen[:j])
  return [row(j) for j in range(num_rows)]


TERRAIN_BUMP_M = 1.0  # grid of the terrain's random bumps
TERRAIN_CELL_M = 0.25  # heightfield resolution
TERRAIN_MARGIN_M = 4.0  # terrain beyond the outer plants
TERRAIN_AMPLITUDE_M = 0.05  # terrain bumps are +- this


def terrain_bumps(rng: np.random.Generator, extent) -> np.ndarray:
  """Heights (m) over `extent`: bumps of +- `TERRAIN_AMPLITUDE_M` on a `TERRAIN_BUMP_M` grid,
  bilinearly refined to `TERRAIN_CELL_M` cells."""
  xmin, xmax, ymin, ymax = extent
  ncol = int(round((xmax - xmin) / TERRAIN_CELL_M)) + 1
  nrow = int(round((ymax - ymin) / TERRAIN_CELL_M)) + 1
  bx = int(np.ceil((xmax - xmin) / TERRAIN_BUMP_M)) + 1
  by = int(np.ceil((ymax - ymin) / TERRAIN_BUMP_M)) + 1
  coarse = rng.uniform(-TERRAIN_AMPLITUDE_M, TERRAIN_AMPLITUDE_M, size=(by, bx))
  u = np.linspace(0, (xmax - xmin) / TERRAIN_BUMP_M, ncol)
  v = np.linspace(0, (ymax - ymin) / TERRAIN_BUMP_M, nrow)
  i0 = np.minimum(np.floor(v).astype(int), by - 2)
  j0 = np.minimum(np.floor(u).astype(int), bx - 2)
  fv, fu = (v - i0)[:, None], (u - j0)[None, :]
  c00 = coarse[i0][:, j0]
  c01 = coarse[i0][:, j0 + 1]
  c10 = coarse[i0 + 1][:, j0]
  c11 = coarse[i0 + 1][:, j0 + 1]
  h = c00 * (1 - fv) * (1 - fu) + c01 * (1 - fv) * fu + c10 * fv * (1 - fu) + c11 * fv * fu
  # MuJoCo rescales heightfield data to [0, 1]; pinning two far corners (in the margin,
  # never driven on) to -+amplitude makes that rescaling the identity for every world.
  h[0, 0], h[-1, -1] = -TERRAIN_AMPLITUDE_M, TERRAIN_AMPLITUDE_M
  return h


def slope_plane(shape: tuple[int, int], extent, slope_pct: float, cross_pct: float):
  """Heights (m) of a plane rising `slope_pct` % along +x and `cross_pct` % along +y, zero
  at the rectangle's centre, on the (nrow, ncol) grid over `extent`."""
  xmin, xmax, ymin, ymax = extent
  x = np.linspace(xmin, xmax, shape[1]) - (xmin + xmax) / 2
  y = np.linspace(ymin, ymax, shape[0]) - (ymin + ymax) / 2
  return slope_pct / 100 * x[None, :] + cross_pct / 100 * y[:, None]


def _pick_gaps(rng, kind, row_of_slot, x_index, n_per_row, num_rows, cfg: WorldConfig,
               varied=False):
  """Boolean mask of plants removed as gaps (test worlds and varied train worlds).

  Single gaps: 4 random plants away from the row ends. Wide gaps: consecutive plants in
  the middle half of a row. The test world has two of 2-3 plants, one in a row bounding
  lane 3 (row 3) and one bounding lane 5 (row 5, the outer row); a varied train world has
  one of `cfg.train_wide_gap_plants` plants in each of `cfg.train_wide_gap_rows` random rows.
  """
  removed = np.zeros(len(row_of_slot), bool)
  if (kind != "test" and not varied) or (varied and min(n_per_row) < 12):
    return removed  # (short varied rows, as in tests, keep every plant)
  if kind == "test":
    wide_rows, (lo, hi) = (3, 5), (2, 3)
  else:
    wide_rows = rng.choice(num_rows, cfg.train_wide_gap_rows, replace=False)
    lo, hi = cfg.train_wide_gap_plants
  for row in wide_rows:
    n = n_per_row[row]
    width = int(rng.integers(lo, hi + 1))
    start = int(rng.integers(n // 4, 3 * n // 4 - width))
    removed |= (row_of_slot == row) & (x_index >= start) & (x_index < start + width)
  singles = 0
  while singles < 4:
    row = int(rng.integers(0, num_rows))
    k = int(rng.integers(2, n_per_row[row] - 2))
    idx = np.flatnonzero((row_of_slot == row) & (x_index == k))[0]
    neighbours = (row_of_slot == row) & (np.abs(x_index - k) <= 1)
    if not removed[neighbours].any():
      removed[idx] = True
      singles += 1
  return removed


def generate_world(kind: str, seed: int, cfg: WorldConfig) -> Vineyard:
  """Generates the train or test vineyard of `seed` (pure function of its arguments),
  dressed for the config's season (`mjxvine.worlds.seasons`)."""
  if kind not in ("train", "test"):
    raise ValueError(f"kind must be 'train' or 'test', got {kind!r}")
  rng = np.random.default_rng([seed, 0 if kind == "train" else 1])
  num_rows = cfg.train_rows if kind == "train" else len(TEST_LANE_SHAPES) + 1
  length = cfg.train_length_m if kind == "train" else cfg.test_length_m
  inter_row = float(rng.uniform(*cfg.inter_row_m))
  spacing = float(rng.uniform(*cfg.spacing_m))
  varied = kind == "train" and cfg.train_layout == "varied"
  if varied:
    offsets = _varied_offsets(rng, num_rows, length, CURVE_AMPLITUDE_M)
  else:
    offsets = _row_offsets(kind, num_rows, length, CURVE_AMPLITUDE_M)
  row_y0 = (np.arange(num_rows) - (num_rows - 1) / 2) * inter_row

  n = int(np.floor(length / spacing)) + 1
  x_nom = np.arange(n) * spacing
  xs, ys, rows, kidx = [], [], [], []
  for j in range(num_rows):
    jitter = rng.triangular(-1, 0, 1, size=(n, 2)) * spacing * JITTER_FRAC
    x = x_nom + jitter[:, 0]
    xs.append(x)
    ys.append(row_y0[j] + offsets[j](x_nom) + jitter[:, 1])
    rows.append(np.full(n, j))
    kidx.append(np.arange(n))
  plant_xy = np.stack([np.concatenate(xs), np.concatenate(ys)], -1)
  plant_row = np.concatenate(rows)
  x_index = np.concatenate(kidx)
  num = len(plant_row)
  plant_yaw = rng.uniform(-np.pi, np.pi, num)
  trunk_height = rng.uniform(*cfg.trunk_height_m, num)
  canopy_top = rng.uniform(*cfg.canopy_top_m, num)
  canopy_half = np.stack([rng.uniform(*cfg.canopy_width_m, num) / 2,
                          rng.uniform(*cfg.canopy_width_m, num) / 2,
                          (canopy_top - trunk_height) / 2], -1)
  canopy_z = (canopy_top + trunk_height) / 2
  keep = ~_pick_gaps(rng, kind, plant_row, x_index, [n] * num_rows, num_rows, cfg,
                     varied)

  xy, row = plant_xy[keep], plant_row[keep]
  shapes = TEST_LANE_SHAPES if kind == "test" else (
      ("varied" if varied else "straight"),) * (num_rows - 1)
  lanes = tuple(Lane(k, shapes[k - 1], k - 1, k, *_centerline(xy, row, k, length))
                for k in range(1, num_rows))
  extent = world_extent(cfg)
  terrain = terrain_bumps(rng, extent)
  if cfg.slope_pct or cfg.cross_slope_pct:
    terrain = terrain + slope_plane(terrain.shape, extent, cfg.slope_pct, cfg.cross_slope_pct)
  classic = Vineyard(
      kind=kind, seed=int(seed), inter_row_m=inter_row, spacing_m=spacing, length_m=length,
      row_y0=row_y0, plant_xy=xy, plant_yaw=plant_yaw[keep],
      plant_row=row, trunk_height=trunk_height[keep],
      trunk_radius=TRUNK_RADIUS_M, canopy_half=canopy_half[keep],
      canopy_z=canopy_z[keep], lanes=lanes, terrain=terrain,
      terrain_extent=extent)
  return dress(classic, cfg)  # (its own random stream: the same layout in every season)


def _centerline(plant_xy, plant_row, lane, length):
  """Ground truth of a lane (docs/design.md, Evaluation protocol): midpoints of its two
  plant rows (each row linearly interpolated over x, so gaps are bridged), fitted with a
  fifth-order polynomial y(x). Returns (centerline (K, 2), eor_forward (2,),
  eor_reverse (2,))."""
  xc = np.linspace(0.0, length, int(round(length / CENTERLINE_STEP_M)) + 1)
  ys = []
  for j in (lane - 1, lane):
    p = plant_xy[plant_row == j]
    order = np.argsort(p[:, 0])
    ys.append(np.interp(xc, p[order, 0], p[order, 1]))
  mid = (ys[0] + ys[1]) / 2
  # Fit in a scaled variable: polyfit of degree 5 over x in [0, 28] is ill-conditioned.
  poly = np.polynomial.Polynomial.fit(xc, mid, 5)
  line = np.stack([xc, poly(xc)], -1)
  return line, line[-1].copy(), line[0].copy()


def world_extent(cfg: WorldConfig) -> tuple[float, float, float, float]:
  """A terrain rectangle that covers every train and test world of `cfg`, so that all
  worlds of a config share one heightfield shape (and so batch into one mjx.Model)."""
  length = max(cfg.train_length_m, cfg.test_length_m)
  half_y = (max(cfg.train_rows, len(TEST_LANE_SHAPES) + 1) - 1) / 2 * cfg.inter_row_m[1]
  m = TERRAIN_MARGIN_M
  return (-m, length + m, -half_y - m, half_y + 2 * CURVE_AMPLITUDE_M + m)


class WorldFileError(ValueError):
  """A world file that is not one `save_world` wrote: one line naming the file and fault."""


_OPTIONAL = {"width_m", "frame", *SCENERY_FIELDS}  # fields that older world files lack
_NOTES = {"robot"}  # what a world file may say besides the world (`Vineyard.to_json`)
MAX_SEED = 2**32 - 1  # numpy's seeds: a larger one would silently wrap


def save_world(world: Vineyard, path: str | Path, robot: str | None = None) -> None:
  """Saves a world as `Vineyard.to_json` has it (exact float64 round trip), atomically:
  the format of the worlds CLI's world.json, which `load_world` reads."""
  from mjxvine import atomic
  d = world.to_json(robot)  # a field a line, to skim it; numbers as repr writes them
  atomic.write_text(path, "{\n" + ",\n".join(
      f"{json.dumps(k)}: {json.dumps(v, separators=(',', ':'))}" for k, v in d.items())
      + "\n}\n")


def _check_counts(path: Path, d: dict) -> None:
  """Refuses a world with more plants, lanes or terrain cells than a vineyard file may
  give (`mjxvine.worlds.limits`): building it would take minutes or the memory."""
  from mjxvine.worlds import limits

  def count(name, nested=False):
    v = d.get(name)
    if not isinstance(v, list):
      return 0
    return sum(len(r) for r in v if isinstance(r, list)) if nested else len(v)
  scenery = sum(count(name) for name in ("post_xy", *SHAPE_TABLES))
  for what, n, most in (("plants", count("plant_xy"), limits.MAX_PLANTS),
                        ("posts and shapes", scenery, limits.MAX_SCENERY),
                        ("lanes", count("lanes"), limits.MAX_ROWS - 1),
                        ("terrain cells", count("terrain", True), limits.MAX_TERRAIN_CELLS)):
    if n > most:
      raise WorldFileError(f"{path}: {n} {what}; a world has at most {most}")


def _array(path: Path, name: str, value, shape: tuple) -> np.ndarray:
  """`value` as a finite float array of `shape` (-1: any length), else WorldFileError."""
  try:
    a = np.asarray(value, np.float64)
  except (TypeError, ValueError):
    raise WorldFileError(f"{path}: {name} is not an array of numbers") from None
  if a.ndim != len(shape) or any(w != -1 and n != w for n, w in zip(a.shape, shape)):
    want = "x".join("N" if w == -1 else str(w) for w in shape) or "a number"
    raise WorldFileError(f"{path}: {name} has shape {a.shape}, expected ({want})")
  if not np.all(np.isfinite(a)):
    raise WorldFileError(f"{path}: {name} has NaN or infinite values")
  return a


def load_world(path: str | Path) -> Vineyard:
  """Loads a world saved by `save_world` or written by the worlds CLI (world.json). A
  file that is not one (unreadable, not JSON, fields missing, misshapen or non-finite
  arrays, more than `mjxvine.worlds.limits` allows) raises WorldFileError, one line
  naming it."""
  try:
    return _load_world(Path(path))
  except WorldFileError as e:  # a path or a field's value may hold control characters
    raise WorldFileError(escaped(str(e))) from None


def _load_world(path: Path) -> Vineyard:
  from mjxvine.worlds import limits
  data = limits.read_bounded(path, limits.MAX_WORLD_FILE_BYTES, WorldFileError, "world file")
  try:
    text = data.decode("utf-8")
    if limits.json_too_deep(text):
      raise WorldFileError(f"{path}: not a world file (JSON nested more than "
                           f"{limits.MAX_JSON_DEPTH} deep)")
    d = json.loads(text)
  except (UnicodeDecodeError, json.JSONDecodeError) as e:
    raise WorldFileError(f"{path}: not a world file (not JSON: {e})") from None
  except (RecursionError, ValueError) as e:  # (a number of thousands of digits)
    if isinstance(e, WorldFileError):
      raise
    raise WorldFileError(f"{path}: not a world file (not JSON: {str(e)[:80]})") from None
  fields = {f.name for f in dataclasses.fields(Vineyard)} - _OPTIONAL
  if isinstance(d, dict) and {"rows", "lanes", "robot"} <= set(d) and "plant_xy" not in d:
    raise WorldFileError(f"{path}: a world description of an older python -m mjxvine.worlds "
                         "(no plant arrays); write the world again with it")
  if not isinstance(d, dict) or not fields <= set(d):
    missing = sorted(fields - set(d)) if isinstance(d, dict) else ["everything"]
    raise WorldFileError(f"{path}: not a world file (python -m mjxvine.worlds writes one); "
                         f"missing {', '.join(missing)}")
  for name in _NOTES:
    d.pop(name, None)
  _check_counts(path, d)
  lane_fields = {f.name for f in dataclasses.fields(Lane)} - _OPTIONAL
  if not isinstance(d["lanes"], list) or not d["lanes"] or not all(
      isinstance(l, dict) and lane_fields <= set(l) <= lane_fields | _OPTIONAL
      for l in d["lanes"]):
    raise WorldFileError(f"{path}: lanes must be a non-empty list of lanes with "
                         f"{', '.join(sorted(lane_fields))}")
  if d.get("frame") is not None and not isinstance(d["frame"], dict):
    raise WorldFileError(f"{path}: frame must be a mapping")
  try:
    lanes = tuple(Lane(id=int(l["id"]), shape=str(l["shape"]), left_row=int(l["left_row"]),
                       right_row=int(l["right_row"]),
                       centerline=_array(path, f"lane {l['id']} centerline", l["centerline"],
                                         (-1, 2)),
                       eor_forward=_array(path, "eor_forward", l["eor_forward"], (2,)),
                       eor_reverse=_array(path, "eor_reverse", l["eor_reverse"], (2,)),
                       width_m=(None if l.get("width_m") is None else
                                float(_array(path, "width_m", l["width_m"], ()))))
                  for l in d.pop("lanes"))
    plants = len(d["plant_xy"]) if isinstance(d["plant_xy"], list) else -1
    shapes = {"row_y0": (-1,), "plant_xy": (plants, 2), "plant_yaw": (plants,),
              "plant_row": (plants,), "trunk_height": (plants,), "canopy_half": (plants, 3),
              "canopy_z": (plants,), "terrain": (-1, -1), "terrain_extent": (4,)}
    posts = len(d["post_xy"]) if isinstance(d.get("post_xy"), list) else -1
    shapes.update({"post_xy": (posts, 2), "post_height": (posts,), "post_radius": (posts,),
                   **{name: (-1, 10) for name in SHAPE_TABLES}})
    for name, shape in shapes.items():
      if name in SCENERY_FIELDS and d.get(name) == []:
        d[name] = np.zeros((0,) + shape[1:])  # (json has no empty (0, 10) array)
      elif name in d:
        d[name] = _array(path, name, d[name], shape)
    if d.setdefault("season", "classic") not in SEASONS:
      raise WorldFileError(f"{path}: season {short_repr(d['season'])}: one of "
                           f"{', '.join(SEASONS)}")
    d["plant_row"] = d["plant_row"].astype(np.int64)
    for name in ("inter_row_m", "spacing_m", "length_m", "trunk_radius"):
      d[name] = float(_array(path, name, d[name], ()))
    d["seed"], d["kind"] = int(d["seed"]), str(d["kind"])
    d["terrain_extent"] = tuple(d["terrain_extent"].tolist())
    return Vineyard(lanes=lanes, **d)
  except (TypeError, ValueError, KeyError) as e:
    if isinstance(e, WorldFileError):
      raise
    from mjxvine.robot_files import clean  # (int("x" * 10**6) quotes the whole value)
    raise WorldFileError(f"{path}: not a world file ({type(e).__name__}: "
                         f"{clean(str(e), 120)})") from None
