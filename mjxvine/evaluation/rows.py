"""The real range of vineyards (`python -m mjxvine.evaluate --sweep rows`): the protocol on
generated test worlds with long rows, over a grid of inter-row distances and slopes.

Real blocks have rows of 50-200 m, 1.8-3.0 m apart, on slopes; the paper's test world has
24 m rows 1.5-2.0 m apart on flat, bumpy ground. Each grid point is the config's test world
(its seed, lane shapes, gaps and bumps) generated with rows `length_m` long, exactly
`inter_row_m` apart, on a plane rising `slope_pct` % along the rows; every lane, both
directions, `runs` runs each, with the time limit of the row's length
(`rollout.lane_steps`). Writes rows.md, rows.json and rows.png under `out`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple, Sequence

import numpy as np

from mjxvine import atomic
from mjxvine.config import replace
from mjxvine.evaluation.report import metric_cell
from mjxvine.evaluation.rollout import PolicySource, Protocol, evaluate
from mjxvine.formatting import fmt

LENGTH_M = 80.0
INTER_ROW_M = (1.8, 2.2, 2.6, 3.0)
SLOPE_PCT = (0.0, 5.0, 10.0)


def grid_config(cfg, length_m: float, inter_row_m: float, slope_pct: float):
  """`cfg` with test worlds of rows `length_m` long, `inter_row_m` apart, on a slope."""
  return replace(cfg, world={"test_length_m": float(length_m),
                             "inter_row_m": (float(inter_row_m), float(inter_row_m)),
                             "slope_pct": float(slope_pct)})


class RowGrid(NamedTuple):
  """The sweep's grid of test worlds: rows `length_m` (m) long, each of `inter_row_m` (m)
  apart on each of `slope_pct` (%, along the rows)."""
  length_m: float = LENGTH_M
  inter_row_m: Sequence[float] = INTER_ROW_M
  slope_pct: Sequence[float] = SLOPE_PCT


def sweep_rows(cfg, source: PolicySource, out: Path, *, grid: RowGrid = RowGrid(),
               runs: int = 1, seed: int = 0, say=print) -> dict:
  """The grid's results, the policy of `source` driving `runs` runs of each lane-direction
  (rollout key `seed`) of each world of `grid`: {"<inter-row>m_<slope>pct": overall
  figures (`metrics.summarize`'s "overall", with `rows_status`)}, also written to `out`."""
  from mjxvine.worlds import TEST_WORLD_SEED, generate_world
  table = {}
  length_m = grid.length_m
  for gap in grid.inter_row_m:
    for slope in grid.slope_pct:
      grid_cfg = grid_config(cfg, length_m, gap, slope)
      world = generate_world("test", TEST_WORLD_SEED, grid_cfg.world)
      doc = evaluate(grid_cfg, source, world,
                     Protocol(runs, grid_cfg.eval.noise_factor, seed=seed))
      o = doc["overall"]
      table[f"{gap:g}m_{slope:g}pct"] = dict(
          inter_row_m=gap, slope_pct=slope, length_m=length_m, success=o["success"],
          runs=o["runs"], mae_m_rows=o["mae_m_rows"], rows_status=o["rows_status"],
          lane_covered_frac=o["lane_covered_frac"],
          failed=[f"{r['lane']}{r['direction']}" for r in doc["rows"]
                  if r["success"] < r["runs"]])
      say(f"rows {length_m:g} m, {gap:g} m apart, slope {slope:g} %: "
          f"{o['success']}/{o['runs']} to the end of the row, MAE {fmt(o['mae_m_rows'], 3)} m")
  out.mkdir(parents=True, exist_ok=True)
  atomic.write_text(out / "rows.md", rows_markdown(table, source.spec, runs))
  atomic.write_text(out / "rows.json", json.dumps(table, indent=1))
  _plot(table, out / "rows.png")
  return table


def rows_markdown(table: dict, policy_spec: str, runs: int) -> str:
  """The grid as a table: one line per inter-row distance, one column per slope."""
  slopes = sorted({v["slope_pct"] for v in table.values()})
  gaps = sorted({v["inter_row_m"] for v in table.values()})
  length = next(iter(table.values()))["length_m"]
  lines = [f"# {policy_spec} on rows of {length:g} m ({runs} run(s) per lane and direction)",
           "", "Success to the end of the row; MAE (m, mean of rows) in brackets.", "",
           "| inter-row | " + " | ".join(f"slope {s:g} %" for s in slopes) + " |",
           "|---" * (len(slopes) + 1) + "|"]
  for gap in gaps:
    cells = []
    for s in slopes:
      v = table[f"{gap:g}m_{s:g}pct"]
      cell = f"{v['success']}/{v['runs']} ({metric_cell({'mae_m': v['mae_m_rows'], 'metrics_status': v['rows_status']}, 'mae_m')})"
      if v["failed"]:
        cell += f"; failed {', '.join(v['failed'])}"
      cells.append(cell)
    lines.append(f"| {gap:g} m | " + " | ".join(cells) + " |")
  return "\n".join(lines) + "\n"


def _plot(table: dict, path: Path) -> None:
  """Success rate over the grid (inter-row x slope), as a heat map with its numbers."""
  import matplotlib.pyplot as plt
  slopes = sorted({v["slope_pct"] for v in table.values()})
  gaps = sorted({v["inter_row_m"] for v in table.values()})
  rate = np.array([[table[f"{g:g}m_{s:g}pct"]["success"] / table[f"{g:g}m_{s:g}pct"]["runs"]
                    for s in slopes] for g in gaps])
  fig, ax = plt.subplots(figsize=(1.6 * len(slopes) + 2, 0.8 * len(gaps) + 1.5))
  im = ax.imshow(rate, vmin=0, vmax=1, cmap="RdYlGn", aspect="auto")
  for i in range(len(gaps)):
    for j in range(len(slopes)):
      ax.text(j, i, f"{100 * rate[i, j]:.0f}%", ha="center", va="center")
  ax.set_xticks(range(len(slopes)), [f"{s:g} %" for s in slopes])
  ax.set_yticks(range(len(gaps)), [f"{g:g} m" for g in gaps])
  ax.set_xlabel("slope along the rows")
  ax.set_ylabel("inter-row distance")
  ax.set_title("success to the end of the row")
  fig.colorbar(im, ax=ax, shrink=0.8)
  fig.tight_layout()
  with atomic.atomic_path(path) as tmp:
    fig.savefig(tmp, dpi=110)
  plt.close(fig)
