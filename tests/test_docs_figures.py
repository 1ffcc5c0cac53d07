"""The figures of the README's results table and of every table of
docs/results/reproduction.md are read from the records under docs/results/.

Each table has a spec here: for every row (by its first cell) and column, the record a
cell quotes and the check that reads it: the paper's suite reports (`report.json`), the
evaluations of held-out, validation and closing worlds (`results.md`-style tables), a run's
`best.json`, `selection.json`, `metrics.jsonl` and `config.yaml`, and the paper's own
figures (`mjxvine.evaluation.paper`). Bold (`**`) marks a met target and is not a figure.
A cell that is not from a record (a target, the machine, a command) names its reason in
the spec instead, and every cell of a specced table that holds a digit is one or the other.
The lists in cells are read as the docs write them: successes as "50/50" or "50"; MAE
lists with "(partial)" after a figure whose rows did not all reach the end (a "(partial)"
at the end of a list may stand for several); a note such as "(world 2 5R 0/5)" names
lane-directions and their successes, each of which must be so (where a column lists the
lane-directions below 4/5, exactly those). "The report" section of reproduction.md is the
shipped policy's suite report as `mjxvine.evaluation.suite.report_markdown` writes it.
"""

from __future__ import annotations

import functools
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import yaml

from mjxvine.config import Config, to_dict
from mjxvine.evaluation import choice, paper

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "docs" / "results"
REPRODUCTION = RESULTS / "reproduction.md"
FACTORS = tuple(paper.PAPER_NOISE)  # the noise test's factors that the paper drove
NSTEP = ("jackal-nstep-seed0", "jackal-nstep-seed1", "jackal-nstep-seed2")  # 3-step returns
SEEDS = tuple(f"jackal-taulate-seed{s}" for s in range(5))  # jackal.yaml
LN = tuple(f"jackal-ln-seed{s}" for s in range(4))  # jackal.yaml without sac.tau_late
NATIVE = tuple(f"jackal-native-seed{s}" for s in range(4))  # jackal-ln without LayerNorm
BATCH128 = tuple(f"jackal-b128-seed{s}" for s in (1, 2, 3))  # jackal.yaml, batch 128, 4 steps
SHIPPED = SEEDS[0]            # the run of models/jackal.npz
BEFORE = LN[0]                # the policy shipped before it
GAPS = "`jackal-gaps`, shipped before `jackal-native`, seeds 0, 1, 2"  # its section
LN_SECTION = "`jackal-ln`, the policy shipped before, seeds 0, 1, 2, 3"
NATIVE_SECTION = "`jackal-native`, shipped before `jackal-ln`, seeds 0, 1, 2, 3"
BATCH128_SECTION = "A batch of 128 on the shipped recipe, seeds 1, 2, 3"
BAR = Config().train.select_success_bar  # the choice's bar: no recipe sets another
HELDOUT = (25, 26, 27)        # test worlds first evaluated after the shipped policy was chosen


# --- records --------------------------------------------------------------------------------

@functools.cache
def record(path: str):
  """A record under docs/results/: JSON, JSON lines or YAML, by its suffix."""
  text = (RESULTS / path).read_text()
  if path.endswith(".jsonl"):
    return [json.loads(line) for line in text.splitlines() if line.strip()]
  return yaml.safe_load(text) if path.endswith(".yaml") else json.loads(text)


def suite(folder: str) -> dict:
  return record(f"{folder}/report.json")


@functools.cache
def evaluation(path: str) -> dict[str, dict]:
  """An evaluation's table (`evaluation.report.results_markdown`): label -> success "k/n",
  its counts, and the MAE cell without the paper's figure ("0.088 (partial)")."""
  out = {}
  for line in (RESULTS / path).read_text().splitlines():
    cells = [c.strip() for c in line.strip().strip("|").split("|")]
    if len(cells) == 8 and re.match(r"^(\d[FR]|overall)$", cells[0]):
      success = cells[7].split(" (")[0]
      k, n = map(int, success.split("/"))
      mae = re.sub(r" \(-?[\d.]+\)$", "", cells[3])
      out[cells[0]] = {"success": success, "k": k, "n": n, "mae": mae}
  assert "overall" in out, path
  return out


def f3(x) -> str:
  return "n/a" if x is None else f"{x:.3f}"


def pct(x: float) -> str:
  return f"{100 * x:.0f} %"


def thousands(n: int) -> str:
  return f"{n:,}"


def minutes_seconds(s: float) -> str:
  s = round(s)
  return f"{s // 60} min {s % 60} s"


def lanes_of(report: dict, world: int) -> dict[str, dict]:
  return {f"{r['lane']}{r['direction']}": r for r in report["worlds"][str(world)]["rows"]}


def overall(report: dict, world: int) -> dict:
  return report["worlds"][str(world)]["overall"]


def noise_runs(report: dict, lane: str) -> list[int]:
  return [report["noise"][str(k)][lane]["success"] for k in FACTORS]


def spread(sps: np.ndarray, ups: np.ndarray) -> str:
  """"43-52 and 21-26 for 90 % of the chunks": the 5th-95th percentiles of both rates."""
  return (f"{np.percentile(sps, 5):.0f}-{np.percentile(sps, 95):.0f} and "
          f"{np.percentile(ups, 5):.0f}-{np.percentile(ups, 95):.0f} for 90 % of the chunks")


def learning_speeds(metrics: list[dict]) -> tuple[np.ndarray, np.ndarray]:
  """env steps/s and gradient steps/s of the chunks that learned (a critic loss)."""
  rows = [r for r in metrics if r["critic_loss"]]
  return np.array([r["sps"] for r in rows]), np.array([r["ups"] for r in rows])


# --- what a cell says -------------------------------------------------------------------------

Check = Callable[[str], None]


def exact(text: str) -> Check:
  def check(cell):
    assert cell == text, f"{cell!r}: the record says {text!r}"
  return check


def contains(*figures: str) -> Check:
  def check(cell):
    missing = [f for f in figures if f not in cell]
    assert not missing, f"{cell!r}: the record's {missing} not in it"
  return check


def both(*checks: Check) -> Check:
  def check(cell):
    for c in checks:
      c(cell)
  return check


def _split_note(cell: str) -> tuple[str, str]:
  """"50, 45, 50 (world 2 5R 0/5)" -> ("50, 45, 50", "world 2 5R 0/5")."""
  m = re.match(r"^(.*?) \(([^()]*)\)$", cell)
  return (m.group(1), m.group(2)) if m and "partial" not in m.group(2) else (cell, "")


