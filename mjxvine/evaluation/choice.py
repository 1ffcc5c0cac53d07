"""The best checkpoint, chosen on validation worlds after training (`python -m
mjxvine.choose`, docs in its module), and the ranking rules of evaluated policies.

Two orders, higher is better:
  * `fresh_start_score`: the trainer's fresh-start evaluations (`starts`): the weaker
    direction's success, then the lower MAE (checkpoints/best, each member's best, the
    candidates here);
  * `rank`: validated candidates: those that meet the test targets' bar on the validation
    protocol (`meets_bar`: successes and an offset the targets allow) by the lower MAE,
    then the others by their successes, then the lower MAE. Offset decides among the
    policies that drive: without the bar, a policy that drove one more noise run at
    factor 10 (where the paper drives none) would win at any offset.

The validation protocol: every lane-direction of `train.select_worlds` test-kind worlds of
seeds `FIRST_WORLD_SEED` and up, `RUNS` runs each, at `eval.noise_factor`; and the noise
test's rows (`paper.NOISE_LANES`, `paper.NOISE_RUNS` runs) of the first validation world
at each of `NOISE_FACTORS`. One batched rollout per candidate, rollout seed 0: the same
cases and keys for every candidate.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from mjxvine.agent_file import agent_path
from mjxvine.atomic import write_bytes, write_text
from mjxvine.config import Config, config_hash, to_dict
from mjxvine.episodes import OUTCOMES
from mjxvine.evaluation import paper
from mjxvine.evaluation.metrics import summarize
from mjxvine.evaluation.rollout import Cases, PolicySource, all_lanes, rollout_cases
from mjxvine.formatting import fmt
from mjxvine.rundir.checkpoints import selection_files

FIRST_WORLD_SEED = 100  # validation worlds: test-kind seeds 100 and up (test tables: below)
RUNS = 2  # runs per lane-direction of a validation world
NOISE_FACTORS = (8.0, 10.0)  # the noise test's factors on the first validation world
SUCCESS_BAR = 0.95  # the share of runs a candidate must drive to rank by its offset
MAE_BAR_M = 0.06  # and the MAE it may keep at most: the test target of test world 0
ALONE_MAE_M = 0.04  # the last policy is taken alone only this near the centreline
SUCCESS_CODE = OUTCOMES.index("success")


# ---------------------------------------------------------------------------- ranking rules
def fresh_start_score(scores: dict) -> tuple:
  """Order of fresh-start evaluations (`eval_success_forward`, `eval_success_reverse`,
  `eval_mae_m` of a metrics row) for the best checkpoint, higher is better: the weaker
  direction's success, then the lower MAE."""
  return (min(scores["eval_success_forward"], scores["eval_success_reverse"]),
          -scores["eval_mae_m"])


def meets_bar(scores: dict, bar: float) -> bool:
  """Whether validated scores (`score_policy`) meet the bar the test targets set: at
  least the fraction `bar` of the validation worlds' runs reach the EoR, their MAE (the
  mean of the worlds' means of rows) is at most `MAE_BAR_M`, and each noise row succeeds
  at least as often as the paper's at every one of the paper's factors (a factor the
  paper did not drive asks nothing)."""
  worlds = scores["worlds"].values()
  if sum(w["success"] for w in worlds) < bar * sum(w["episodes"] for w in worlds):
    return False
  if scores["mae_m"] is None or scores["mae_m"] > MAE_BAR_M:
    return False
  for factor, rows in scores["noise"].items():
    need = paper.PAPER_NOISE.get(float(factor), ())
    if any(rows[f"{lane}{way}"] < n for (lane, way), n in zip(paper.noise_rows(), need)):
      return False
  return True


def rank(scores: dict, bar: float) -> tuple:
  """Order of validated candidates (`score_policy`), higher is better: those that meet
  the bar (`meets_bar`) first, by the lower MAE; the others by their successes, then the
  lower MAE (no MAE ranks last)."""
  mae = scores["mae_m"]
  lower_mae = -(mae if mae is not None else float("inf"))
  return (1, lower_mae, 0) if meets_bar(scores, bar) else (0, scores["success"], lower_mae)


