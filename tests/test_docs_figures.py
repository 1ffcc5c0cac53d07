"""The figures of the README's results table and of every table of
docs/results/reproduction.md (the shipped agent's page) are read from the records under
docs/results/: `shipped-agent/` (the run of models/jackal.npz), `shipped-recipe-seeds/`
(seeds 1, 2 and 7 of its recipe, `seedN-*`) and `baselines/` (`oracle-jackal-results.json`).
Each folder is flat: a run's files are named by its prefix (`shipped-recipe-seeds/seed1-`
+ `suite.json`, `selection.json`, ...; the shipped agent's have none).

Each table has a spec here: for every row (by its first cell) and column, the record a
cell quotes and the check that reads it: the paper's suite reports (`suite.json`), the
evaluations of held-out and closing worlds (`results.md`-style tables), a run's
`selection.json`, `metrics.jsonl`, `record.json` and `config.yaml`, and the paper's own
figures (`mjxvine.evaluation.paper`). Bold (`**`) marks a met target and is not a figure.
A cell that is not from a record (a target, the machine, a command) names its reason in
the spec instead, and every cell of a specced table that holds a digit is one or the other.
The lists in cells are read as the docs write them: successes as "50/50" or "50"; MAE
lists with "(partial)" after a figure whose rows did not all reach the end (a "(partial)"
at the end of a list may stand for several); a note such as "(world 2 5R 0/5)" names
lane-directions and their successes, each of which must be so (where a column lists the
lane-directions below 4/5, exactly those). "The report" section of reproduction.md is the
shipped policy's suite report as `mjxvine.evaluation.suite.report_markdown` writes it,
less its opening paragraph (the page writes its own).
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

from mjxvine.evaluation import choice, paper

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "docs" / "results"
README = ROOT / "README.md"
REPRODUCTION = RESULTS / "reproduction.md"
FACTORS = tuple(paper.PAPER_NOISE)  # the noise test's factors that the paper drove
# A run is the prefix of its files' paths under docs/results/ (f"{run}selection.json").
SHIPPED = "shipped-agent/"    # the run of models/jackal.npz: experiments/jackal.yaml, seed 0
SEED_NUMBERS = (0, 1, 2, 7)  # the recipe's seeds on record; 0 is the shipped agent's run
SEEDS = (SHIPPED, *(f"shipped-recipe-seeds/seed{s}-" for s in SEED_NUMBERS[1:]))
SEEDS_COLUMN = "seeds 0, 1, 2, 7 of its recipe"  # README's column of them
ORACLE = "baselines/oracle-jackal-results.json"
HELDOUT = (25, 26, 27)        # test worlds first evaluated after the shipped policy was chosen


def rank(scores: dict) -> tuple:
  """`choice.rank` at the choice's bar (no recipe sets another)."""
  return choice.rank(scores, choice.SUCCESS_BAR)


def meets_bar(scores: dict) -> bool:
  return choice.meets_bar(scores, choice.SUCCESS_BAR)


# --- records --------------------------------------------------------------------------------

@functools.cache
def record(path: str):
  """A record under docs/results/: JSON, JSON lines or YAML, by its suffix."""
  text = (RESULTS / path).read_text()
  if path.endswith(".jsonl"):
    return [json.loads(line) for line in text.splitlines() if line.strip()]
  return yaml.safe_load(text) if path.endswith(".yaml") else json.loads(text)


def suite(run: str) -> dict:
  return record(f"{run}suite.json")


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


def heldout_path(world: int) -> str:
  return f"{SHIPPED}heldout-world{world}.md"


def f3(x) -> str:
  return "n/a" if x is None else f"{x:.3f}"


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


def heldout_rows() -> dict[int, dict[str, tuple[int, int]]]:
  return {w: {lane: (r["k"], r["n"]) for lane, r in evaluation(heldout_path(w)).items()
              if lane != "overall"} for w in HELDOUT}


def heldout_cell(world: int) -> Check:
  """"48/50, 0.045 (partial)" of the held-out world's table."""
  o = evaluation(heldout_path(world))["overall"]
  return exact(f"{o['success']}, {o['mae']}")


