"""The paper's evaluation protocol on the test vineyard (docs/design.md, Evaluation protocol).

  python -m mjxvine.evaluate --policy oracle --out out/eval_oracle
  python -m mjxvine.evaluate --policy random --runs 1 --out out/eval_random
  python -m mjxvine.evaluate --policy models/jackal.npz --sweep noise --out out/noise

5 lanes x {forward, reverse} x `--runs` runs, all batched in one rollout, with the
policy's deterministic action. Runs differ by the depth noise. MAE and RMSE are the
distances of the trajectory to the lane's ground-truth line (midline of its two plant
rows fitted with a fifth-order polynomial), over the part of the trajectory inside the row.

A run that ends early (collision, leaving the lane, ...) has a short trajectory, and its
MAE/RMSE are not comparable to the paper's: each row reports the part of the lane covered
(m and fraction of the centreline's arc length) and `metrics_status`: "full" when every
run reached the end of the row (EoR), "partial" when some did, "n/a" when none did (then
MAE/RMSE are null in results.json and "n/a" in results.md; `mae_m_raw`/`rmse_m_raw` keep
the numbers). --which picks the checkpoint of a run dir: best (default) or last.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jp
import numpy as np

from mjxvine import policies
from mjxvine.checkpoint import WHICH, checkpoint_item
from mjxvine.config import (ROBOT_NAMES, Config, add_config_args, config_from_args,
                            enable_compile_cache, replace)
# One error class for every policy problem (`deploy.PolicyFormatError` is a subclass).
from mjxvine.deploy import PolicyError, read_policy_file
from mjxvine.env import OUTCOMES, SUCCESS, VineyardEnv, pure_pursuit
from mjxvine.worlds import Vineyard, make_world

# The paper's table (docs/design.md, Evaluation protocol):
# lane-direction -> (MAE, RMSE, v, v_std, w, w_std, succ)
PAPER = {
    "1F": (0.076, 0.089, 0.493, 0.020, -0.027, 0.538, 5), "1R": (0.131, 0.141, 0.478, 0.053, -0.030, 0.623, 5),
    "2F": (0.068, 0.076, 0.488, 0.037, -0.028, 0.642, 5), "2R": (0.087, 0.105, 0.489, 0.037, -0.001, 0.610, 5),
    "3F": (0.120, 0.154, 0.497, 0.003, -0.012, 0.353, 5), "3R": (0.100, 0.130, 0.494, 0.017, -0.036, 0.610, 2),
    "4F": (0.164, 0.191, 0.468, 0.079, -0.008, 0.687, 5), "4R": (0.081, 0.097, 0.484, 0.059, -0.014, 0.493, 5),
    "5F": (0.112, 0.145, 0.486, 0.057, -0.005, 0.571, 3), "5R": (0.201, 0.233, 0.445, 0.122, -0.042, 0.656, 5),
    "overall": (0.114, 0.136, 0.482, 0.048, -0.020, 0.578, 45),
}
PAPER_NOISE = {2: (3, 3), 4: (3, 3), 6: (3, 3), 8: (2, 3), 10: (0, 0)}  # (straight, curved)
PAPER_ROBOTS = {("jackal", "1F"): (3, 0.079, 0.088), ("husky", "1F"): (3, 0.081, 0.098),
                ("jackal", "4F"): (3, 0.085, 0.101), ("husky", "4F"): (2, 0.112, 0.138)}
CHUNK_STEPS = 50

Policy = Callable  # policy(state, key) -> action (2,), one env (vmapped by the rollout)


def random_policy(env: VineyardEnv) -> Policy:
  def policy(state, key):
    del state
    return jax.random.uniform(key, (2,), minval=env.action_low, maxval=env.action_high)
  return policy


def load_policy(spec: str, env: VineyardEnv, which: str = "best") -> tuple[Policy, str]:
  """`oracle`, `random`, a run directory / checkpoint, or an exported `.npz` actor.
  which: the checkpoint of a run directory, "best" or "last" (`checkpoint.checkpoint_item`)."""
  if spec == "oracle":
    return pure_pursuit(env), "oracle (pure pursuit, privileged pose)"
  if spec == "random":
    return random_policy(env), "random"
  path = check_policy_file(spec, which)
  return policies.load_actor_policy(path, env, which), str(path)


def check_policy_file(spec: str, which: str = "best") -> Path:
  """The path of a policy given as a run dir or .npz, checked before anything is built:
  it exists, an .npz reads as a policy file, a run dir holds a checkpoint (`which`)."""
  path = Path(spec)
  if not path.exists():
    what = "policy not found" if path.suffix == ".npz" else "no such run directory"
    raise PolicyError(f"{what}: {spec} (give oracle, random, a run dir or a .npz)")
  if path.suffix == ".npz":
    read_policy_file(path)
  else:
    try:
      checkpoint_item(path, which)
    except FileNotFoundError as e:
      raise PolicyError(str(e)) from None
  return path


def _closest(points: np.ndarray, line: np.ndarray):
  """For points (n, 2) and the polyline `line` (k, 2): the distances (n,) (m) to the line,
  the index (n,) of the closest segment and the fraction (n,) along it."""
  a, b = line[:-1], line[1:]
  ab = b - a
  t = np.clip(np.einsum("nkd,kd->nk", points[:, None] - a, ab) / np.sum(ab * ab, -1), 0, 1)
  dist = np.linalg.norm(points[:, None] - (a + t[..., None] * ab), axis=-1)
  seg = np.argmin(dist, axis=1)
  rows = np.arange(len(points))
  return dist[rows, seg], seg, t[rows, seg]


def distance_to_line(points: np.ndarray, line: np.ndarray) -> np.ndarray:
  """Distance (m) of each point (n, 2) to the polyline `line` (k, 2)."""
  return _closest(points, line)[0]


def arc_length(line: np.ndarray) -> float:
  """Length (m) of the polyline `line` (k, 2)."""
  return float(np.linalg.norm(np.diff(line, axis=0), axis=1).sum())


def along_line(points: np.ndarray, line: np.ndarray) -> np.ndarray:
  """Arc-length coordinate (m, from line[0]) of the closest point of `line` (k, 2) to each
  point (n, 2): (n,), in [0, arc_length(line)]."""
  _, seg, t = _closest(points, line)
  lengths = np.linalg.norm(np.diff(line, axis=0), axis=1)
  return np.concatenate([[0.0], np.cumsum(lengths)])[seg] + t * lengths[seg]


def lane_progress(xy: np.ndarray, line: np.ndarray, direction: str) -> float:
  """How far (m) a trajectory xy (n, 2) got along the lane centreline `line` (k, 2), from
  the lane's start in its travel direction ("F": from line[0], "R": from line[-1]): the
  along-lane coordinate of its furthest point, in [0, arc_length(line)]."""
  if len(xy) == 0:
    return 0.0
  s = along_line(xy, line)
  return float(s.max() if direction == "F" else arc_length(line) - s.min())


def trajectory_errors(xy: np.ndarray, line: np.ndarray) -> np.ndarray:
  """Distances to the ground-truth line of the trajectory points inside the row (their
  x within the line's x extent)."""
  inside = (xy[:, 0] >= line[0, 0]) & (xy[:, 0] <= line[-1, 0])
  return distance_to_line(xy[inside], line) if inside.any() else np.zeros(0)


def rollout(env: VineyardEnv, policy: Policy, lanes, directions, key, max_steps: int,
            worlds=None, noise=None):
  """Runs one episode per (lane, direction) pair from the lane's start, batched.

  lanes (0-based), directions (+1 / -1), and optionally worlds (indices into `env`'s
  worlds; default 0) and noise (the depth noise factor of each episode; default the
  env's): sequences of length B.
  Returns numpy arrays over time T and envs B: xy (T, B, 2), action (T, B, 2),
  alive (T, B) (step taken before the episode ended, inclusive), outcome (B,), steps (B,).
  """
  b = len(lanes)
  worlds = np.zeros(b, np.int32) if worlds is None else np.asarray(worlds, np.int32)
  noise = np.full(b, env.noise_factor, np.float32) if noise is None else np.asarray(
      noise, np.float32)
  k_reset, k_run = jax.random.split(key)
  reset = jax.jit(jax.vmap(lambda k, w, l, d, n: env.reset_to(k, w, l, d, noise_factor=n)))
  state = reset(jax.random.split(k_reset, b), jp.asarray(worlds), jp.asarray(lanes),
                jp.asarray(directions), jp.asarray(noise))

  def body(carry, k):
    state, alive = carry
    action = jax.vmap(policy)(state, jax.random.split(k, b))
    state = jax.vmap(env.step)(state, action)
    out = (state.pipeline_state.qpos[:, :2], action, alive, state.info["outcome"])
    return (state, alive & (state.done == 0)), out

  scan = jax.jit(lambda c, k: jax.lax.scan(body, c, jax.random.split(k, CHUNK_STEPS)))
  step = jax.jit(body)

  def run(carry, k):
    if jax.default_backend() != "cpu":
      return scan(carry, k)
    # XLA:CPU runs convolutions inside a loop body slowly (jax-ml/jax#12868): the same
    # steps, with the same keys, looped on the host
    outs = []
    for k_step in jax.random.split(k, CHUNK_STEPS):
      carry, out = step(carry, k_step)
      outs.append(out)
    return carry, jax.tree.map(lambda *x: jp.stack(x), *outs)

  carry = (state, jp.ones(b, bool))
  xy, act, alive, outcome = [], [], [], np.zeros(b, np.int32)
  for t0 in range(0, max_steps, CHUNK_STEPS):
    k_run, k = jax.random.split(k_run)
    carry, (p, a, al, oc) = run(carry, k)
    al, oc = np.asarray(al), np.asarray(oc)
    for t in range(al.shape[0]):
      ended = al[t] & (oc[t] != 0) & (outcome == 0)
      outcome[ended] = oc[t][ended]
    xy.append(np.asarray(p))
    act.append(np.asarray(a))
    alive.append(al)
    if not np.asarray(carry[1]).any():
      break
  xy, act, alive = (np.concatenate(x)[:max_steps] for x in (xy, act, alive))
  outcome[outcome == 0] = OUTCOMES.index("timeout")
  return xy, act, alive, outcome, alive.sum(0)


def metrics_status(successes: int, runs: int) -> str:
  """"full" when every run reached its EoR, "partial" when some did, "n/a" when none did."""
  return "full" if runs and successes == runs else "partial" if successes else "n/a"


def _summary(errs, acts, outcomes, steps, dt, covered_m, covered_frac) -> dict:
  """Metrics of a group of runs: errs/acts per run (n_i,)/(n_i, 2), outcome codes, steps
  per run, the control step dt (s), lane covered per run (m, fraction of the lane)."""
  errs = np.concatenate(errs) if errs else np.zeros(0)
  acts = np.concatenate(acts) if acts else np.zeros((0, 2))
  succ = [o == SUCCESS for o in outcomes]
  times = [s * dt for s, ok in zip(steps, succ) if ok]
  status = metrics_status(int(sum(succ)), len(outcomes))
  mae = float(np.mean(errs)) if errs.size else None
  rmse = float(np.sqrt(np.mean(errs ** 2))) if errs.size else None
  return {
      "success": int(sum(succ)), "runs": len(outcomes), "metrics_status": status,
      # no run reached the EoR: the errors of a few metres of lane say nothing comparable
      "mae_m": None if status == "n/a" else mae, "rmse_m": None if status == "n/a" else rmse,
      "mae_m_raw": mae, "rmse_m_raw": rmse,
      "lane_covered_m": float(np.mean(covered_m)),
      "lane_covered_frac": float(np.mean(covered_frac)),
      "v_mean": float(acts[:, 0].mean()), "v_std": float(acts[:, 0].std()),
      "w_mean": float(acts[:, 1].mean()), "w_std": float(acts[:, 1].std()),
      "time_to_eor_s": float(np.mean(times)) if times else None,
  }


def rollout_cases(cfg: Config, policy_spec: str, worlds: list[Vineyard], cases, *,
                  seed: int = 0, policy: Policy | None = None, which: str = "best"):
  """One batched rollout of every case: (world index, lane (1-based), direction "F"/"R",
  noise factor) tuples over `worlds`. Returns (raw, policy name) with raw = dict of
  the `rollout` arrays (xy, act, alive, outcome, steps) and wall_s."""
  # the protocol's episode limit, whatever the training episodes were
  cfg = replace(cfg, env={"max_steps": cfg.eval.max_steps})
  env = VineyardEnv(cfg, list(worlds))
  name = policy_spec
  if policy is None:
    policy, name = load_policy(policy_spec, env, which)
  t0 = time.time()
  xy, act, alive, outcome, steps = rollout(
      env, policy, [l - 1 for _, l, _, _ in cases], [1.0 if d == "F" else -1.0
                                                     for _, _, d, _ in cases],
      jax.random.PRNGKey(seed), cfg.env.max_steps, worlds=[w for w, _, _, _ in cases],
      noise=[n for _, _, _, n in cases])
  raw = dict(xy=xy, act=act, alive=alive, outcome=outcome, steps=steps,
             wall_s=time.time() - t0)
  return raw, name


def summarize(cfg: Config, world: Vineyard, cases, idx, raw: dict) -> dict:
  """The rows (one per lane-direction, in case order), the overall figures and the
  trajectories of the cases `idx` (indices into `cases` and `raw`), all on `world`.

  overall: the pooled metrics of every trajectory point, plus the mean of the rows
  (`mae_m_rows`, `rmse_m_rows`, `v_mean_rows`, `w_mean_rows`, ...): the paper's overall
  row is the mean of its ten row values, so that is what compares with it."""
  xy, act, alive, outcome, steps = (raw[k] for k in ("xy", "act", "alive", "outcome", "steps"))
  keys = list(dict.fromkeys((cases[i][1], cases[i][2]) for i in idx))
  rows, all_err, all_act, all_m, all_frac, trajs = [], [], [], [], [], []
  for lane, direction in keys:
    group = [i for i in idx if cases[i][1:3] == (lane, direction)]
    line = world.lanes[lane - 1].centerline
    length = arc_length(line)
    errs = [trajectory_errors(xy[alive[:, i], i], line) for i in group]
    acts = [act[alive[:, i], i] for i in group]
    # A run that reached its EoR covered the lane, though it stops within the success
    # radius of the line's end.
    covered = [length if outcome[i] == SUCCESS else
               min(lane_progress(xy[alive[:, i], i], line, direction), length) for i in group]
    row = _summary(errs, acts, [int(outcome[i]) for i in group],
                   [int(steps[i]) for i in group], cfg.env.control_dt, covered,
                   [c / length for c in covered])
    row.update(lane=lane, direction=direction, shape=world.lanes[lane - 1].shape,
               lane_length_m=length, outcomes=[OUTCOMES[int(outcome[i])] for i in group])
    rows.append(row)
    all_err += errs
    all_act += acts
    all_m += covered
    all_frac += [c / length for c in covered]
    trajs += [{"lane": lane, "direction": direction, "outcome": OUTCOMES[int(outcome[i])],
               "lane_covered_m": round(c, 3), "xy": xy[alive[:, i], i].round(3).tolist()}
              for i, c in zip(group, covered)]
  overall = _summary(all_err, all_act, [int(outcome[i]) for i in idx],
                     [int(steps[i]) for i in idx], cfg.env.control_dt, all_m, all_frac)
  overall.update(mean_of_rows(rows))
  return {"robot": cfg.robot.name, "world": {"kind": world.kind, "seed": world.seed},
          "overall": overall, "rows": rows, "wall_s": raw["wall_s"], "trajectories": trajs}


def mean_of_rows(rows: list[dict]) -> dict:
  """The paper's overall figures: means of the row values (MAE, RMSE, v, w and their
  stds), `*_rows` keys. MAE/RMSE average the rows that have them (`rows_status`: "full"
  when every row's runs all reached the EoR, else "partial", "n/a" when none has them)."""
  out = {}
  for key in ("v_mean", "v_std", "w_mean", "w_std"):
    out[f"{key}_rows"] = float(np.mean([r[key] for r in rows]))
  for key in ("mae_m", "rmse_m"):
    vals = [r[key] for r in rows if r[key] is not None]
    out[f"{key}_rows"] = float(np.mean(vals)) if vals else None
  full = all(r["metrics_status"] == "full" for r in rows)
  out["rows_status"] = "full" if full else "partial" if out["mae_m_rows"] is not None else "n/a"
  return out


def evaluate(cfg: Config, policy_spec: str, world: Vineyard, *, runs: int,
             noise_factor: float, lanes=None, directions=("F", "R"), seed: int = 0,
             policy: Policy | None = None, which: str = "best") -> dict:
  """Runs the protocol and returns the results document (docs/evaluation.md). which: the
  checkpoint of a run directory given as `policy_spec`, "best" or "last"."""
  if runs < 1:
    raise ValueError(f"runs={runs}: need at least 1 run per lane and direction")
  if noise_factor < 0:
    raise ValueError(f"noise factor {noise_factor}: must be >= 0")
  lanes = list(range(1, len(world.lanes) + 1)) if lanes is None else list(lanes)
  cases = [(0, l, d, noise_factor) for l in lanes for d in directions for _ in range(runs)]
  raw, name = rollout_cases(cfg, policy_spec, [world], cases, seed=seed, policy=policy,
                            which=which)
  doc = summarize(cfg, world, cases, range(len(cases)), raw)
  return {"policy": name, "noise": noise_factor, **doc}


def _fmt(x, nd=3):
  return "-" if x is None else f"{x:.{nd}f}"


def _metric(r: dict, key: str, nd: int = 3) -> str:
  """MAE/RMSE cell of a row: "n/a" when no run reached its EoR, "(partial)" when some did."""
  if r["metrics_status"] == "n/a":
    return "n/a"
  return _fmt(r[key], nd) + (" (partial)" if r["metrics_status"] == "partial" else "")


def _covered(r: dict) -> str:
  return f"{r['lane_covered_frac']:.0%} ({r['lane_covered_m']:.1f} m)"


def results_markdown(doc: dict) -> str:
  """A table laid out like the paper's, with the paper's numbers beside ours."""
  lines = [f"# Evaluation: {doc['policy']} ({doc['robot']}, noise x{doc['noise']})", "",
           "| test row | shape | lane covered | MAE m (paper) | RMSE m (paper) | v m/s (paper) "
           "| w rad/s (paper) | success (paper) |", "|---|---|---|---|---|---|---|---|"]
  o = doc["overall"]
  # the paper's overall row is the mean of its rows: so is ours (the pooled one below)
  by_rows = dict(o, lane="overall", direction="", shape="mean of rows",
                 mae_m=o["mae_m_rows"], rmse_m=o["rmse_m_rows"], metrics_status=o["rows_status"],
                 v_mean=o["v_mean_rows"], v_std=o["v_std_rows"], w_mean=o["w_mean_rows"],
                 w_std=o["w_std_rows"])
  for r in doc["rows"] + [by_rows]:
    key = f"{r['lane']}{r['direction']}"
    p = PAPER.get(key)
    ps = (lambda i, nd=3: f" ({p[i]:.{nd}f})") if p else (lambda i, nd=3: "")
    lines.append(
        f"| {key} | {r['shape']} | {_covered(r)} | {_metric(r, 'mae_m')}{ps(0)} | "
        f"{_metric(r, 'rmse_m')}{ps(1)} | "
        f"{r['v_mean']:.3f} +- {r['v_std']:.3f}{ps(2)} | {r['w_mean']:.3f} +- {r['w_std']:.3f}"
        f"{ps(4)} | {r['success']}/{r['runs']}" + (f" ({p[6]}/{5 if key != 'overall' else 50})"
                                                  if p else "") + " |")
  lines += ["", "Lane covered: mean over the runs of the part of the lane's centreline driven "
            "from its start (a run that reached the EoR covers all of it). MAE/RMSE: n/a when "
            "no run of the row reached the EoR; (partial) when only some did: they then "
            "include runs that stopped early and are not comparable to the paper's. Overall: "
            "the mean of the rows, as the paper's; pooled over every trajectory point: MAE "
            f"{_metric(o, 'mae_m')} m, RMSE {_metric(o, 'rmse_m')} m.",
            "", f"Rollout wall-clock: {doc['wall_s']:.1f} s."]
  return "\n".join(lines) + "\n"


# Outcome colours that stand out against the green plants and the grey centrelines.
OUTCOME_COLOURS = {"success": "tab:blue", "collision": "tab:red", "left_lane": "tab:orange",
                   "reversed": "tab:purple", "timeout": "0.15", "physics": "magenta"}


def _title(doc: dict) -> str:
  o = doc["overall"]
  status = o.get("rows_status", o["metrics_status"])
  metrics = ("MAE/RMSE n/a (no run reached the EoR)" if status == "n/a" else
             f"MAE {_fmt(o.get('mae_m_rows', o['mae_m']))} m, RMSE "
             f"{_fmt(o.get('rmse_m_rows', o['rmse_m']))} m (mean of rows)" +
             (" (partial: only some runs reached the EoR)" if status == "partial" else ""))
  return (f"{doc['policy']} - {doc['robot']}, noise x{doc['noise']}: {o['success']}/{o['runs']}"
          f" success, lane covered {o['lane_covered_frac']:.0%}\n{metrics}")


def plot_trajectories(doc: dict, world: Vineyard, path) -> None:
  """Top-down vineyard with every trajectory: colour by outcome, solid forward and dashed
  reverse runs, a circle at each start and a cross where a failed run ended."""
  import matplotlib.pyplot as plt
  from matplotlib.lines import Line2D

  from mjxvine.worlds.plot import draw_vineyard
  fig, ax = plt.subplots(figsize=(13, 6.5))
  world_handles, _ = draw_vineyard(ax, world, terrain=False)
  counts: dict[str, int] = {}
  for t in doc["trajectories"]:
    xy = np.asarray(t["xy"]).reshape(-1, 2)
    counts[t["outcome"]] = counts.get(t["outcome"], 0) + 1
    if not len(xy):
      continue
    colour = OUTCOME_COLOURS[t["outcome"]]
    ax.plot(xy[:, 0], xy[:, 1], color=colour, lw=1.0, alpha=0.85,
            ls="-" if t["direction"] == "F" else (0, (4, 2)))
    ax.plot(*xy[0], "o", ms=5, mfc=colour, mec="white", mew=0.8, zorder=5)
    if t["outcome"] != "success":
      ax.plot(*xy[-1], "x", ms=7, mew=1.8, color=colour, zorder=5)
  # every outcome, with its count: the same colour key in every figure
  handles = [Line2D([], [], color=c, lw=2, label=f"{o} ({counts.get(o, 0)})")
             for o, c in OUTCOME_COLOURS.items()]
  handles += [Line2D([], [], color="0.3", lw=1.2, label="forward run"),
              Line2D([], [], color="0.3", lw=1.2, ls=(0, (4, 2)), label="reverse run"),
              Line2D([], [], ls="", marker="o", ms=6, mfc="0.3", mec="white", label="start"),
              Line2D([], [], ls="", marker="x", ms=7, mew=1.8, color="0.3",
                     label="end of a failed run")]
  ax.legend(handles=handles + world_handles, loc="upper left", bbox_to_anchor=(1.01, 1.0),
            fontsize=8)
  ax.set_title(_title(doc), fontsize=10)
  fig.savefig(path, dpi=110, bbox_inches="tight")
  plt.close(fig)


def write_results(doc: dict, world: Vineyard, out: Path) -> None:
  out.mkdir(parents=True, exist_ok=True)
  (out / "results.json").write_text(json.dumps(doc))
  (out / "results.md").write_text(results_markdown(doc))
  plot_trajectories(doc, world, out / "trajectories.png")


def sweep_noise(cfg, policy_spec, world, out: Path, seed=0, which="best") -> dict:
  """The robustness table: noise factors 2..10 on lanes 1F and 4F, 3 runs each."""
  table = {}
  for k in sorted(PAPER_NOISE):
    doc = evaluate(cfg, policy_spec, world, runs=3, noise_factor=float(k), lanes=(1, 4),
                   directions=("F",), seed=seed, which=which)
    table[k] = {f"{r['lane']}F": r for r in doc["rows"]}
  lines = ["# Noise robustness (lanes 1F straight, 4F curved; 3 runs each)", "",
           "| noise factor | " + " | ".join(str(k) for k in table) + " |",
           "|---" * (len(table) + 1) + "|"]
  for lane, label, col in (("1F", "straight", 0), ("4F", "curved", 1)):
    lines.append(f"| success ({label}) (paper) | " + " | ".join(
        f"{table[k][lane]['success']}/3 ({PAPER_NOISE[k][col]}/3)" for k in table) + " |")
    lines.append(f"| v mean +- std ({label}) | " + " | ".join(
        f"{table[k][lane]['v_mean']:.2f} +- {table[k][lane]['v_std']:.2f}" for k in table) + " |")
  out.mkdir(parents=True, exist_ok=True)
  (out / "noise.md").write_text("\n".join(lines) + "\n")
  (out / "noise.json").write_text(json.dumps({str(k): v for k, v in table.items()}))
  import matplotlib.pyplot as plt
  fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
  ks = list(table)
  for lane in ("1F", "4F"):
    for ax, key in zip(axes, ("v", "w")):
      ax.errorbar(ks, [table[k][lane][f"{key}_mean"] for k in ks],
                  [table[k][lane][f"{key}_std"] for k in ks], marker="o", capsize=3, label=lane)
      ax.set_xlabel("noise factor")
      ax.set_ylabel(f"{key} ({'m/s' if key == 'v' else 'rad/s'})")
  axes[0].legend()
  fig.tight_layout()
  fig.savefig(out / "noise.png", dpi=110)
  plt.close(fig)
  return table


def sweep_robots(cfg, policy_spec, world, out: Path, seed=0, which="best") -> dict:
  """The platform table: Jackal vs Husky on lanes 1F and 4F, 3 runs each."""
  table = {}
  for robot in ROBOT_NAMES:
    doc = evaluate(replace(cfg, robot={"name": robot}), policy_spec, world, runs=3,
                   noise_factor=cfg.eval.noise_factor, lanes=(1, 4), directions=("F",), seed=seed,
                   which=which)
    for r in doc["rows"]:
      table[(robot, f"{r['lane']}F")] = r
  lines = ["# Robots (3 runs each)", "", "| row | robot | success (paper) | T_avg s (paper) | "
           "MAE m (paper) | RMSE m (paper) |", "|---|---|---|---|---|---|"]
  paper_t = {("jackal", "1F"): 78, ("husky", "1F"): 69, ("jackal", "4F"): 78, ("husky", "4F"): 88}
  order = lambda kv: (kv[0][1], ROBOT_NAMES.index(kv[0][0]))  # by lane, then robot
  for (robot, lane), r in sorted(table.items(), key=order):
    p = PAPER_ROBOTS[(robot, lane)]
    lines.append(f"| {lane} | {robot} | {r['success']}/3 ({p[0]}/3) | {_fmt(r['time_to_eor_s'], 1)}"
                 f" ({paper_t[(robot, lane)]}) | {_metric(r, 'mae_m')} ({p[1]}) | "
                 f"{_metric(r, 'rmse_m')} ({p[2]}) |")
  out.mkdir(parents=True, exist_ok=True)
  (out / "robots.md").write_text("\n".join(lines) + "\n")
  (out / "robots.json").write_text(json.dumps({f"{k[0]}_{k[1]}": v for k, v in table.items()}))
  import matplotlib.pyplot as plt
  fig, ax = plt.subplots(figsize=(6, 3.5))
  labels = [f"{r} {l}" for (r, l) in table]
  ax.bar(labels, [v["mae_m"] or 0 for v in table.values()], color="tab:green")
  ax.set_ylabel("MAE (m)")
  fig.tight_layout()
  fig.savefig(out / "robots.png", dpi=110)
  plt.close(fig)
  return table


def main(argv=None) -> int:
  p = argparse.ArgumentParser(prog="python -m mjxvine.evaluate", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--policy", required=True, help="oracle, random, a run dir or a .npz")
  p.add_argument("--which", choices=WHICH, default="best",
                 help="with a run dir as --policy: its best checkpoint (the highest step "
                      "under RUN/checkpoints/best/; the last step when the run has none) or "
                      "the last one (the newest step under RUN/checkpoints/). Default: best")
  p.add_argument("--robot", choices=ROBOT_NAMES, default=None)
  p.add_argument("--noise", type=float, default=None,
                 help="depth noise factor, >= 0 (default: the config's eval.noise_factor)")
  p.add_argument("--runs", type=int, default=None,
                 help="runs per lane and direction, >= 1 (default: the config's eval.runs)")
  p.add_argument("--world", default=None, help="test-world seed or world .json file")
  p.add_argument("--sweep", choices=("noise", "robots"), default=None)
  p.add_argument("--suite", choices=("paper",), default=None,
                 help="paper: the paper's whole evaluation (test worlds 0-3 with --runs, "
                      "default 5; the noise and robot tests) in one report (mjxvine.suite)")
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--out", required=True)
  add_config_args(p)
  args = p.parse_args(argv)
  enable_compile_cache()
  if args.runs is not None and args.runs < 1:
    p.error(f"--runs {args.runs}: need at least 1 run per lane and direction")
  if args.noise is not None and not args.noise >= 0:  # also NaN
    p.error(f"--noise {args.noise}: the noise factor must be >= 0")
  extra = [f"robot.name={args.robot}"] if args.robot else []
  cfg = config_from_args(args, extra)
  noise = cfg.eval.noise_factor if args.noise is None else args.noise
  runs = cfg.eval.runs if args.runs is None else args.runs
  try:
    if args.policy not in ("oracle", "random"):  # fail before the worlds are built
      check_policy_file(args.policy, args.which)
    world = make_world(args.world or str(cfg.world.test_seed), cfg.world)
    out = Path(args.out)
    if args.suite == "paper":
      from mjxvine.suite import paper_suite
      print(f"evaluating {args.policy}: the paper's suite (compiling first)...",
            file=sys.stderr, flush=True)
      paper_suite(cfg, args.policy, out, runs=args.runs or 5, seed=args.seed, which=args.which)
      print((out / "report.md").read_text())
    elif args.sweep == "noise":
      sweep_noise(cfg, args.policy, world, out, args.seed, args.which)
      print((out / "noise.md").read_text())
    elif args.sweep == "robots":
      sweep_robots(cfg, args.policy, world, out, args.seed, args.which)
      print((out / "robots.md").read_text())
    else:
      print(f"evaluating {args.policy}: {len(world.lanes) * 2 * runs} runs on the "
            f"{world.kind} world (compiling first)...", file=sys.stderr, flush=True)
      doc = evaluate(cfg, args.policy, world, runs=runs, noise_factor=noise, seed=args.seed,
                     which=args.which)
      write_results(doc, world, out)
      print(results_markdown(doc))
  except (PolicyError, FileNotFoundError, ValueError) as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  return 0


if __name__ == "__main__":
  sys.exit(main())
