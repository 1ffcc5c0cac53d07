"""Prints the table of every config key of docs/reference.md (Configs) from
mjxvine/config.py: key, default, allowed range or choices, and what the key does.

  python scripts/config_table.py           # prints the table
  python scripts/config_table.py --write   # replaces the table in docs/reference.md

tests/test_docs_config.py checks that docs/reference.md holds this table as printed.
"""

import dataclasses
import sys
import typing
from pathlib import Path

from mjxvine.config import Config

REFERENCE = Path(__file__).resolve().parent.parent / "docs" / "reference.md"
BEGIN = "<!-- config table: python scripts/config_table.py --write -->"
END = "<!-- end of config table -->"


def value(v) -> str:
  """A value as a YAML config file writes it."""
  if isinstance(v, bool):
    return "true" if v else "false"
  if isinstance(v, tuple):
    return "[" + ", ".join(value(x) for x in v) + "]"
  if isinstance(v, str):
    return v if v else '""'
  return repr(v)


def allowed(meta: dict, tp) -> str:
  """The choices, or the inclusive range [lo, hi] (of each item of a pair)."""
  if meta.get("choices"):
    return ", ".join(meta["choices"])
  if meta.get("lo") is None:
    return ""
  lo, hi = meta["lo"], meta["hi"]
  if typing.get_origin(tp) is not tuple:
    item = tp
  else:
    item = typing.get_args(tp)[0]
  return f"[{value(item(lo))}, {value(item(hi))}]"


def rows() -> list[tuple[str, str, str, str]]:
  """(key, default, range or choices, doc) of every config key, in config.py's order."""
  out = []
  for section in dataclasses.fields(Config):
    cls = section.type if isinstance(section.type, type) else type(section.default)
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
      meta = dict(f.metadata)
      out.append((f"{section.name}.{f.name}", value(f.default), allowed(meta, hints[f.name]),
                  meta.get("doc", "")))
  return out


def table() -> str:
  """The markdown table, between its begin and end markers."""
  lines = [BEGIN, "", "| key | default | range | what |", "|---|---|---|---|"]
  for key, default, rng, doc in rows():
    cells = [f"`{key}`", f"`{default}`", rng, doc.replace("|", "\\|")]
    lines.append("| " + " | ".join(cells) + " |")
  return "\n".join(lines + ["", END]) + "\n"


def written_table(text: str) -> str | None:
  """The table of a reference page, its markers included; None if it has none."""
  begin, end = text.find(BEGIN), text.find(END)
  if begin < 0 or end < begin:
    return None
  return text[begin:end + len(END)] + "\n"


def main(argv: list[str]) -> int:
  if argv == ["--write"]:
    text = REFERENCE.read_text()
    old = written_table(text)
    if old is None:
      print(f"{REFERENCE}: no {BEGIN} ... {END}", file=sys.stderr)
      return 2
    REFERENCE.write_text(text.replace(old, table()))
    return 0
  if argv:
    print(__doc__, file=sys.stderr)
    return 2
  sys.stdout.write(table())
  return 0


if __name__ == "__main__":
  sys.exit(main(sys.argv[1:]))