# ---------------------------------------------------------------------------- a run's policies
def policy_file(run_dir: Path, env_steps: int, member: int | None = None) -> Path:
  """RUN/eval_policies/env<steps>.npz: the policy evaluated at `env_steps`; of one member
  of a run of several, RUN/eval_policies/member<k>/env<steps>.npz."""
  folder = Path(run_dir) / "eval_policies"
  return (folder if member is None else folder / f"member{member}") / f"env{env_steps}.npz"


def member_ids(count: int) -> tuple | range:
  """How the choice's files name the members of a run of `count`: (None,) for a run of
  one (its files in the run directory itself), else 0 .. count - 1."""
  return (None,) if count == 1 else range(count)


def kept_policies(run_dir: Path, member: int | None = None) -> dict[int, Path]:
  """{env steps: policy file} of the run's (or one member's) kept policies."""
  folder = policy_file(run_dir, 0, member).parent
  names = ((re.fullmatch(r"env(\d+)", f.stem), f) for f in folder.glob("env*.npz"))
  return {int(m.group(1)): f for m, f in names if m}


def trainer_evaluations(run_dir: Path, member: int = 0) -> dict[int, dict]:
  """{env steps: the eval_* values} of one member's fresh-start evaluations, from
  RUN/metrics.jsonl (the last row of a step wins: a resumed run rewrites its tail)."""
  out = {}
  path = Path(run_dir) / "metrics.jsonl"
  for line in path.read_text().splitlines() if path.is_file() else ():
    row = json.loads(line)
    if row.get("member", 0) == member and "eval_success_forward" in row:
      out[int(row["env_steps"])] = {k: row[k] for k in row if k.startswith("eval_")}
  return out


def candidates(evaluations: dict[int, dict], kept: set[int], k: int) -> list[int]:
  """The env steps of `k` evaluations whose policy was kept: the last first, then the
  `k - 1` best of the others by `fresh_start_score`, best first (the earlier of equal
  scores first, as the trainer keeps the first of equals as checkpoints/best)."""
  steps = sorted(s for s in evaluations if s in kept)
  if not steps:
    return []
  others = sorted(steps[:-1], key=lambda s: fresh_start_score(evaluations[s]), reverse=True)
  return [steps[-1], *others[:k - 1]]


# ---------------------------------------------------------------------------- validation
def validation_worlds(cfg: Config) -> list:
  """The `train.select_worlds` validation worlds (test-kind, seeds `FIRST_WORLD_SEED`...)."""
  from mjxvine.worlds import make_world
  return [make_world(str(FIRST_WORLD_SEED + i), cfg.world)
          for i in range(cfg.train.select_worlds)]


def validation_cases(worlds: list, runs: int, noise0: float, noise_factors) -> tuple:
  """(cases, tables, noise): the `rollout.Cases` of the validation protocol; tables[i]
  the case indices of world i's table, noise[k] those of the noise test's rows of world 0
  at noise factor k (a float)."""
  cases = Cases()
  tables = [cases.add(wi, all_lanes(world), noise0, runs) for wi, world in enumerate(worlds)]
  noise = {float(k): cases.add(0, paper.noise_rows(), float(k), paper.NOISE_RUNS)
           for k in noise_factors}
  return cases, tables, noise