def heldout_note() -> Check:
  """The lane-directions below 4/5 of the held-out worlds, exactly ("none" if none)."""
  return lambda cell: check_note(cell, heldout_rows(), complete=True)


def heldout_summary() -> Check:
  """"145/150 (world 26 3R 0/5), MAE 0.026, 0.020, 0.037 (partial)"."""
  docs = [evaluation(heldout_path(w)) for w in HELDOUT]

  def check(cell):
    m = re.match(r"^(\d+)/(\d+)(?: \(([^()]*)\))?, MAE (.*)$", cell)
    assert m, f"{cell!r}: not 'k/n[ (note)], MAE ...'"
    k = sum(d["overall"]["k"] for d in docs)
    n = sum(d["overall"]["n"] for d in docs)
    assert (int(m.group(1)), int(m.group(2))) == (k, n), f"{cell!r}: the records say {k}/{n}"
    check_note(m.group(3) or "", heldout_rows())
    maes([(d["overall"]["mae"].removesuffix(" (partial)"),
           "partial" if "partial" in d["overall"]["mae"] else "full") for d in docs])(m.group(4))
  return check


def selected_candidate(run: str) -> dict:
  """The entry of `selection.json`'s candidates that the run selected."""
  s = record(f"{run}selection.json")
  return next(c for c in s["candidates"] if c["env_steps"] == s["selected"])


def candidate_steps(run: str) -> str:
  """"100k, 110k, 120k, 130k": the candidates' env steps, in the order of the record."""
  return ", ".join(f"{c['env_steps'] // 1000}k"
                   for c in record(f"{run}selection.json")["candidates"])


def chosen_validation(run: str) -> Check:
  """"66/72, MAE 0.023 m": the chosen candidate's successes on the validation worlds and
  their noise rows (`selection.json`), and its MAE."""
  v = selected_candidate(run)["validation"]
  return exact(f"{v['success']}/{v['episodes']}, MAE {f3(v['mae_m'])} m")


def seeds_range() -> Check:
  """README: "world 0 200/200 at MAE 0.019-0.033; worlds 1-3 600/600" over `SEEDS`."""
  reports = [suite(run) for run in SEEDS]
  w0 = [overall(r, 0) for r in reports]
  w123 = [overall(r, w) for r in reports for w in (1, 2, 3)]
  mae = [o["mae_m_rows"] for o in w0]
  return exact(f"world 0 {sum(o['success'] for o in w0)}/{sum(o['runs'] for o in w0)} at MAE "
               f"{f3(min(mae))}-{f3(max(mae))}; worlds 1-3 "
               f"{sum(o['success'] for o in w123)}/{sum(o['runs'] for o in w123)}")


def test_every_recorded_choice_is_what_rank_chooses():
  """Each recipe seed's `*selection.json` selected what `choice.rank` selects today among
  its candidates (the lever records of unlearning/ are curves, not the recipe's choice)."""
  records = sorted([*RESULTS.glob("shipped-agent/*selection.json"),
                    *RESULTS.glob("shipped-recipe-seeds/*selection.json")])
  assert len(records) == len(SEEDS)
  for path in records:
    sel = json.loads(path.read_text())
    best = max(sel["candidates"], key=lambda c: rank(c["validation"]))
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
# The seeds table's target column: the project's goals, but where they quote the paper.
SEED_TARGETS = {
    "noise 1F / 4F at factors 2, 4, 6, 8, 10": exact(">= " + PAPER_NOISE_TEXT),
    "Husky 1F / 4F": exact(f"{paper.ROBOT_RUNS}/{paper.ROBOT_RUNS} each, MAE <= "
                           f"{_H[0][1]} / {_H[1][1]}"),
    "test world 0: success": TARGET, "test world 0: MAE (mean of rows)": TARGET,
    "test worlds 1, 2, 3: success": TARGET, "test worlds 1, 2, 3: MAE": TARGET}


# --- the tables ---------------------------------------------------------------------------------

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


# --- the specs: table row -> one check (or reason) per column ------------------------------

