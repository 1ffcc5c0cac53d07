"""The realism suite (`mjxvine.evaluation.realism`): its conditions as config values, its
report, and the evaluate command's flags for it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mjxvine.config import SENSOR_PRESETS, load_config
from mjxvine.evaluation import choice, realism

# the realism recipe's seeds in realism.md and the records of each seed's choice (seed 3's:
# its 40,000-step policy, the choice within 0.04 m)
RECIPE_CHOICES = {0: "realism-recipe-seed0", 1: "realism-recipe-seed1",
                  3: "realism-recipe-seed3-40k", 5: "realism-recipe-seed5",
                  6: "realism-recipe-seed6", 7: "realism-recipe-seed7"}


def test_each_condition_sets_only_its_factor():
  """Every condition sets every factor: "ideal" turns them all off whatever the policy
  trained with (here the realism recipe), a factor's condition turns on its own alone, and
  "all" every one; nothing else of the config changes."""
  trained = load_config("experiments/realism.yaml")
  ideal = realism.condition_config(trained, "ideal")
  defaults = load_config()
  assert (ideal.sensor, ideal.world.season, ideal.world.tuft_density_per_m2) == (
      defaults.sensor, "classic", 0.0)
  assert {k: getattr(ideal.robot, k) for k in realism.ROBOT_HIGH} == {
      k: getattr(defaults.robot, k) for k in realism.ROBOT_HIGH}
  for name in realism.CONDITIONS:
    c = realism.condition_config(trained, name)
    for section in ("camera", "env", "sac", "train", "eval"):
      assert getattr(c, section) == getattr(trained, section), (name, section)
    off = [f for f in ("sensor", "world", "robot")
           if getattr(c, f) == getattr(ideal, f)]
    assert (len(off) == 3) == (name == "ideal"), name
    assert (len(off) == 0) == (name == "all"), name
  sensor = realism.condition_config(trained, "sensor").sensor
  assert sensor.preset == realism.FIELD_SENSOR
  assert sensor.stereo_baseline_m == SENSOR_PRESETS[realism.FIELD_SENSOR]["stereo_baseline_m"]
  every = realism.condition_config(trained, "all")
  assert every.sensor == sensor
  for key, value in realism.ROBOT_HIGH.items():
    assert getattr(every.robot, key) == value
  assert realism.condition_config(trained, "winter").world.season == "winter"
  with pytest.raises(ValueError, match="condition 'dusk'"):
    realism.condition_config(trained, "dusk")


def test_the_conditions_are_valid_config_values():
  """Every condition's values pass the config's own checks (types, ranges, choices), as
  `evaluate --condition` gives them."""
  from mjxvine.evaluate import condition_overrides, parser
  for name in realism.CONDITIONS:
    args = parser().parse_args(["--policy", "oracle", "--out", "x", "--condition", name])
    c = load_config(None, condition_overrides(args))
    assert c == realism.condition_config(load_config(), name)


def test_evaluate_refuses_a_condition_with_the_suite(capsys):
  from mjxvine.evaluate import main
  with pytest.raises(SystemExit) as e:
    main(["--policy", "oracle", "--suite", "realism", "--sensor", "d435", "--out", "x"])
  assert e.value.code == 2
  assert "sets its own conditions" in capsys.readouterr().err
  with pytest.raises(SystemExit) as e:
    main(["--policy", "oracle", "--sensor", "d999", "--out", "x"])
  assert e.value.code == 2
  last = capsys.readouterr().err.strip().splitlines()[-1]  # argparse's: usage, then the error
  assert "--sensor: invalid choice: 'd999' (choose from" in last


def test_the_table_names_the_worst_case():
  report = {"policy": "p.npz", "seed": 0, "runs": 5, "block": None, "wall_s": 3.0,
            "conditions": {
                "ideal": {"0": {"success": 50, "runs": 50, "mae_m": 0.02, "worst": {
                    "row": "1F", "success": 5, "runs": 5, "mae_m_raw": 0.03}},
                          "1": {"success": 49, "runs": 50, "mae_m": 0.03, "worst": {
                              "row": "3R", "success": 4, "runs": 5, "mae_m_raw": 0.05}}},
                "all": {"0": {"success": 40, "runs": 50, "mae_m": None, "worst": {
                    "row": "4F", "success": 0, "runs": 5, "mae_m_raw": 0.4}},
                        "1": {"success": 45, "runs": 50, "mae_m": 0.05, "worst": {
                            "row": "2R", "success": 1, "runs": 5, "mae_m_raw": 0.2}}}}}
  md = realism.report_markdown(report)
  assert "| condition | world 0 | world 1 | worst case |" in md
  assert "| ideal | 50/50, 0.020 | 49/50, 0.030 | 1 3R: 4/5 |" in md
  assert "| all | 40/50, n/a | 45/50, 0.050 | 0 4F: 0/5 |" in md


@pytest.mark.slow  # a compilation per condition
def test_the_suite_drives_each_condition(tmp_path):
  """The oracle (the true pose) on a short test world under three conditions: every run
  reaches its row's end, the report holds each condition and world, and each condition's
  line is said as it ends."""
  cfg = load_config(None, ["world.test_length_m=8", "camera.width=16", "camera.height=12",
                           "eval.max_steps=200"])
  from mjxvine.evaluation.rollout import PolicySource
  said = []
  report = realism.realism_suite(cfg, PolicySource("oracle"), tmp_path,
                                 realism.SuiteRuns(runs=1, worlds=(2,)),
                                 conditions=("ideal", "latency", "winter"), say=said.append)
  doc = json.loads((tmp_path / "report.json").read_text())
  assert doc == json.loads(json.dumps(report))
  assert list(doc["conditions"]) == ["ideal", "latency", "winter"]
  for name, worlds in doc["conditions"].items():
    r = worlds["2"]
    assert r["success"] == r["runs"] == 10, name
    assert np.isfinite(r["mae_m"])
  assert "| latency | 10/10" in (tmp_path / "report.md").read_text()
  # each condition's result is said as it finishes (a suite takes minutes a condition)
  mae = doc["conditions"]["winter"]["2"]["mae_m"]
  assert f"realism suite: winter: world 2 10/10, {mae:.3f}" in said


def test_the_results_page_is_its_record():
  """docs/results/realism.md's table of the shipped agent is its suite record, cell by cell
  (success / runs, MAE to 3 decimals), and the README's MAE ranges and run counts are
  that record's."""
  from pathlib import Path
  root = Path(__file__).resolve().parent.parent
  record = json.loads((root / "docs/results/realism/shipped-agent-suite.json").read_text())
  page = (root / "docs/results/realism.md").read_text()
  page = page[page.index("## models/jackal.npz"):page.index("## A first agent")]
  rows = {}
  for line in page.splitlines():
    cells = [c.strip() for c in line.strip("|").split("|")]
    if line.startswith("| ") and cells[0].split(" ")[0] in record["conditions"]:
      rows[cells[0].split(" ")[0]] = cells[1:]
  assert list(rows) == list(record["conditions"])
  for name, cells in rows.items():
    worlds = record["conditions"][name].values()
    assert cells == [f"{r['success']}/{r['runs']}, {r['mae_m']:.3f}" for r in worlds], name
  every = [r["mae_m"] for label, r in record["conditions"]["all"].items() if label.isdigit()]
  ideal = [r["mae_m"] for label, r in record["conditions"]["ideal"].items() if label.isdigit()]
  readme = " ".join((root / "README.md").read_text().split())
  assert f"MAE is {min(every):.3f}-{max(every):.3f} m on test worlds 0-3" in readme
  assert f"({min(ideal):.3f}-{max(ideal):.3f} m ideal)" in readme
  runs = sum(r["runs"] for c in record["conditions"].values() for r in c.values())
  done = sum(r["success"] for c in record["conditions"].values() for r in c.values())
  assert f"{done:,} of its {runs:,} runs reach the end of the row" in readme
  assert f"**{done:,} of {runs:,} runs reach the end of their row.**" in " ".join(page.split())