def claims(note: str, worlds: tuple[int, ...]) -> set[tuple[int, str, int, int]]:
  """(world, lane-direction, successes, runs) of a note such as "world 1 5F, 5R; world 3
  3F 0/5" (a count is that of every lane-direction named since the previous count; one
  with no world named holds on each of `worlds`)."""
  out, pending, world = set(), [], None
  for m in re.finditer(r"world (\d+)|(\d[FR])\b|(\d+)/(\d+)", note):
    if m.group(1):
      world = int(m.group(1))
    elif m.group(2):
      pending += [(w, m.group(2)) for w in ((world,) if world is not None else worlds)]
    else:
      out |= {(w, lane, int(m.group(3)), int(m.group(4))) for w, lane in pending}
      pending = []
  assert not pending and out, f"{note!r}: lane-directions without a count"
  return out


def check_note(note: str, rows: dict[int, dict[str, tuple[int, int]]], *,
               complete: bool = False) -> None:
  """Every lane-direction the note names has those successes (`rows`: world -> label ->
  (successes, runs)); with `complete`, the note names every one below 4/5."""
  worlds = tuple(rows)
  said = set() if note in ("", "none") else claims(note, worlds)
  for w, lane, k, n in said:
    assert lane in rows.get(w, {}), f"{note!r}: no world {w} {lane} in the record"
    assert rows[w][lane] == (k, n), f"{note!r}: world {w} {lane} is {rows[w][lane]}"
  if complete:
    weak = {(w, lane, k, n) for w, r in rows.items() for lane, (k, n) in r.items()
            if k < 0.8 * n}
    assert said == weak, f"{note!r}: the lane-directions below 4/5 are {sorted(weak)}"


def suite_rows(report: dict, worlds) -> dict[int, dict[str, tuple[int, int]]]:
  return {w: {lane: (r["success"], r["runs"]) for lane, r in lanes_of(report, w).items()}
          for w in worlds}


def successes(report: dict, worlds=(1, 2, 3)) -> Check:
  """"50, 45, 50 (world 2 5R 0/5)" or "50/50, 50/50, 50/50" of a suite's test worlds."""
  def check(cell):
    main, note = _split_note(cell)
    items = main.split(", ")
    assert len(items) == len(worlds), cell
    for item, w in zip(items, worlds):
      o = overall(report, w)
      assert item in (f"{o['success']}/{o['runs']}", str(o["success"])), (
          f"{cell!r}: world {w} is {o['success']}/{o['runs']}")
    check_note(note, suite_rows(report, worlds))
  return check


def maes(values: list[tuple[str, str]]) -> Check:
  """A list of MAEs ("0.029, 0.045 (partial), 0.038", "n/a"), each (text, status) as
  `metrics.mean_of_rows` gives them; a unit " m" at the end is allowed."""
  def check(cell):
    cell = cell.removesuffix(" m")
    if cell == "n/a":
      assert all(v == "n/a" for v, _ in values), f"{cell!r}: the record says {values}"
      return
    items = cell.split(", ")
    assert len(items) == len(values), f"{cell!r}: the record says {values}"
    for i, (item, (value, status)) in enumerate(zip(items, values)):
      number = item.removesuffix(" (partial)")
      assert number == value, f"{cell!r}: the record says {[v for v, _ in values]}"
      if item.endswith("(partial)") and i < len(items) - 1:
        assert status == "partial", f"{cell!r}: {value} is {status}"
    partial = any(s != "full" for _, s in values)
    assert ("(partial)" in cell) == partial, f"{cell!r}: the record's statuses {values}"
  return check


def world_maes(report: dict, worlds=(1, 2, 3)) -> Check:
  return maes([(f3(overall(report, w)["mae_m_rows"]), overall(report, w)["rows_status"])
               for w in worlds])


def mae_rmse(o: dict, mae="mae_m_rows", rmse="rmse_m_rows", status="rows_status") -> Check:
  """"0.045 / 0.053", "0.043 (partial)" or "0.043 / 0.062 (partial)" (a unit " m" allowed)."""
  def check(cell):
    cell = cell.removesuffix(" m")
    if o[status] == "n/a":  # no run of any row reached the end
      assert cell == "n/a", f"{cell!r}: no run reached the end of a row"
      return
    partial = o[status] != "full"
    assert cell.endswith(" (partial)") == partial, f"{cell!r}: the record is {o[status]}"
    figures = cell.removesuffix(" (partial)").split(" / ")
    assert figures[0] == f3(o[mae]), f"{cell!r}: the record's MAE is {f3(o[mae])}"
    assert len(figures) == 2 or partial, f"{cell!r}: the RMSE is missing"
    if len(figures) == 2:
      assert figures[1] == f3(o[rmse]), f"{cell!r}: the record's RMSE is {f3(o[rmse])}"
  return check


def world0(report: dict) -> Check:
  """"44/50 (5R 0/5)": world 0's successes and its note."""
  def check(cell):
    main, note = _split_note(cell)
    o = overall(report, 0)
    assert main == f"{o['success']}/{o['runs']}", f"{cell!r}: the record's {o['success']}"
    check_note(note, suite_rows(report, (0,)))
  return check


def world0_all(report: dict) -> Check:
  """"50/50, every lane-direction 5/5"."""
  o, lanes = overall(report, 0), lanes_of(report, 0)
  text = f"{o['success']}/{o['runs']}"
  if all(r["success"] == r["runs"] for r in lanes.values()):
    text += f", every lane-direction {paper.RUNS}/{paper.RUNS}"
  return exact(text)


def noise(report: dict) -> Check:
  """"3,3,3,1,0 / 3,3,3,0,0" of lanes 1F / 4F at factors 2-10; "all 0/3" when none."""
  seqs = [noise_runs(report, lane) for lane in ("1F", "4F")]
  if not any(map(any, seqs)):
    return exact(f"all 0/{paper.NOISE_RUNS}")
  return exact(" / ".join(",".join(map(str, s)) for s in seqs))


def husky(report: dict) -> Check:
  """"3/3 (0.023), 3/3 (0.069)": the MAE where every run reached the end."""
  cells = []
  for lane in ("1F", "4F"):
    r = report["robots"][f"husky_{lane}"]
    cells.append(f"{r['success']}/{r['runs']}" +
                 (f" ({f3(r['mae_m'])})" if r["metrics_status"] == "full" else ""))
  return exact(", ".join(cells))


def noise_8_10(report: dict) -> Check:
  """README: successes of 1F and 4F together at factor 8 / at factor 10."""
  def at(k):
    rows = report["noise"][str(k)].values()
    return f"{sum(r['success'] for r in rows)}/{sum(r['runs'] for r in rows)}"
  return exact(f"{at(8)} / {at(10)}")


def best_fresh_starts(run: str, *, plain: bool = False) -> Check:
  """"62 % / 69 % (120,000)": the best checkpoint's fresh starts, forward / reverse."""
  b = record(f"{run}/best.json")
  text = f"{pct(b['eval_success_forward'])} / {pct(b['eval_success_reverse'])}"
  return exact(f"({text} plain, {thousands(b['env_steps'])})" if plain
               else f"{text} ({thousands(b['env_steps'])})")


