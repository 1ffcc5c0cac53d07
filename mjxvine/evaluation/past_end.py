"""`evaluate --past-end`: every lane driven on past its end into the headland, and where
the end-of-row detector (`mjxvine.deploy.numpy_policy`, The end of the row) stopped the
robot.

The env's episodes then end `PAST_END_M` past the end line instead of at it (`env.past_end_m`);
the detector runs on the image the policy saw after each step, with the speed it had
commanded. Where it first says "row ended" is the robot's stop (the ROS 2 node stops
publishing motion there: `mjxvine.deploy.node_logic`). Per lane-direction (`report`):

  stop_error_m        mean over the runs that stopped of the stop's signed distance to the
                      end of the row along its end direction (m; < 0: before it), or None
  stopped_within_1m   runs whose stop lies within 1 m of the end of the row
  false_stops         runs that stopped more than 1 m before it (a gap taken for the end)
  missed              runs with no stop before their episode ended (past the headland line,
                      or a collision, a time-out)
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jp
import numpy as np

from mjxvine.config import Config
from mjxvine.deploy import RowEnd, band_rows, read_policy_file, row_cue, row_start, row_update

PAST_END_M = 3.0  # how far past the end line an episode drives on (m)
WITHIN_M = 1.0  # a stop this near the end of the row is right; further before it is false


def settings_of(spec: str) -> RowEnd:
  """The detector settings a policy file carries (its metadata's "row_end"), else the
  defaults (a run directory, a policy file from before the detector)."""
  if str(spec).endswith(".npz") and Path(spec).is_file():
    return RowEnd.from_meta(read_policy_file(spec)[1].get("row_end"))
  return RowEnd()


def end_of(world, lane: int, direction: str) -> tuple[np.ndarray, np.ndarray]:
  """(the end of the row (2,) m, its unit direction (2,)) of lane `lane` (1-based) driven in
  `direction` ("F"/"R"): the env's EoR and end line."""
  line = world.lanes[lane - 1].centerline
  end, before = (line[-1], line[-2]) if direction == "F" else (line[0], line[1])
  t = end - before
  return end, t / np.linalg.norm(t)


class Detector(NamedTuple):
  """The detector of one evaluation: its settings, the band of image rows it reads, and
  the control step (s)."""
  settings: RowEnd
  rows: int
  dt_s: float

  @classmethod
  def of(cls, cfg: Config, spec: str) -> "Detector":
    s = settings_of(spec)
    return cls(s, band_rows(cfg.camera.height, cfg.camera.fovy_deg, s.min_elevation_deg),
               cfg.env.control_dt)

  def cue(self, depth):
    """(share (B,), mean depth (B,)) of depth (B, H, W): inside the rollout's step."""
    return row_cue(depth, self.rows, self.settings, xp=jp)

  def ended(self, share: np.ndarray, depth_m: np.ndarray, speed: np.ndarray) -> np.ndarray:
    """(T, B) bool: "row ended" after each step, from the cues (T, B) and the commanded
    speeds (T, B), the detector's memory carried from each run's start."""
    def step(memory, x):
      memory, ended = row_update(memory, *x, self.dt_s, self.settings, xp=jp)
      return memory, ended
    _, out = jax.lax.scan(step, row_start(share.shape[1:], xp=jp),
                          (jp.asarray(share), jp.asarray(depth_m), jp.asarray(speed)))
    return np.asarray(out)

  def report(self, world, cases, raw: dict) -> dict:
    """The results' "row_end" section for the cases (`rollout.Cases`) of `raw`
    (`rollout.rollout_cases` with this detector's `cue`)."""
    share, depth_m = raw["cue"]
    ended = self.ended(share, depth_m, raw["act"][..., 0]) & raw["alive"]
    rows, stops = {}, []
    for i, (_, lane, direction, _) in enumerate(cases):
      end, t = end_of(world, lane, direction)
      hits = np.nonzero(ended[:, i])[0]
      stop = float((raw["xy"][hits[0], i] - end) @ t) if len(hits) else None
      rows.setdefault(f"{lane}{direction}", []).append(stop)
      stops.append(stop)
    table = {key: _counts(v) for key, v in rows.items()}
    return {"past_end_m": PAST_END_M, "settings": self.settings._asdict(), **_counts(stops),
            "rows": table}


def _counts(stops: list) -> dict:
  """The figures of a set of runs' stops (m from the end of the row, None: no stop)."""
  made = [s for s in stops if s is not None]
  return {"runs": len(stops),
          "stopped_within_1m": sum(abs(s) <= WITHIN_M for s in made),
          "false_stops": sum(s < -WITHIN_M for s in made),
          "missed": len(stops) - len(made),
          "stop_error_m": round(float(np.mean(made)), 3) if made else None,
          "stops_m": [None if s is None else round(s, 3) for s in stops]}