def _section_table_is_its_records(heading: str, names: tuple[str, ...]) -> int:
  """Checks each cell of the realism table under `heading` of realism.md against the
  records `names` (one per column): the successes per world and their MAE range. Returns
  the cells checked."""
  from pathlib import Path
  root = Path(__file__).resolve().parent.parent / "docs/results"
  reports = [json.loads((root / f"realism/{name}.json").read_text()) for name in names]
  page = (root / "realism.md").read_text()
  start = page.index(heading)
  page = page[start:page.index("\n## ", start)]
  checked = 0
  for line in page.splitlines():
    cells = [c.strip() for c in line.strip("|").split("|")]
    if not line.startswith("| ") or cells[0] not in realism.CONDITIONS:
      continue
    for cell, report in zip(cells[1:], reports):
      if cell == "-":
        assert cells[0] not in report["conditions"]
        continue
      worlds = [report["conditions"][cells[0]][str(w)] for w in range(4)]
      maes = [r["mae_m"] for r in worlds if r["mae_m"] is not None]
      assert cell == (", ".join(str(r["success"]) for r in worlds)
                      + f"; MAE {min(maes):.3f}-{max(maes):.3f}"), (cells[0], cell)
      checked += 1
  return checked


def test_the_trained_seeds_tables_are_their_records():
  """The realism-trained seeds' tables: each cell the records' successes per world and
  their MAE range, beside the shipped agent."""
  assert _section_table_is_its_records("## The shipped recipe trained against the field", (
      "realism70k-seed0-suite", "realism70k-seed0-50k-suite", "realism70k-seed1-suite",
      "realism70k-seed2-suite", "realism70k-seed3-suite", "shipped-agent-suite")) == 60
  assert _section_table_is_its_records("## The realism recipe", tuple(
      f"{name}-suite" for name in RECIPE_CHOICES.values())) == 10 * len(RECIPE_CHOICES)