def heldout_cell(name: str, world: int) -> Check:
  """"48/50, 0.045 (partial)" of heldout/<name>-world<N>.md."""
  o = evaluation(f"heldout/{name}-world{world}.md")["overall"]
  return exact(f"{o['success']}, {o['mae']}")


def heldout_note(name: str, worlds) -> Check:
  """The lane-directions below 4/5 of the held-out worlds, exactly ("none" if none)."""
  docs = {w: evaluation(f"heldout/{name}-world{w}.md") for w in worlds}
  rows = {w: {lane: (r["k"], r["n"]) for lane, r in d.items() if lane != "overall"}
          for w, d in docs.items()}
  return lambda cell: check_note(cell, rows, complete=True)


def heldout_summary(name: str, worlds, *, mae_prefix: str = "MAE ") -> Check:
  """"145/150 (world 18 3R 0/5), MAE 0.026, 0.020, 0.037 (partial)"."""
  docs = [evaluation(f"heldout/{name}-world{w}.md") for w in worlds]
  rows = {w: {lane: (r["k"], r["n"]) for lane, r in d.items() if lane != "overall"}
          for w, d in zip(worlds, docs)}

  def check(cell):
    m = re.match(rf"^(\d+)/(\d+)(?: \(([^()]*)\))?, {mae_prefix}(.*)$", cell)
    assert m, f"{cell!r}: not 'k/n[ (note)], {mae_prefix}...'"
    k = sum(d["overall"]["k"] for d in docs)
    n = sum(d["overall"]["n"] for d in docs)
    assert (int(m.group(1)), int(m.group(2))) == (k, n), f"{cell!r}: the records say {k}/{n}"
    check_note(m.group(3) or "", rows)
    maes([(d["overall"]["mae"].removesuffix(" (partial)"),
           "partial" if "partial" in d["overall"]["mae"] else "full") for d in docs])(m.group(4))
  return check


def selected_candidate(run: str) -> dict:
  """The entry of `selection.json`'s candidates that the run selected."""
  s = record(f"{run}/selection.json")
  return next(c for c in s["candidates"] if c["env_steps"] == s["selected"])


def candidate_steps(run: str) -> str:
  """"100k, 110k, 120k, 130k": the candidates' env steps, in the order of the record."""
  return ", ".join(f"{c['env_steps'] // 1000}k"
                   for c in record(f"{run}/selection.json")["candidates"])


def chosen_validation(run: str) -> Check:
  """"66/72, MAE 0.023 m": the chosen candidate's successes on the validation worlds and
  their noise rows (`selection.json`), and its MAE."""
  v = selected_candidate(run)["validation"]
  return exact(f"{v['success']}/{v['episodes']}, MAE {f3(v['mae_m'])} m")


def candidates(run: str) -> Check:
  """`candidate_steps`, exactly."""
  return exact(candidate_steps(run))


def validation_scores(run: str) -> Check:
  """"72, 69, 69, 61; 0.040 m": each candidate's validation successes, then the selected
  one's MAE."""
  s = record(f"{run}/selection.json")
  return exact(", ".join(str(c["validation"]["success"]) for c in s["candidates"])
               + f"; {f3(selected_candidate(run)['validation']['mae_m'])} m")


def meeting_the_bar(run: str) -> Check:
  """"80k (0.047), 40k (0.076)": the candidates that meet the choice's bar
  (`choice.meets_bar`, the default bar: no recipe sets another) and their validation
  MAE, in the order of the record."""
  return exact(", ".join(f"{c['env_steps'] // 1000}k ({f3(c['validation']['mae_m'])})"
                         for c in record(f"{run}/selection.json")["candidates"]
                         if choice.meets_bar(c["validation"], BAR)) or "none")


def test_every_recorded_choice_is_what_rank_chooses():
  """Each selection.json under docs/results selected what `choice.rank` selects today (the
  bar of today's default: records from before it have none), so a recipe beside its
  record still reproduces the policy it names."""
  records = sorted(RESULTS.glob("**/selection.json"))
  assert len(records) >= 9
  for path in records:
    sel = json.loads(path.read_text())
    best = max(sel["candidates"], key=lambda c: choice.rank(c["validation"], BAR))
    assert best["env_steps"] == sel["selected"], path


# --- the paper's figures ----------------------------------------------------------------------

P = paper.PAPER["overall"]
PAPER_SUCCESS = exact(f"{P[6]}/{paper.PAPER_RUNS}")
PAPER_MAE_RMSE = exact(f"{P[0]:.3f} / {P[1]:.3f} m")
PAPER_NOISE_TEXT = " / ".join(",".join(str(paper.PAPER_NOISE[k][i]) for k in FACTORS)
                              for i in range(len(paper.NOISE_LANES)))
_H = [paper.PAPER_ROBOTS[("husky", lane)] for lane in ("1F", "4F")]
PAPER_HUSKY = exact(f"{_H[0][0]}/{paper.ROBOT_RUNS} (MAE {_H[0][1]}), "
                    f"{_H[1][0]}/{paper.ROBOT_RUNS} ({_H[1][1]})")

TARGET = "a target: the project's goal, not a measurement"
NAMES = "names the records, not figures"
MACHINE = "the machine and versions the run used; no record names them"
COMMAND = "the command, not a figure"
WHICH = "which config and seeds, not figures"
NONE = "no figure"
# The seeds tables' target column: the project's goals, but where they quote the paper.
SEED_TARGETS = {
    "noise 1F / 4F at factors 2, 4, 6, 8, 10": exact(">= " + PAPER_NOISE_TEXT),
    "Husky 1F / 4F": exact(f"{paper.ROBOT_RUNS}/{paper.ROBOT_RUNS} each, MAE <= "
                           f"{_H[0][1]} / {_H[1][1]}"),
    "test world 0: success": TARGET, "test world 0: MAE / RMSE (mean of rows)": TARGET,
    "test world 0: MAE (mean of rows)": TARGET, "test worlds 1, 2, 3: success": TARGET,
    "test worlds 1, 2, 3: MAE": TARGET}


# --- the specs: table row -> one check (or reason) per column ------------------------------

@dataclass
class Table:
  where: str     # file:line
  heading: str   # the heading above it
  header: list[str]
  rows: list[list[str]]


def _cells(line: str) -> list[str]:
  return [" ".join(c.replace("**", "").split()) for c in line.strip().strip("|").split("|")]


def tables(path: Path) -> list[Table]:
  """The markdown tables of a page, with the heading each is under."""
  out, heading, lines = [], "", path.read_text().splitlines()
  i = 0
  while i < len(lines):
    if lines[i].startswith("#"):
      heading = lines[i].lstrip("#").strip()
    if (lines[i].startswith("|") and i + 1 < len(lines)
        and re.match(r"^\|[-|: ]+\|$", lines[i + 1])):
      start, header, rows = i, _cells(lines[i]), []
      i += 2
      while i < len(lines) and lines[i].startswith("|"):
        rows.append(_cells(lines[i]))
        i += 1
      out.append(Table(f"{path.relative_to(ROOT)}:{start + 1}", heading, header, rows))
      continue
    i += 1
  return out


