"""Batched rollouts from the lanes' starts: the evaluator's stepping (`protocol_steps`,
`rollout`; `drive` steps one env the same way, for the live viewer), the rollout cases
(`Cases`: which world, lane, direction and noise factor each episode drives; `PolicySource`:
which policy drives them), and the paper's protocol on one test world (`Protocol`,
`run_protocol`, `evaluate`).

The protocol: every lane of the world x {forward, reverse} x `runs` runs, all batched in
one rollout, with the policy's deterministic action. Runs differ by the depth noise.
Lanes are 1-based and directions "F"/"R" in the cases and tables; the env takes 0-based
lanes and directions +1/-1.
"""

from __future__ import annotations

import time
from typing import Callable, Iterator, NamedTuple, Sequence

import jax
import jax.numpy as jp
import numpy as np

from mjxvine.config import Config, replace
from mjxvine.episodes import OUTCOMES, RUNNING
from mjxvine.evaluation.geometry import signed_offsets
from mjxvine.evaluation.metrics import summarize
from mjxvine.evaluation.paper import DIRECTIONS
from mjxvine.evaluation.policies import Policy, load_policy
from mjxvine.lanes import lane_steps as steps_for_length

CHUNK_STEPS = 50  # control steps per compiled chunk; the host checks for the end between


def lane_steps(cfg: Config, world, lane: int) -> int:
  """The protocol's time limit (control steps) on lane `lane` (1-based) of `world`:
  `eval.max_steps` (the paper's 700) for rows up to 24 m, in proportion beyond
  (`mjxvine.lanes.lane_steps`; the env ends each episode there itself)."""
  line = world.lanes[lane - 1].centerline
  return steps_for_length(cfg.eval.max_steps, line[-1, 0] - line[0, 0])