def _readme_suite(run: str) -> dict:
  """README's columns of a suite report."""
  r = suite(run)
  return {"world 0: success": world0(r), "MAE / RMSE m": mae_rmse(overall(r, 0)),
          "worlds 1, 2, 3": successes(r), "noise test at factor 8 / 10": noise_8_10(r),
          "agent": WHICH}


def _readme_single(path: str) -> dict:
  """README's columns of one evaluation (results.json): MAE / RMSE the mean of its rows,
  as the table says, whatever the record's overall line pools."""
  doc = record(path)
  o = {"mae": np.mean([r["mae_m"] for r in doc["rows"]]),
       "rmse": np.mean([r["rmse_m"] for r in doc["rows"]]),
       "status": "full" if doc["overall"]["success"] == doc["overall"]["runs"] else "partial"}
  return {"world 0: success": exact(f"{doc['overall']['success']}/{doc['overall']['runs']}"),
          "MAE / RMSE m": mae_rmse(o, "mae", "rmse", "status"),
          "worlds 1, 2, 3": exact("-"), "noise test at factor 8 / 10": exact("-"),
          SEEDS_COLUMN: exact("-")}


def readme_spec() -> dict[str, dict]:
  """README's results table: row (first cell) -> column -> check or reason."""
  return {
      "the paper's SAC agent": {
          "world 0: success": PAPER_SUCCESS, "MAE / RMSE m": exact(f"{P[0]:.3f} / {P[1]:.3f}"),
          "worlds 1, 2, 3": exact("-"),
          "noise test at factor 8 / 10": exact(" / ".join(
              f"{sum(paper.PAPER_NOISE[k])}/{2 * paper.NOISE_RUNS}" for k in (8, 10))),
          SEEDS_COLUMN: exact("-")},
      "`models/jackal.npz` (`experiments/jackal.yaml`, seed 0)": {
          **_readme_suite(SHIPPED), SEEDS_COLUMN: seeds_range()},
      "oracle: pure pursuit on the true pose": _readme_single(ORACLE),
  }


def _suite_column(report: dict, *, every: bool = False) -> dict:
  """The rows of the "against the paper" and seeds tables, for one suite report."""
  o0 = overall(report, 0)
  return {
      "w0": world0_all(report) if every else world0(report),
      "w0 mae rmse": mae_rmse(o0),
      "w0 mae": exact("n/a" if o0["rows_status"] == "n/a" else f3(o0["mae_m_rows"]) + (
          "" if o0["rows_status"] == "full" else " (partial)")),
      "w123": successes(report), "w123 mae": world_maes(report), "noise": noise(report),
      "husky": husky(report)}


# The shipped recipe's targets (the seeds table's target column): world 0 (successes of
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


AGAINST = {  # row label of the "against the paper" table -> (column key, the paper's cell)
    "test world 0: success": ("w0", PAPER_SUCCESS),
    "test world 0: MAE / RMSE (mean of the rows)": ("w0 mae rmse", PAPER_MAE_RMSE),
    "test worlds 1, 2, 3 (never trained on): success": ("w123", exact("-")),
    "test worlds 1, 2, 3: MAE (mean of the rows)": ("w123 mae", exact("-")),
    "noise, lanes 1F and 4F, 3 runs: success at factors 2, 4, 6, 8, 10": (
        "noise", exact(PAPER_NOISE_TEXT)),
    "Husky, lanes 1F and 4F, 3 runs": ("husky", PAPER_HUSKY),
    "validation worlds 100-102 and their noise rows (the choice's 72 runs)": (
        "validation", exact("-")),
    "held-out test worlds 25, 26, 27": ("heldout", exact("-")),
}
SEED_ROWS = {  # row label of the seeds table -> column key
    "test world 0: success": "w0", "test world 0: MAE (mean of rows)": "w0 mae",
    "test worlds 1, 2, 3: success": "w123", "test worlds 1, 2, 3: MAE": "w123 mae",
    "noise 1F / 4F at factors 2, 4, 6, 8, 10": "noise", "Husky 1F / 4F": "husky",
    "selected checkpoint (env steps)": "selected", "wall-clock, whole command (min)": "wall",
}