def _max_minutes(run: str) -> str:
  return f"{record(f'{run}/config.yaml')['train']['max_minutes']:g}"


def _readme_suite(folder: str) -> dict:
  """README's columns of a suite report."""
  r = suite(folder)
  return {"world 0: success": world0(r), "MAE / RMSE m": mae_rmse(overall(r, 0)),
          "worlds 1, 2, 3": successes(r), "noise test at factor 8 / 10": noise_8_10(r),
          "policy (config)": WHICH, "trained on": MACHINE}


def _readme_single(path: str) -> dict:
  """README's columns of one evaluation (results.json): MAE / RMSE the mean of its rows,
  as the table says, whatever the record's overall line pools."""
  doc = record(path)
  o = {"mae": np.mean([r["mae_m"] for r in doc["rows"]]),
       "rmse": np.mean([r["rmse_m"] for r in doc["rows"]]),
       "status": "full" if doc["overall"]["success"] == doc["overall"]["runs"] else "partial"}
  return {"world 0: success": exact(f"{doc['overall']['success']}/{doc['overall']['runs']}"),
          "MAE / RMSE m": mae_rmse(o, "mae", "rmse", "status"),
          "worlds 1, 2, 3": exact("-"), "noise test at factor 8 / 10": exact("-")}


def _joined(*columns: dict) -> dict:
  """README cells of several seeds, "; "-separated, each checked by its own column."""
  def joined(col):
    def check(cell):
      parts = cell.split("; ")
      assert len(parts) == len(columns), f"{cell!r}: {len(columns)} seeds"
      for part, c in zip(parts, columns):
        c[col](part)
    return check
  return {col: joined(col) if callable(check) else check for col, check in columns[0].items()}


def readme_spec() -> dict[str, dict]:
  """README's results table: row (first cell) -> column -> check or reason."""
  end_to_end = (RESULTS / "jackal-gaps-seed0/end-to-end/README.md").read_text()
  total = re.search(r"the whole command\*\* \| \*\*(\d+) min \d+ s\*\*", end_to_end).group(1)
  cpu_camera = record("cpu-hour/config.yaml")["camera"]
  gaps = ("jackal-gaps-seed0", "jackal-gaps-seed1", "jackal-gaps-seed2")
  assert len({_max_minutes(r) for r in gaps}) == 1
  return {
      "the paper's SAC agent": {
          "world 0: success": PAPER_SUCCESS, "MAE / RMSE m": exact(f"{P[0]:.3f} / {P[1]:.3f}"),
          "worlds 1, 2, 3": exact("-"),
          "noise test at factor 8 / 10": exact(" / ".join(
              f"{sum(paper.PAPER_NOISE[k])}/{2 * paper.NOISE_RUNS}" for k in (8, 10)))},
      "`models/jackal.npz` (`jackal.yaml`, seed 0)": {
          **_readme_suite(f"{SHIPPED}/suite"),
          "wall-clock": exact(minutes_seconds(record(f"{SHIPPED}/record.json")["wall_s"])
                              + " (end to end, alone)")},
      "`jackal.yaml`, seeds 1, 2, 3, 4": {
          **_joined(*(_readme_suite(f"{run}/suite") for run in SEEDS[1:])),
          "wall-clock": exact("shared")},
      "`jackal-ln` (no slower late target), seeds 0-3: seed 0 shipped before": {
          **_joined(*(_readme_suite(f"{run}/suite") for run in LN)),
          "wall-clock": exact(minutes_seconds(record(f"{BEFORE}/record.json")["wall_s"])
                              + " (seed 0, end to end)")},
      "`jackal-native` (no LayerNorm either), seeds 0-3: seed 0 shipped before that": {
          **_joined(*(_readme_suite(f"{run}/suite") for run in NATIVE)),
          "wall-clock": exact(minutes_seconds(record(f"{NATIVE[0]}/record.json")["wall_s"])
                              + " (seed 0, end to end)")},
      "`jackal-gaps` (`shift` tower), seeds 0, 1, 2: seed 0 shipped before that": {
          **_joined(*(_readme_suite(f) for f in ("jackal-gaps-seed0/suite",
                                                 "jackal-gaps-seed1/suite-selected",
                                                 "jackal-gaps-seed2/suite-selected"))),
          "wall-clock": exact(f"{total} min; {_max_minutes(gaps[0])} min of training each")},
      "`jackal/recipe.yaml`, seed 0 (shipped earlier)": {
          **_readme_suite("jackal/suite"), "wall-clock": exact(f"{_max_minutes('jackal')} min")},
      # the release (mjxvine 0.1.0) is in no record: the image size is
      "`cpu.yaml` (at 40x40, mjxvine 0.1.0)": {
          **_readme_single("cpu-hour/results.json"), "trained on": MACHINE,
          "policy (config)": contains(f"{cpu_camera['width']}x{cpu_camera['height']}"),
          "wall-clock": exact(f"{_max_minutes('cpu-hour')} min")},
      "oracle: pure pursuit on the true pose": _readme_single("eval-oracle_jackal/results.json"),
  }


def _training(run: str) -> dict:
  """The figures of a "what | figure" training table of `run` (percentages as "62.5 %" or
  rounded, "56 %")."""
  metrics = record(f"{run}/metrics.jsonl")
  best = record(f"{run}/best.json")
  cfg = record(f"{run}/config.yaml")
  sps, ups = learning_speeds(metrics)
  starts = cfg["train"]["eval_starts"]

  def fresh(cell):
    for key, word in (("eval_success_forward", "forward"), ("eval_success_reverse", "reverse")):
      x = 100 * best[key]
      assert f"{x:g} % {word}" in cell or f"{x:.0f} % {word}" in cell, (
          f"{cell!r}: the record's {word} {x:g} %")
  closing = evaluation(f"{run}/closing-eval.md")["overall"]["success"]
  return {
      "command": COMMAND, "device": MACHINE, "run record": NAMES,
      "wall-clock": contains(f"{_max_minutes(run)} min of training",
                             f"`train.max_minutes: {_max_minutes(run)}`",
                             f"test world 0, {closing}"),
      "env steps": contains(f"{thousands(metrics[-1]['env_steps'])} (",
                            f"{np.median(sps):.0f} env-steps/s",
                            f"{np.median(ups):.0f} gradient steps/s"),
      "best checkpoint": both(fresh, contains(f"{thousands(best['env_steps'])} env steps",
                                              f"of {starts} + {starts} fresh starts")),
  }


