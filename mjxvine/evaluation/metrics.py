"""The protocol's figures of a group of runs (docs/evaluation.md): successes, MAE and RMSE
of the trajectory's distance to the lane's ground-truth line (over the part inside the
row), the part of the lane covered, and the commanded speeds v (m/s) and w (rad/s).

A run that ends early (collision, leaving the lane, ...) has a short trajectory, and its
MAE/RMSE are not comparable to the paper's: `metrics_status` is "full" when every run of a
group reached the end of the row (EoR), "partial" when some did, "n/a" when none did (then
`mae_m`/`rmse_m` are None; `mae_m_raw`/`rmse_m_raw` keep the numbers).
"""

from __future__ import annotations

import numpy as np

from mjxvine.episodes import OUTCOMES, SUCCESS
from mjxvine.evaluation.geometry import arc_length, lane_progress, trajectory_errors


def metrics_status(successes: int, runs: int) -> str:
  """"full" when every run reached its EoR, "partial" when some did, "n/a" when none did."""
  return "full" if runs and successes == runs else "partial" if successes else "n/a"


def group_metrics(errs, acts, outcomes, steps, dt, covered_m, covered_frac) -> dict:
  """Metrics of a group of runs: errs/acts per run (n_i,) m / (n_i, 2), outcome codes,
  steps per run, the control step dt (s), lane covered per run (m, fraction of the lane)."""
  errs = np.concatenate(errs) if errs else np.zeros(0)
  acts = np.concatenate(acts) if acts else np.zeros((0, 2))
  succ = [o == SUCCESS for o in outcomes]
  times = [s * dt for s, ok in zip(steps, succ) if ok]
  status = metrics_status(int(sum(succ)), len(outcomes))
  mae = float(np.mean(errs)) if errs.size else None
  rmse = float(np.sqrt(np.mean(errs ** 2))) if errs.size else None
  return {
      "success": int(sum(succ)), "runs": len(outcomes), "metrics_status": status,
      # no run reached the EoR: the errors of a few metres of lane say nothing comparable
      "mae_m": None if status == "n/a" else mae, "rmse_m": None if status == "n/a" else rmse,
      "mae_m_raw": mae, "rmse_m_raw": rmse,
      "lane_covered_m": float(np.mean(covered_m)),
      "lane_covered_frac": float(np.mean(covered_frac)),
      "v_mean": float(acts[:, 0].mean()), "v_std": float(acts[:, 0].std()),
      "w_mean": float(acts[:, 1].mean()), "w_std": float(acts[:, 1].std()),
      "time_to_eor_s": float(np.mean(times)) if times else None,
  }


def summarize(cfg, world, cases, idx, raw: dict) -> dict:
  """The rows (one per lane-direction, in case order), the overall figures and the
  trajectories of the cases `idx` (indices into `cases` and `raw`), all on `world`.

  cfg: the `Config` of the rollout (its robot and control step); cases: the
  `rollout.Cases` tuples (world index, lane, direction, noise); raw: `rollout_cases`'s
  arrays. overall: the pooled metrics of every trajectory point, plus the mean of the rows
  (`mae_m_rows`, `rmse_m_rows`, `v_mean_rows`, `w_mean_rows`, ...): the paper's overall
  row is the mean of its ten row values, so that is what compares with it."""
  xy, act, alive, outcome, steps = (raw[k] for k in ("xy", "act", "alive", "outcome", "steps"))
  keys = list(dict.fromkeys((cases[i][1], cases[i][2]) for i in idx))
  rows, all_err, all_act, all_m, all_frac, trajs = [], [], [], [], [], []
  for lane, direction in keys:
    group = [i for i in idx if cases[i][1:3] == (lane, direction)]
    line = world.lanes[lane - 1].centerline
    length = arc_length(line)
    errs = [trajectory_errors(xy[alive[:, i], i], line) for i in group]
    acts = [act[alive[:, i], i] for i in group]
    # A run that reached its EoR covered the lane, though it stops within the success
    # radius of the line's end.
    covered = [length if outcome[i] == SUCCESS else
               min(lane_progress(xy[alive[:, i], i], line, direction), length) for i in group]
    row = group_metrics(errs, acts, [int(outcome[i]) for i in group],
                        [int(steps[i]) for i in group], cfg.env.control_dt, covered,
                        [c / length for c in covered])
    row.update(lane=lane, direction=direction, shape=world.lanes[lane - 1].shape,
               lane_length_m=length, outcomes=[OUTCOMES[int(outcome[i])] for i in group])
    rows.append(row)
    all_err += errs
    all_act += acts
    all_m += covered
    all_frac += [c / length for c in covered]
    trajs += [{"lane": lane, "direction": direction, "outcome": OUTCOMES[int(outcome[i])],
               "lane_covered_m": round(c, 3), "xy": xy[alive[:, i], i].round(3).tolist()}
              for i, c in zip(group, covered)]
  overall = group_metrics(all_err, all_act, [int(outcome[i]) for i in idx],
                          [int(steps[i]) for i in idx], cfg.env.control_dt, all_m, all_frac)
  overall.update(mean_of_rows(rows))
  where = {"kind": world.kind, "seed": world.seed}
  if world.frame:  # a vineyard file's block
    where["source"] = world.frame.get("source", "")
  return {"robot": cfg.robot.name, "world": where,
          "overall": overall, "rows": rows, "wall_s": raw["wall_s"], "trajectories": trajs}


def mean_of_rows(rows: list[dict]) -> dict:
  """The paper's overall figures: means of the row values (MAE, RMSE, v, w and their
  stds), `*_rows` keys. MAE/RMSE average the rows that have them (`rows_status`: "full"
  when every row's runs all reached the EoR, else "partial", "n/a" when none has them)."""
  out = {}
  for key in ("v_mean", "v_std", "w_mean", "w_std"):
    out[f"{key}_rows"] = float(np.mean([r[key] for r in rows]))
  for key in ("mae_m", "rmse_m"):
    vals = [r[key] for r in rows if r[key] is not None]
    out[f"{key}_rows"] = float(np.mean(vals)) if vals else None
  full = all(r["metrics_status"] == "full" for r in rows)
  out["rows_status"] = "full" if full else "partial" if out["mae_m_rows"] is not None else "n/a"
  return out