def _seed_column(run: str) -> dict:
  """A column of the seeds table: the chosen policy's suite report, the choice, the time."""
  return {**_suite_column(suite(run)),
          "selected": exact(thousands(record(f"{run}selection.json")["selected"])),
          "wall": exact(f"{record(f'{run}record.json')['wall_s'] / 60:.1f}")}


def _timed_end_to_end(run: str) -> dict:
  """The wall-clock and env-steps checks of a run timed end to end alone (its record.json
  the whole command; the choice's and the closing evaluation's times from their records)."""
  metrics, sel = record(f"{run}metrics.jsonl"), record(f"{run}selection.json")
  sps, ups = learning_speeds(metrics)
  closing = evaluation(f"{run}closing-eval.md")["overall"]["success"]
  closing_s = float(re.search(r"Rollout wall-clock: ([\d.]+) s",
                              (RESULTS / f"{run}closing-eval.md").read_text()).group(1))
  wall_s = record(f"{run}record.json")["wall_s"]
  choice_s = sum(c["validation"]["wall_s"] for c in sel["candidates"])
  assert record(f"{run}config.yaml")["train"]["total_env_steps"] == metrics[-1]["env_steps"]
  return {
      "wall-clock": contains(
          minutes_seconds(wall_s) + " from the command's start",
          minutes_seconds(wall_s - choice_s - closing_s) + " for start-up",
          minutes_seconds(choice_s) + " for the choice", f"{closing_s:.0f} s for the rollouts",
          f"test world 0, {closing}"),
      "env steps": contains(
          f"{thousands(metrics[-1]['env_steps'])} (median {np.median(sps):.0f} env-steps/s "
          f"and {np.median(ups):.0f} gradient steps/s while learning; {spread(sps, ups)})")}


PROFILE_WORDS = {  # run.json's phases as the Training table names them
    "setup": "start-up", "compile": "compilation of the training iteration",
    "collection": "collection", "gradient_steps": "gradient steps",
    "fresh_start_evaluations": "fresh-start evaluations", "logs": "logs",
    "checkpoints": "checkpoints", "choice": "the choice",
    "closing_evaluation": "the closing evaluation"}
TRAINING_PHASES = ("compile", "collection", "gradient_steps")  # the training chunks


def profile_cell(run: str) -> Check:
  """"start-up 19 s, ..., the closing evaluation 34 s: 3 min 46 s outside the training
  chunks and their compilation" from the run's `run.json` profile."""
  phases = record(f"{run}run.json")["profile"]["phases_s"]
  outside = sum(v for k, v in phases.items() if k not in TRAINING_PHASES)
  return contains(*(f"{PROFILE_WORDS[k]} {v:.0f} s" for k, v in phases.items()),
                  f"{minutes_seconds(outside)} outside the training chunks")


def reproduction_spec() -> dict[tuple[str, int], dict]:
  """reproduction.md: (heading, index of the table under it) -> row -> [check or reason per
  column]; "__header__": checks of the header cells after the first."""
  out = {}
  column = {**_suite_column(suite(SHIPPED), every=True),
            "validation": chosen_validation(SHIPPED), "heldout": heldout_summary()}
  out[("Against the paper", 0)] = {
      label: [paper_cell, TARGET, column[key]] for label, (key, paper_cell) in AGAINST.items()}

  sel, chosen = record(f"{SHIPPED}selection.json"), selected_candidate(SHIPPED)
  timed = _timed_end_to_end(SHIPPED)
  out[("Training", 0)] = {label: [check] for label, check in {
      "command": COMMAND, "device": MACHINE, "run record": NAMES,
      "wall-clock": timed["wall-clock"], "env steps": timed["env steps"],
      "where the time went": profile_cell(SHIPPED),
      "chosen checkpoint": contains(
          f"{thousands(sel['selected'])} env steps, of the candidates "
          + candidate_steps(SHIPPED),
          f"drove {chosen['validation']['success']} of the {chosen['validation']['episodes']} "
          "validation runs"),
  }.items()}

  columns = [_seed_column(run) for run in SEEDS]
  out[("Seeds", 0)] = {label: [SEED_TARGETS.get(label, NONE), *(c[key] for c in columns)]
                       for label, key in SEED_ROWS.items()}
  out[("Seeds", 0)]["__header__"] = [None, *(contains(f"seed {s}") for s in SEED_NUMBERS)]

  out[("Held-out test worlds 25, 26, 27", 0)] = {
      "`models/jackal.npz`": [*(heldout_cell(w) for w in HELDOUT), heldout_note()],
      "__header__": [contains(f"world {w}") for w in HELDOUT] + [None]}
  return out


