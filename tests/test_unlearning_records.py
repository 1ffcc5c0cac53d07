"""The validation curves of docs/results/unlearning.md's lever tables are their records: in
each row that names a record (`NAME-seedN`) with a `selection.json` in
docs/results/unlearning/, every "Nk M" of the curve is the validation successes of the kept
policy of N thousand env steps (a "+" marks a rollout stopped early: at least M), and the
best, last and drop columns follow from the curve."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

RESULTS = Path(__file__).resolve().parent.parent / "docs" / "results"
PAGE = RESULTS / "unlearning.md"
RECORD = re.compile(r"\(`([a-z0-9-]+-seed\d+)`")
POINT = re.compile(r"(\d+(?:\.\d+)?)k (\d+)(\+?)")


def lever_rows() -> list[tuple[str, list[str]]]:
  """(record name, cells) of every table row of the page that names a record with a
  selection.json and gives its curve point by point."""
  rows = []
  for line in PAGE.read_text().splitlines():
    cells = [c.strip() for c in line.strip().strip("|").split("|")]
    match = RECORD.search(cells[0]) if line.startswith("|") else None
    if match and (RESULTS / "unlearning" / f"{match[1]}-selection.json").exists():
      if len(cells) == 7 and POINT.search(cells[3]):
        rows.append((match[1], cells))
  return rows


def curve(cell: str) -> list[tuple[int, int, bool]]:
  """[(env steps, successes, stopped early)] of a curve cell such as "10k 0, 138.8k 72"."""
  return [(round(float(k) * 1000), int(m), plus == "+") for k, m, plus in POINT.findall(cell)]


def test_the_page_has_lever_rows_to_check():
  names = {name for name, _ in lever_rows()}
  assert {"n3-seed4", "n3-seed0", "n3-seed1", "n3-seed2", "lane-seed4", "droq-seed0",
          "steer-seed4", "steer-seed2", "pose1-seed0", "n3vmin-seed2", "steerw-seed4",
          "steerw-seed2", "priv-seed4", "priv-seed2", "priv-seed0", "priv-seed1", "priv-seed6",
          "succ100-seed4", "recipe70k-seed0", "recipe70k-seed1", "recipe70k-seed2",
          "recipe70k-seed7"} <= names


@pytest.mark.parametrize("name,cells", lever_rows(), ids=lambda v: v if isinstance(v, str) else "")
def test_a_curve_is_its_record(name, cells):
  selection = json.loads((RESULTS / "unlearning" / f"{name}-selection.json").read_text())
  scored = {c["env_steps"]: c["validation"] for c in selection["candidates"]}
  points = curve(cells[3])
  for steps, successes, stopped in points:
    assert steps in scored, f"{name}: no validation of {steps} env steps in its record"
    assert scored[steps]["success"] == successes, (name, steps)
    assert bool(scored[steps].get("stopped_early")) == stopped, (name, steps)
  values = [m for _, m, _ in points]
  best, last, drop = (int(c) for c in cells[4:7])
  assert (best, last, drop) == (max(values), values[-1], max(values) - values[-1]), name
