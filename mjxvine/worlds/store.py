"""The committed test world, resolving a world argument (seed or file), and the pool of
train worlds (generated, and blocks from vineyard files)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from mjxvine.config import Config, WorldConfig
from mjxvine.worlds.build import terrain_height
from mjxvine.worlds.layout import (MAX_SEED, TERRAIN_CELL_M, Vineyard, generate_world,
                                   load_world)
from mjxvine.worlds.seasons import classic_config, dress

DATA_DIR = Path(__file__).parent / "data"
TEST_WORLD_SEED = 0  # "test world 0": the one every result is measured on
TEST_WORLD_FILE = DATA_DIR / "test_world_seed0.json"


def load_test_world(cfg: WorldConfig) -> Vineyard:
  """The test world every result is measured on: seed 0, loaded from the committed file.

  The file is used only with the default world settings, or with only the season and the
  other realism keys changed: then it is dressed for them (`seasons.dress`, the same rows
  in every season); a config that changes how worlds are laid out gets its test world
  generated (and its results are not comparable).
  """
  if classic_config(cfg) == WorldConfig() and TEST_WORLD_FILE.is_file():
    return dress(load_world(TEST_WORLD_FILE), cfg)
  return generate_world("test", TEST_WORLD_SEED, cfg)


VINEYARD_SUFFIXES = (".geojson", ".csv")


def make_world(spec: str, cfg: WorldConfig, kind: str = "test", flag: str = "--world",
               robot_width_m: float = 0.0, plant_spacing_m: float | None = None) -> Vineyard:
  """A world from a command-line argument (`flag`, named in errors): a vineyard file
  (.geojson, .csv; `mjxvine.worlds.geo`, its lanes checked for a robot `robot_width_m`
  wide, LineString rows planted every `plant_spacing_m` unless the file says), a path to a
  saved world JSON (a GeoJSON .json too), or an integer seed in [0, 2^32 - 1]. Raises
  FileNotFoundError, WorldFileError or ValueError, each one line naming the flag or file."""
  path = Path(spec)
  if path.suffix.lower() in (*VINEYARD_SUFFIXES, ".json") or path.exists():
    if not path.is_file():
      raise FileNotFoundError(f"{flag} {spec}: world file not found")
    if path.suffix.lower() in VINEYARD_SUFFIXES or _is_geojson(path):
      from mjxvine.worlds.geo import read_vineyard
      return read_vineyard(path, cfg, robot_width_m=robot_width_m,
                           plant_spacing_m=plant_spacing_m)
    return load_world(path)
  try:
    seed = int(spec)
  except ValueError:
    raise ValueError(f"{flag} {spec!r}: give a seed or a world .json file") from None
  if not 0 <= seed <= MAX_SEED:
    raise ValueError(f"{flag} {spec}: a seed is a whole number from 0 to {MAX_SEED}")
  if kind == "test" and seed == TEST_WORLD_SEED:
    return load_test_world(cfg)
  return generate_world(kind, seed, cfg)


def _is_geojson(path: Path) -> bool:
  """Whether a .json file is GeoJSON (a "type" member first) rather than a saved world."""
  try:
    with open(path, "rb") as f:
      head = f.read(4096).decode("utf-8", "replace")
  except OSError:
    return False
  return '"type"' in head and '"plant_xy"' not in head


def world_of(spec: str, cfg: Config, **kw) -> Vineyard:
  """`make_world` for a whole config: vineyard files' lanes checked for its robot."""
  return make_world(spec, cfg.world, robot_width_m=cfg.robot.spec.width, **kw)


def train_files(cfg: WorldConfig) -> list[str]:
  """The vineyard files of `world.train_files` (comma-separated)."""
  return [f.strip() for f in cfg.train_files.split(",") if f.strip()]


def pool_worlds(cfg: Config) -> list[Vineyard]:
  """The train worlds of `cfg`: `world.pool_size` generated ones (seeds 0 on), then the
  blocks of `world.train_files`. With files, every world's terrain is resampled onto one
  grid shape (`common_terrain_grid`), so that all batch together."""
  worlds = [generate_world("train", i, cfg.world) for i in range(cfg.world.pool_size)]
  files = train_files(cfg.world)
  if not files:
    return worlds
  worlds += [world_of(f, cfg, flag="world.train_files") for f in files]
  return common_terrain_grid(worlds, TERRAIN_CELL_M)


def common_terrain_grid(worlds: list[Vineyard], cell_m: float) -> list[Vineyard]:
  """`worlds` with their heightfields resampled (bilinear, edge values beyond a world's
  own terrain) onto grids of one shape and cell `cell_m`, each from its own corner
  (xmin, ymin) and as large as the largest world's: one `mjx.Model` structure for all."""
  width = max(w.terrain_extent[1] - w.terrain_extent[0] for w in worlds)
  height = max(w.terrain_extent[3] - w.terrain_extent[2] for w in worlds)
  ncol, nrow = math.ceil(width / cell_m - 1e-9) + 1, math.ceil(height / cell_m - 1e-9) + 1
  out = []
  for w in worlds:
    xmin, _, ymin, _ = w.terrain_extent
    xs, ys = xmin + np.arange(ncol) * cell_m, ymin + np.arange(nrow) * cell_m
    terrain = terrain_height(w, xs[None, :], ys[:, None])
    extent = (xmin, float(xs[-1]), ymin, float(ys[-1]))
    out.append(dataclasses.replace(w, terrain=terrain, terrain_extent=extent))
  return out
