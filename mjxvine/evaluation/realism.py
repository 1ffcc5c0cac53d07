"""The realism suite: a policy where a field run would fail first, one factor at a time.

  python -m mjxvine.evaluate --policy models/jackal.npz --suite realism --out out/realism

Each condition is a set of config values (`CONDITIONS`) that sets every factor, whatever
the policy was trained with: the ideal simulator (`IDEAL`), then each
factor alone at the high end of its field range (the stereo camera, command latency, the
velocity loop's lag, the camera mount's error, the IMU's yaw drift), each season, and all
of them together. Every condition drives the paper's protocol (every lane-direction,
`runs` runs each, deterministic action) on test worlds 0-3 in one batched rollout and,
when given, on a vineyard file's block (`BLOCK_RUNS` runs per lane-direction) in a second.

Writes report.json (`conditions` -> condition -> world -> `success`, `runs`, `mae_m`,
`worst`) and report.md (one table: success and MAE per world, the worst lane-direction
named). The numbers behind each condition are in docs/sim-to-real.md.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable, NamedTuple

from mjxvine import atomic
from mjxvine.config import SENSOR_PRESETS, Config, replace
from mjxvine.evaluation import paper
from mjxvine.evaluation.metrics import summarize
from mjxvine.evaluation.rollout import Cases, PolicySource, all_lanes, rollout_cases
from mjxvine.formatting import fmt
from mjxvine.worlds import make_world, world_of
from mjxvine.worlds.seasons import DRAWN_SEASONS

FIELD_SENSOR = "d435"
# The robot's faults at the high end of their field ranges (docs/sim-to-real.md): the
# realism recipe trains on [0, these], the velocity lag on [0, 0.1] s.
ROBOT_HIGH = {"latency_steps": (2, 2), "velocity_lag_s": (0.25, 0.25),
              "mount_pitch_deg": (3.0, 3.0), "mount_roll_deg": (2.0, 2.0),
              "mount_height_m": (0.03, 0.03), "yaw_walk_deg": 0.3}
SEASONS = DRAWN_SEASONS  # spring, summer, winter
ALL_SEASON = "summer"  # the season of "all": posts, a full canopy, shoots and tufts
BLOCK_RUNS = 2  # runs of each lane-direction of a vineyard file's block


TUFTS_PER_M2 = 1.0  # grass and weed tufts on the lane floor of every season


def _sensor(preset: str) -> dict:
  return {"preset": preset, **SENSOR_PRESETS[preset]}


# Every factor off: the ideal simulator, whatever the policy was trained with.
IDEAL = {"sensor": _sensor("ideal"),
         "robot": {"latency_steps": (0, 0), "velocity_lag_s": (0.0, 0.0),
                   "mount_pitch_deg": (0.0, 0.0), "mount_roll_deg": (0.0, 0.0),
                   "mount_height_m": (0.0, 0.0), "yaw_walk_deg": 0.0},
         "world": {"season": "classic", "tuft_density_per_m2": 0.0}}


def _with(**sections: dict) -> dict:
  """`IDEAL` with the values of `sections` laid over it, section by section."""
  return {s: {**v, **sections.get(s, {})} for s, v in IDEAL.items()}


def _robot(*keys: str) -> dict:
  return {k: ROBOT_HIGH[k] for k in keys}


def _season(season: str) -> dict:
  return {"season": season, "tuft_density_per_m2": TUFTS_PER_M2}


CONDITIONS: dict[str, dict] = {
    "ideal": IDEAL,
    "sensor": _with(sensor=_sensor(FIELD_SENSOR)),
    "latency": _with(robot=_robot("latency_steps")),
    "lag": _with(robot=_robot("velocity_lag_s")),
    "mount": _with(robot=_robot("mount_pitch_deg", "mount_roll_deg", "mount_height_m")),
    "yaw_drift": _with(robot=_robot("yaw_walk_deg")),
    **{season: _with(world=_season(season)) for season in SEASONS},
    "all": _with(sensor=_sensor(FIELD_SENSOR), robot=_robot(*ROBOT_HIGH),
                 world=_season(ALL_SEASON)),
}


def condition_config(cfg: Config, name: str) -> Config:
  """`cfg` under the suite's condition `name` (`CONDITIONS`); ValueError for an unknown
  name."""
  if name not in CONDITIONS:
    raise ValueError(f"condition {name!r}: one of {', '.join(CONDITIONS)}")
  return replace(cfg, **CONDITIONS[name])


def _rank(r: dict) -> tuple:
  """Sort key of a lane-direction, weakest first: fewest successes, then the largest MAE."""
  mae = r["mae_m_raw"] if r.get("mae_m_raw") is not None else float("inf")
  return (r["success"] / max(r["runs"], 1), -mae)


def _worst(rows: list[dict]) -> dict | None:
  """The weakest lane-direction of `rows` (`_rank`): its row, successes, runs, MAE."""
  if not rows:
    return None
  r = min(rows, key=_rank)
  return {"row": f"{r['lane']}{r['direction']}", "success": r["success"], "runs": r["runs"],
          "mae_m_raw": r["mae_m_raw"]}


class SuiteRuns(NamedTuple):
  """What each condition drives: `runs` runs of every lane-direction of the test worlds
  `worlds` (seeds), `BLOCK_RUNS` of every lane-direction of the vineyard file `block`
  (None: none), with rollout key `seed`."""
  runs: int = paper.RUNS
  worlds: tuple = paper.SUITE_WORLDS
  block: str | None = None
  seed: int = 0


def realism_suite(cfg: Config, source: PolicySource, out: Path,
                  drive: SuiteRuns = SuiteRuns(), conditions=tuple(CONDITIONS),
                  say: Callable[[str], None] = print) -> dict:
  """Runs the suite (module docstring) for the policy of `source` under each of
  `conditions` and writes report.json and report.md under `out`. Returns the report."""
  out = Path(out)
  runs, worlds, block, seed = drive
  report = {"policy": source.spec, "seed": seed, "runs": runs, "block": block,
            "conditions": {}, "wall_s": 0.0}
  for name in conditions:
    ccfg = condition_config(cfg, name)
    groups = [([make_world(str(s), ccfg.world) for s in worlds], [str(s) for s in worlds],
               runs)]
    if block:  # its own rollout: its longer rows would hold the test worlds' runs back
      groups.append(([world_of(block, ccfg)], [Path(block).stem], BLOCK_RUNS))
    say(f"realism suite: {name}...")
    report["conditions"][name] = {}
    for tests, labels, n in groups:
      cases = Cases()
      idx = [cases.add(i, all_lanes(w), ccfg.eval.noise_factor, n) for i, w in enumerate(tests)]
      raw, report["policy"] = rollout_cases(ccfg, source, tests, cases, seed=seed)
      report["wall_s"] += raw["wall_s"]
      for label, world, group in zip(labels, tests, idx):
        doc = summarize(ccfg, world, cases, group, raw)
        o = doc["overall"]
        report["conditions"][name][label] = {
            "success": o["success"], "runs": o["runs"], "mae_m": o["mae_m_rows"],
            "worst": _worst(doc["rows"])}
    say(f"realism suite: {name}: " + "; ".join(
        f"{_column(label)} {_cell(r)}" for label, r in report["conditions"][name].items()))
  out.mkdir(parents=True, exist_ok=True)
  atomic.write_text(out / "report.json", json.dumps(report))
  atomic.write_text(out / "report.md", report_markdown(report))
  return report


def _column(label: str) -> str:
  """A world's name in the report: "world 2" for a test world's seed, a file's stem as is."""
  return f"world {label}" if label.isdigit() else label