def score_policy(cfg: Config, path: Path, worlds: list, runs: int,
                 noise_factors=(), below_bar_stops: bool = False) -> dict:
  """One policy file's validation scores: {"worlds": {seed: {success, episodes,
  mae_m_rows, rows_status, failed}}, "noise": {factor: {"1F": successes, "4F": ...}},
  "success", "episodes" (over all of it), "mae_m" (the mean of the worlds' mean-of-rows
  MAE; None when no world has one), "wall_s"}. `below_bar_stops`: the rollout stops once
  so many of the worlds' runs failed that the policy cannot meet `SUCCESS_BAR`; its
  scores then hold "stopped_early": the worlds' runs that had failed, and count the runs
  not finished as failed (its successes are a lower bound)."""
  cases, tables, noise = validation_cases(worlds, runs, cfg.eval.noise_factor, noise_factors)
  world_cases = np.concatenate([np.asarray(t, int) for t in tables])
  allowed = (1 - SUCCESS_BAR) * len(world_cases)  # failures the bar allows
  cut = []  # the failures when the rollout stopped with runs unfinished

  def below_bar(outcome: np.ndarray) -> bool:
    ended = outcome[world_cases]
    failed = int(np.sum((ended != 0) & (ended != SUCCESS_CODE)))
    if failed <= allowed:
      return False
    if np.any(outcome == 0):
      cut.append(failed)
    return True

  raw, _ = rollout_cases(cfg, PolicySource(str(path)), worlds, cases,
                         stop=below_bar if below_bar_stops else None)
  out = {"worlds": {}, "noise": {}}
  for world, idx in zip(worlds, tables):
    doc = summarize(cfg, world, cases, idx, raw)
    out["worlds"][str(world.seed)] = {
        "success": int(sum(r["success"] for r in doc["rows"])), "episodes": len(idx),
        "mae_m_rows": doc["overall"]["mae_m_rows"],
        "rows_status": doc["overall"]["rows_status"],
        "failed": [f"{r['lane']}{r['direction']}" for r in doc["rows"]
                   if r["success"] < r["runs"]]}
  for k, idx in noise.items():
    doc = summarize(cfg, worlds[0], cases, idx, raw)
    out["noise"][str(k)] = {f"{r['lane']}F": int(r["success"]) for r in doc["rows"]}
  maes = [w["mae_m_rows"] for w in out["worlds"].values() if w["mae_m_rows"] is not None]
  out["success"] = (sum(w["success"] for w in out["worlds"].values())
                    + sum(sum(v.values()) for v in out["noise"].values()))
  out["episodes"] = len(cases)
  out["mae_m"] = float(np.mean(maes)) if maes else None
  out["wall_s"] = raw["wall_s"]
  if cut:
    out["stopped_early"] = cut[0]
  return out


def protocol(cfg: Config) -> dict:
  """What the validation scores depend on besides the policy: a selection.json with other
  values is scored again. `conditions`: a hash of the config's world, robot, camera, sensor
  and env sections (the sensor model and the robot's faults drive with the policy)."""
  t = cfg.train
  conditions = {k: to_dict(getattr(cfg, k)) for k in ("world", "robot", "camera", "sensor",
                                                      "env")}
  return {"worlds": [FIRST_WORLD_SEED + i for i in range(t.select_worlds)],
          "runs": RUNS, "noise_factor": cfg.eval.noise_factor,
          "noise_factors": list(NOISE_FACTORS),
          "noise_lanes": list(paper.NOISE_LANES), "noise_runs": paper.NOISE_RUNS,
          "max_steps": cfg.eval.max_steps, "rollout_seed": 0,
          "conditions": config_hash(conditions)}