def _suite_column(report: dict, *, every: bool = False) -> dict:
  """The rows of the "against the targets" and seeds tables, for one suite report."""
  o0 = overall(report, 0)
  w123 = successes(report)
  return {
      "w0": world0_all(report) if every else world0(report),
      "w0 mae rmse": mae_rmse(o0),
      "w0 mae": exact("n/a" if o0["rows_status"] == "n/a" else f3(o0["mae_m_rows"]) + (
          "" if o0["rows_status"] == "full" else " (partial)")),
      "w123": w123, "w123 mae": world_maes(report), "noise": noise(report),
      "husky": husky(report)}


# The shipped recipe's targets (the seeds tables' target column): world 0 (successes of
# 50, MAE m) and each of worlds 1-3 (the same); besides, the noise test at least the
# paper's and the Husky every run, at most the paper's MAE.
WORLD0_TARGET, WORLDS123_TARGET = (49, 0.06), (48, 0.08)


def meets_targets(report: dict) -> bool:
  """Whether a suite report meets every target of the shipped recipe."""
  for w in paper.SUITE_WORLDS:
    need, mae = WORLD0_TARGET if w == 0 else WORLDS123_TARGET
    o = overall(report, w)
    if o["success"] < need or o["mae_m_rows"] is None or o["mae_m_rows"] > mae:
      return False
  noise_ok = all(report["noise"][str(k)][f"{lane}{way}"]["success"] >= n
                 for k, need in paper.PAPER_NOISE.items()
                 for (lane, way), n in zip(paper.noise_rows(), need))
  robots = [(report["robots"][f"husky_{lane}{way}"], paper.PAPER_ROBOTS[("husky", f"{lane}{way}")])
            for lane, way in paper.robot_rows()]
  husky_ok = all(r["success"] == paper.ROBOT_RUNS and r["mae_m"] <= mae
                 for r, (_, mae, _) in robots)
  return noise_ok and husky_ok


def config_changes(run: str, base: str = f"{NATIVE[0]}/config.yaml") -> set[str]:
  """"`sac.n_step: 3`" for each setting of `run`'s config.yaml that differs from `base`'s
  in what is trained (the worlds, robot, camera, env, SAC and the env-step budget; not the
  seed, the evaluations or the choice's settings, which some records predate). A key that
  `base` predates counts at its default, with which `base` trained."""
  def flat(doc, prefix=""):
    for k, v in doc.items():
      if isinstance(v, dict):
        yield from flat(v, f"{prefix}{k}.")
      else:
        yield f"{prefix}{k}", v
  a = dict(flat(record(f"{run}/config.yaml")))
  b = {**dict(flat(to_dict(Config()))), **dict(flat(record(base)))}
  return {f"`{k}: {yaml.safe_dump(v, default_flow_style=True).splitlines()[0]}`"
          for k, v in a.items() if b.get(k) != v
          and (k.split(".")[0] in ("world", "robot", "camera", "env", "sac")
               or k == "train.total_env_steps")}


def lever_row(runs: tuple[str, ...]) -> list:
  """A row of the levers table: checks of its change, tower, seeds, the seeds that meet
  every target, world 0's MAE and the test worlds' successes per seed, the wall-clocks."""
  reports = [suite(f"{run}/suite") for run in runs]
  seeds = [record(f"{run}/config.yaml")["train"]["seed"] for run in runs]
  met = [s for s, r in zip(seeds, reports) if meets_targets(r)]
  changes = set.union(*map(config_changes, runs))
  towers = {record(f"{run}/record.json")["tower"] for run in runs}
  def change(cell):
    named = set(re.findall(r"`[^`]+`", cell))
    assert named == changes, f"{cell!r}: the records change {sorted(changes)}"
  return [
      change, exact(" ".join(towers)), exact(", ".join(map(str, seeds))),
      exact((", ".join(map(str, met)) or "none") + f" ({len(met)} of {len(runs)})"),
      exact(", ".join(f3(overall(r, 0)["mae_m_rows"]) for r in reports)),
      exact(", ".join(str(sum(overall(r, w)["success"] for w in paper.SUITE_WORLDS))
                      for r in reports)),
      exact(", ".join(f"{record(f'{run}/record.json')['wall_s'] / 60:.1f}" for run in runs))]


LEVERS = {  # the levers table of reproduction.md: row label -> its seeds' records
    "`jackal-native`, shipped before": NATIVE, "3-step returns": NSTEP,
    "LayerNorm in the critics: `jackal-ln`, shipped before": LN,
    "LayerNorm, batch 128, 4 gradient steps": BATCH128,
    "LayerNorm, a 5x slower target from 25 % of the budget: `jackal.yaml`, shipped": SEEDS}


AGAINST = {  # row label of an "against the targets" table -> (column key, the paper's cell)
    "test world 0: success": ("w0", PAPER_SUCCESS),
    "test world 0: MAE / RMSE (mean of the rows)": ("w0 mae rmse", PAPER_MAE_RMSE),
    "test worlds 1, 2, 3 (never trained on): success": ("w123", exact("-")),
    "test worlds 1, 2, 3 (never trained or tuned on): success": ("w123", exact("-")),
    "test worlds 1, 2, 3: MAE (mean of the rows)": ("w123 mae", exact("-")),
    "noise, lanes 1F and 4F, 3 runs: success at factors 2, 4, 6, 8, 10": (
        "noise", exact(PAPER_NOISE_TEXT)),
    "Husky, lanes 1F and 4F, 3 runs": ("husky", PAPER_HUSKY),
    "validation worlds 100-102 and their noise rows (the choice's 72 runs)": (
        "validation", exact("-")),
    "held-out test worlds 25, 26, 27 ([below](#held-out-test-worlds-25-26-27))": (
        "heldout", exact("-")),
}
SEED_ROWS = {  # row label of a seeds table -> column key
    "test world 0: success": "w0", "test world 0: MAE / RMSE (mean of rows)": "w0 mae rmse",
    "test world 0: MAE (mean of rows)": "w0 mae", "test worlds 1, 2, 3: success": "w123",
    "test worlds 1, 2, 3: MAE": "w123 mae", "noise 1F / 4F at factors 2, 4, 6, 8, 10": "noise",
    "Husky 1F / 4F": "husky", "best checkpoint: fresh starts F / R": "best",
    "candidates (env steps)": "candidates", "validation successes /72, MAE": "validation",
    "selected checkpoint": "selected", "env steps in 52 min": "env steps",
    "meeting the bar (validation MAE, m)": "bar",
    "held-out test worlds 16, 17, 18 (first evaluated after every choice)": "heldout",
    "the same checkpoint with the plain action: worlds 0-3": "plain",
}


CHOSEN_ROWS = [  # a seeds table of runs that chose their checkpoint on validation worlds
    "candidates (env steps)", "validation successes /72, MAE", "selected checkpoint",
    "test world 0: success", "test world 0: MAE (mean of rows)", "test worlds 1, 2, 3: success",
    "test worlds 1, 2, 3: MAE", "noise 1F / 4F at factors 2, 4, 6, 8, 10", "Husky 1F / 4F"]


