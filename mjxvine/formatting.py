"""How numbers are printed in reports, progress lines and benchmark tables: one place, so
that a table and the line that summarises it agree."""

from __future__ import annotations


def fmt(x: float | None, nd: int = 3) -> str:
  """`x` with `nd` decimals; "-" for a missing value (None)."""
  return "-" if x is None else f"{x:.{nd}f}"


def fmt_value(v) -> str:
  """A table cell: floats with 4 significant digits (whole numbers from 1e5 on), anything
  else as `str`."""
  if isinstance(v, float):
    return f"{v:.4g}" if abs(v) < 1e5 else f"{v:.0f}"
  return str(v)
