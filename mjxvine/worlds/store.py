"""The committed test world, and resolving a world argument (seed or file)."""

from __future__ import annotations

from pathlib import Path

from mjxvine.config import WorldConfig
from mjxvine.worlds.layout import MAX_SEED, Vineyard, generate_world, load_world

DATA_DIR = Path(__file__).parent / "data"
TEST_WORLD_FILE = DATA_DIR / "test_world_seed0.json"


def load_test_world(cfg: WorldConfig) -> Vineyard:
  """The test world every result is measured on: seed 0, loaded from the committed file.

  The file is used only with the default world settings; a config that changes how
  worlds are generated gets its test world generated (and its results are not comparable).
  """
  if cfg == WorldConfig() and TEST_WORLD_FILE.is_file():
    return load_world(TEST_WORLD_FILE)
  return generate_world("test", cfg.test_seed, cfg)


def make_world(spec: str, cfg: WorldConfig, kind: str = "test", flag: str = "--world") -> Vineyard:
  """A world from a command-line argument (`flag`, named in errors): a path to a saved
  world JSON, or an integer seed in [0, 2^32 - 1]. Raises FileNotFoundError, WorldFileError
  or ValueError, each one line naming the flag or the file."""
  path = Path(spec)
  if path.suffix == ".json" or path.exists():
    if not path.is_file():
      raise FileNotFoundError(f"{flag} {spec}: world file not found")
    return load_world(path)
  try:
    seed = int(spec)
  except ValueError:
    raise ValueError(f"{flag} {spec!r}: give a seed or a world .json file") from None
  if not 0 <= seed <= MAX_SEED:
    raise ValueError(f"{flag} {spec}: a seed is a whole number from 0 to {MAX_SEED}")
  if kind == "test" and seed == cfg.test_seed:
    return load_test_world(cfg)
  return generate_world(kind, seed, cfg)
