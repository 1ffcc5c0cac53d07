"""Interrupts one training run again and again, resuming after each interruption, and
checks that every resume works and that metrics.jsonl ends with each chunk exactly once.

  python scripts/chaos_check.py --out /tmp/chaos --kills 20

Each interruption is kill -9 or SIGTERM (alternating), sent at a random moment (uniform
in [--min-s, --max-s] seconds after the process starts, so it may fall in start-up,
compilation, a chunk or a checkpoint write; the first run, which compiles, only after its
first checkpoint). Extra arguments after `--` go to the first
`train` command (default: experiments/smoke.yaml with checkpoints every 2 chunks). Prints
one line per interruption and a JSON summary; exits 1 if a check failed.
"""

from __future__ import annotations

import argparse
import json
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DEFAULT = ["--config", "experiments/smoke.yaml", "--no-eval", "--set",
           "train.total_env_steps=8000", "--set", "train.checkpoint_every_chunks=2"]


def main(argv=None) -> int:
  p = argparse.ArgumentParser(allow_abbrev=False, description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--out", dest="run_dir", type=Path, required=True)
  p.add_argument("--kills", type=int, default=20)
  p.add_argument("--min-s", type=float, default=5.0)
  p.add_argument("--max-s", type=float, default=40.0)
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("train_args", nargs="*")
  args = p.parse_args(argv)
  rng = random.Random(args.seed)
  base = [sys.executable, "-m", "mjxvine.train"]
  first = base + (args.train_args or DEFAULT) + ["--out", str(args.run_dir)]
  resume = base + ["--resume", str(args.run_dir), "--no-eval"]
  log, failures = [], []
  for i in range(args.kills + 1):
    cmd = first if i == 0 else resume
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    if i == 0:  # the first run compiles: interrupt it once it has a checkpoint
      while proc.poll() is None and not any(
          p.name.isdigit() for p in (args.run_dir / "checkpoints").glob("*")):
        time.sleep(0.5)
    if i < args.kills:
      sig = signal.SIGKILL if i % 2 == 0 else signal.SIGTERM
      delay = rng.uniform(args.min_s, args.max_s)
      try:
        proc.wait(timeout=delay)  # ended by itself (a complete run)
      except subprocess.TimeoutExpired:
        proc.send_signal(sig)
    else:
      sig, delay = None, None
    _, err = proc.communicate()
    resumed = next((l for l in err.splitlines() if l.startswith(("resumed", "no usable"))
                    or "is complete" in l), "")
    # SIGTERM: 143 from the run's handler; -15 when it lands before Python installed it
    # (start-up), as does a kill -9 at any time. A resume must not fail on its own, and
    # one that ran past its restore must say what it restored.
    expected = {0, -signal.SIGKILL, -signal.SIGTERM, 128 + signal.SIGTERM} if sig else {0}
    trained = "compiling the training iteration" in err
    ok = (proc.returncode in expected and "Traceback" not in err
          and (i == 0 or resumed or not trained))
    entry = {"try": i, "signal": sig.name if sig else None, "after_s": delay and round(delay, 1),
             "exit": proc.returncode, "resume": resumed[:80], "trained": trained,
             "last_line": (err.strip().splitlines() or [""])[-1][-100:], "ok": bool(ok)}
    log.append(entry)
    print(json.dumps(entry), flush=True)
    if not ok:
      failures.append({**entry, "stderr": err[-2000:]})
  rows = [json.loads(l) for l in (args.run_dir / "metrics.jsonl").read_text().splitlines()]
  chunks = [r["chunk"] for r in rows]
  once = chunks == list(range(1, len(chunks) + 1))
  summary = {"interruptions": args.kills, "resumes_ok": sum(e["ok"] for e in log[1:]),
             "interrupted_while_training": sum(e["trained"] for e in log[:-1]),
             "sigterm_exits_143": sum(e["exit"] == 143 for e in log),
             "rows": len(rows), "chunks_once_in_order": once, "last_chunk": chunks[-1:],
             "failures": failures}
  print(json.dumps(summary, indent=1))
  return 0 if once and not failures else 1


if __name__ == "__main__":
  sys.exit(main())
