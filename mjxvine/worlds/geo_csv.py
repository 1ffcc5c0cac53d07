"""The plant CSV of a vineyard file (`mjxvine.worlds.geo`, its docstring: the format) parsed
into plant rows, bounded as the lines come (`mjxvine.worlds.limits`)."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from mjxvine.robot_files import clean, short_repr
from mjxvine.worlds.geo_write import SIZE_KEYS
from mjxvine.worlds.layout import WorldFileError
from mjxvine.worlds.limits import MAX_PLANTS, MAX_ROW_PLANTS, MAX_ROWS


BLOCK_KEYS = ("season", "post_spacing_m")  # columns that say one thing of the whole block


def read_csv_rows(path: Path, text: str
                  ) -> tuple[dict[str, list], dict[str, dict[str, list]], dict[str, tuple]]:
  """({row label: [(x, y), ...]}, {row label: {size key: [value, ...]}}, {block key:
  (first line, value)}) of the CSV `text` of `path`, rows in the order first seen, plants
  in file order; a block key's cells (`BLOCK_KEYS`, empty ones aside) must all say the
  same. Else one-line WorldFileError naming the file and line."""
  reader = csv.reader(io.StringIO(text, newline=""))
  try:
    header = next((r for r in reader if any(c.strip() for c in r)), None)
    if header is None:
      raise WorldFileError(f"{path}: empty; a plant CSV is a header row,x_m,y_m and one plant "
                           "per line")
    header_line = reader.line_num
    names = [c.strip().lower() for c in header]
    lacking = [c for c in ("row", "x_m", "y_m") if c not in names]
    if lacking:
      hint = " (separated by ';'? use commas)" if ";" in ",".join(header) else ""
      raise WorldFileError(f"{path}: line {header_line}: the header "
                           f"{short_repr(','.join(header))} has no {', '.join(lacking)}"
                           f"{hint}: a plant CSV starts with row,x_m,y_m")
    twice = sorted({c for c in names if c and names.count(c) > 1})
    if twice:
      raise WorldFileError(f"{path}: line {header_line}: column(s) "
                           f"{clean(', '.join(twice), 80)} twice in the header")
    col = {c: names.index(c) for c in ("row", "x_m", "y_m", *SIZE_KEYS, *BLOCK_KEYS)
           if c in names}
    rows: dict[str, list] = {}
    sizes: dict[str, dict[str, list]] = {}
    block: dict[str, tuple] = {}
    plants = 0
    for cells in reader:
      line = reader.line_num
      if not any(c.strip() for c in cells):
        continue
      if len(cells) < len(names) or any(c.strip() for c in cells[len(names):]):
        raise WorldFileError(f"{path}: line {line}: {len(cells)} fields, the header has "
                             f"{len(names)}")
      label = cells[col["row"]].strip()
      if not label:
        raise WorldFileError(f"{path}: line {line}: the row label is empty")
      x, y = (_csv_number(path, line, cells, col, k) for k in ("x_m", "y_m"))
      row = rows.setdefault(label, [])
      row.append((x, y))
      plants += 1  # the limits as the lines come: a huge file stops at the first beyond
      if plants > MAX_PLANTS:
        raise WorldFileError(f"{path}: line {line}: more than {MAX_PLANTS} plants; a block "
                             f"has at most {MAX_PLANTS}")
      if len(row) > MAX_ROW_PLANTS:
        raise WorldFileError(f"{path}: line {line}: more than {MAX_ROW_PLANTS} plants in "
                             f"row {short_repr(label)}; a row has at most {MAX_ROW_PLANTS}")
      if len(rows) > MAX_ROWS:
        raise WorldFileError(f"{path}: line {line}: more than {MAX_ROWS} rows (labels); a "
                             f"block has at most {MAX_ROWS}")
      given = sizes.setdefault(label, {})
      for key in SIZE_KEYS:
        if key in col and cells[col[key]].strip():
          v = _csv_number(path, line, cells, col, key)
          if v <= 0:
            raise WorldFileError(f"{path}: line {line}: {key} {v:g}: give a positive number "
                                 "of metres")
          given.setdefault(key, []).append(v)
      for key in BLOCK_KEYS:
        if key in col and cells[col[key]].strip():
          v = (cells[col[key]].strip() if key == "season" else
               _csv_number(path, line, cells, col, key))
          first = block.setdefault(key, (line, v))
          if first[1] != v:
            raise WorldFileError(f"{path}: line {line}: {key} {short_repr(v)} differs from "
                                 f"{short_repr(first[1])} on line {first[0]}: a block has "
                                 "one")
  except csv.Error as e:
    raise WorldFileError(f"{path}: line {reader.line_num}: not CSV ({e})") from None
  return rows, sizes, block


def _csv_number(path: Path, line: int, cells: list, col: dict, key: str) -> float:
  cell = cells[col[key]].strip()
  try:
    v = float(cell)
  except ValueError:
    raise WorldFileError(f"{path}: line {line}: {key} {short_repr(cell, 30)} is not a "
                         "number") from None
  if not math.isfinite(v):
    raise WorldFileError(f"{path}: line {line}: {key} {short_repr(cell, 30)} is not a finite "
                         "number")
  return v