# --- the tests --------------------------------------------------------------------------------

README_TABLE = next(t for t in tables(README) if t.heading == "Results")
# "The report" and its sub-sections: the suite's report, checked as a whole below
REPORT_HEADINGS = ("The report", "Noise (world 0, lanes 1F and 4F, 3 runs each)",
                   "Robots (world 0, 3 runs each; the policy was trained on the Jackal)",
                   "Test world 0", "Test world 1", "Test world 2", "Test world 3")


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
  writes it from the record (headings one level down, figure paths from the page), less
  the report's opening paragraph and the words "(the paper's)" after test world 0: the
  page says what test world 0 is."""
  from mjxvine.evaluation.suite import report_markdown
  lines = report_markdown(suite(SHIPPED)).splitlines()
  assert lines[0].startswith("# The paper's evaluation: ") and not lines[1]
  expected = "\n".join("#" + l if l.startswith("## ") else l for l in lines[2:])
  expected = re.sub(r"\]\(world(\d+)/trajectories\.png\)",
                    rf"]({SHIPPED}suite-world\1-trajectories.png)", expected).strip()
  expected = expected.split("\n\n", 1)[1].replace("Test world 0 (the paper's)", "Test world 0")
  page = REPRODUCTION.read_text()
  section = page[page.index("\n## The report\n"):].split("\n", 3)[3]
  end = re.search(r"^## ", section, re.M)
  section = (section[:end.start()] if end else section).strip()
  section = section.split("\n\n", 1)[1]  # the page's own opening paragraph
  assert section == expected.strip(), (
      f"reproduction.md's report differs from docs/results/{SHIPPED}suite.json as "
      "mjxvine.evaluation.suite.report_markdown writes it")


def test_the_seeds_that_meet_every_target():
  """reproduction.md: "Seeds 0 and 1 meet every target" (seeds 2 and 7 miss the Husky's)."""
  met = [n for n, run in zip(SEED_NUMBERS, SEEDS) if meets_targets(suite(run))]
  assert met == [0, 1]
  assert "Seeds 0 and 1 meet every target." in " ".join(REPRODUCTION.read_text().split())


def test_prose_figures_are_the_records():
  """The README's figures in prose: the shipped run's wall-clock, and its policy as the
  last of its budget (the run's choice kept the last policy, which met the bar)."""
  wall = minutes_seconds(record(f"{SHIPPED}record.json")["wall_s"])
  steps = record(f"{SHIPPED}metrics.jsonl")[-1]["env_steps"]
  readme = " ".join(README.read_text().split())
  assert f"trained in {wall} end to end" in readme
  assert record(f"{SHIPPED}selection.json")["selected"] == steps
  assert f"the last policy of its {thousands(steps)} env steps" in readme
  assert meets_bar(selected_candidate(SHIPPED)["validation"])


def test_a_wrong_figure_fails():
  """A figure changed in a table is caught, and the readers of notes and lists hold the
  docs' forms (a broken reader would pass wrong figures)."""
  table = README_TABLE
  row = next(r for r in table.rows if r[0].startswith("`models/jackal.npz`"))
  bad = [list(r) for r in table.rows]
  for col, wrong in (("MAE / RMSE m", "9.999 / 9.999"),
                     (SEEDS_COLUMN, "world 0 200/200 at MAE 0.019-0.099; "
                                    "worlds 1-3 599/600")):
    bad[table.rows.index(row)][table.header.index(col)] = wrong
    assert _failures(Table(table.where, table.heading, table.header, bad),
                     _specs()[("README", 0)])
    bad = [list(r) for r in table.rows]
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
