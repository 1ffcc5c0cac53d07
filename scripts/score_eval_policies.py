"""Scores every policy a run kept with `train.keep_eval_policies` on validation worlds, so
that rules for choosing the best checkpoint can be compared without training again.

  python scripts/score_eval_policies.py runs/RUN [--worlds 100,101,102] [--runs 2]
      [--steps 50000,90000]

For each RUN/eval_policies/env<steps>.npz, one batched rollout of the evaluation protocol
(`mjxvine.evaluate`): every lane-direction of each validation world (test-kind seeds that
the test tables never use) with `--runs` runs at the config's noise factor, and rows 1F
and 4F of the first validation world with 3 runs at each `--noise` factor. Besides, the
fresh-start evaluation of the trainer (`mjxvine.starts`) on the training pool at the
config's noise factor (`--pool-starts` per direction; the trainer's own draws its noise
per episode from env.train_noise_factor), a candidate yardstick that needs no test world.

One JSON line per policy is appended to RUN/eval_policies/scores.jsonl (policies already
there are skipped, so an interrupted scoring resumes); the trainer's own evaluation of
that policy (RUN/metrics.jsonl) is copied beside; a policy none of whose fresh starts
succeeded there is skipped. Prints which policy each candidate rule of `RULES` picks.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from mjxvine import evaluate as ev  # noqa: E402
from mjxvine import networks as nw  # noqa: E402
from mjxvine import policies, starts  # noqa: E402
from mjxvine import train as train_lib  # noqa: E402
from mjxvine.config import load_config, replace  # noqa: E402
from mjxvine.env import training_env  # noqa: E402
from mjxvine.worlds import make_world  # noqa: E402

NOISE_LANES = (1, 4)
NOISE_RUNS = 3


def trainer_evals(run: Path) -> dict[int, dict]:
  """{env_steps: the trainer's eval_* values} from RUN/metrics.jsonl."""
  out = {}
  for line in (run / "metrics.jsonl").read_text().splitlines():
    row = json.loads(line)
    if "eval_success_forward" in row:
      out[row["env_steps"]] = {k: row[k] for k in row if k.startswith("eval_")}
  return out


def score(cfg, path: Path, worlds, runs: int, noise_factors, pool_env, pool_eval) -> dict:
  """One policy's scores: {worlds: {seed: success, episodes, mae_m_rows, ...}, noise:
  {factor: {"1F": successes, "4F": ...}}, pool_noise1: the fresh-start evaluation}."""
  tests = [make_world(str(s), cfg.world) for s in worlds]
  noise0 = cfg.eval.noise_factor
  cases, tables, noise = [], {}, {}
  for wi, world in enumerate(tests):
    first = len(cases)
    cases += [(wi, lane, d, noise0) for lane in range(1, len(world.lanes) + 1)
              for d in ("F", "R") for _ in range(runs)]
    tables[wi] = range(first, len(cases))
  for k in noise_factors:
    first = len(cases)
    cases += [(0, lane, "F", float(k)) for lane in NOISE_LANES for _ in range(NOISE_RUNS)]
    noise[k] = range(first, len(cases))
  raw, _ = ev.rollout_cases(cfg, str(path), tests, cases)
  out = {"worlds": {}, "noise": {}}
  for wi, world in enumerate(tests):
    doc = ev.summarize(cfg, world, cases, tables[wi], raw)
    out["worlds"][str(worlds[wi])] = {
        "success": int(sum(r["success"] for r in doc["rows"])),
        "episodes": len(tables[wi]), "mae_m_rows": doc["overall"]["mae_m_rows"],
        "rows_status": doc["overall"]["rows_status"],
        "failed": [f"{r['lane']}{r['direction']}" for r in doc["rows"]
                   if r["success"] < r["runs"]]}
  for k in noise_factors:
    doc = ev.summarize(cfg, tests[0], cases, noise[k], raw)
    out["noise"][str(k)] = {f"{r['lane']}F": int(r["success"]) for r in doc["rows"]}
  pool = pool_eval(policies.load_actor_params(path, pool_env), jax.random.PRNGKey(0))
  out["pool_noise1"] = {k: float(v) for k, v in pool.items()}
  out["wall_s"] = raw["wall_s"]
  return out


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("run", type=Path)
  p.add_argument("--worlds", default="100,101,102")
  p.add_argument("--runs", type=int, default=2)
  p.add_argument("--noise", default="8,10", help="noise factors of rows 1F and 4F")
  p.add_argument("--pool-starts", type=int, default=16)
  p.add_argument("--steps", default="", help="only these env steps (comma-separated)")
  args = p.parse_args(argv)
  worlds = [int(s) for s in args.worlds.split(",")]
  noise_factors = [float(s) for s in args.noise.split(",") if s]
  cfg = load_config(args.run / "config.yaml")
  files = sorted((args.run / "eval_policies").glob("env*.npz"),
                 key=lambda f: int(re.findall(r"\d+", f.stem)[0]))
  out_file = args.run / "eval_policies" / "scores.jsonl"
  only = {int(s) for s in args.steps.split(",") if s}
  done = {json.loads(l)["env_steps"] for l in out_file.read_text().splitlines()} \
      if out_file.is_file() else set()
  trainer = trainer_evals(args.run)

  # the training pool at the config's noise factor: no per-episode noise draw
  pool_cfg = replace(cfg, env={"train_noise_factor": (0.0, 0.0)})
  env = training_env(pool_cfg)
  nets = nw.make_networks_from_config(pool_cfg)
  mirror = policies.averaging_mirror(pool_cfg)
  pool_eval = starts.make_start_eval(
      env, lambda prm, obs, key: nw.act_deterministic(nets, prm, obs, mirror),
      args.pool_starts)
  for f in files:
    steps = int(re.findall(r"\d+", f.stem)[0])
    evals = trainer.get(steps, {})
    drove = evals.get("eval_success_forward", 0) + evals.get("eval_success_reverse", 0)
    if steps in done or (only and steps not in only) or not drove:
      continue  # scored already, not asked for, or no fresh start succeeded
    row = {"env_steps": steps, "trainer": evals,
           **score(cfg, f, worlds, args.runs, noise_factors, env, pool_eval)}
    with out_file.open("a") as fh:
      fh.write(json.dumps(row) + "\n")
    w = row["worlds"]
    print(f"{steps:>7}: " + "  ".join(f"w{k} {v['success']}/{v['episodes']} "
                                      f"{v['mae_m_rows'] or float('nan'):.3f}"
                                      for k, v in w.items()),
          " noise", row["noise"], " pool@1", {k: round(v, 3) for k, v in
                                               row["pool_noise1"].items()}, flush=True)
  rows = [json.loads(l) for l in out_file.read_text().splitlines()]
  for name, rule in RULES.items():
    best = max((r for r in rows if r["trainer"]), key=rule, default=None)
    if best is not None:
      print(f"{name:>28}: {best['env_steps']:>7} env steps, validation {val_line(best)}")
  return 0


def _minmax(s: dict) -> tuple:
  return min(s["success_forward"], s["success_reverse"]), \
      s["success_forward"] + s["success_reverse"]


def _trainer(r: dict) -> dict:
  return {k[len("eval_"):]: v for k, v in r["trainer"].items()}


# Candidate rules for the best checkpoint, each a sort key over a scored row (higher is
# better); "trainer" is the trainer's own evaluation, "pool@1" the noise-1 one above.
RULES = {
    "weaker, -MAE (the trainer's)": lambda r: train_lib._score(r["trainer"]),
    "weaker, sum, -MAE": lambda r: (*_minmax(_trainer(r)), -_trainer(r)["mae_m"]),
    "pool@1 weaker, sum, -MAE": lambda r: (*_minmax(r["pool_noise1"]),
                                           -r["pool_noise1"]["mae_m"]),
    "weaker of both, -MAE@1": lambda r: (min(_minmax(_trainer(r))[0],
                                             _minmax(r["pool_noise1"])[0]),
                                         -r["pool_noise1"]["mae_m"]),
}


def val_line(r: dict) -> str:
  w = r["worlds"]
  maes = [v["mae_m_rows"] for v in w.values() if v["mae_m_rows"] is not None]
  return (" ".join(f"{v['success']}/{v['episodes']}" for v in w.values())
          + f", MAE {np.mean(maes) if maes else float('nan'):.3f}; noise "
          + " ".join(f"{k}: {sum(v.values())}/{NOISE_RUNS * len(NOISE_LANES)}"
                     for k, v in r["noise"].items()))


if __name__ == "__main__":
  sys.exit(main())