# ---------------------------------------------------------------------------- the choice
def select(cfg: Config, run_dir: Path, say=print, member: int | None = None,
           every: bool = False) -> dict:
  """Chooses the run's best policy on the validation worlds (the module's docstring), or
  one member's of a run of several (`member`: its own evaluations and kept policies);
  writes the selection record and the chosen policy (`checkpoints.selection_files`:
  RUN/selection.json and RUN/selected.npz, or RUN/selected_members/selection<k>.json and
  member<k>.npz) and returns the record: {"protocol", "candidates": [{"env_steps",
  "trainer": eval_* values, "validation": `score_policy`}, in the order driven],
  "selected": env steps}.

  The choice is a safeguard: the last policy drives first, and when it meets the bar
  within `ALONE_MAE_M` of the centreline it is chosen and nothing else drives. Otherwise
  the others (`candidates`) drive, each stopped as soon as it cannot meet the bar once one
  has met it (it could not be chosen); the lowest MAE of those that meet it wins.
  `every`: every kept policy drives, in the order of training, none stopped early (the
  validation curve of the run); the choice among them by `rank`."""
  run_dir = Path(run_dir)
  if cfg.train.select_worlds < 1:
    raise ValueError(f"{run_dir}: train.select_worlds = 0 in its config: give --set "
                     "train.select_worlds=N (N validation worlds)")
  evaluations = trainer_evaluations(run_dir, member or 0)
  kept = kept_policies(run_dir, member)
  chosen = (sorted(s for s in evaluations if s in kept) if every else
            candidates(evaluations, set(kept), cfg.train.select_candidates))
  if not chosen:
    where = policy_file(run_dir, 0, member).parent.relative_to(run_dir)
    raise FileNotFoundError(f"{run_dir}: no evaluated policy to choose from (RUN/{where}/"
                            "env<steps>.npz beside the evaluations of metrics.jsonl)")
  record_path, selected_path = selection_files(run_dir, member)
  selected_path.parent.mkdir(parents=True, exist_ok=True)
  old = json.loads(record_path.read_text()) if record_path.is_file() else {}
  record = {"protocol": protocol(cfg), "candidates": [], "selected": None}
  done = ({c["env_steps"]: c["validation"] for c in old.get("candidates", [])
           if not (every and c["validation"].get("stopped_early"))}
          if old.get("protocol") == record["protocol"] else {})
  worlds = validation_worlds(cfg)
  who = "" if member is None else f"member {member}: "
  say(f"{who}choosing the best of {len(chosen)} evaluated policies "
      f"({', '.join(map(str, chosen))} env steps) on validation worlds "
      f"{record['protocol']['worlds']}...")
  bar, met = SUCCESS_BAR, False
  for steps in chosen:
    scores = done.get(steps) or score_policy(cfg, kept[steps], worlds, RUNS, NOISE_FACTORS,
                                             below_bar_stops=met and not every)
    record["candidates"].append({"env_steps": steps, "trainer": evaluations[steps],
                                 "validation": scores})
    write_text(record_path, json.dumps(record, indent=1))  # resumable after each candidate
    meets = meets_bar(scores, bar)
    say(f"  {steps:>8} env steps: {summary(scores)}"
        + (" (meets the bar)" if meets else ""))
    met = met or meets
    if meets and not every and steps == chosen[0] and scores["mae_m"] <= ALONE_MAE_M:
      say(f"{who}the last policy meets the bar within {ALONE_MAE_M} m: no other drives")
      break
  best = max(record["candidates"], key=lambda c: rank(c["validation"], bar))  # first of equals
  record["selected"] = best["env_steps"]
  # over an earlier choice, whole: it stays until this one is ready (a stop keeps it)
  write_bytes(selected_path, kept[best["env_steps"]].read_bytes())
  agent = agent_path(kept[best["env_steps"]])
  if agent.is_file():  # what training can continue from (`train --init`)
    write_bytes(agent_path(selected_path), agent.read_bytes())
  write_text(record_path, json.dumps(record, indent=1))
  say(f"{who}selected the policy of {best['env_steps']} env steps: {selected_path}")
  return record


def summary(scores: dict) -> str:
  """One line: successes per validation world and at each noise factor, and the MAE."""
  worlds = ", ".join(f"world {s} {w['success']}/{w['episodes']}"
                     for s, w in scores["worlds"].items())
  noise = ", ".join(f"noise {k} {sum(v.values())}/{paper.NOISE_RUNS * len(paper.NOISE_LANES)}"
                    for k, v in scores["noise"].items())
  mae = "-" if scores["mae_m"] is None else f"{fmt(scores['mae_m'])} m"
  if scores.get("stopped_early"):
    return (f"stopped once {scores['stopped_early']} runs of its worlds had failed: it "
            "cannot meet the bar")
  return f"{scores['success']}/{scores['episodes']} ({worlds}; {noise}), MAE {mae}"
