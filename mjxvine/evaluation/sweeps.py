"""The robustness tables of `python -m mjxvine.evaluate --sweep noise|robots`, each beside
the paper's figures: the noise test's rows at the depth noise factors the paper reports,
and the robot test's rows on each robot (`paper`). Each writes <name>.md, <name>.json and
<name>.png under `out`; one protocol rollout per noise factor or robot.
"""

from __future__ import annotations

import json
from pathlib import Path

from mjxvine import atomic
from mjxvine.config import replace
from mjxvine.evaluation import paper
from mjxvine.evaluation.report import metric_cell
from mjxvine.evaluation.rollout import PolicySource, Protocol, evaluate
from mjxvine.formatting import fmt


def sweep_noise(cfg, policy_spec, world, out: Path, seed=0, which="best", member=None) -> dict:
  """The robustness table: noise factors 2..10 (those of `paper.PAPER_NOISE`) on the noise
  test's rows (lanes 1F and 4F), 3 runs each, of `world` (a `Vineyard`) under `cfg`.
  Returns {noise factor: {"1F": row, "4F": row}} (`metrics.summarize` rows)."""
  table = {}
  for k in sorted(paper.PAPER_NOISE):
    doc = evaluate(cfg, PolicySource(policy_spec, which, member), world,
                   Protocol(paper.NOISE_RUNS, float(k), paper.NOISE_LANES,
                            (paper.NOISE_DIRECTION,), seed))
    table[k] = {f"{r['lane']}{r['direction']}": r for r in doc["rows"]}
  runs = paper.NOISE_RUNS
  rows = ", ".join(f"{lane}{paper.NOISE_DIRECTION} {shape}"
                   for lane, shape in zip(paper.NOISE_LANES, paper.NOISE_SHAPES))
  lines = [f"# Noise robustness (lanes {rows}; {runs} runs each)", "",
           "| noise factor | " + " | ".join(str(k) for k in table) + " |",
           "|---" * (len(table) + 1) + "|"]
  for col, (lane, label) in enumerate(zip(paper.NOISE_LANES, paper.NOISE_SHAPES)):
    row = f"{lane}{paper.NOISE_DIRECTION}"
    lines.append(f"| success ({label}) (paper) | " + " | ".join(
        f"{table[k][row]['success']}/{runs} ({paper.PAPER_NOISE[k][col]}/{runs})"
        for k in table) + " |")
    lines.append(f"| v mean +- std ({label}) | " + " | ".join(
        f"{table[k][row]['v_mean']:.2f} +- {table[k][row]['v_std']:.2f}" for k in table) + " |")
  out.mkdir(parents=True, exist_ok=True)
  atomic.write_text(out / "noise.md", "\n".join(lines) + "\n")
  atomic.write_text(out / "noise.json", json.dumps({str(k): v for k, v in table.items()}))
  _plot_noise(table, out / "noise.png")
  return table


def _plot_noise(table: dict, path: Path) -> None:
  """v and w (mean +- std) of each noise row against the noise factor."""
  import matplotlib.pyplot as plt
  fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
  ks = list(table)
  for lane in (f"{lane}{paper.NOISE_DIRECTION}" for lane in paper.NOISE_LANES):
    for ax, key in zip(axes, ("v", "w")):
      ax.errorbar(ks, [table[k][lane][f"{key}_mean"] for k in ks],
                  [table[k][lane][f"{key}_std"] for k in ks], marker="o", capsize=3, label=lane)
      ax.set_xlabel("noise factor")
      ax.set_ylabel(f"{key} ({'m/s' if key == 'v' else 'rad/s'})")
  axes[0].legend()
  fig.tight_layout()
  with atomic.atomic_path(path) as tmp:
    fig.savefig(tmp, dpi=110)
  plt.close(fig)


def sweep_robots(cfg, policy_spec, world, out: Path, seed=0, which="best", member=None) -> dict:
  """The platform table: Jackal vs Husky on the robot test's rows (lanes 1F and 4F), 3
  runs each, of `world` at the config's noise. Returns {(robot, "1F"): row, ...}."""
  table = {}
  for robot in paper.ROBOTS:
    doc = evaluate(replace(cfg, robot={"name": robot}), PolicySource(policy_spec, which, member),
                   world, Protocol(paper.ROBOT_RUNS, cfg.eval.noise_factor, paper.ROBOT_LANES,
                                   (paper.ROBOT_DIRECTION,), seed))
    for r in doc["rows"]:
      table[(robot, f"{r['lane']}{r['direction']}")] = r
  runs = paper.ROBOT_RUNS
  lines = [f"# Robots ({runs} runs each)", "", "| row | robot | success (paper) | T_avg s "
           "(paper) | MAE m (paper) | RMSE m (paper) |", "|---|---|---|---|---|---|"]
  order = lambda kv: (kv[0][1], paper.ROBOTS.index(kv[0][0]))  # by lane, then robot
  for (robot, lane), r in sorted(table.items(), key=order):
    p = paper.PAPER_ROBOTS[(robot, lane)]
    lines.append(f"| {lane} | {robot} | {r['success']}/{runs} ({p[0]}/{runs}) | "
                 f"{fmt(r['time_to_eor_s'], 1)} ({paper.PAPER_ROBOT_TIMES[(robot, lane)]}) | "
                 f"{metric_cell(r, 'mae_m')} ({p[1]}) | {metric_cell(r, 'rmse_m')} ({p[2]}) |")
  out.mkdir(parents=True, exist_ok=True)
  atomic.write_text(out / "robots.md", "\n".join(lines) + "\n")
  atomic.write_text(out / "robots.json",
                    json.dumps({f"{k[0]}_{k[1]}": v for k, v in table.items()}))
  import matplotlib.pyplot as plt
  fig, ax = plt.subplots(figsize=(6, 3.5))
  labels = [f"{r} {l}" for (r, l) in table]
  ax.bar(labels, [v["mae_m"] or 0 for v in table.values()], color="tab:green")
  ax.set_ylabel("MAE (m)")
  fig.tight_layout()
  with atomic.atomic_path(out / "robots.png") as tmp:
    fig.savefig(tmp, dpi=110)
  plt.close(fig)
  return table
