"""The table of a seed study: for each run record, every member's best fresh-start
evaluation (a run of `--num-seeds K` trains K members from the keys of `train.seed`; a
single run is one member), as the trainer keeps it
(`mjxvine.evaluation.choice.fresh_start_score`: the weaker direction's success, then the
lower lateral MAE).

  python scripts/seed_table.py docs/results/default-seeds/*-record.json [--every 6]
  python scripts/seed_table.py --write docs/results/default-seeds.md

`--write PAGE` rewrites every table of PAGE under a `<!-- seed table: [--every K] NAME
... -->` line from the records that PAGE's folder of the same name holds, as
`tests/test_seed_study.py` checks them.

A record NAME is three files side by side in its folder: the run's `NAME-metrics.jsonl`
and `NAME-config.yaml` and a `NAME-record.json` ({"command", "tower", "wall_s", "device",
"release", "note"}); it is named by the path FOLDER/NAME (or any of its files). `--every K`
keeps only the evaluations at chunks that are multiples of K, so that runs evaluated at
different intervals compare (an evaluation has its own key and does not change
training). Prints a markdown table: each member's weaker direction in %, and how many
reach 80 %.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import yaml

from mjxvine.evaluation.choice import fresh_start_score

TARGET = 0.8  # the weaker direction's success a member must reach
FILES = ("record.json", "metrics.jsonl", "config.yaml")  # a record's files: NAME-<file>


def record_file(run: Path, what: str) -> Path:
  """One file of the record `run` (FOLDER/NAME): FOLDER/NAME-<what>."""
  return run.parent / f"{run.name}-{what}"


def as_record(path: Path) -> Path:
  """FOLDER/NAME from FOLDER/NAME or from one of its files (FOLDER/NAME-record.json)."""
  for what in FILES:
    if path.name.endswith(f"-{what}"):
      return path.parent / path.name[:-len(what) - 1]
  return path


def records_in(folder: Path) -> list[Path]:
  """Every record of a folder (each FOLDER/NAME with a NAME-record.json), by name."""
  return sorted(as_record(p) for p in folder.glob("*-record.json"))


def best_per_seed(run: Path, every: int = 1) -> dict[int, dict]:
  """seed -> the metrics row of its best fresh-start evaluation (chunks % every == 0)."""
  best: dict[int, dict] = {}
  for line in record_file(run, "metrics.jsonl").read_text().splitlines():
    row = json.loads(line) if line.strip() else {}
    if row.get("eval_success_forward") is None or row["chunk"] % every:
      continue
    seed = row["seed"]
    if seed not in best or fresh_start_score(row) > fresh_start_score(best[seed]):
      best[seed] = row
  return best


def weaker(row: dict) -> float:
  return min(row["eval_success_forward"], row["eval_success_reverse"])


def table(runs: list[Path], every: int = 1) -> str:
  lines = ["| record | tower | `train.seed` (members) | best evaluation, weaker direction, "
           "per member (%) | members >= 80 % | wall-clock |",
           "|---|---|---|---|---:|---:|"]
  for run in runs:
    record = json.loads(record_file(run, "record.json").read_text())
    cfg = yaml.safe_load(record_file(run, "config.yaml").read_text())
    best = best_per_seed(run, every)
    seeds = sorted(best)
    cells = ", ".join(f"{100 * weaker(best[s]):.0f}" for s in seeds)
    passed = sum(weaker(best[s]) >= TARGET for s in seeds)
    count = cfg["train"]["num_seeds"]
    members = f"{count} vmapped" if count > 1 else "a single run"
    lines.append(f"| [{run.name}]({run.parent.name}/{run.name}-record.json) | {record['tower']} | "
                 f"{cfg['train']['seed']} ({members}) | {cells} | {passed}/{len(seeds)} | "
                 f"{record['wall_s'] / 60:.1f} min |")
  return "\n".join(lines)


MARK = re.compile(r"^<!-- seed table: (.+?) -->$")


def marked_tables(page: Path):
  """(line index of each marker, every, records (FOLDER/NAME), the table lines after it)."""
  lines = page.read_text().splitlines()
  records = page.with_suffix("")
  for i, line in enumerate(lines):
    m = MARK.match(line)
    if m:
      args, every = m.group(1).split(), 1
      if args[0] == "--every":
        every, args = int(args[1]), args[2:]
      rows = []
      for row in lines[i + 1:]:
        if not row.startswith("|"):
          break
        rows.append(row)
      yield i, every, [records / name for name in args], rows


def write(page: Path) -> None:
  """Rewrites every marked table of `page` from its records."""
  lines = page.read_text().splitlines()
  for i, every, runs, rows in reversed(list(marked_tables(page))):
    lines[i + 1:i + 1 + len(rows)] = table(runs, every).splitlines()
  page.write_text("\n".join(lines) + "\n")


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
  parser.add_argument("runs", nargs="*", type=Path,
                      help="records: FOLDER/NAME, or one of its files (FOLDER/NAME-record.json)")
  parser.add_argument("--every", type=int, default=1,
                      help="only evaluations at chunks that are multiples of this")
  parser.add_argument("--write", type=Path, metavar="PAGE",
                      help="rewrite the marked tables of this page instead")
  args = parser.parse_args(argv)
  if args.write:
    write(args.write)
  else:
    print(table(list(dict.fromkeys(as_record(r) for r in args.runs)), args.every))


if __name__ == "__main__":
  main()