def _chosen_column(run: str, folder: str = "suite") -> dict:
  """A seeds-table column of a run that chose its checkpoint on validation worlds (its
  chosen policy's suite report in `run/folder`)."""
  assert all(c["validation"]["episodes"] == 72
             for c in record(f"{run}/selection.json")["candidates"])
  return {**_suite_column(suite(f"{run}/{folder}")), "candidates": candidates(run),
          "validation": validation_scores(run),
          "selected": exact(thousands(record(f"{run}/selection.json")["selected"]))}


def _against(labels: list[str], *columns: dict, target: bool = True) -> dict:
  return {label: [AGAINST[label][1], *([TARGET] if target else []),
                  *(c[AGAINST[label][0]] for c in columns)] for label in labels}


def _seeds(labels: list[str], *columns: dict) -> dict:
  return {label: [SEED_TARGETS.get(label, NONE), *(c[SEED_ROWS[label]] for c in columns)]
          for label in labels}


def _timed_end_to_end(run: str) -> dict:
  """The wall-clock and env-steps checks of a run timed end to end alone (its record.json
  the whole command; the choice's and the closing evaluation's times from their records)."""
  metrics, sel = record(f"{run}/metrics.jsonl"), record(f"{run}/selection.json")
  sps, ups = learning_speeds(metrics)
  closing = evaluation(f"{run}/closing-eval.md")["overall"]["success"]
  closing_s = float(re.search(r"Rollout wall-clock: ([\d.]+) s",
                              (RESULTS / f"{run}/closing-eval.md").read_text()).group(1))
  wall_s = record(f"{run}/record.json")["wall_s"]
  choice_s = sum(c["validation"]["wall_s"] for c in sel["candidates"])
  assert record(f"{run}/config.yaml")["train"]["total_env_steps"] == metrics[-1]["env_steps"]
  return {
      "wall-clock": contains(
          minutes_seconds(wall_s) + " from the command's start",
          minutes_seconds(wall_s - choice_s - closing_s) + " for start-up",
          minutes_seconds(choice_s) + " for the choice", f"{closing_s:.0f} s for the rollouts",
          f"test world 0, {closing}"),
      "env steps": contains(
          f"{thousands(metrics[-1]['env_steps'])} (median {np.median(sps):.0f} env-steps/s "
          f"and {np.median(ups):.0f} gradient steps/s while learning; {spread(sps, ups)})")}