def _cell(r: dict) -> str:
  """A world's result under a condition: "successes/runs, MAE m" ("n/a": none arrived)."""
  return f"{r['success']}/{r['runs']}, " + ("n/a" if r["mae_m"] is None else fmt(r["mae_m"]))


def report_markdown(report: dict) -> str:
  """The suite's table: a row per condition, success and MAE per world, the worst case."""
  names = list(report["conditions"])
  labels = list(report["conditions"][names[0]]) if names else []
  block = f", {BLOCK_RUNS} on the block of {report['block']}" if report.get("block") else ""
  lines = [f"# The realism suite: {report['policy']}", "",
           f"Deterministic action; {report['runs']} runs per lane-direction on each test "
           f"world{block}; rollout seed "
           f"{report['seed']}. Each cell: successes / runs, MAE m (the mean of the rows). "
           "Conditions: docs/sim-to-real.md.", "",
           "| condition | " + " | ".join(map(_column, labels))
           + " | worst case |",
           "|---" * (len(labels) + 2) + "|"]
  for name in names:
    per_world = report["conditions"][name]
    cells = [_cell(r) for r in per_world.values()]
    named = [(label, r["worst"]) for label, r in per_world.items() if r["worst"]]
    worst = "-"
    if named:
      label, w = min(named, key=lambda lw: _rank(lw[1]))
      worst = f"{label} {w['row']}: {w['success']}/{w['runs']}"
    lines.append(f"| {name} | " + " | ".join(cells) + f" | {worst} |")
  lines += ["", f"Rollout wall-clock: {report['wall_s']:.0f} s."]
  return "\n".join(lines) + "\n"