def test_the_realism_recipes_paper_suite_is_its_records():
  """realism.md's paper-suite line of the realism recipe's seeds: test world 0's successes
  and MAE, and the noise test at factor 10, as their records have them."""
  from pathlib import Path
  root = Path(__file__).resolve().parent.parent / "docs/results"
  docs = [json.loads((root / f"realism/{name}-paper.json").read_text())
          for name in RECIPE_CHOICES.values()]
  page = " ".join((root / "realism.md").read_text().split())
  world0 = [d["worlds"]["0"]["overall"] for d in docs]
  assert ("test world 0 " + ", ".join(str(w["success"]) for w in world0[:-1])
          + f" and {world0[-1]['success']} of 50 (MAE "
          + ", ".join(f"{w['mae_m']:.3f}" for w in world0) + " m)") in page
  at10 = [sum(r["success"] for r in d["noise"]["10"].values()) for d in docs]
  assert f"at 10 {', '.join(map(str, at10[:-1]))} and {at10[-1]};" in page


def test_the_realism_recipes_validation_curves_are_their_records():
  """realism.md's validation curve of each realism-recipe seed (every kept policy, by env
  steps) is its `choose --every` record, and each seed's choice the rule's: the last
  policy when it meets the bar within `ALONE_MAE_M`, else the best by `rank`."""
  from pathlib import Path
  root = Path(__file__).resolve().parent.parent / "docs/results"
  page = " ".join((root / "realism.md").read_text().split())
  for seed in RECIPE_CHOICES:
    every = json.loads((root / f"realism/realism-recipe-seed{seed}-selection-every.json")
                       .read_text())
    curve = sorted((c["env_steps"], c["validation"]["success"]) for c in every["candidates"])
    assert [steps for steps, _ in curve] == [20000, 40000, 60000, 70000], seed
    assert f"seed {seed} " + ", ".join(str(n) for _, n in curve) in page, seed
    scores = {c["env_steps"]: c["validation"] for c in every["candidates"]}
    last = scores[70000]
    alone = choice.meets_bar(last, choice.SUCCESS_BAR) and last["mae_m"] <= choice.ALONE_MAE_M
    best = max(scores, key=lambda steps: choice.rank(scores[steps], choice.SUCCESS_BAR))
    chosen = json.loads((root / f"realism/realism-recipe-seed{seed}-selection.json").read_text())
    assert chosen["selected"] == (70000 if alone else best), seed
    assert RECIPE_CHOICES[seed].endswith("-40k") == (chosen["selected"] == 40000), seed