def reproduction_spec() -> dict[tuple[str, int], dict]:
  """reproduction.md: (heading, index of the table under it) -> row -> [check or reason per
  column]; "__header__": checks of the header cells after the first."""
  out = {}

  # Training: jackal.yaml seed 0 with the native tower, timed end to end alone
  sel, chosen = record(f"{SHIPPED}/selection.json"), selected_candidate(SHIPPED)
  timed = _timed_end_to_end(SHIPPED)
  out[("Training", 0)] = {label: [check] for label, check in {
      "command": COMMAND, "device": MACHINE, "run record": NAMES, "seeds": WHICH,
      "the policy shipped before": WHICH,
      "wall-clock": both(timed["wall-clock"], contains(
          minutes_seconds(record(f"{BEFORE}/record.json")["wall_s"])
          + " without the slower late target")),
      "env steps": timed["env steps"],
      "chosen checkpoint": contains(
          f"{thousands(sel['selected'])} env steps, of the candidates "
          + candidate_steps(SHIPPED),
          f"drove {chosen['validation']['success']} of the {chosen['validation']['episodes']} "
          "validation runs"),
  }.items()}

  # Against the targets: the shipped policy and the one before it
  columns = [{**_suite_column(suite(f"{run}/suite"), every=run == SHIPPED),
              "validation": chosen_validation(run),
              "heldout": heldout_summary(run, HELDOUT)} for run in (SHIPPED, BEFORE)]
  out[("Against the targets", 0)] = _against(list(AGAINST)[:3] + list(AGAINST)[4:], *columns)

  # Seeds of jackal.yaml, of jackal-native, shipped before, and of batch 128
  bar_rows = [*CHOSEN_ROWS[:2], "meeting the bar (validation MAE, m)", *CHOSEN_ROWS[2:]]
  for heading, runs in (("Seeds", SEEDS), (LN_SECTION, LN), (NATIVE_SECTION, NATIVE),
                        (BATCH128_SECTION, BATCH128)):
    out[(heading, 0)] = _seeds(bar_rows, *({**_chosen_column(run), "bar": meeting_the_bar(run)}
                                           for run in runs))

  # the levers tried on the shipped recipe
  out[("Levers tried on the shipped recipe", 0)] = {
      label: lever_row(runs) for label, runs in LEVERS.items()}

  # jackal-gaps, shipped before: its training, timed end to end on a second run
  t = _training("jackal-gaps-seed0")
  e2e = (RESULTS / "jackal-gaps-seed0/end-to-end/README.md").read_text()
  choice_s = round(sum(c["validation"]["wall_s"] for c in
                       record("jackal-gaps-seed0/end-to-end/selection.json")["candidates"]))
  t["wall-clock"] = both(_training("jackal-gaps-seed0/end-to-end")["wall-clock"], contains(
      re.search(r"the whole command\*\* \| \*\*([^*]+)\*\*", e2e).group(1)
      + " from the command's start",
      f"{choice_s // 60} min {choice_s % 60} s for the choice",
      re.search(r"the closing evaluation [^|]*\| (\d+ s), ", e2e).group(1)
      + " for the closing evaluation"))
  sps, ups = learning_speeds(record("jackal-gaps-seed0/metrics.jsonl"))
  t["env steps"] = both(t["env steps"], contains(spread(sps, ups)))
  best = record("jackal-gaps-seed0/best.json")
  evals = {r["env_steps"]: r for r in record("jackal-gaps-seed0/metrics.jsonl")
           if "eval_mae_m" in r}
  weaker = min(best["eval_success_forward"], best["eval_success_reverse"])
  ties = [s for s, r in evals.items() if s != best["env_steps"] and
          min(r["eval_success_forward"], r["eval_success_reverse"]) == weaker]
  assert all(evals[s]["eval_mae_m"] > best["eval_mae_m"] for s in ties)
  t["best checkpoint"] = both(t["best checkpoint"], contains(
      "the evaluations at " + " and ".join(thousands(s) for s in ties) + " env steps tied it"))
  firsts = [record(f"jackal-gaps-seed{s}/best.json") for s in (0, 1, 2)]
  fr = [f"{pct(b['eval_success_forward'])} / {pct(b['eval_success_reverse'])}" for b in firsts]
  t["seeds"] = contains(f"({fr[0]}, against {fr[1]} and {fr[2]})")
  out[(GAPS, 0)] = {label: [check] for label, check in t.items()}

  # its seeds
  columns = [{**_chosen_column(f"jackal-gaps-seed{s}", "suite" if s == 0 else "suite-selected"),
              "heldout": heldout_summary(f"jackal-gaps-seed{s}", (16, 17, 18))}
             for s in (0, 1, 2)]
  out[(GAPS, 1)] = _seeds([
      "candidates (env steps)", "validation successes /72, MAE", "selected checkpoint",
      "test world 0: success", "test world 0: MAE / RMSE (mean of rows)",
      "test worlds 1, 2, 3: success", "test worlds 1, 2, 3: MAE",
      "noise 1F / 4F at factors 2, 4, 6, 8, 10", "Husky 1F / 4F",
      "held-out test worlds 16, 17, 18 (first evaluated after every choice)"], *columns)

  # 3-step returns on the shipped recipe: seed 0 timed end to end (record.json), 3 seeds
  heading = "3-step returns on the shipped recipe, seeds 0, 1, 2"
  out[(heading, 0)] = {label: [check] for label, check in {
      "command": COMMAND, "device": MACHINE, "run record": NAMES,
      **_timed_end_to_end(NSTEP[0])}.items()}
  out[(heading, 1)] = _seeds(CHOSEN_ROWS, *map(_chosen_column, NSTEP))

  # jackal/recipe.yaml: its training, against the targets (beside the noise drawn from [0.5, 6])
  heading = "`jackal/recipe.yaml`, the earlier shipped policy, seeds 0, 1, 2"
  t = _training("jackal")
  best, metrics = record("jackal/best.json"), record("jackal/metrics.jsonl")
  assert best["env_steps"] == metrics[-1]["env_steps"]
  t["best checkpoint"] = both(t["best checkpoint"],
                              contains(f"chunk {best['chunk']}, ", " (the last)"))
  lo, hi = record("jackal-noise6/config.yaml")["env"]["train_noise_factor"]
  t.update({"seeds": WHICH, "the policy shipped before it": contains(f"[{lo:g}, {hi:g}]")})
  out[(heading, 0)] = {label: [check] for label, check in t.items()}
  out[(heading, 1)] = _against(
      list(AGAINST)[:2] + list(AGAINST)[3:7],
      _suite_column(suite("jackal/suite"), every=True),
      _suite_column(suite("jackal-noise6/suite")), target=False)
  out[(heading, 1)]["__header__"] = [None, None, contains(f"[{lo:g}, {hi:g}]")]
  runs = ("jackal", "jackal-seed1", "jackal-seed2")
  assert {_max_minutes(r) for r in runs} == {"52"}  # the row label's "in 52 min"
  columns = [{**_suite_column(suite(f"{run}/suite")), "best": best_fresh_starts(run),
              "env steps": exact(thousands(record(f"{run}/metrics.jsonl")[-1]["env_steps"]))}
             for run in runs]
  out[(heading, 2)] = _seeds([
      "env steps in 52 min", "best checkpoint: fresh starts F / R", "test world 0: success",
      "test world 0: MAE (mean of rows)", "test worlds 1, 2, 3: success",
      "test worlds 1, 2, 3: MAE", "noise 1F / 4F at factors 2, 4, 6, 8, 10", "Husky 1F / 4F"],
      *columns)

  # the log-uniform draw, seeds 0 and 1; the mirror-averaged action, seeds 0, 1, 2
  labels = ["best checkpoint: fresh starts F / R", "test world 0: success",
            "test world 0: MAE / RMSE (mean of rows)", "test worlds 1, 2, 3: success",
            "test worlds 1, 2, 3: MAE", "noise 1F / 4F at factors 2, 4, 6, 8, 10",
            "Husky 1F / 4F"]
  out[("The log-uniform noise draw, seeds 0 and 1", 0)] = _seeds(labels, *(
      {**_suite_column(suite(f"jackal-lognoise-seed{s}/suite")),
       "best": best_fresh_starts(f"jackal-lognoise-seed{s}")} for s in (0, 1)))
  plain = [exact(", ".join(str(overall(suite(f"jackal-lognoise-seed{s}/suite"), w)["success"])
                           for w in paper.SUITE_WORLDS)) for s in (0, 1)]
  out[("The mirror-averaged action, `jackal-sym`, seeds 0, 1, 2", 0)] = _seeds(
      labels + ["the same checkpoint with the plain action: worlds 0-3"],
      {**_suite_column(suite("jackal-sym-seed0/suite")), "plain": plain[0],
       "best": best_fresh_starts("jackal-sym-seed0")},
      {**_suite_column(suite("jackal-lognoise-seed1/suite-mirror-average")), "plain": plain[1],
       "best": best_fresh_starts("jackal-lognoise-seed1", plain=True)},
      {**_suite_column(suite("jackal-sym-seed2/suite")), "plain": exact("not run"),
       "best": best_fresh_starts("jackal-sym-seed2")})

  # held-out worlds: heldout/<policy>-world<N>.md
  for heading, worlds, policies in (
      ("Held-out test worlds 4, 5, 6", (4, 5, 6), {
          "`jackal/recipe.yaml` seed 0 (shipped then; uniform draw)": "jackal-seed0",
          "log-uniform draw, seed 1": "lognoise-seed1",
          "log-uniform draw, seed 0": "lognoise-seed0"}),
      ("Held-out test worlds 7, 8, 9", (7, 8, 9), {
          "`jackal/recipe.yaml` seed 0 (shipped then)": "jackal-seed0",
          "`jackal-sym` seed 0": "jackal-sym-seed0",
          "`jackal-sym` seed 1 (the log-uniform checkpoint, averaged action)":
              "jackal-sym-seed1",
          "`jackal-sym` seed 2": "jackal-sym-seed2"}),
      ("Held-out test worlds 10, 11, 12", (10, 11, 12), {
          "`jackal/recipe.yaml` seed 0 (shipped then)": "jackal-seed0",
          "`jackal.yaml` seed 1": "jackal-gaps-seed1",
          "`jackal.yaml` seed 2": "jackal-gaps-seed2"}),
      ("Held-out test worlds 13, 14, 15", (13, 14, 15), {
          "`jackal-gaps` seed 0 (shipped then)": "jackal-gaps-seed0",
          "`jackal/recipe.yaml` seed 0 (shipped before)": "jackal-seed0"}),
      ("Held-out test worlds 19, 20, 21", (19, 20, 21), {
          "`jackal-native` seed 0 (shipped then)": NATIVE[0],
          "`jackal-gaps` seed 0 (shipped before it)": "jackal-gaps-seed0"}),
      ("Held-out test worlds 22, 23, 24", (22, 23, 24), {
          "`jackal-ln` seed 0 (shipped then)": BEFORE,
          "`jackal-native` seed 0 (shipped before it)": NATIVE[0]}),
      ("Held-out test worlds 25, 26, 27", HELDOUT, {
          "`models/jackal.npz` (`jackal.yaml` seed 0)": SHIPPED,
          "`jackal-ln` seed 0 (shipped before)": BEFORE})):
    out[(heading, 0)] = {
        label: [*(heldout_cell(name, w) for w in worlds), heldout_note(name, worlds)]
        for label, name in policies.items()}
    out[(heading, 0)]["__header__"] = [contains(f"world {w}") for w in worlds] + [None]
  return out


