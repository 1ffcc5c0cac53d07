"""The paper's whole evaluation of one policy, in one command:

  python -m mjxvine.evaluate --policy models/jackal.npz --suite paper --out out/paper

  * the test-world table (the paper's protocol: 5 lanes x 2 directions x 5 runs) on test
    world 0 (this generator's seed 0, laid out as the paper's test vineyard), and the same
    table on test worlds 1, 2 and 3, drawn by the same generator and never used in training (`paper.SUITE_WORLDS`);
  * the noise test: lanes 1F (straight) and 4F (curved) of world 0, 3 runs each, depth
    noise factors 1, 2, 4, 6, 8 and 10 (`paper.NOISE_FACTORS`);
  * the robot test: the policy on the Husky, lanes 1F and 4F of world 0, 3 runs each,
    beside the Jackal's runs of the same lanes.

Every Jackal case (242 episodes) runs in one batched rollout, the Husky's in a second.
Writes report.md (a summary with the paper's numbers beside ours, then every table),
report.json, and world<k>/ (results.json, results.md, trajectories.png) per test world.
"""

from __future__ import annotations

import json
from pathlib import Path

from mjxvine import atomic
from mjxvine.config import Config, replace
from mjxvine.evaluation import paper
from mjxvine.evaluation.metrics import summarize
from mjxvine.evaluation.report import metric_cell, write_results
from mjxvine.evaluation.rollout import Cases, PolicySource, all_lanes, rollout_cases
from mjxvine.formatting import fmt
from mjxvine.worlds import make_world


def paper_suite(cfg: Config, policy_spec: str, out: Path, *, runs: int = paper.RUNS,
                worlds=paper.SUITE_WORLDS, seed: int = 0, which: str = "best",
                member: int | None = None) -> dict:
  """Runs the suite (see the module docstring) and writes its report under `out`.
  Returns the report document (report.json)."""
  out = Path(out)
  tests = [make_world(str(s), cfg.world) for s in worlds]
  noise0 = cfg.eval.noise_factor
  cases = Cases()
  tables = {wi: cases.add(wi, all_lanes(world), noise0, runs) for wi, world in enumerate(tests)}
  noise = {k: cases.add(0, paper.noise_rows(), float(k), paper.NOISE_RUNS)
           for k in paper.NOISE_FACTORS}
  jackal = cases.add(0, paper.robot_rows(), noise0, paper.ROBOT_RUNS)
  source = PolicySource(policy_spec, which, member)
  raw, name = rollout_cases(cfg, source, tests, cases, seed=seed)

  report = {"policy": name, "seed": seed, "runs": runs, "worlds": {}, "noise": {},
            "robots": {}, "wall_s": raw["wall_s"]}
  for wi, world in enumerate(tests):
    doc = {"policy": name, "noise": noise0, **summarize(cfg, world, cases, tables[wi], raw)}
    write_results(doc, world, out / f"world{worlds[wi]}")
    report["worlds"][str(worlds[wi])] = {"overall": doc["overall"], "rows": [
        {k: v for k, v in r.items() if k != "outcomes"} for r in doc["rows"]]}
  for k in paper.NOISE_FACTORS:
    doc = summarize(cfg, tests[0], cases, noise[k], raw)
    report["noise"][str(k)] = {f"{r['lane']}F": r for r in doc["rows"]}

  # the other robots: a rollout each (their own env), of the Jackal's rows
  docs = {"jackal": summarize(cfg, tests[0], cases, jackal, raw)}
  for robot in paper.ROBOTS[1:]:
    other = replace(cfg, robot={"name": robot})
    r_cases = Cases()
    r_cases.add(0, paper.robot_rows(), noise0, paper.ROBOT_RUNS)
    r_raw, _ = rollout_cases(other, source, tests[:1], r_cases, seed=seed)
    report["wall_s"] += r_raw["wall_s"]
    docs[robot] = summarize(other, tests[0], r_cases, range(len(r_cases)), r_raw)
  for robot, doc in docs.items():
    for r in doc["rows"]:
      report["robots"][f"{robot}_{r['lane']}F"] = r

  out.mkdir(parents=True, exist_ok=True)
  atomic.write_text(out / "report.json", json.dumps(report))
  atomic.write_text(out / "report.md", report_markdown(report, worlds))
  return report


def _row_label(r: dict) -> str:
  return f"{r['lane']}{r['direction']}"


def report_markdown(report: dict, worlds=paper.SUITE_WORLDS) -> str:
  """The suite's report: a summary, then the noise, robot and per-world tables."""
  lines = _summary_table(report, worlds) + _noise_table(report) + _robot_table(report)
  for w in worlds:
    lines += _world_table(report, w)
  lines += ["", f"Rollout wall-clock: {report['wall_s']:.0f} s."]
  return "\n".join(lines) + "\n"


