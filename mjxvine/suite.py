"""The paper's whole evaluation of one policy, in one command:

  python -m mjxvine.evaluate --policy models/jackal.npz --suite paper --out out/paper

  * the test-world table (the paper's protocol: 5 lanes x 2 directions x 5 runs) on test
    world 0, the paper's vineyard, and the same table on test worlds 1, 2 and 3, drawn by
    the same generator and never used in training (`SUITE_WORLDS`);
  * the noise test: lanes 1F (straight) and 4F (curved) of world 0, 3 runs each, depth
    noise factors 1, 2, 4, 6, 8 and 10 (`NOISE_FACTORS`);
  * the robot test: the policy on the Husky, lanes 1F and 4F of world 0, 3 runs each,
    beside the Jackal's runs of the same lanes.

Every Jackal case (226 episodes) runs in one batched rollout, the Husky's in a second.
Writes report.md (a summary with the paper's numbers beside ours, then every table),
report.json, and world<k>/ (results.json, results.md, trajectories.png) per test world.
"""

from __future__ import annotations

import json
from pathlib import Path

from mjxvine import evaluate as ev
from mjxvine.config import Config, replace
from mjxvine.worlds import make_world

SUITE_WORLDS = (0, 1, 2, 3)
NOISE_FACTORS = (1, 2, 4, 6, 8, 10)
NOISE_LANES = ((1, "straight"), (4, "curved"))
SMALL_RUNS = 3  # runs per lane of the noise and robot tests, as the paper's


def paper_suite(cfg: Config, policy_spec: str, out: Path, *, runs: int = 5,
                worlds=SUITE_WORLDS, seed: int = 0, which: str = "best",
                member: int | None = None) -> dict:
  """Runs the suite (see the module docstring) and writes its report under `out`.
  Returns the report document (report.json)."""
  out = Path(out)
  tests = [make_world(str(s), cfg.world) for s in worlds]
  noise0 = cfg.eval.noise_factor
  cases, tables, noise = [], {}, {}

  def add(world, lane, direction, factor, n):
    first = len(cases)
    cases.extend([(world, lane, direction, factor)] * n)
    return list(range(first, len(cases)))

  for wi, world in enumerate(tests):
    tables[wi] = [i for lane in range(1, len(world.lanes) + 1) for d in ("F", "R")
                  for i in add(wi, lane, d, noise0, runs)]
  for k in NOISE_FACTORS:
    noise[k] = [i for lane, _ in NOISE_LANES for i in add(0, lane, "F", float(k), SMALL_RUNS)]
  jackal = [i for lane, _ in NOISE_LANES for i in add(0, lane, "F", noise0, SMALL_RUNS)]
  raw, name = ev.rollout_cases(cfg, policy_spec, tests, cases, seed=seed, which=which,
                               member=member)

  report = {"policy": name, "seed": seed, "runs": runs, "worlds": {}, "noise": {},
            "robots": {}, "wall_s": raw["wall_s"]}
  for wi, world in enumerate(tests):
    doc = {"policy": name, "noise": noise0, **ev.summarize(cfg, world, cases, tables[wi], raw)}
    ev.write_results(doc, world, out / f"world{worlds[wi]}")
    report["worlds"][str(worlds[wi])] = {"overall": doc["overall"], "rows": [
        {k: v for k, v in r.items() if k != "outcomes"} for r in doc["rows"]]}
  for k in NOISE_FACTORS:
    doc = ev.summarize(cfg, tests[0], cases, noise[k], raw)
    report["noise"][str(k)] = {f"{r['lane']}F": r for r in doc["rows"]}

  husky = replace(cfg, robot={"name": "husky"})
  h_cases = [(0, lane, "F", noise0) for lane, _ in NOISE_LANES for _ in range(SMALL_RUNS)]
  h_raw, _ = ev.rollout_cases(husky, policy_spec, tests[:1], h_cases, seed=seed, which=which,
                              member=member)
  report["wall_s"] += h_raw["wall_s"]
  h_doc = ev.summarize(husky, tests[0], h_cases, range(len(h_cases)), h_raw)
  for robot, doc in (("jackal", ev.summarize(cfg, tests[0], cases, jackal, raw)),
                     ("husky", h_doc)):
    for r in doc["rows"]:
      report["robots"][f"{robot}_{r['lane']}F"] = r

  out.mkdir(parents=True, exist_ok=True)
  (out / "report.json").write_text(json.dumps(report))
  (out / "report.md").write_text(report_markdown(report, worlds))
  return report


