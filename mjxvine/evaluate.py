"""The paper's evaluation protocol on the test vineyard (docs/design.md, Evaluation protocol).

  python -m mjxvine.evaluate --policy oracle --out out/eval_oracle
  python -m mjxvine.evaluate --policy random --runs 1 --out out/eval_random
  python -m mjxvine.evaluate --policy models/jackal.npz --sweep noise --out out/noise
  python -m mjxvine.evaluate --policy runs/RUN --video [--gif] [--video-lanes 1F,4R] --out ev

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

A run dir brings its own config.yaml (an .npz its metadata): camera, networks, world and
env options; --config/--set only override, never what the networks need (`mjxvine.runs`).
--member K picks a member of a --seeds run (default: the one checkpoints/best follows).
--video films the first run of each lane-direction to OUT/videos/ (`mjxvine.video`).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Callable, Sequence

import jax
import jax.numpy as jp
import numpy as np

from mjxvine import policies
from mjxvine.checkpoint import WHICH, checkpoint_item
from mjxvine.config import (ROBOT_NAMES, Config, ConfigError, add_config_args,
                            enable_compile_cache, replace)
# One error class for every policy problem (`deploy.PolicyFormatError` is a subclass).
from mjxvine.deploy import PolicyError, read_policy_file
from mjxvine.env import OUTCOMES, SUCCESS, VineyardEnv, pure_pursuit
from mjxvine.runs import policy_config
from mjxvine.video import RenderError
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


def load_policy(spec: str, env: VineyardEnv, which: str = "best",
                member: int | None = None) -> tuple[Policy, str]:
  """`oracle`, `random`, a run directory / checkpoint, or an exported `.npz` actor.
  which: the checkpoint of a run directory, "best" or "last" (`checkpoint.checkpoint_item`);
  member: of a `--seeds` / sweep run, which one (None: the one checkpoints/best follows)."""
  if spec == "oracle":
    return pure_pursuit(env), "oracle (pure pursuit, privileged pose)"
  if spec == "random":
    return random_policy(env), "random"
  path = check_policy_file(spec, which)
  return policies.load_actor_policy(path, env, which, member), str(path)


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


def protocol_steps(env: VineyardEnv, policy: Policy, b: int, record: Sequence[int] = ()):
  """The evaluator's stepping of `b` envs, jitted: (reset, step, frames).

  reset(key, lanes (b,) 0-based, directions (b,) +1/-1[, worlds (b,), noise (b,)]) ->
  carry (State, alive (b,)): the envs at their lanes' starts, in `env`'s worlds `worlds`
  (default 0) with depth noise factors `noise` (default the env's).
  step(carry, key) -> (carry, out): every env takes the policy's action and one control step; alive turns False after an env's episode ended;
  out = (xy (b, 2), action (b, 2), alive (b,) before the step, outcome (b,),
  frames(state)). frames(state): the qpos (R, nq) and float16 depth (R, H, W) of the
  envs `record`, () when none. The evaluator and `mjxvine.view` step through these.
  """
  rec = jp.asarray(list(record), jp.int32)

  def reset(key, lanes, directions, worlds=None, noise=None):
    keys = jax.random.split(key, b)
    if worlds is None and noise is None:
      state = jax.vmap(lambda k, l, d: env.reset_to(k, 0, l, d))(keys, lanes, directions)
    else:
      worlds = jp.zeros(b, jp.int32) if worlds is None else worlds
      noise = jp.full(b, env.noise_factor, jp.float32) if noise is None else noise
      state = jax.vmap(lambda k, w, l, d, n: env.reset_to(k, w, l, d, noise_factor=n))(
          keys, worlds, lanes, directions, noise)
    return state, jp.ones(b, bool)

  def frames(state):
    if not len(record):
      return ()
    return (state.pipeline_state.qpos[rec], state.obs["depth"][rec, ..., 0].astype(jp.float16))

  def body(carry, k):
    state, alive = carry
    action = jax.vmap(policy)(state, jax.random.split(k, b))
    state = jax.vmap(env.step)(state, action)
    out = (state.pipeline_state.qpos[:, :2], action, alive, state.info["outcome"], frames(state))
    return (state, alive & (state.done == 0)), out

  return jax.jit(reset), body, frames


def rollout(env: VineyardEnv, policy: Policy, lanes, directions, key, max_steps: int,
            worlds=None, noise=None, record: Sequence[int] = ()):
  """Runs one episode per (lane, direction) pair from the lane's start, batched.

  lanes (0-based), directions (+1 / -1), and optionally worlds (indices into `env`'s
  worlds; default 0) and noise (the depth noise factor of each episode; default the
  env's): sequences of length B.
  Returns numpy arrays over time T and envs B: xy (T, B, 2), action (T, B, 2),
  alive (T, B) (step taken before the episode ended, inclusive), outcome (B,), steps (B,),
  and for the envs `record` (R of them, for videos) the frames from the start on:
  {"qpos": (T + 1, R, nq), "depth": (T + 1, R, H, W) float16 m, the image the policy saw}
  ({} when none are recorded).
  """
  b = len(lanes)
  k_reset, k_run = jax.random.split(key)
  reset, body, frames = protocol_steps(env, policy, b, record)
  carry = reset(k_reset, jp.asarray(lanes), jp.asarray(directions, jp.float32),
                None if worlds is None else jp.asarray(worlds, jp.int32),
                None if noise is None else jp.asarray(noise, jp.float32))
  state = carry[0]

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

  xy, act, alive, outcome = [], [], [], np.zeros(b, np.int32)
  recorded = [jax.tree.map(lambda x: np.asarray(x)[None], frames(state))]
  for t0 in range(0, max_steps, CHUNK_STEPS):
    k_run, k = jax.random.split(k_run)
    carry, (p, a, al, oc, fr) = run(carry, k)
    al, oc = np.asarray(al), np.asarray(oc)
    for t in range(al.shape[0]):
      ended = al[t] & (oc[t] != 0) & (outcome == 0)
      outcome[ended] = oc[t][ended]
    xy.append(np.asarray(p))
    act.append(np.asarray(a))
    alive.append(al)
    recorded.append(jax.tree.map(np.asarray, fr))
    if not np.asarray(carry[1]).any():
      break
  xy, act, alive = (np.concatenate(x)[:max_steps] for x in (xy, act, alive))
  outcome[outcome == 0] = OUTCOMES.index("timeout")
  tracks = {}
  if len(record):
    qpos, depth = (np.concatenate(x)[:max_steps + 1] for x in zip(*recorded))
    tracks = {"qpos": qpos, "depth": depth}
  return xy, act, alive, outcome, alive.sum(0), tracks


def signed_offsets(points: np.ndarray, line: np.ndarray, direction: str) -> np.ndarray:
  """Lateral offset (m) of points (n, 2) from the polyline `line` (k, 2), positive on the
  left of the travel direction ("F": along the line, "R": against it): (n,)."""
  dist, seg, _ = _closest(points, line)
  tangent = line[seg + 1] - line[seg]
  rel = points - line[seg]
  side = np.sign(tangent[:, 0] * rel[:, 1] - tangent[:, 1] * rel[:, 0])
  return dist * side * (1.0 if direction == "F" else -1.0)


def video_after_train(world: Vineyard) -> list[tuple[int, str]]:
  """The runs `train.video` films: a straight lane forward and a curved one in reverse
  (1F and 4R of the test world)."""
  return [(1, "F"), (min(4, len(world.lanes)), "R")]



def all_lanes(world: Vineyard) -> list[tuple[int, str]]:
  """Every lane-direction of `world`: [(1, "F"), (1, "R"), (2, "F"), ...]."""
  return [(lane, d) for lane in range(1, len(world.lanes) + 1) for d in ("F", "R")]


def parse_lanes(text: str, num_lanes: int) -> list[tuple[int, str]]:
  """"1F,4R" -> [(1, "F"), (4, "R")]; ValueError naming a lane-direction that the world
  (`num_lanes` lanes, directions F and R) does not have."""
  out = []
  for item in filter(None, (x.strip().upper() for x in text.split(","))):
    lane, direction = item[:-1], item[-1:]
    if direction not in ("F", "R") or not lane.isdigit() or not 1 <= int(lane) <= num_lanes:
      raise ValueError(f"--video-lanes {text!r}: {item!r} is not a lane-direction of this "
                       f"world (1F .. {num_lanes}R)")
    out.append((int(lane), direction))
  return out


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


def evaluate(cfg: Config, policy_spec: str, world: Vineyard, *, runs: int,
             noise_factor: float, lanes=None, directions=("F", "R"), seed: int = 0,
             policy: Policy | None = None, which: str = "best",
             member: int | None = None) -> dict:
  """Runs the protocol and returns the results document (docs/evaluation.md). which: the
  checkpoint of a run directory given as `policy_spec`, "best" or "last"; member: of a
  run that trained several, which one (None: the one checkpoints/best follows)."""
  return run_protocol(cfg, policy_spec, world, runs=runs, noise_factor=noise_factor,
                      lanes=lanes, directions=directions, seed=seed, policy=policy,
                      which=which, member=member)[0]


def rollout_cases(cfg: Config, policy_spec: str, worlds: list[Vineyard], cases, *,
                  seed: int = 0, policy: Policy | None = None, which: str = "best",
                  member: int | None = None, record: Sequence[int] = ()):
  """One batched rollout of every case: (world index, lane (1-based), direction "F"/"R",
  noise factor) tuples over `worlds`. Returns (raw, policy name) with raw = dict of
  the `rollout` arrays (xy, act, alive, outcome, steps, frames of the cases `record`) and
  wall_s."""
  # the protocol's episode limit, whatever the training episodes were
  cfg = replace(cfg, env={"max_steps": cfg.eval.max_steps})
  env = VineyardEnv(cfg, list(worlds))
  name = policy_spec
  if policy is None:
    policy, name = load_policy(policy_spec, env, which, member)
  t0 = time.time()
  xy, act, alive, outcome, steps, frames = rollout(
      env, policy, [l - 1 for _, l, _, _ in cases], [1.0 if d == "F" else -1.0
                                                     for _, _, d, _ in cases],
      jax.random.PRNGKey(seed), cfg.env.max_steps, worlds=[w for w, _, _, _ in cases],
      noise=[n for _, _, _, n in cases], record=record)
  raw = dict(xy=xy, act=act, alive=alive, outcome=outcome, steps=steps, frames=frames,
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


def run_protocol(cfg: Config, policy_spec: str, world: Vineyard, *, runs: int,
                 noise_factor: float, lanes=None, directions=("F", "R"), seed: int = 0,
                 policy: Policy | None = None, which: str = "best", member: int | None = None,
                 video: Sequence[tuple[int, str]] = ()) -> tuple[dict, list]:
  """`evaluate`, and the `video.Track` of the first run of each lane-direction in `video`
  ((lane, "F"|"R") pairs): (results document, tracks)."""
  if runs < 1:
    raise ValueError(f"runs={runs}: need at least 1 run per lane and direction")
  if noise_factor < 0:
    raise ValueError(f"noise factor {noise_factor}: must be >= 0")
  lanes = list(range(1, len(world.lanes) + 1)) if lanes is None else list(lanes)
  cases = [(0, l, d, noise_factor) for l in lanes for d in directions for _ in range(runs)]
  record = [cases.index((0, l, d, noise_factor)) for l, d in video
            if (0, l, d, noise_factor) in cases]
  raw, name = rollout_cases(cfg, policy_spec, [world], cases, seed=seed, policy=policy,
                            which=which, member=member, record=record)
  frames = raw["frames"]
  tracks = [_track(cfg, world, cases[i][1:3], frames["qpos"][:, j], frames["depth"][:, j],
                   raw["act"][:, i], int(raw["steps"][i]), OUTCOMES[int(raw["outcome"][i])])
            for j, i in enumerate(record)]
  doc = summarize(cfg, world, cases, range(len(cases)), raw)
  return {"policy": name, "noise": noise_factor, **doc}, tracks


def _track(cfg: Config, world: Vineyard, case: tuple[int, str], qpos, depth, action,
           steps: int, outcome: str):
  """The `video.Track` of one recorded run of `steps` steps: frames 0 .. steps."""
  from mjxvine.video import Track
  lane, direction = case
  qpos, depth = qpos[:steps + 1], depth[:steps + 1]
  action = np.concatenate([np.zeros((1, 2), np.float32), action[:steps]])
  offset = signed_offsets(qpos[:, :2], world.lanes[lane - 1].centerline, direction)
  return Track(lane, direction, qpos, depth.astype(np.float32), action, offset, outcome,
               cfg.env.control_dt, cfg.camera.max_depth_m)


def write_videos(tracks, world: Vineyard, cfg: Config, out: Path, *, mp4: bool = True,
                 gif: bool = False, fps: float | None = None, size=(480, 360),
                 say=print) -> list[Path]:
  """Renders each `video.Track` of `world` to out/<lane><dir>.mp4 (and .gif); returns the
  files written. fps: frames per second of the file (default: twice real time)."""
  from mjxvine import video
  from mjxvine.worlds import build_models
  model = build_models([world], cfg)[0]
  fps = 2.0 / cfg.env.control_dt if fps is None else fps
  written = []
  for track in tracks:
    t0 = time.time()
    paths = {k: out / f"{track.label}.{k}" for k, on in (("mp4", mp4), ("gif", gif)) if on}
    n = video.write_video(video.render_frames(model, track, *size), fps=fps, **paths)
    written += list(paths.values())
    say(f"  {' and '.join(str(p) for p in paths.values())}: {n} frames ({track.outcome}) "
        f"in {time.time() - t0:.0f} s")
  return written


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


def sweep_noise(cfg, policy_spec, world, out: Path, seed=0, which="best", member=None) -> dict:
  """The robustness table: noise factors 2..10 on lanes 1F and 4F, 3 runs each."""
  table = {}
  for k in sorted(PAPER_NOISE):
    doc = evaluate(cfg, policy_spec, world, runs=3, noise_factor=float(k), lanes=(1, 4),
                   directions=("F",), seed=seed, which=which, member=member)
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


def sweep_robots(cfg, policy_spec, world, out: Path, seed=0, which="best", member=None) -> dict:
  """The platform table: Jackal vs Husky on lanes 1F and 4F, 3 runs each."""
  table = {}
  for robot in ROBOT_NAMES:
    doc = evaluate(replace(cfg, robot={"name": robot}), policy_spec, world, runs=3,
                   noise_factor=cfg.eval.noise_factor, lanes=(1, 4), directions=("F",), seed=seed,
                   which=which, member=member)
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


def _size(text: str) -> tuple[int, int]:
  """"480x360" -> (480, 360): even sizes (what H.264 in yuv420p needs), 32..2048 px."""
  try:
    w, h = (int(v) for v in text.lower().split("x"))
  except ValueError:
    raise argparse.ArgumentTypeError(f"{text!r}: expected WIDTHxHEIGHT, e.g. 480x360") from None
  if not (32 <= w <= 2048 and 32 <= h <= 2048 and w % 2 == 0 and h % 2 == 0):
    raise argparse.ArgumentTypeError(f"{text!r}: width and height must be even, 32..2048")
  return w, h


def main(argv=None) -> int:
  p = argparse.ArgumentParser(prog="python -m mjxvine.evaluate", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--policy", required=True, help="oracle, random, a run dir or a .npz; a run "
                 "dir's config.yaml (an .npz's metadata) gives the camera, networks and env "
                 "options, --config/--set only override")
  p.add_argument("--which", choices=WHICH, default="best",
                 help="with a run dir as --policy: its best checkpoint (the highest step "
                      "under RUN/checkpoints/best/; the last step when the run has none) or "
                      "the last one (the newest step under RUN/checkpoints/). Default: best")
  p.add_argument("--member", type=int, default=None,
                 help="of a run that trained several members (--seeds, sweeps): which one "
                      "(default: the one checkpoints/best follows, member 0)")
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
  v = p.add_argument_group("videos (OUT/videos/<lane><dir>.mp4; MuJoCo's renderer, headless "
                           "with EGL or OSMesa)")
  v.add_argument("--video", action="store_true",
                 help="an MP4 of the first run of each lane-direction (or --video-lanes)")
  v.add_argument("--gif", action="store_true", help="a GIF of each (half the frames, 320 px "
                 "wide: for a README); with --video as well as the MP4")
  v.add_argument("--video-lanes", default=None, metavar="1F,4R",
                 help="the lane-directions to film (default: all of them)")
  v.add_argument("--video-size", type=_size, default=(480, 360), metavar="WxH",
                 help="frame size in pixels (default 480x360)")
  v.add_argument("--video-fps", type=float, default=None,
                 help="frames per second of the file (default: twice real time, 20)")
  add_config_args(p)
  args = p.parse_args(argv)
  enable_compile_cache()
  if args.runs is not None and args.runs < 1:
    p.error(f"--runs {args.runs}: need at least 1 run per lane and direction")
  if args.noise is not None and not args.noise >= 0:  # also NaN
    p.error(f"--noise {args.noise}: the noise factor must be >= 0")
  if args.video_fps is not None and not args.video_fps > 0:
    p.error(f"--video-fps {args.video_fps}: must be > 0")
  filming = args.video or args.gif
  if filming and (args.sweep or args.suite):
    p.error("--video/--gif film the protocol's runs, not a --sweep or --suite")
  if args.sweep and args.suite:
    p.error("--sweep and --suite: choose one (the paper suite includes both sweeps)")
  if args.video_lanes and not filming:
    p.error("--video-lanes: give --video or --gif too")
  extra = [f"robot.name={args.robot}"] if args.robot else []
  try:
    if args.policy not in ("oracle", "random"):  # fail before the worlds are built
      check_policy_file(args.policy, args.which)
    try:
      cfg, source = policy_config(args.policy, args.config, [*extra, *args.overrides],
                                  args.which)
    except ConfigError as e:
      print(f"config error: {e}", file=sys.stderr)
      return 2
    noise = cfg.eval.noise_factor if args.noise is None else args.noise
    runs = cfg.eval.runs if args.runs is None else args.runs
    world = make_world(args.world or str(cfg.world.test_seed), cfg.world)
    lanes = all_lanes(world)
    if args.video_lanes:
      lanes = parse_lanes(args.video_lanes, len(world.lanes))
    if filming:  # before the rollout: no GL, no ffmpeg is one line, not a wasted run
      from mjxvine import video
      video.choose_gl()
      if args.video:
        video.check_mp4()
    out = Path(args.out)
    if args.suite == "paper":
      from mjxvine.suite import paper_suite
      print(f"evaluating {args.policy}: the paper's suite (compiling first)...",
            file=sys.stderr, flush=True)
      paper_suite(cfg, args.policy, out, runs=args.runs or 5, seed=args.seed, which=args.which,
                  member=args.member)
      print((out / "report.md").read_text())
    elif args.sweep == "noise":
      sweep_noise(cfg, args.policy, world, out, args.seed, args.which, args.member)
      print((out / "noise.md").read_text())
    elif args.sweep == "robots":
      sweep_robots(cfg, args.policy, world, out, args.seed, args.which, args.member)
      print((out / "robots.md").read_text())
    else:
      print(f"evaluating {args.policy} (config: {source}): {len(world.lanes) * 2 * runs} runs "
            f"on the {world.kind} world (compiling first)...", file=sys.stderr, flush=True)
      doc, tracks = run_protocol(cfg, args.policy, world, runs=runs, noise_factor=noise,
                                 seed=args.seed, which=args.which, member=args.member,
                                 video=lanes if filming else ())
      write_results(doc, world, out)
      print(results_markdown(doc))
      if tracks:
        print(f"rendering {len(tracks)} video(s) to {out / 'videos'}/ ...", file=sys.stderr,
              flush=True)
        write_videos(tracks, world, cfg, out / "videos", mp4=args.video, gif=args.gif,
                     fps=args.video_fps, size=args.video_size,
                     say=lambda m: print(m, file=sys.stderr, flush=True))
  except (PolicyError, FileNotFoundError, ValueError, RenderError) as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  return 0


if __name__ == "__main__":
  sys.exit(main())
