"""How much a vineyard file (`mjxvine.worlds.geo`) or a saved world (`layout.load_world`)
may ask for: every reader checks these before the work, so that no file, however made,
hangs a command or fills the memory; beyond them it refuses in one line.

Measured on a 2-core CPU (shared: times vary by a third from run to run). build_spec +
compile of a block, rows 2.5 m apart, a plant every 0.8 m: 12,500 plants 1.4 s; 37,500
13-16 s and 600 MB; 50,000-56,000 33-42 s and 700-760 MB; 100,000 92 s and 1.1 GB: it
grows with the square of the plants. The terrain heightfield (0.25 m cells, 4 m margins)
takes ~55 bytes a cell to make: 4 million cells 0.5 s and 490 MB, 32 million 4 s and 2
GB. A large real block, 100 rows of 300 m (37,500 plants), has 1.3 million cells; its
world file is 34 MiB and loads in 1.4 s. json reads ~20 MiB a second.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

# a vineyard file: 50,000 plants as GeoJSON points are ~2 MB (~4 MB pretty-printed), read
# in 0.8 s at this bound
MAX_FILE_BYTES = 16 << 20
# a saved world: its terrain at full precision, ~21 bytes a cell (4 million cells and
# 48,000 plants: 83 MiB, loaded in 4 s)
MAX_WORLD_FILE_BYTES = 128 << 20
MAX_JSON_DEPTH = 16  # arrays and objects inside each other: GeoJSON needs 6, a world 5
MAX_ROWS = 500  # plant rows of a block (a large one has 100+)
MAX_ROW_PLANTS = 10_000  # plants of one row: 5 km at 0.5 m
MAX_PLANTS = 50_000  # plants of a block: build_spec takes 30-45 s and 700 MB there
# posts, cordons, lobes, shoots and tufts of a world, a geom each (a plant is two): a
# summer block of 12 rows of 300 m with 2 tufts a m^2, 45,000 geoms, builds in 4.3 s
MAX_SCENERY = 100_000
MAX_LINE_VERTICES = 10_000  # vertices of a LineString row: a surveyed line every 0.5 m for 5 km
MIN_PLANT_SPACING_M = 0.1  # plants of a row nearer than this: not vines (a unit mistake)
MAX_TERRAIN_CELLS = 4_000_000  # heightfield cells of a block: 25 ha, margins included

_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"')  # a JSON string (brackets in it don't nest)
_NOT_BRACKET = re.compile(r"[^\[\]{}]+")
_CHUNK = 1 << 20


def read_bounded(path: Path, max_bytes: int, error, what: str) -> bytes:
  """The bytes of `path`, refused with `error` (one line) beyond `max_bytes`: read no
  further than that, so a device or a pipe cannot fill the memory either."""
  try:
    with open(path, "rb") as f:
      size = os.fstat(f.fileno()).st_size  # (0 for a pipe) so that a small file does not
      parts = [f.read(min(size, max_bytes) + 1)] if size else []  # get a max_bytes buffer
      got = sum(map(len, parts))
      while got <= max_bytes and (more := f.read(min(_CHUNK, max_bytes + 1 - got))):
        parts.append(more)  # a pipe, or a file that grew since
        got += len(more)
      data = b"".join(parts)
  except OSError as e:
    raise error(f"{path}: cannot be read ({e.strerror or type(e).__name__})") from None
  if len(data) > max_bytes:
    raise error(f"{path}: more than {max_bytes >> 20} MiB; a {what} is at most that")
  return data


def json_too_deep(text: str, max_depth: int = MAX_JSON_DEPTH) -> bool:
  """Whether the JSON `text` nests arrays and objects more than `max_depth` deep (Python's
  json has no bound of its own), found without parsing it: brackets outside strings,
  counted in chunks."""
  import numpy as np
  brackets = _NOT_BRACKET.sub("", _STRING.sub("", text)).encode("ascii")
  depth = 0
  for start in range(0, len(brackets), _CHUNK):
    chunk = np.frombuffer(brackets[start:start + _CHUNK], np.uint8)
    step = np.where((chunk == ord("[")) | (chunk == ord("{")), 1, -1).astype(np.int32)
    levels = depth + np.cumsum(step)
    if levels.max() > max_depth:
      return True
    depth = int(levels[-1])
  return False
