"""Scores every policy a run kept with `train.keep_eval_policies` on validation worlds, so
that rules for choosing the best checkpoint can be compared without training again.

  python scripts/score_eval_policies.py runs/RUN [--worlds 100,101,102] [--runs 2]
      [--steps 50000,90000]

For each RUN/eval_policies/env<steps>.npz, one batched rollout of the validation protocol
that the choice of checkpoint uses (`mjxvine.evaluation.choice.score_policy`): every
lane-direction of each validation world (test-kind seeds that the test tables never use)
with `--runs` runs at the config's noise factor, and rows 1F and 4F of the first
validation world with 3 runs at each `--noise` factor. Besides, the
fresh-start evaluation of the trainer (`mjxvine.evaluation.starts`) on the training pool at the
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
import sys
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from mjxvine import networks as nw  # noqa: E402
from mjxvine.evaluation import choice, paper, policies, starts  # noqa: E402
from mjxvine.config import load_run_config, replace  # noqa: E402
from mjxvine.env import training_env  # noqa: E402
from mjxvine.worlds import make_world  # noqa: E402

def score(cfg, path: Path, worlds, runs: int, noise_factors, pool_env, pool_eval) -> dict:
  """One policy's scores: `choice.score_policy` on the validation worlds, and
  pool_noise1: the fresh-start evaluation at the config's noise factor."""
  tests = [make_world(str(s), cfg.world) for s in worlds]
  out = choice.score_policy(cfg, path, tests, runs, noise_factors)
  pool = pool_eval(policies.load_actor_params(path, pool_env), jax.random.PRNGKey(0))
  out["pool_noise1"] = {k: float(v) for k, v in pool.items()}
  return out


def main(argv=None) -> int:
  p = argparse.ArgumentParser(allow_abbrev=False, description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("run", type=Path)
  first = choice.FIRST_WORLD_SEED
  p.add_argument("--worlds", default=f"{first},{first + 1},{first + 2}")
  p.add_argument("--runs", type=int, default=choice.RUNS)
  p.add_argument("--noise", default=",".join(f"{k:g}" for k in choice.NOISE_FACTORS),
                 help="noise factors of rows 1F and 4F")
  p.add_argument("--pool-starts", type=int, default=16)
  p.add_argument("--steps", default="", help="only these env steps (comma-separated)")
  args = p.parse_args(argv)
  worlds = [int(s) for s in args.worlds.split(",")]
  noise_factors = [float(s) for s in args.noise.split(",") if s]
  cfg = load_run_config(args.run / "config.yaml")
  files = sorted(choice.kept_policies(args.run).items())
  out_file = args.run / "eval_policies" / "scores.jsonl"
  only = {int(s) for s in args.steps.split(",") if s}
  done = {json.loads(l)["env_steps"] for l in out_file.read_text().splitlines()} \
      if out_file.is_file() else set()
  trainer = choice.trainer_evaluations(args.run)

  # the training pool at the config's noise factor: no per-episode noise draw
  pool_cfg = replace(cfg, env={"train_noise_factor": (0.0, 0.0)})
  env = training_env(pool_cfg)
  nets = nw.make_networks_from_config(pool_cfg)
  mirror = policies.averaging_mirror(pool_cfg)
  pool_eval = starts.make_start_eval(
      env, lambda prm, obs, key: nw.act_deterministic(nets, prm, obs, mirror),
      args.pool_starts)
  for steps, f in files:
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
    "weaker, -MAE (the trainer's)": lambda r: choice.fresh_start_score(r["trainer"]),
    "weaker, sum, -MAE": lambda r: (*_minmax(_trainer(r)), -_trainer(r)["mae_m"]),
    "pool@1 weaker, sum, -MAE": lambda r: (*_minmax(r["pool_noise1"]),
                                           -r["pool_noise1"]["mae_m"]),
    "weaker of both, -MAE@1": lambda r: (min(_minmax(_trainer(r))[0],
                                             _minmax(r["pool_noise1"])[0]),
                                         -r["pool_noise1"]["mae_m"]),
    # the choice's order (mjxvine.evaluation.choice.rank), over every scored policy (not
    # its top candidates only)
    "validation: the bar, then -MAE": lambda r: choice.rank(r, choice.SUCCESS_BAR),
}


def val_line(r: dict) -> str:
  w = r["worlds"]
  noise_runs = paper.NOISE_RUNS * len(paper.NOISE_LANES)
  maes = [v["mae_m_rows"] for v in w.values() if v["mae_m_rows"] is not None]
  return (" ".join(f"{v['success']}/{v['episodes']}" for v in w.values())
          + f", MAE {np.mean(maes) if maes else float('nan'):.3f}; noise "
          + " ".join(f"{k}: {sum(v.values())}/{noise_runs}"
                     for k, v in r["noise"].items()))


if __name__ == "__main__":
  sys.exit(main())
