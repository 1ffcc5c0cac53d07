"""Where a training run's wall-clock goes, by phase: kept in RUN/run.json ("profile") and
printed at the end of the run (`Profile.line`, and the "profile" of the last JSON line).

Phases (seconds of wall-clock, `time.perf_counter`):
- setup: the config checked, worlds and envs built, programs traced, the state made
  (or restored), the run directory prepared;
- compile: the first call of each program of the training iteration (compilation and one
  execution);
- collection: env steps, replay inserts and the host's bookkeeping of each iteration;
- gradient_steps: the SAC updates;
- training_chunks: collection and gradient steps where they run as one program (the scan
  of an accelerator: `iteration.scan_chunks`), which cannot be split;
- fresh_start_evaluations: the trainer's evaluations from fresh starts, their compilation,
  the best checkpoint and the kept policies included;
- logs: metrics.jsonl, TensorBoard, the progress bar, the learning curve;
- checkpoints: the periodic and the last checkpoint;
- choice: the best checkpoint chosen on validation worlds (`evaluation.choice`);
- closing_evaluation: the closing report (baselines from fresh starts, the test world).

On the CPU the collection and gradient-step calls are timed to their end
(`jax.block_until_ready`), so each phase holds its own compute. `untracked_s` is the
wall-clock of `loop.train` that no phase holds (a few tenths of a second).
"""

from __future__ import annotations

import contextlib
import time

PHASES = ("setup", "compile", "collection", "gradient_steps", "training_chunks",
          "fresh_start_evaluations", "logs", "checkpoints", "choice", "closing_evaluation")


class Profile:
  """Seconds per phase of one process's part of a run, from its creation on."""

  def __init__(self):
    self.start = time.perf_counter()
    self.seconds = dict.fromkeys(PHASES, 0.0)

  def add(self, phase: str, seconds: float) -> None:
    self.seconds[phase] += seconds

  def total(self) -> float:
    """The seconds of every phase so far."""
    return sum(self.seconds.values())

  @contextlib.contextmanager
  def phase(self, name: str):
    """Adds the wall-clock of the `with` block to phase `name`."""
    t0 = time.perf_counter()
    try:
      yield
    finally:
      self.add(name, time.perf_counter() - t0)

  def record(self) -> dict:
    """{"wall_s", "phases_s" (the phases that took time, in PHASES order), "untracked_s"}."""
    wall = time.perf_counter() - self.start
    phases = {k: round(v, 2) for k, v in self.seconds.items() if v > 0}
    return {"wall_s": round(wall, 2), "phases_s": phases,
            "untracked_s": round(wall - sum(self.seconds.values()), 2)}

  def line(self) -> str:
    """'time by phase: setup 12 s, compile 41 s, ...; 1,380 s in all'."""
    rec = self.record()
    parts = [f"{k.replace('_', ' ')} {v:,.0f} s" for k, v in rec["phases_s"].items()]
    return f"time by phase: {', '.join(parts)}; {rec['wall_s']:,.0f} s in all"
