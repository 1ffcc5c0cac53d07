"""The validation curves of runs: for each run's selection.json (`python -m mjxvine.choose
--policy RUN --every` scores every kept policy), the validation successes (of the
protocol's runs) at every evaluated policy, and beside them the critics' mean value
(`q_mean` of RUN/metrics.jsonl), as one figure and one Markdown table.

  python scripts/validation_curves.py NAME=RUN [NAME=RUN ...] --out FIGURE.png [--table T.md]

A run directory or a folder holding its selection.json and metrics.jsonl (a record in
docs/results/) both work; a record's files may carry a prefix: NAME=DIR/seed1- reads
DIR/seed1-selection.json and DIR/seed1-metrics.jsonl.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def read_run(spec: str) -> tuple[dict[int, dict], dict[int, dict]]:
  """({env steps: validation scores}, {env steps: metrics row}) of a run or record."""
  path = Path(spec)
  prefix = "" if path.is_dir() else path.name
  folder = path if path.is_dir() else path.parent
  selection = json.loads((folder / f"{prefix}selection.json").read_text())
  rows = [json.loads(line) for line in
          (folder / f"{prefix}metrics.jsonl").read_text().splitlines() if line]
  scores = {c["env_steps"]: c["validation"] for c in selection["candidates"]}
  return scores, {r["env_steps"]: r for r in rows if r.get("member", 0) == 0}


def table(runs: dict[str, tuple]) -> str:
  """Markdown: one row per run: its validation successes at each evaluated policy (a "+"
  marks a rollout stopped early: at least that many), the best, the last and the drop."""
  lines = ["| run | validation successes by env steps (k) | best | last scored | drop |",
           "|---|---|---:|---:|---:|"]
  for name, (scores, _) in runs.items():
    steps = sorted(scores)
    cells = ", ".join(f"{s // 1000}k {scores[s]['success']}"
                      + ("+" if scores[s].get("stopped_early") else "") for s in steps)
    best = max(scores[s]["success"] for s in steps)
    last = scores[steps[-1]]["success"]
    lines.append(f"| {name} | {cells} | {best} | {last} | {best - last} |")
  return "\n".join(lines) + "\n"


def figure(runs: dict[str, tuple], out: Path) -> None:
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  fig, (ax_v, ax_q) = plt.subplots(1, 2, figsize=(13, 4.8))
  for i, (name, (scores, rows)) in enumerate(runs.items()):
    steps = sorted(scores)
    episodes = scores[steps[0]]["episodes"]
    ax_v.plot([s / 1000 for s in steps], [scores[s]["success"] for s in steps], "o-",
              color=f"C{i % 10}", label=name)
    q = sorted(rows)
    ax_q.plot([s / 1000 for s in q], [rows[s].get("q_mean", float("nan")) for s in q],
              color=f"C{i % 10}", label=name)
  ax_v.axhline(0.95 * episodes, color="grey", ls=":", lw=1)
  ax_v.set(xlabel="env steps (thousands)", ylabel=f"validation successes (of {episodes})",
           title="every evaluated policy on the validation worlds")
  ax_q.set(xlabel="env steps (thousands)", ylabel="critics' mean value (scaled reward)",
           title="q_mean of the training batches")
  for ax in (ax_v, ax_q):
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
  fig.tight_layout()
  fig.savefig(out, dpi=110)


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter,
                              allow_abbrev=False)
  p.add_argument("runs", nargs="+", metavar="NAME=RUN", help="a name and its run or record")
  p.add_argument("--out", type=Path, required=True, help="the figure (PNG)")
  p.add_argument("--table", type=Path, default=None, help="also write the Markdown table")
  args = p.parse_args(argv)
  runs = {}
  for spec in args.runs:
    name, sep, path = spec.partition("=")
    if not sep:
      p.error(f"{spec}: give NAME=RUN")
    try:
      runs[name] = read_run(path)
    except (OSError, ValueError, KeyError) as e:
      p.error(f"{spec}: {type(e).__name__}: {e}")
  figure(runs, args.out)
  text = table(runs)
  if args.table:
    args.table.write_text(text)
  print(text, end="")
  return 0


if __name__ == "__main__":
  raise SystemExit(main())
