"""The protocol's report of one test world: results.json (the document of
`rollout.run_protocol`), results.md (a table laid out like the paper's, with the paper's
numbers beside ours) and trajectories.png (the runs on a top-down vineyard); and the
table cells the suite and the sweeps share.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mjxvine import atomic
from mjxvine.evaluation.paper import PAPER, PAPER_RUNS, RUNS
from mjxvine.formatting import fmt

# Outcome colours that stand out against the green plants and the grey centrelines.
OUTCOME_COLOURS = {"success": "tab:blue", "collision": "tab:red", "left_lane": "tab:orange",
                   "reversed": "tab:purple", "timeout": "0.15", "physics": "magenta"}


def metric_cell(r: dict, key: str, nd: int = 3) -> str:
  """MAE/RMSE cell of a row `r` (`metrics.group_metrics`): "n/a" when no run reached its
  EoR, "(partial)" after the number when only some did."""
  if r["metrics_status"] == "n/a":
    return "n/a"
  return fmt(r[key], nd) + (" (partial)" if r["metrics_status"] == "partial" else "")


def covered_cell(r: dict) -> str:
  """Lane-covered cell of a row: "62% (15.0 m)"."""
  return f"{r['lane_covered_frac']:.0%} ({r['lane_covered_m']:.1f} m)"


def results_markdown(doc: dict) -> str:
  """A table laid out like the paper's, with the paper's numbers beside ours (not on a
  vineyard file's block: its lanes are not the paper's)."""
  source = doc.get("world", {}).get("source")
  paper = {} if source is not None else PAPER
  head = ("| test row | shape | lane covered | MAE m (paper) | RMSE m (paper) | v m/s (paper) "
          "| w rad/s (paper) | success (paper) |") if paper else (
          "| lane | shape | lane covered | MAE m | RMSE m | v m/s | w rad/s | success |")
  where = f" on {source}" if source is not None else ""
  lines = [f"# Evaluation: {doc['policy']} ({doc['robot']}, noise x{doc['noise']}){where}", "",
           head, "|---|---|---|---|---|---|---|---|"]
  o = doc["overall"]
  # the paper's overall row is the mean of its rows: so is ours (the pooled one below)
  by_rows = dict(o, lane="overall", direction="", shape="mean of rows",
                 mae_m=o["mae_m_rows"], rmse_m=o["rmse_m_rows"], metrics_status=o["rows_status"],
                 v_mean=o["v_mean_rows"], v_std=o["v_std_rows"], w_mean=o["w_mean_rows"],
                 w_std=o["w_std_rows"])
  for r in doc["rows"] + [by_rows]:
    key = f"{r['lane']}{r['direction']}"
    p = paper.get(key)
    ps = (lambda i, nd=3: f" ({p[i]:.{nd}f})") if p else (lambda i, nd=3: "")
    lines.append(
        f"| {key} | {r['shape']} | {covered_cell(r)} | {metric_cell(r, 'mae_m')}{ps(0)} | "
        f"{metric_cell(r, 'rmse_m')}{ps(1)} | "
        f"{r['v_mean']:.3f} +- {r['v_std']:.3f}{ps(2)} | {r['w_mean']:.3f} +- {r['w_std']:.3f}"
        f"{ps(4)} | {r['success']}/{r['runs']}" + (
            f" ({p[6]}/{RUNS if key != 'overall' else PAPER_RUNS})" if p else "") + " |")
  lines += ["", "Lane covered: mean over the runs of the part of the lane's centreline driven "
            "from its start (a run that reached the EoR covers all of it). MAE/RMSE: n/a when "
            "no run of the row reached the EoR; (partial) when only some did: they then "
            "include runs that stopped early and are not comparable to the paper's. Overall: "
            "the mean of the rows, as the paper's; pooled over every trajectory point: MAE "
            f"{metric_cell(o, 'mae_m')} m, RMSE {metric_cell(o, 'rmse_m')} m.",
            "", f"Rollout wall-clock: {doc['wall_s']:.1f} s."]
  if "row_end" in doc:
    lines += [""] + row_end_markdown(doc["row_end"])
  return "\n".join(lines) + "\n"


def row_end_markdown(section: dict) -> list[str]:
  """The `--past-end` table: where the end-of-row detector stopped, per lane-direction."""
  cell = lambda r: "-" if r["stop_error_m"] is None else f"{r['stop_error_m']:+.2f}"
  lines = ["## The end of the row", "",
           f"Each run drove on {section['past_end_m']:g} m past the end of the row (success "
           "above: it got there); the stop is where the end-of-row detector first fired, in "
           "m along the row from its end (< 0: before it).", "",
           "| lane | stop m (mean) | within 1 m | false stops | no stop |", "|---|---|---|---|---|"]
  for key, r in [*section["rows"].items(), ("all", section)]:
    lines.append(f"| {key} | {cell(r)} | {r['stopped_within_1m']}/{r['runs']} | "
                 f"{r['false_stops']} | {r['missed']} |")
  return lines


def figure_title(doc: dict) -> str:
  """The title of trajectories.png: policy, robot, noise, successes, lane covered and the
  mean-of-rows MAE/RMSE (or why there is none)."""
  o = doc["overall"]
  status = o.get("rows_status", o["metrics_status"])
  metrics = ("MAE/RMSE n/a (no run reached the EoR)" if status == "n/a" else
             f"MAE {fmt(o.get('mae_m_rows', o['mae_m']))} m, RMSE "
             f"{fmt(o.get('rmse_m_rows', o['rmse_m']))} m (mean of rows)" +
             (" (partial: only some runs reached the EoR)" if status == "partial" else ""))
  return (f"{doc['policy']} - {doc['robot']}, noise x{doc['noise']}: {o['success']}/{o['runs']}"
          f" success, lane covered {o['lane_covered_frac']:.0%}\n{metrics}")


def plot_trajectories(doc: dict, world, path) -> None:
  """Top-down vineyard (`world`, a `Vineyard`) with every trajectory of `doc`: colour by
  outcome, solid forward and dashed reverse runs, a circle at each start and a cross where
  a failed run ended. Written to `path` (a PNG)."""
  import matplotlib.pyplot as plt
  from matplotlib.lines import Line2D

  from mjxvine.worlds.plot import draw_vineyard
  fig, ax = plt.subplots(figsize=(13, 6.5))
  world_handles, _ = draw_vineyard(ax, world, terrain=False)
  counts: dict[str, int] = {}
  for t in doc["trajectories"]:
    xy = np.asarray(t["xy"]).reshape(-1, 2)
    counts[t["outcome"]] = counts.get(t["outcome"], 0) + 1
    if not len(xy):
      continue
    colour = OUTCOME_COLOURS[t["outcome"]]
    ax.plot(xy[:, 0], xy[:, 1], color=colour, lw=1.0, alpha=0.85,
            ls="-" if t["direction"] == "F" else (0, (4, 2)))
    ax.plot(*xy[0], "o", ms=5, mfc=colour, mec="white", mew=0.8, zorder=5)
    if t["outcome"] != "success":
      ax.plot(*xy[-1], "x", ms=7, mew=1.8, color=colour, zorder=5)
  # every outcome, with its count: the same colour key in every figure
  handles = [Line2D([], [], color=c, lw=2, label=f"{o} ({counts.get(o, 0)})")
             for o, c in OUTCOME_COLOURS.items()]
  handles += [Line2D([], [], color="0.3", lw=1.2, label="forward run"),
              Line2D([], [], color="0.3", lw=1.2, ls=(0, (4, 2)), label="reverse run"),
              Line2D([], [], ls="", marker="o", ms=6, mfc="0.3", mec="white", label="start"),
              Line2D([], [], ls="", marker="x", ms=7, mew=1.8, color="0.3",
                     label="end of a failed run")]
  ax.legend(handles=handles + world_handles, loc="upper left", bbox_to_anchor=(1.01, 1.0),
            fontsize=8)
  ax.set_title(figure_title(doc), fontsize=10)
  with atomic.atomic_path(path) as tmp:
    fig.savefig(tmp, dpi=110, bbox_inches="tight")
  plt.close(fig)


def write_results(doc: dict, world, out: Path) -> None:
  """out/results.json, out/results.md and out/trajectories.png of `doc` on `world`."""
  out.mkdir(parents=True, exist_ok=True)
  atomic.write_text(out / "results.json", json.dumps(doc))
  atomic.write_text(out / "results.md", results_markdown(doc))
  plot_trajectories(doc, world, out / "trajectories.png")
