"""The paper's evaluation protocol (SPEC section 7) on the test vineyard.

  python -m mjxvine.evaluate --policy oracle --out out/eval_oracle
  python -m mjxvine.evaluate --policy random --runs 1 --out out/eval_random
  python -m mjxvine.evaluate --policy models/jackal.npz --sweep noise --out out/noise

5 lanes x {forward, reverse} x `--runs` runs, all batched in one rollout, with the
policy's deterministic action. Runs differ by the depth noise. MAE and RMSE are the
distances of the trajectory to the lane's ground-truth line (midline of its two plant
rows fitted with a fifth-order polynomial), over the part of the trajectory inside the row.
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

from mjxvine.config import Config, add_config_args, config_from_args, replace
from mjxvine.env import OUTCOMES, RUNNING, SUCCESS, VineyardEnv, pure_pursuit
from mjxvine.worlds import Vineyard, make_world

# The paper's Table (SPEC section 7): lane-direction -> (MAE, RMSE, v, v_std, w, w_std, succ)
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


class PolicyError(ValueError):
  """A policy cannot be loaded or does not fit the evaluation setting."""


def random_policy(env: VineyardEnv) -> Policy:
  def policy(state, key):
    del state
    return jax.random.uniform(key, (2,), minval=env.action_low, maxval=env.action_high)
  return policy


def load_policy(spec: str, env: VineyardEnv) -> tuple[Policy, str]:
  """`oracle`, `random`, a run directory / checkpoint, or an exported `.npz` actor."""
  if spec == "oracle":
    return pure_pursuit(env), "oracle (pure pursuit, privileged pose)"
  if spec == "random":
    return random_policy(env), "random"
  path = Path(spec)
  if not path.exists():
    raise PolicyError(f"policy not found: {spec} (give oracle, random, a run dir or a .npz)")
  from mjxvine import policies
  return policies.load_actor_policy(path, env), str(path)


def distance_to_line(points: np.ndarray, line: np.ndarray) -> np.ndarray:
  """Distance (m) of each point (n, 2) to the polyline `line` (k, 2)."""
  a, b = line[:-1], line[1:]
  ab = b - a
  t = np.clip(np.einsum("nkd,kd->nk", points[:, None] - a, ab) / np.sum(ab * ab, -1), 0, 1)
  closest = a + t[..., None] * ab
  return np.min(np.linalg.norm(points[:, None] - closest, axis=-1), axis=1)


def trajectory_errors(xy: np.ndarray, line: np.ndarray) -> np.ndarray:
  """Distances to the ground-truth line of the trajectory points inside the row (their
  x within the line's x extent)."""
  inside = (xy[:, 0] >= line[0, 0]) & (xy[:, 0] <= line[-1, 0])
  return distance_to_line(xy[inside], line) if inside.any() else np.zeros(0)


def rollout(env: VineyardEnv, policy: Policy, lanes, directions, key, max_steps: int,
            noise_factor: float | None = None):
  """Runs one episode per (lane, direction) pair from the lane's start, batched.

  Returns numpy arrays over time T and envs B: xy (T, B, 2), action (T, B, 2),
  alive (T, B) (step taken before the episode ended, inclusive), outcome (B,), steps (B,).
  """
  b = len(lanes)
  k_reset, k_run = jax.random.split(key)
  reset = jax.jit(jax.vmap(lambda k, l, d: env.reset_to(k, 0, l, d)))
  state = reset(jax.random.split(k_reset, b), jp.asarray(lanes), jp.asarray(directions))

  def body(carry, k):
    state, alive = carry
    action = jax.vmap(policy)(state, jax.random.split(k, b))
    state, _ = env.step_batch(state, action)
    out = (state.pipeline_state.qpos[:, :2], action, alive, state.info["outcome"])
    return (state, alive & (state.done == 0)), out

  run = jax.jit(lambda c, k: jax.lax.scan(body, c, jax.random.split(k, CHUNK_STEPS)))
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


def start_outcomes(env: VineyardEnv, policy: Callable, params, key: jax.Array,
                   episodes: int) -> jax.Array:
  """Outcome codes (episodes,) of one episode each from the env's own random starts (its
  train-world pool, `env.reset`), run batched under one `lax.scan` of env.max_steps.
  `policy(params, state, key) -> action` (one env) takes its parameters as an argument,
  so that one compiled rollout serves every policy of that shape (jit it with
  `env`/`policy`/`episodes` static). The quick check of a training run."""
  k_reset, k_run = jax.random.split(key)
  state = jax.vmap(env.reset)(jax.random.split(k_reset, episodes))

  def body(carry, k):
    state, outcome = carry
    action = jax.vmap(policy, (None, 0, 0))(params, state, jax.random.split(k, episodes))
    state, _ = env.step_batch(state, action)
    first = (outcome == RUNNING) & (state.done > 0)
    return (state, jp.where(first, state.info["last_outcome"], outcome)), None

  (_, outcome), _ = jax.lax.scan(body, (state, jp.zeros(episodes, jp.int32)),
                                 jax.random.split(k_run, env.cfg.env.max_steps))
  return outcome


def _summary(errs, acts, outcomes, steps, dt) -> dict:
  errs = np.concatenate(errs) if errs else np.zeros(0)
  acts = np.concatenate(acts) if acts else np.zeros((0, 2))
  succ = [o == SUCCESS for o in outcomes]
  times = [s * dt for s, ok in zip(steps, succ) if ok]
  return {
      "success": int(sum(succ)), "runs": len(outcomes),
      "mae_m": float(np.mean(errs)) if errs.size else None,
      "rmse_m": float(np.sqrt(np.mean(errs ** 2))) if errs.size else None,
      "v_mean": float(acts[:, 0].mean()), "v_std": float(acts[:, 0].std()),
      "w_mean": float(acts[:, 1].mean()), "w_std": float(acts[:, 1].std()),
      "time_to_eor_s": float(np.mean(times)) if times else None,
  }


def evaluate(cfg: Config, policy_spec: str, world: Vineyard, *, runs: int,
             noise_factor: float, lanes=None, directions=("F", "R"), seed: int = 0,
             policy: Policy | None = None) -> dict:
  """Runs the protocol and returns the results document (see README)."""
  env = VineyardEnv(cfg, [world], noise_factor=noise_factor, auto_reset=False)
  name = policy_spec
  if policy is None:
    policy, name = load_policy(policy_spec, env)
  lanes = list(range(1, len(world.lanes) + 1)) if lanes is None else list(lanes)
  cases = [(l, d, r) for l in lanes for d in directions for r in range(runs)]
  t0 = time.time()
  xy, act, alive, outcome, steps = rollout(
      env, policy, [l - 1 for l, _, _ in cases], [1.0 if d == "F" else -1.0 for _, d, _ in cases],
      jax.random.PRNGKey(seed), cfg.env.max_steps)
  wall = time.time() - t0
  rows, all_err, all_act, trajs = [], [], [], []
  for (lane, direction) in [(l, d) for l in lanes for d in directions]:
    idx = [i for i, c in enumerate(cases) if c[:2] == (lane, direction)]
    line = world.lanes[lane - 1].centerline
    errs = [trajectory_errors(xy[alive[:, i], i], line) for i in idx]
    acts = [act[alive[:, i], i] for i in idx]
    row = _summary(errs, acts, [int(outcome[i]) for i in idx], [int(steps[i]) for i in idx],
                   cfg.env.control_dt)
    row.update(lane=lane, direction=direction, shape=world.lanes[lane - 1].shape,
               outcomes=[OUTCOMES[int(outcome[i])] for i in idx])
    rows.append(row)
    all_err += errs
    all_act += acts
    trajs += [{"lane": lane, "direction": direction, "outcome": OUTCOMES[int(outcome[i])],
               "xy": xy[alive[:, i], i].round(3).tolist()} for i in idx]
  overall = _summary(all_err, all_act, [int(o) for o in outcome], [int(s) for s in steps],
                     cfg.env.control_dt)
  return {"policy": name, "robot": cfg.robot.name, "noise": noise_factor,
          "world": {"kind": world.kind, "seed": world.seed}, "overall": overall, "rows": rows,
          "wall_s": wall, "trajectories": trajs}


def _fmt(x, nd=3):
  return "-" if x is None else f"{x:.{nd}f}"


def results_markdown(doc: dict) -> str:
  """A table laid out like the paper's, with the paper's numbers beside ours."""
  lines = [f"# Evaluation: {doc['policy']} ({doc['robot']}, noise x{doc['noise']})", "",
           "| test row | shape | MAE m (paper) | RMSE m (paper) | v m/s (paper) | w rad/s (paper) "
           "| success (paper) |", "|---|---|---|---|---|---|---|"]
  for r in doc["rows"] + [dict(doc["overall"], lane="overall", direction="", shape="")]:
    key = f"{r['lane']}{r['direction']}"
    p = PAPER.get(key)
    ps = (lambda i, nd=3: f" ({p[i]:.{nd}f})") if p else (lambda i, nd=3: "")
    lines.append(
        f"| {key} | {r['shape']} | {_fmt(r['mae_m'])}{ps(0)} | {_fmt(r['rmse_m'])}{ps(1)} | "
        f"{r['v_mean']:.3f} +- {r['v_std']:.3f}{ps(2)} | {r['w_mean']:.3f} +- {r['w_std']:.3f}"
        f"{ps(4)} | {r['success']}/{r['runs']}" + (f" ({p[6]}/{5 if key != 'overall' else 50})"
                                                  if p else "") + " |")
  lines += ["", f"Rollout wall-clock: {doc['wall_s']:.1f} s."]
  return "\n".join(lines) + "\n"


def plot_trajectories(doc: dict, world: Vineyard, path) -> None:
  """Top-down vineyard with every trajectory, coloured by outcome."""
  import matplotlib.pyplot as plt

  from mjxvine.worlds.plot import draw_vineyard
  colours = {"success": "tab:green", "collision": "tab:red", "left_lane": "tab:orange",
             "reversed": "tab:purple", "timeout": "tab:gray", "physics": "black"}
  fig, ax = plt.subplots(figsize=(13, 6.5))
  draw_vineyard(ax, world, terrain=False)
  seen = set()
  for t in doc["trajectories"]:
    xy = np.asarray(t["xy"]).reshape(-1, 2)
    lab = t["outcome"] if t["outcome"] not in seen else None
    seen.add(t["outcome"])
    ax.plot(xy[:, 0], xy[:, 1], color=colours[t["outcome"]], lw=0.9, alpha=0.8, label=lab)
  ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
  o = doc["overall"]
  ax.set_title(f"{doc['policy']} - {doc['robot']}, noise x{doc['noise']}: "
               f"{o['success']}/{o['runs']} success, MAE {_fmt(o['mae_m'])} m, "
               f"RMSE {_fmt(o['rmse_m'])} m")
  fig.savefig(path, dpi=110, bbox_inches="tight")
  plt.close(fig)


def write_results(doc: dict, world: Vineyard, out: Path) -> None:
  out.mkdir(parents=True, exist_ok=True)
  (out / "results.json").write_text(json.dumps(doc))
  (out / "results.md").write_text(results_markdown(doc))
  plot_trajectories(doc, world, out / "trajectories.png")


def sweep_noise(cfg, policy_spec, world, out: Path, seed=0) -> dict:
  """The robustness table: noise factors 2..10 on lanes 1F and 4F, 3 runs each."""
  table = {}
  for k in sorted(PAPER_NOISE):
    doc = evaluate(cfg, policy_spec, world, runs=3, noise_factor=float(k), lanes=(1, 4),
                   directions=("F",), seed=seed)
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


def sweep_robots(cfg, policy_spec, world, out: Path, seed=0) -> dict:
  """The platform table: Jackal vs Husky on lanes 1F and 4F, 3 runs each."""
  table = {}
  for robot in ("jackal", "husky"):
    doc = evaluate(replace(cfg, robot={"name": robot}), policy_spec, world, runs=3,
                   noise_factor=cfg.eval.noise_factor, lanes=(1, 4), directions=("F",), seed=seed)
    for r in doc["rows"]:
      table[(robot, f"{r['lane']}F")] = r
  lines = ["# Robots (3 runs each)", "", "| row | robot | success (paper) | T_avg s (paper) | "
           "MAE m (paper) | RMSE m (paper) |", "|---|---|---|---|---|---|"]
  paper_t = {("jackal", "1F"): 78, ("husky", "1F"): 69, ("jackal", "4F"): 78, ("husky", "4F"): 88}
  for (robot, lane), r in sorted(table.items(), key=lambda kv: (kv[0][1], kv[0][0] != "jackal")):
    p = PAPER_ROBOTS[(robot, lane)]
    lines.append(f"| {lane} | {robot} | {r['success']}/3 ({p[0]}/3) | {_fmt(r['time_to_eor_s'], 1)}"
                 f" ({paper_t[(robot, lane)]}) | {_fmt(r['mae_m'])} ({p[1]}) | "
                 f"{_fmt(r['rmse_m'])} ({p[2]}) |")
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
  p.add_argument("--robot", choices=("jackal", "husky"), default=None)
  p.add_argument("--noise", type=float, default=None, help="depth noise factor")
  p.add_argument("--runs", type=int, default=None, help="runs per lane and direction")
  p.add_argument("--world", default=None, help="test-world seed or world .json file")
  p.add_argument("--sweep", choices=("noise", "robots"), default=None)
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--out", required=True)
  add_config_args(p)
  args = p.parse_args(argv)
  extra = [f"robot.name={args.robot}"] if args.robot else []
  cfg = config_from_args(args, extra)
  noise = cfg.eval.noise_factor if args.noise is None else args.noise
  runs = cfg.eval.runs if args.runs is None else args.runs
  try:
    world = make_world(args.world or str(cfg.world.test_seed), cfg.world)
    out = Path(args.out)
    if args.sweep == "noise":
      sweep_noise(cfg, args.policy, world, out, args.seed)
      print((out / "noise.md").read_text())
    elif args.sweep == "robots":
      sweep_robots(cfg, args.policy, world, out, args.seed)
      print((out / "robots.md").read_text())
    else:
      doc = evaluate(cfg, args.policy, world, runs=runs, noise_factor=noise, seed=args.seed)
      write_results(doc, world, out)
      print(results_markdown(doc))
  except (PolicyError, FileNotFoundError, ValueError) as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  return 0


if __name__ == "__main__":
  sys.exit(main())
