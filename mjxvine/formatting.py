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


def first_line(error: BaseException, limit: int = 400) -> str:
  """An error's first non-empty line, for a one-line message: whole, cut at a word only
  past `limit` characters (libraries' first lines say what failed; some run to whole
  trees); the error's type when it has no text."""
  lines = [l.strip() for l in str(error).splitlines() if l.strip()]
  if not lines:
    return type(error).__name__
  line = lines[0]
  return line if len(line) <= limit else line[:limit].rsplit(" ", 1)[0] + " ..."