# --- the tests --------------------------------------------------------------------------------

README_TABLE = next(t for t in tables(ROOT / "README.md") if t.heading == "Results")
# "The report" and its sub-sections: the suite's report, checked as a whole below
REPORT_HEADINGS = ("The report", "Noise (world 0, lanes 1F and 4F, 3 runs each)",
                   "Robots (world 0, 3 runs each; the policy was trained on the Jackal)",
                   "Test world 0 (the paper's)", "Test world 1", "Test world 2", "Test world 3")


def _reproduction_tables() -> dict[tuple[str, int], Table]:
  """reproduction.md's tables by (heading, index under it), the report's left out."""
  out, seen = {}, {}
  for t in tables(REPRODUCTION):
    if t.heading not in REPORT_HEADINGS:
      seen[t.heading] = seen.get(t.heading, -1) + 1
      out[(t.heading, seen[t.heading])] = t
  return out


@functools.cache
def _specs() -> dict[tuple[str, int], dict]:
  """Every table's spec as row -> [check or reason per column after the first]."""
  readme = readme_spec()
  out = {("README", 0): {label: [readme[label].get(col) for col in README_TABLE.header[1:]]
                         for label in readme}}
  return {**out, **reproduction_spec()}


def _all_tables() -> dict[tuple[str, int], Table]:
  return {("README", 0): README_TABLE, **_reproduction_tables()}


def _failures(table: Table, spec: dict) -> list[str]:
  """What in `table` disagrees with its records; [] if nothing."""
  rows = {label: checks for label, checks in spec.items() if label != "__header__"}
  labels = [r[0] for r in table.rows]
  assert sorted(labels) == sorted(rows), (
      f"{table.where}: rows without a spec {sorted(set(labels) - set(rows))}, specs "
      f"without a row {sorted(set(rows) - set(labels))} (tests/test_docs_figures.py)")
  cells = [("header", h, check) for h, check in zip(table.header[1:], spec.get("__header__", []))]
  for row in table.rows:
    assert len(rows[row[0]]) == len(row) - 1, f"{table.where}: row {row[0]!r}"
    cells += [(row[0], cell, check) for cell, check in zip(row[1:], rows[row[0]])]
  out = []
  for label, cell, check in cells:
    if callable(check):
      try:
        check(cell)
      except AssertionError as e:
        out.append(f"{table.where}: row {label!r}: {e}")
  return out


@pytest.mark.parametrize("key", list(_all_tables()), ids=lambda k: f"{k[0]}#{k[1]}")
def test_table_is_its_records(key):
  """Every figure of the README's results table, or of a table of reproduction.md, is
  what its record says."""
  table = _all_tables()[key]
  assert key in _specs(), f"{table.where}: a table without a spec in tests/test_docs_figures.py"
  failures = _failures(table, _specs()[key])
  assert not failures, "\n".join(failures)


def test_every_figure_has_a_record_or_a_reason():
  """Every cell that holds a digit is checked against a record or says why it is not;
  every table of reproduction.md has a spec."""
  uncovered = []
  for key, table in _all_tables().items():
    spec = _specs().get(key)
    assert spec, f"{table.where}: a table without a spec"
    for row in table.rows:
      for col, cell, check in zip(table.header[1:], row[1:], spec.get(row[0], [])):
        if re.search(r"\d", cell) and (check is None or check == NONE):
          uncovered.append(f"{table.where}: row {row[0]!r}, column {col!r}: {cell!r}")
  assert not uncovered, "\n".join(uncovered)


def test_the_report_section_is_the_suite_report():
  """reproduction.md's "The report" is the shipped policy's suite report as the suite
  writes it from the record (headings one level down, figure paths from the page)."""
  from mjxvine.evaluation.suite import report_markdown
  folder = f"{SHIPPED}/suite"
  lines = report_markdown(suite(folder)).splitlines()
  assert lines[0].startswith("# The paper's evaluation: ") and not lines[1]
  expected = "\n".join("#" + l if l.startswith("## ") else l for l in lines[2:])
  expected = expected.replace("](world", f"]({folder}/world").strip()
  page = REPRODUCTION.read_text()
  section = page[page.index("\n## The report\n"):].split("\n", 3)[3]
  end = re.search(r"^## ", section, re.M)
  section = (section[:end.start()] if end else section).strip()
  assert section == expected, (
      f"reproduction.md's report differs from docs/results/{folder}/report.json as "
      "mjxvine.evaluation.suite.report_markdown writes it")


def test_a_wrong_figure_fails():
  """A figure changed in a table is caught, and the readers of notes and lists hold the
  docs' forms (a broken reader would pass wrong figures)."""
  table = README_TABLE
  row = next(r for r in table.rows if r[0].startswith("`models/jackal.npz`"))
  col = table.header.index("MAE / RMSE m")
  bad = [list(r) for r in table.rows]
  bad[table.rows.index(row)][col] = "9.999 / 9.999"
  assert _failures(Table(table.where, table.heading, table.header, bad), _specs()[("README", 0)])
  assert claims("world 1 5F, 5R; world 3 3F, 3R, 5R 0/5", (1, 2, 3)) == {
      (1, "5F", 0, 5), (1, "5R", 0, 5), (3, "3F", 0, 5), (3, "3R", 0, 5), (3, "5R", 0, 5)}
  assert claims("3R and 5R 0/5", (1, 2)) == {
      (1, "3R", 0, 5), (2, "3R", 0, 5), (1, "5R", 0, 5), (2, "5R", 0, 5)}
  rows = {3: {"3R": (2, 5), "5R": (0, 5), "1F": (5, 5)}}
  check_note("world 3 3R 2/5, 5R 0/5", rows, complete=True)
  with pytest.raises(AssertionError):
    check_note("world 3 5R 0/5", rows, complete=True)
  with pytest.raises(AssertionError):
    check_note("world 3 3R 3/5", rows)
  check = maes([("0.029", "full"), ("0.045", "partial"), ("0.038", "full")])
  check("0.029, 0.045 (partial), 0.038")
  for wrong in ("0.029, 0.045, 0.038", "0.029, 0.046 (partial), 0.038",
                "0.029 (partial), 0.045, 0.038"):
    with pytest.raises(AssertionError):
      check(wrong)
  mae_rmse({"m": 0.0434, "r": 0.0621, "s": "partial"}, "m", "r", "s")("0.043 (partial)")
  with pytest.raises(AssertionError):
    mae_rmse({"m": 0.0434, "r": 0.0621, "s": "full"}, "m", "r", "s")("0.043 (partial)")