def _row_label(r: dict) -> str:
  return f"{r['lane']}{r['direction']}"


def report_markdown(report: dict, worlds=SUITE_WORLDS) -> str:
  """The suite's report: a summary, then the noise, robot and per-world tables."""
  lines = [f"# The paper's evaluation: {report['policy']}", "",
           f"Deterministic action, {report['runs']} runs per lane-direction on each test "
           f"world, rollout seed {report['seed']}; test world 0 is the paper's vineyard, "
           "1-3 are drawn by the same generator. MAE/RMSE: the mean of the ten rows (the "
           "paper's overall figure), \"(partial)\" when some runs of a row stopped before "
           "the end of the row.", "",
           "| test world | success | lane-directions below 4/5 | MAE m | RMSE m |",
           "|---|---|---|---|---|"]
  p = ev.PAPER["overall"]
  for w in worlds:
    o, rows = report["worlds"][str(w)]["overall"], report["worlds"][str(w)]["rows"]
    weak = [f"{_row_label(r)} {r['success']}/{r['runs']}" for r in rows
            if r["success"] < 0.8 * r["runs"]]
    part = "" if o["rows_status"] == "full" else f" ({o['rows_status']})"
    lines.append(f"| {w} | {o['success']}/{o['runs']} | {', '.join(weak) or 'none'} | "
                 f"{ev._fmt(o['mae_m_rows'])}{part} | {ev._fmt(o['rmse_m_rows'])}{part} |")
  lines.append(f"| paper (world 0) | {p[6]}/50 | 3R 2/5, 5F 3/5 | {p[0]:.3f} | {p[1]:.3f} |")

  lines += ["", "## Noise (world 0, lanes 1F and 4F, 3 runs each)", "",
            "| noise factor | " + " | ".join(str(k) for k in NOISE_FACTORS) + " |",
            "|---" * (len(NOISE_FACTORS) + 1) + "|"]
  for lane, label in NOISE_LANES:
    col = 0 if label == "straight" else 1
    cells = []
    for k in NOISE_FACTORS:
      r = report["noise"][str(k)][f"{lane}F"]
      paper = ev.PAPER_NOISE.get(k)
      cells.append(f"{r['success']}/{r['runs']}" + (f" ({paper[col]}/3)" if paper else ""))
    lines.append(f"| {lane}F {label}: success (paper) | " + " | ".join(cells) + " |")
    lines.append(f"| {lane}F: MAE m | " + " | ".join(
        ev._metric(report["noise"][str(k)][f"{lane}F"], "mae_m") for k in NOISE_FACTORS) + " |")

  lines += ["", "## Robots (world 0, 3 runs each; the policy was trained on the Jackal)", "",
            "| row | robot | success (paper) | MAE m (paper) | RMSE m (paper) |",
            "|---|---|---|---|---|"]
  for lane, _ in NOISE_LANES:
    for robot in ("jackal", "husky"):
      r = report["robots"][f"{robot}_{lane}F"]
      pr = ev.PAPER_ROBOTS[(robot, f"{lane}F")]
      lines.append(f"| {lane}F | {robot} | {r['success']}/{r['runs']} ({pr[0]}/3) | "
                   f"{ev._metric(r, 'mae_m')} ({pr[1]}) | {ev._metric(r, 'rmse_m')} ({pr[2]}) |")

  for w in worlds:
    doc = report["worlds"][str(w)]
    lines += ["", f"## Test world {w}" + (" (the paper's)" if w == 0 else ""), "",
              f"![trajectories](world{w}/trajectories.png)", "",
              "| row | shape | success | lane covered | MAE m | RMSE m | v m/s | w rad/s |"
              + (" paper: success, MAE, RMSE |" if w == 0 else ""),
              "|---|---|---|---|---|---|---|---|" + ("---|" if w == 0 else "")]
    for r in doc["rows"]:
      pr = ev.PAPER.get(_row_label(r))
      lines.append(
          f"| {_row_label(r)} | {r['shape']} | {r['success']}/{r['runs']} | "
          f"{r['lane_covered_frac']:.0%} | {ev._metric(r, 'mae_m')} | {ev._metric(r, 'rmse_m')} | "
          f"{r['v_mean']:.3f} | {r['w_mean']:.3f} |"
          + (f" {pr[6]}/5, {pr[0]:.3f}, {pr[1]:.3f} |" if w == 0 and pr else ""))
  lines += ["", f"Rollout wall-clock: {report['wall_s']:.0f} s."]
  return "\n".join(lines) + "\n"