def _summary_table(report: dict, worlds) -> list[str]:
  """The report's title, what it is, and one line per test world beside the paper's."""
  lines = [f"# The paper's evaluation: {report['policy']}", "",
           f"Deterministic action, {report['runs']} runs per lane-direction on each test "
           f"world, rollout seed {report['seed']}; test world 0 is the generator's seed 0 "
           "(the paper's figures come from its own simulator), 1-3 are its seeds 1-3. MAE/RMSE: the mean of the ten rows (the "
           "paper's overall figure), \"(partial)\" when some runs of a row stopped before "
           "the end of the row.", "",
           "| test world | success | lane-directions below 4/5 | MAE m | RMSE m |",
           "|---|---|---|---|---|"]
  p = paper.PAPER["overall"]
  for w in worlds:
    o, rows = report["worlds"][str(w)]["overall"], report["worlds"][str(w)]["rows"]
    weak = [f"{_row_label(r)} {r['success']}/{r['runs']}" for r in rows
            if r["success"] < 0.8 * r["runs"]]
    part = "" if o["rows_status"] == "full" else f" ({o['rows_status']})"
    lines.append(f"| {w} | {o['success']}/{o['runs']} | {', '.join(weak) or 'none'} | "
                 f"{fmt(o['mae_m_rows'])}{part} | {fmt(o['rmse_m_rows'])}{part} |")
  lines.append(f"| paper (world 0) | {p[6]}/{paper.PAPER_RUNS} | "
               f"{', '.join(paper.weak_rows(0.8))} | {p[0]:.3f} | {p[1]:.3f} |")
  return lines


def _noise_table(report: dict) -> list[str]:
  """Successes and MAE of the noise test's rows at each noise factor, beside the paper's."""
  rows = " and ".join(f"{lane}{d}" for lane, d in paper.noise_rows())
  lines = ["", f"## Noise (world 0, lanes {rows}, {paper.NOISE_RUNS} runs each)", "",
           "| noise factor | " + " | ".join(str(k) for k in paper.NOISE_FACTORS) + " |",
           "|---" * (len(paper.NOISE_FACTORS) + 1) + "|"]
  for col, (lane, label) in enumerate(zip(paper.NOISE_LANES, paper.NOISE_SHAPES)):
    cells = []
    for k in paper.NOISE_FACTORS:
      r = report["noise"][str(k)][f"{lane}F"]
      figure = paper.PAPER_NOISE.get(k)
      cells.append(f"{r['success']}/{r['runs']}" +
                   (f" ({figure[col]}/{paper.NOISE_RUNS})" if figure else ""))
    lines.append(f"| {lane}F {label}: success (paper) | " + " | ".join(cells) + " |")
    lines.append(f"| {lane}F: MAE m | " + " | ".join(
        metric_cell(report["noise"][str(k)][f"{lane}F"], "mae_m")
        for k in paper.NOISE_FACTORS) + " |")
  return lines


def _robot_table(report: dict) -> list[str]:
  """The robot test's rows on each robot, beside the paper's."""
  lines = ["", f"## Robots (world 0, {paper.ROBOT_RUNS} runs each; the policy was trained on "
           "the Jackal)", "",
           "| row | robot | success (paper) | MAE m (paper) | RMSE m (paper) |",
           "|---|---|---|---|---|"]
  for lane, d in paper.robot_rows():
    for robot in paper.ROBOTS:
      r = report["robots"][f"{robot}_{lane}{d}"]
      pr = paper.PAPER_ROBOTS[(robot, f"{lane}{d}")]
      lines.append(f"| {lane}{d} | {robot} | {r['success']}/{r['runs']} "
                   f"({pr[0]}/{paper.ROBOT_RUNS}) | {metric_cell(r, 'mae_m')} ({pr[1]}) | "
                   f"{metric_cell(r, 'rmse_m')} ({pr[2]}) |")
  return lines


def _world_table(report: dict, w: int) -> list[str]:
  """Test world `w`'s rows (and, for world 0, the paper's figures beside them)."""
  doc = report["worlds"][str(w)]
  lines = ["", f"## Test world {w}", "",
           f"![trajectories](world{w}/trajectories.png)", "",
           "| row | shape | success | lane covered | MAE m | RMSE m | v m/s | w rad/s |"
           + (" paper: success, MAE, RMSE |" if w == 0 else ""),
           "|---|---|---|---|---|---|---|---|" + ("---|" if w == 0 else "")]
  for r in doc["rows"]:
    pr = paper.PAPER.get(_row_label(r))
    lines.append(
        f"| {_row_label(r)} | {r['shape']} | {r['success']}/{r['runs']} | "
        f"{r['lane_covered_frac']:.0%} | {metric_cell(r, 'mae_m')} | {metric_cell(r, 'rmse_m')} | "
        f"{r['v_mean']:.3f} | {r['w_mean']:.3f} |"
        + (f" {pr[6]}/{paper.RUNS}, {pr[0]:.3f}, {pr[1]:.3f} |" if w == 0 and pr else ""))
  return lines