def protocol_steps(env, policy: Policy, b: int, record: Sequence[int] = (),
                   cue: Callable | None = None):
  """The evaluator's stepping of `b` envs of `env` (a `VineyardEnv`), jitted:
  (reset, step, frames).

  reset(key, lanes (b,) 0-based, directions (b,) +1/-1[, worlds (b,), noise (b,)]) ->
  carry (State, alive (b,)): the envs at their lanes' starts, in `env`'s worlds `worlds`
  (default 0) with depth noise factors `noise` (default the env's).
  step(carry, key) -> (carry, out): every env takes the policy's action and one control
  step; alive turns False after an env's episode ended;
  out = (xy (b, 2), action (b, 2), alive (b,) before the step, outcome (b,),
  frames(state), cue(depth (b, H, W)) of the new image or () without `cue`).
  frames(state): the qpos (R, nq) and float16 depth (R, H, W) of the envs `record`, ()
  when none. The evaluator and `drive` step through these.
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
    seen = cue(state.obs["depth"][..., 0]) if cue is not None else ()
    out = (state.pipeline_state.qpos[:, :2], action, alive, state.info["outcome"],
           frames(state), seen)
    return (state, alive & (state.done == 0)), out

  return jax.jit(reset), body, frames


class EnvStarts(NamedTuple):
  """Where each of the B episodes of a `rollout` starts, in the env's terms: sequences of
  length B of lanes (0-based) and directions (+1 / -1), and optionally worlds (indices
  into the env's worlds; None: 0) and noise (each episode's depth noise factor; None: the
  env's)."""
  lanes: Sequence[int]
  directions: Sequence[float]
  worlds: Sequence[int] | None = None
  noise: Sequence[float] | None = None


def rollout(env, policy: Policy, starts: EnvStarts, key, max_steps: int,
            record: Sequence[int] = (), stop: Callable[[np.ndarray], bool] | None = None,
            cue: Callable | None = None):
  """Runs one episode per start of `starts` (`EnvStarts`, B of them) from its lane's
  start, batched. `stop(outcome)`, asked after every `CHUNK_STEPS` steps with the
  outcome codes so far ((B,), 0 for an episode still running): True ends the rollout
  there (an outcome that can no longer change a decision); the episodes still running
  then count as timeouts.

  Returns numpy arrays over time T and envs B: xy (T, B, 2), action (T, B, 2),
  alive (T, B) (step taken before the episode ended, inclusive), outcome (B,), steps (B,),
  and for the envs `record` (R of them, for videos) the frames from the start on:
  {"qpos": (T + 1, R, nq), "depth": (T + 1, R, H, W) float16 m, the image the policy saw}
  ({} when none are recorded); with `cue` (depth (B, H, W) -> a tuple of (B,) arrays: a
  per-frame summary, `mjxvine.deploy.row_cue`) also "cue": that tuple of (T, B) arrays, of
  the image after each step.
  """
  b = len(starts.lanes)
  k_reset, k_run = jax.random.split(key)
  reset, body, frames = protocol_steps(env, policy, b, record, cue)
  carry = reset(k_reset, jp.asarray(starts.lanes), jp.asarray(starts.directions, jp.float32),
                None if starts.worlds is None else jp.asarray(starts.worlds, jp.int32),
                None if starts.noise is None else jp.asarray(starts.noise, jp.float32))
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

  xy, act, alive, cues, outcome = [], [], [], [], np.zeros(b, np.int32)
  recorded = [jax.tree.map(lambda x: np.asarray(x)[None], frames(state))]
  for t0 in range(0, max_steps, CHUNK_STEPS):
    k_run, k = jax.random.split(k_run)
    carry, (p, a, al, oc, fr, cu) = run(carry, k)
    al, oc = np.asarray(al), np.asarray(oc)
    for t in range(al.shape[0]):
      ended = al[t] & (oc[t] != 0) & (outcome == 0)
      outcome[ended] = oc[t][ended]
    xy.append(np.asarray(p))
    act.append(np.asarray(a))
    alive.append(al)
    recorded.append(jax.tree.map(np.asarray, fr))
    cues.append(jax.tree.map(np.asarray, cu))
    if not np.asarray(carry[1]).any() or (stop is not None and stop(outcome)):
      break
  xy, act, alive = (np.concatenate(x)[:max_steps] for x in (xy, act, alive))
  outcome[outcome == 0] = OUTCOMES.index("timeout")
  tracks = {}
  if len(record):
    qpos, depth = (np.concatenate(x)[:max_steps + 1] for x in zip(*recorded))
    tracks = {"qpos": qpos, "depth": depth}
  if cue is not None:
    tracks["cue"] = tuple(np.concatenate(x)[:max_steps] for x in zip(*cues))
  return xy, act, alive, outcome, alive.sum(0), tracks


def drive(env, policy: Policy, lane: int, direction: str, key, max_steps: int | None = None
          ) -> Iterator[tuple[np.ndarray, np.ndarray, int]]:
  """Steps one env of `env` (a `VineyardEnv`) with `policy` from the start of `lane`
  (1-based) in `direction` ("F"/"R"), as the evaluator does (`protocol_steps` with one
  env). Yields (qpos (nq,), action (2,) [v m/s, w rad/s], outcome code) after each control
  step, first the start (action 0, outcome running), and stops after the step that ends
  the episode or after `max_steps` (default the protocol's, `lane_steps`). The keys (depth
  noise, a stochastic policy's draws) are `rollout`'s for the same `key`."""
  worlds = getattr(env, "worlds", None)  # (an env without vineyards: eval.max_steps)
  limit = max_steps if max_steps is not None else (
      lane_steps(env.cfg, worlds[0], lane) if worlds else env.cfg.eval.max_steps)
  reset, body, _ = protocol_steps(env, policy, 1)
  step = jax.jit(body)
  k_reset, k_run = jax.random.split(key)
  carry = reset(k_reset, jp.asarray([lane - 1]),
                jp.asarray([1.0 if direction == "F" else -1.0], jp.float32))
  yield np.asarray(carry[0].pipeline_state.qpos[0]), np.zeros(2, np.float32), RUNNING
  t = 0
  while t < limit:  # the evaluator's keys: one per step, CHUNK_STEPS from each chunk key
    k_run, k = jax.random.split(k_run)
    for k_step in jax.random.split(k, CHUNK_STEPS)[:limit - t]:
      carry, (_, action, _, outcome, _, _) = step(carry, k_step)
      code, t = int(outcome[0]), t + 1
      yield np.asarray(carry[0].pipeline_state.qpos[0]), np.asarray(action[0]), code
      if code != RUNNING:
        return


# ---------------------------------------------------------------------------- cases
def all_lanes(world) -> list[tuple[int, str]]:
  """Every lane-direction of `world` (a `Vineyard`): [(1, "F"), (1, "R"), (2, "F"), ...]."""
  return [(lane, d) for lane in range(1, len(world.lanes) + 1) for d in DIRECTIONS]


def parse_lanes(text: str, num_lanes: int) -> list[tuple[int, str]]:
  """"1F,4R" -> [(1, "F"), (4, "R")]; ValueError naming a lane-direction that the world
  (`num_lanes` lanes, directions F and R) does not have."""
  out = []
  for item in filter(None, (x.strip().upper() for x in text.split(","))):
    lane, direction = item[:-1], item[-1:]
    if direction not in DIRECTIONS or not lane.isdigit() or not 1 <= int(lane) <= num_lanes:
      raise ValueError(f"--video-lanes {text!r}: {item!r} is not a lane-direction of this "
                       f"world (1F .. {num_lanes}R)")
    out.append((int(lane), direction))
  return out


class Cases(list):
  """The episodes of one batched rollout, as (world index, lane (1-based), direction
  "F"/"R", noise factor) tuples, built group by group with `add`. The order is the
  rollout's: an episode's keys (its depth noise) depend on its index."""

  def add(self, world: int, rows: Sequence[tuple[int, str]], noise: float,
          runs: int) -> range:
    """`runs` episodes of each lane-direction of `rows` ((lane, "F"|"R") pairs, in that
    order) on world index `world` at depth noise factor `noise`: their indices."""
    first = len(self)
    self.extend((world, lane, d, noise) for lane, d in rows for _ in range(runs))
    return range(first, len(self))


class PolicySource(NamedTuple):
  """Which policy drives: `spec` (oracle, random, a run dir or an .npz, loaded by
  `policies.load_policy`) with, of a run dir, its checkpoint `which` ("best" or "last")
  and `member` (of a run that trained several; None: the one checkpoints/best follows);
  or `policy`, built already, which `spec` then only names."""
  spec: str
  which: str = "best"
  member: int | None = None
  policy: Policy | None = None


def rollout_cases(cfg: Config, source: PolicySource, worlds: list, cases, *,
                  seed: int = 0, record: Sequence[int] = (), stop=None, cue=None):
  """One batched rollout of every case: (world index, lane (1-based), direction "F"/"R",
  noise factor) tuples over `worlds` (`Vineyard`s; see `Cases`), driven by the policy of
  `source` with rollout key `seed` (`stop`, `cue`: see `rollout`). Returns (raw, policy
  name) with raw = dict of the `rollout` arrays (xy, act, alive, outcome, steps, frames of
  the cases `record`, the `cue` arrays or None) and wall_s (s)."""
  from mjxvine.env import VineyardEnv  # (the env's imports are heavy: only when needed)
  # the protocol's episode limits (`lane_steps`, applied by the env per lane), whatever
  # the training episodes were
  limits = [lane_steps(cfg, worlds[w], lane) for w, lane, _, _ in cases]
  cfg = replace(cfg, env={"max_steps": cfg.eval.max_steps})
  env = VineyardEnv(cfg, list(worlds))
  policy, name = source.policy, source.spec
  if policy is None:
    policy, name = load_policy(source.spec, env, source.which, source.member)
  starts = EnvStarts([l - 1 for _, l, _, _ in cases],
                     [1.0 if d == "F" else -1.0 for _, _, d, _ in cases],
                     [w for w, _, _, _ in cases], [n for _, _, _, n in cases])
  t0 = time.time()
  xy, act, alive, outcome, steps, frames = rollout(
      env, policy, starts, jax.random.PRNGKey(seed), max(limits), record=record, stop=stop,
      cue=cue)
  raw = dict(xy=xy, act=act, alive=alive, outcome=outcome, steps=steps,
             cue=frames.pop("cue", None), frames=frames, wall_s=time.time() - t0)
  return raw, name


# ---------------------------------------------------------------------------- the protocol
class Protocol(NamedTuple):
  """The protocol's settings on one world: `runs` runs (>= 1) of each lane (1-based; None:
  all of them) in each direction ("F"/"R"), at depth noise factor `noise_factor` (>= 0),
  with rollout key `seed`."""
  runs: int
  noise_factor: float
  lanes: Sequence[int] | None = None
  directions: Sequence[str] = DIRECTIONS
  seed: int = 0
  past_end: bool = False  # on into the headland; the end-of-row detector's stops reported


def run_protocol(cfg: Config, source: PolicySource, world, protocol: Protocol, *,
                 video: Sequence[tuple[int, str]] = ()) -> tuple[dict, list]:
  """`evaluate`, and the `video.Track` of the first run of each lane-direction in `video`
  ((lane, "F"|"R") pairs): (results document, tracks)."""
  runs, noise_factor, lanes = protocol.runs, protocol.noise_factor, protocol.lanes
  if runs < 1:
    raise ValueError(f"runs={runs}: need at least 1 run per lane and direction")
  if noise_factor < 0:
    raise ValueError(f"noise factor {noise_factor}: must be >= 0")
  lanes = list(range(1, len(world.lanes) + 1)) if lanes is None else list(lanes)
  cases = Cases()
  cases.add(0, [(l, d) for l in lanes for d in protocol.directions], noise_factor, runs)
  record = [cases.index((0, l, d, noise_factor)) for l, d in video
            if (0, l, d, noise_factor) in cases]
  detector = None
  if protocol.past_end:
    from mjxvine.evaluation.past_end import PAST_END_M, Detector
    cfg = replace(cfg, env={"past_end_m": PAST_END_M})
    detector = Detector.of(cfg, source.spec)
  raw, name = rollout_cases(cfg, source, [world], cases, seed=protocol.seed, record=record,
                            cue=detector.cue if detector else None)
  frames = raw["frames"]
  tracks = [_track(cfg, world, cases[i][1:3], frames["qpos"][:, j], frames["depth"][:, j],
                   raw["act"][:, i], int(raw["steps"][i]), OUTCOMES[int(raw["outcome"][i])])
            for j, i in enumerate(record)]
  doc = summarize(cfg, world, cases, range(len(cases)), raw)
  if detector:
    doc["row_end"] = detector.report(world, cases, raw)
  return {"policy": name, "noise": noise_factor, **doc}, tracks


def evaluate(cfg: Config, source: PolicySource, world, protocol: Protocol) -> dict:
  """Runs the protocol (`Protocol`: runs, noise factor, lanes, directions, seed) on `world`
  (a `Vineyard`) with the policy of `source` (`PolicySource`: spec, checkpoint, member)
  and returns the results document (docs/evaluation.md)."""
  return run_protocol(cfg, source, world, protocol)[0]


def _track(cfg: Config, world, case: tuple[int, str], qpos, depth, action, steps: int,
           outcome: str):
  """The `video.Track` of one recorded run of `steps` steps: frames 0 .. steps."""
  from mjxvine.evaluation.video import Track
  lane, direction = case
  qpos, depth = qpos[:steps + 1], depth[:steps + 1]
  action = np.concatenate([np.zeros((1, 2), np.float32), action[:steps]])
  offset = signed_offsets(qpos[:, :2], world.lanes[lane - 1].centerline, direction)
  return Track(lane, direction, qpos, depth.astype(np.float32), action, offset, outcome,
               cfg.env.control_dt, cfg.camera.max_depth_m)
