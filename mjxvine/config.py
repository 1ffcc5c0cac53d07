"""Frozen configuration dataclasses, loaded from YAML with `--set section.key=value` overrides.

Every field carries its allowed range (or choices) in its metadata; `load_config`
rejects unknown keys, wrong types and out-of-range values with one line naming the
key. Defaults are the paper's setting (docs/design.md).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import hashlib
import json
import math
import sys
import typing
from pathlib import Path
from typing import Any, Sequence

import yaml

from mjxvine import robot_files
from mjxvine.robot_files import ROBOTS, RobotSpec


class ConfigError(ValueError):
  """A config file or override is invalid; the message names the key."""


def _f(default, lo=None, hi=None, choices=None, doc=""):
  """A dataclass field with its allowed range [lo, hi] (inclusive) or its choices."""
  return dataclasses.field(
      default=default, metadata={"lo": lo, "hi": hi, "choices": choices, "doc": doc})


@dataclasses.dataclass(frozen=True)
class WorldConfig:
  """Procedural vineyards (docs/design.md, World layout). Lengths in metres."""
  inter_row_m: tuple[float, float] = _f((1.5, 2.0), 0.3, 10.0, doc="inter-row distance range")
  spacing_m: tuple[float, float] = _f((0.7, 1.0), 0.2, 5.0, doc="in-row plant spacing range")
  jitter_frac: float = _f(0.1, 0.0, 0.5, doc="plant position jitter, fraction of spacing (triangular)")
  train_rows: int = _f(4, 2, 12, doc="plant rows in a train world (lanes = rows - 1)")
  train_layout: str = _f("straight", choices=("straight", "varied"),
                         doc="train worlds: straight rows without gaps (the paper), or rows "
                         "that bend, widen their lanes and have single and wide gaps, each "
                         "drawn per world (domain randomisation; test worlds are unchanged)")
  train_wide_gap_rows: int = _f(2, 0, 12, doc="rows of a varied train world that get one "
                                "wide gap each (at most train_rows)")
  train_wide_gap_plants: tuple[int, int] = _f((2, 3), 1, 5, doc="plants missing in a wide "
                                              "gap of a varied train world (range; test worlds: 2-3)")
  train_length_m: float = _f(20.0, 4.0, 300.0, doc="row length of train worlds")
  test_length_m: float = _f(24.0, 8.0, 300.0, doc="row length of test worlds (the time "
                            "limit of an episode follows it: max_steps per 24 m)")
  curve_amplitude_m: float = _f(0.7, 0.0, 2.0, doc="lateral wander of curved test rows")
  trunk_radius_m: float = _f(0.04, 0.01, 0.2)
  trunk_height_m: tuple[float, float] = _f((0.6, 0.8), 0.1, 2.0)
  canopy_width_m: tuple[float, float] = _f((0.3, 0.5), 0.05, 2.0)
  canopy_top_m: tuple[float, float] = _f((1.6, 1.9), 0.5, 4.0)
  terrain_amplitude_m: float = _f(0.05, 0.0, 0.5, doc="terrain bumps are +- this")
  slope_pct: float = _f(0.0, -30.0, 30.0, doc="terrain gradient along the rows (+x), %")
  cross_slope_pct: float = _f(0.0, -30.0, 30.0, doc="terrain gradient across the rows, %")
  terrain_bump_m: float = _f(1.0, 0.1, 10.0, doc="grid of the random bumps")
  terrain_cell_m: float = _f(0.25, 0.05, 2.0, doc="heightfield resolution")
  terrain_margin_m: float = _f(4.0, 0.5, 20.0, doc="terrain beyond the outer plants")
  plant_slots: int = _f(0, 0, 4096, doc="plant slots per world (0: as many as the batch needs)")
  train_seed: int = _f(0, 0, 2**31 - 1, doc="seed of the first train world of the pool")
  pool_size: int = _f(8, 1, 4096, doc="train worlds in the pool")
  train_files: str = _f("", doc="vineyard files (.geojson, .csv, comma-separated) whose "
                        "blocks join the pool of generated train worlds")
  test_seed: int = _f(0, 0, 2**31 - 1)


def robot_spec(name_or_path: str) -> RobotSpec:
  """The robot of `robot.name`: a built-in name (`ROBOTS`, from the package's robot files)
  or a robot file FILE.yaml (docs/your-robot.md), read once per resolved path. Lives here
  because validation needs it; `mjxvine.worlds.robots` re-exports it. ConfigError, one
  line naming the file and its fault, if it is bad (`mjxvine.robot_files`)."""
  try:
    return robot_files.robot_spec(name_or_path)
  except robot_files.RobotFileError as e:
    raise ConfigError(str(e)) from None


ROBOT_NAMES = tuple(ROBOTS)  # the built-in robots (evaluation sweeps name theirs)


@dataclasses.dataclass(frozen=True)
class RobotConfig:
  """Which robot (docs/design.md, Robots; docs/your-robot.md) and its drive.

  A robot file may give camera.fovx_deg, fovy_deg, width, height and env.v_max, w_max
  (`robot_files.CONFIG_KEYS`). The rule, by rising precedence: the defaults, `base` and the
  config file, the robot file, `--set`. A trained policy's image size and action box cannot
  change (`rundir.settings.POLICY_KEYS`): a robot file asking for others is one ConfigError
  line, and `--set KEY=VALUE` of the policy's value keeps it."""
  name: str = _f("jackal", doc="a built-in robot (jackal, husky) or a robot file FILE.yaml "
                 "(relative to the working directory)")
  wheel_kv: float = _f(1.0, 0.001, 100.0, doc="wheel velocity-servo gain per kg of robot, N m s / rad / kg")
  wheel_armature: float = _f(0.005, 0.0, 1.0, doc="wheel motor armature per kg of robot, kg m^2 / kg")
  wheel_friction: float = _f(0.8, 0.05, 5.0)


@dataclasses.dataclass(frozen=True)
class CameraConfig:
  """Depth camera (docs/design.md, Camera and noise)."""
  width: int = _f(112, 1, 1024)
  height: int = _f(112, 1, 1024)
  fovx_deg: float = _f(60.0, 1.0, 170.0)
  fovy_deg: float = _f(46.8, 1.0, 170.0)
  max_depth_m: float = _f(5.0, 0.1, 100.0)
  noise_factor: float = _f(1.0, 0.0, 100.0, doc="k in clip(d + k (n1 + n2), 0, max)")
  noise_sigma_m: float = _f(0.2, 0.0, 5.0, doc="std of the depth-independent term n1")
  noise_clip_m: float = _f(0.5, 0.0, 5.0, doc="each noise term is clipped to +- this")


@dataclasses.dataclass(frozen=True)
class EnvConfig:
  """Task, reward and termination (docs/design.md, Observation and action; Reward and
  terminations)."""
  num_envs: int = _f(1, 1, 1 << 20)
  control_dt: float = _f(0.1, 0.01, 1.0, doc="seconds per action")
  physics_dt: float = _f(0.02, 0.001, 0.1, doc="MJX timestep; control_dt / physics_dt sub-steps")
  max_steps: int = _f(700, 1, 100000, doc="episode limit T (a truncation) on rows up "
                      "to 24 m, in proportion on longer ones (`lanes.lane_steps`)")
  v_min: float = _f(0.0, 0.0, 5.0, doc="lowest commanded speed, m/s (0: the paper's box; "
                    "> 0: the robot cannot stop in the row, so time-outs cannot be "
                    "waited out)")
  v_max: float = _f(0.5, 0.01, 5.0, doc="linear speed box [v_min, v_max] m/s")
  w_max: float = _f(1.0, 0.01, 10.0, doc="angular speed box [-w_max, w_max] rad/s")
  heading_weight: float = _f(0.6, 0.0, 1e3)
  progress_weight: float = _f(35.0, 0.0, 1e4)
  success_reward: float = _f(1000.0, -1e5, 1e5)
  collision_reward: float = _f(-500.0, -1e5, 1e5)
  reverse_reward: float = _f(-500.0, -1e5, 1e5)
  yaw_limit_deg: float = _f(85.0, 1.0, 180.0)
  success_radius_m: float = _f(0.4, 0.01, 5.0)
  collision_margin_m: float = _f(0.05, 0.0, 1.0)
  pose_reset_every: int = _f(10, 1, 100000, doc="episodes between new start poses")
  start_yaw_jitter_deg: float = _f(10.0, 0.0, 90.0)
  start_lateral_jitter_m: float = _f(0.1, 0.0, 1.0)
  start_along: tuple[float, float] = _f(
      (0.0, 0.6), 0.0, 0.95, doc="training starts lie this fraction of the row length from "
      "the lane's start in the travel direction, drawn uniformly (a random point along the "
      "lane); the evaluation from fresh starts always draws from [0, 0.6] "
      "(evaluation.starts.EVAL_START_ALONG)")
  yaw_reference: str = _f("start", choices=("start", "world"),
                          doc="the state's yaw: relative to the heading at the episode start "
                          "(a robot zeroing its IMU at the row entrance; this project's "
                          "default) or the world yaw (the paper's input)")
  yaw_reference_jitter_deg: float = _f(20.0, 0.0, 180.0,
                                       doc="yaw_reference=start: a random offset in +- this "
                                       "added to the reference at every training episode "
                                       "start, so that the relative yaw is not the heading "
                                       "error of a straight row (0 in evaluation)")
  yaw_offset_deg: float = _f(0.0, -180.0, 180.0, doc="yaw_reference=world: added to the world "
                             "yaw of the state input (90 keeps the rows' two directions "
                             "away from the +-pi wrap)")
  heading_reward: str = _f("paper", choices=("paper", "speed_weighted"),
                           doc="r_h as in the paper, or scaled by the forward speed / v_max "
                           "(no heading reward for standing still facing the EoR)")
  heading_target: str = _f("eor", choices=("eor", "lane"),
                           doc="the point r_h's angle phi is measured to: the end of the row "
                           "(the paper) or the centreline heading_lookahead_m ahead of the "
                           "robot (pays for driving on the centreline, not only towards the "
                           "EoR)")
  heading_lookahead_m: float = _f(2.0, 0.1, 50.0, doc="heading_target=lane: distance along "
                                  "the centreline from the robot's nearest point, m")
  train_noise_factor: tuple[float, float] = _f(
      (0.0, 0.0), 0.0, 100.0, doc="training episodes draw their depth noise factor k "
      "from this range (domain randomisation; as train_noise_draw says); [0, 0]: "
      "camera.noise_factor always. "
      "Evaluation always uses camera.noise_factor (or the noise sweep's)")
  train_noise_draw: str = _f("uniform", choices=("uniform", "log_uniform"),
                             doc="how train_noise_factor's k is drawn: uniformly, or "
                             "log-uniformly (as many episodes in [1, 2] as in [5, 10]: "
                             "most see a usable image, some a near-blind one; needs lo > 0)")
  start_directions: str = _f("both", choices=("both", "forward", "reverse"),
                             doc="travel directions of random starts (forward: +x, world "
                             "yaw near 0; reverse: yaw near +-pi, where the yaw input wraps)")


@dataclasses.dataclass(frozen=True)
class SACConfig:
  """Soft Actor-Critic (docs/design.md, SAC hyper-parameters)."""
  learning_rate: float = _f(2e-4, 1e-7, 1.0)
  lr_end_fraction: float = _f(1.0, 0.0, 1.0, doc="the actor's and critics' learning rate "
                              "decays linearly with env steps to this fraction of "
                              "learning_rate at train.total_env_steps (1.0: constant)")
  gamma: float = _f(0.99, 0.0, 1.0)
  n_step: int = _f(1, 1, 64, doc="the critics learn from n-step returns: the discounted "
                   "rewards of up to n consecutive steps of an episode, then the bootstrapped "
                   "value (uncorrected for the policy's change, as in DrQ-v2; 1: the paper's "
                   "one-step target)")
  tau: float = _f(5e-3, 0.0, 1.0, doc="the target critics' Polyak rate per gradient step")
  tau_late: float = _f(0.0, 0.0, 1.0, doc="the target critics' rate from tau_late_from on "
                       "(0: tau throughout); jackal.yaml slows the target five times "
                       "once epsilon reaches its floor")
  tau_late_from: float = _f(0.25, 0.0, 1.0, doc="fraction of train.total_env_steps from which "
                            "tau_late applies (0.25: where the paper's epsilon reaches its "
                            "floor)")
  alpha: float = _f(0.2, 0.0, 100.0, doc="entropy temperature (initial value if auto_alpha)")
  auto_alpha: bool = _f(False)
  target_entropy: float = _f(-2.0, -100.0, 100.0, doc="auto_alpha's target policy entropy, "
                             "nats of the density on the action box (the paper's -2): "
                             "-dim(A) on [-1, 1]^2 is -2 + log(0.25 * 1) = -3.39 on the "
                             "vineyard's [0, 0.5] x [-1, 1]")
  batch_size: int = _f(128, 1, 1 << 16)
  buffer_size: int = _f(100_000, 1, 1 << 26)
  replay_depth_dtype: str = _f("uint16", choices=("uint8", "uint16"),
                               doc="stored depth: uint8 (9.8 mm steps) fits 1e6 x 112^2 in 13 GB")
  warmup_steps: int = _f(10_000, 0, 1 << 30, doc="uniformly random env steps before learning")
  eps_start: float = _f(1.0, 0.0, 1.0)
  eps_decay: float = _f(0.992, 0.0, 1.0, doc="epsilon multiplier per episode of the budget")
  eps_budget_episodes: float = _f(1500.0, 1.0, 1e9, doc="the budget train.total_env_steps "
                                  "counts as this many episodes for epsilon's decay, over all "
                                  "envs together: eps = max(eps_min, eps_start * eps_decay ** "
                                  "(eps_budget_episodes * env_steps / total_env_steps)); the "
                                  "paper's 1500 episodes reach the floor at 25 % of the budget")
  eps_min: float = _f(0.05, 0.0, 1.0)
  hidden: int = _f(256, 1, 8192)
  conv_features: int = _f(32, 1, 1024)
  log_std_min: float = _f(-20.0, -100.0, 0.0)
  log_std_max: float = _f(2.0, -10.0, 10.0)
  grad_steps_per_iter: int = _f(1, 1, 1 << 16, doc="gradient steps per training iteration")
  compute_dtype: str = _f("float32", choices=("float32", "bfloat16"),
                          doc="dtype the convs and hidden layers compute in (bfloat16: "
                          "mixed precision for accelerators; parameters, heads, losses and "
                          "optimiser states stay float32)")
  actor_ema_tau: float = _f(0.0, 0.0, 1.0, doc="the actor that is evaluated, kept as best "
                            "and exported is a Polyak average of the learning actor, moved "
                            "by this rate every gradient step (0: the learning actor "
                            "itself); acting during training always uses the learning actor")
  mirror_augment: bool = _f(False, doc="every sampled transition is mirrored left-right "
                            "with probability 1/2 (depth columns reversed, turn rate and yaw "
                            "negated: the task is symmetric), so that both networks learn "
                            "from each experience on both sides and the actor gets no "
                            "steering bias from unbalanced data; no extra cost")
  mirror_average: bool = _f(False, doc="the test-time (deterministic) action is the mean "
                            "of the actor's action on the observation and the mirror of its "
                            "action on the mirrored observation: a policy exactly symmetric "
                            "left-right, with no steering bias, at twice the actor's cost; "
                            "used by the evaluations, the best-checkpoint choice and the "
                            "exported policy (exploration keeps the stochastic actor)")
  conv_impl: str = _f("auto", choices=("auto", "xla", "shift", "native"),
                      doc="how the learner computes the conv tower (the same parameters "
                      "and numbers to float32 rounding; evaluation and export use XLA's): "
                      "native = the whole tower as the hand-written CPU kernel "
                      "(mjxvine.native, x86-64 Linux with a C++ compiler); shift = "
                      "XLA's convs but the first as a sum of slices; auto = native on the "
                      "CPU where it builds, else shift, and xla elsewhere")
  image_shift_px: int = _f(0, 0, 16, doc="every sampled depth image (obs and next_obs, "
                           "apart) is moved by a random whole-pixel offset of up to this "
                           "many pixels along each axis, its edge values repeated into the "
                           "border (DrQ's random shift): the conv towers learn from views a "
                           "few pixels apart; acting and evaluation see the image as it is "
                           "(0: off)")
  actor_mean_init_scale: float = _f(1.0, 0.0, 10.0, doc="the actor's mean head starts "
                                    "with its initial weights (LeCun normal) times this: "
                                    "1 is flax's default; a small value starts every seed "
                                    "at nearly the same action, the box's centre (0.25 m/s "
                                    "straight ahead), instead of a turn that some "
                                    "initialisations draw")
  critic_layer_norm: bool = _f(False, doc="LayerNorm before each hidden ReLU of the "
                               "critics (not the paper's; the actor, and so the exported "
                               "policy, unchanged)")
  reuse_critic_features: bool = _f(False, doc="the actor loss reuses the critics' tower "
                                    "features of obs from the critic loss and the critics "
                                    "as they were before this step's update (as brax's SAC "
                                    "does): 6 tower passes per gradient step instead of 8. "
                                    "False: the actor loss re-runs the updated critics")
  reward_scale: float = _f(1.0, 1e-6, 1e6, doc="rewards are multiplied by this before the "
                           "replay (1: the paper; returns are logged unscaled)")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
  seed: int = _f(0, 0, 2**31 - 1)
  total_env_steps: int = _f(1_050_000, 1, 1 << 40)
  iters_per_chunk: int = _f(100, 1, 1 << 20, doc="iterations per chunk between host logs")
  chunk_loop: str = _f("auto", choices=("auto", "scan", "host"),
                       doc="a chunk as one lax.scan, or a host loop of jitted iterations "
                       "(auto: host on CPU, where convs in loops are slow)")
  checkpoint_every_chunks: int = _f(10, 1, 1 << 20)
  save_replay: bool = _f(False)
  num_seeds: int = _f(1, 1, 1024)
  sweep: str = _f("", doc="grid of hyper-parameters trained at once with the seeds (vmap), "
                  "e.g. 'sac.learning_rate=1e-4,1e-3; sac.alpha=0.1,0.2'")
  devices: int = _f(0, 0, 1 << 16, doc="devices the envs, replay and batches are split over "
                    "(0: all; see mjxvine.training.parallel)")
  max_minutes: float = _f(0.0, 0.0, 1e6, doc="a safety net on the wall-clock: stop "
                          "(checkpoint, evaluate) after the chunk that passes it, and say so "
                          "in the last line and RUN/run.json (0: none). The budget is "
                          "total_env_steps: the same command then gives the same policy")
  eval_every_chunks: int = _f(0, 0, 1 << 20, doc="deterministic evaluation from fresh starts "
                              "of the training pool, forward and reverse apart, every this "
                              "many chunks and at the end; keeps checkpoints/best (0: only at "
                              "the end)")
  eval_starts: int = _f(32, 1, 4096, doc="fresh starts per direction of that evaluation")
  keep_eval_policies: bool = _f(False, doc="write the evaluated policy at every such "
                                "evaluation as RUN/eval_policies/env<steps>.npz (of a run of "
                                "several members, each member's in eval_policies/member<k>/; "
                                "a policy file: "
                                "under 0.1 MB for the CPU configs' networks, 0.4 MB for the "
                                "paper's), to compare checkpoint choices afterwards")
  select_worlds: int = _f(0, 0, 64, doc="choose the best checkpoint on this many "
                          "validation worlds (test-kind worlds of seeds select_world_seed "
                          "and up, never a test table's) among the train.select_candidates "
                          "best fresh-start evaluations, after training, for each member "
                          "(mjxvine.evaluation.choice; writes their policies as "
                          "train.keep_eval_policies does; 0: the best fresh-start "
                          "evaluation is the best checkpoint)")
  select_world_seed: int = _f(100, 100, 2**31 - 1, doc="the first validation world's seed "
                              "(test tables use seeds below 100)")
  select_candidates: int = _f(4, 1, 1024, doc="fresh-start evaluations scored on the "
                              "validation worlds: the best by the weaker direction's "
                              "success, then the lower MAE")
  select_runs: int = _f(2, 1, 100, doc="runs per lane-direction of each validation world")
  select_success_bar: float = _f(0.95, 0.0, 1.0, doc="the share of the validation worlds' "
                                 "runs a candidate must drive to the EoR, its noise rows "
                                 "at least the paper's, to be ranked by its MAE ahead of "
                                 "the candidates that do not (they rank by successes)")
  select_noise_factors: tuple[float, float] = _f(
      (8.0, 10.0), 0.0, 100.0, doc="depth-noise factors at which rows 1F and 4F of the "
      "first validation world are driven too, 3 runs each (as the noise test)")
  video: bool = _f(False, doc="the closing report films the best policy on the test world "
                   "(lanes 1F and 4R): MP4s in RUN/eval/videos/ (needs OpenGL and "
                   "imageio-ffmpeg, `pip install mjxvine[video]`; eval.runs_after_train >= 1)")


@dataclasses.dataclass(frozen=True)
class EvalConfig:
  runs: int = _f(5, 1, 1000, doc="runs per lane and direction")
  max_steps: int = _f(700, 1, 100000, doc="episode limit T of the test-world protocol (the "
                      "paper's 700) on rows up to 24 m, in proportion on longer ones; "
                      "whatever env.max_steps training used")
  noise_factor: float = _f(1.0, 0.0, 100.0)
  runs_after_train: int = _f(1, 0, 1000)


@dataclasses.dataclass(frozen=True)
class Config:
  world: WorldConfig = WorldConfig()
  robot: RobotConfig = RobotConfig()
  camera: CameraConfig = CameraConfig()
  env: EnvConfig = EnvConfig()
  sac: SACConfig = SACConfig()
  train: TrainConfig = TrainConfig()
  eval: EvalConfig = EvalConfig()


def _coerce(key: str, value: Any, tp: Any, meta: dict) -> Any:
  """Converts `value` (from YAML or a `--set` string) to `tp`, checking its range."""
  origin = typing.get_origin(tp)
  if origin is tuple:
    if isinstance(value, str):
      value = yaml.safe_load(value)
    item_types = typing.get_args(tp)
    if not isinstance(value, (list, tuple)) or len(value) != len(item_types):
      raise ConfigError(f"{key} = {value!r}: expected a list of {len(item_types)} numbers")
    out = tuple(_coerce(key, v, t, meta) for v, t in zip(value, item_types))
    if any(a > b for a, b in zip(out, out[1:])):
      raise ConfigError(f"{key} = {list(out)}: the range must be increasing [min, max]")
    return out
  if isinstance(value, str) and tp is not str:
    value = yaml.safe_load(value)
  if tp is bool:
    if not isinstance(value, bool):
      raise ConfigError(f"{key} = {value!r}: expected true or false")
    return value
  if tp is int:
    if isinstance(value, bool) or not (isinstance(value, int) or
                                       (isinstance(value, float) and value.is_integer())):
      raise ConfigError(f"{key} = {value!r}: expected an integer")
    value = int(value)
  elif tp is float:
    if isinstance(value, str):  # YAML 1.1 reads "3e-4" (no dot) as a string
      try:
        value = float(value)
      except ValueError:
        pass
    if isinstance(value, bool) or not isinstance(value, (int, float)):
      raise ConfigError(f"{key} = {value!r}: expected a number")
    value = float(value)
    if not math.isfinite(value):
      raise ConfigError(f"{key} = {value!r}: expected a finite number")
  elif tp is str:
    value = str(value)
  lo, hi, choices = meta.get("lo"), meta.get("hi"), meta.get("choices")
  if choices is not None and value not in choices:
    raise ConfigError(f"{key} = {value!r}: must be one of {', '.join(choices)}")
  if lo is not None and not (lo <= value <= hi):
    raise ConfigError(f"{key} = {value!r}: must be in [{lo}, {hi}]")
  return value


def _build(cls, data: dict, prefix: str):
  if not isinstance(data, dict):
    raise ConfigError(f"{prefix.rstrip('.') or 'config'}: expected a mapping, got {data!r}")
  hints = typing.get_type_hints(cls)
  names = {f.name: f for f in dataclasses.fields(cls)}
  for key in data:
    if key not in names:
      raise ConfigError(f"{prefix}{key}: unknown key (known: {', '.join(names)})")
  kwargs = {}
  for name, field in names.items():
    tp, key = hints[name], prefix + name
    if dataclasses.is_dataclass(tp):
      kwargs[name] = _build(tp, data.get(name, {}) or {}, key + ".")
    elif name in data:
      kwargs[name] = _coerce(key, data[name], tp, dict(field.metadata))
  return cls(**kwargs)


def _check_cross_fields(cfg: Config) -> None:
  robot = robot_spec(cfg.robot.name)
  width = robot.width
  lo = cfg.world.inter_row_m[0]
  if lo - cfg.world.canopy_width_m[1] <= width:
    raise ConfigError(
        f"world.inter_row_m = {list(cfg.world.inter_row_m)}: the lane (inter-row distance "
        f"minus canopy width {cfg.world.canopy_width_m[1]}) must be wider than the "
        f"{robot.name} ({width} m); must be > {width + cfg.world.canopy_width_m[1]:.3f}")
  if cfg.world.trunk_height_m[1] >= cfg.world.canopy_top_m[0]:
    raise ConfigError(f"world.trunk_height_m = {list(cfg.world.trunk_height_m)}: "
                      f"must stay below world.canopy_top_m {list(cfg.world.canopy_top_m)}")
  if cfg.world.train_wide_gap_rows > cfg.world.train_rows:
    raise ConfigError(f"world.train_wide_gap_rows = {cfg.world.train_wide_gap_rows}: must "
                      f"be at most world.train_rows = {cfg.world.train_rows}")
  if cfg.env.train_noise_draw == "log_uniform" and cfg.env.train_noise_factor[0] <= 0:
    raise ConfigError(f"env.train_noise_factor = {list(cfg.env.train_noise_factor)}: "
                      "env.train_noise_draw = log_uniform needs a range above 0")
  if cfg.env.v_min >= cfg.env.v_max:
    raise ConfigError(f"env.v_min = {cfg.env.v_min}: must be < env.v_max = {cfg.env.v_max}")
  steps = cfg.env.control_dt / cfg.env.physics_dt
  if abs(steps - round(steps)) > 1e-6:
    raise ConfigError(f"env.physics_dt = {cfg.env.physics_dt}: must divide env.control_dt "
                      f"= {cfg.env.control_dt}")
  parse_sweep(cfg.train.sweep)
  if cfg.train.video and cfg.eval.runs_after_train < 1:
    raise ConfigError("train.video = true: films the closing test-world runs, which need "
                      "eval.runs_after_train >= 1 (got 0)")
  rows = cfg.sac.buffer_size // cfg.env.num_envs
  if cfg.sac.n_step >= rows:
    raise ConfigError(f"sac.n_step = {cfg.sac.n_step}: must be below the steps per env "
                      f"that the replay holds (sac.buffer_size // env.num_envs = {rows})")
  if cfg.sac.log_std_min >= cfg.sac.log_std_max:
    raise ConfigError(f"sac.log_std_min = {cfg.sac.log_std_min}: must be < sac.log_std_max")
  for key in ("mirror_augment", "mirror_average"):
    if (getattr(cfg.sac, key) and cfg.env.yaw_reference == "world"
        and cfg.env.yaw_offset_deg != 0.0):
      raise ConfigError(f"sac.{key} = true: the mirror negates the yaw input, which "
                        f"needs env.yaw_offset_deg = 0 with env.yaw_reference = world "
                        f"(got {cfg.env.yaw_offset_deg})")


# Hyper-parameters that a vmapped sweep may vary (they live in the learner state).
SWEEPABLE = ("sac.learning_rate", "sac.alpha")


def parse_sweep(text: str) -> dict[str, tuple[float, ...]]:
  """'sac.learning_rate=1e-4,1e-3; sac.alpha=0.1' -> {"sac.learning_rate": (1e-4, 1e-3),
  "sac.alpha": (0.1,)}; raises ConfigError naming train.sweep on a bad entry."""
  out = {}
  for item in filter(None, (x.strip() for x in text.split(";"))):
    key, _, values = item.partition("=")
    key = key.strip()
    if key not in SWEEPABLE:
      raise ConfigError(f"train.sweep: {key!r} cannot be swept (sweepable: "
                        f"{', '.join(SWEEPABLE)})")
    try:
      vals = tuple(float(v) for v in values.split(","))
    except ValueError:
      raise ConfigError(f"train.sweep: {item!r}: expected {key}=v1,v2,...") from None
    if not all(math.isfinite(v) and v > 0 for v in vals):
      raise ConfigError(f"train.sweep: {item!r}: values must be positive numbers")
    out[key] = vals
  return out


def _set_nested(data: dict, dotted: str, value: str) -> None:
  parts = dotted.split(".")
  node = data
  for p in parts[:-1]:
    node = node.setdefault(p, {})
    if not isinstance(node, dict):
      raise ConfigError(f"{dotted}: {p} is not a section")
  node[parts[-1]] = value


# The experiment configs shipped inside the package (copies of the repository's
# experiments/*.yaml, kept identical by tests/test_config.py), so that an installed
# package trains its documented default and `--config cpu.yaml` works from any folder.
PACKAGED_CONFIGS = Path(__file__).resolve().parent / "configs"
DEFAULT_CONFIG_NAME = "default.yaml"


def packaged_configs() -> list[str]:
  """The names of the shipped experiment configs (`default.yaml`, `cpu.yaml`, ...)."""
  return sorted(p.name for p in PACKAGED_CONFIGS.glob("*.yaml"))


def resolve_config_path(path: str | Path) -> Path:
  """`path` if it is a file; else, for a bare name (`cpu.yaml`, `cpu`,
  `experiments/cpu.yaml`) of a shipped config, the packaged copy; else `path` unchanged
  (load_config then reports it as not found)."""
  path = Path(path)
  if path.is_file():
    return path
  if path.parent in (Path("."), Path("experiments")):
    name = path.name if path.suffix else path.name + ".yaml"
    if (PACKAGED_CONFIGS / name).is_file():
      return PACKAGED_CONFIGS / name
  return path


def read_yaml(path: str | Path) -> dict:
  """The mapping of a YAML config file; ConfigError (naming the file) if missing or invalid.
  `path` may also name a shipped experiment config (`resolve_config_path`)."""
  path = resolve_config_path(path)
  if not path.is_file():
    raise ConfigError(f"config file not found: {path} (shipped configs: "
                      f"{', '.join(packaged_configs())})")
  data = robot_files.load_yaml(path, str(path), ConfigError, "config")
  if data is None:
    # An empty file is more likely a mistake than a wish for the defaults (a 112x112
    # run with a multi-GB replay): "{}" says the latter.
    raise ConfigError(f"{path}: empty (write {{}} to train the defaults)")
  if not isinstance(data, dict):
    raise ConfigError(f"{path}: expected a mapping of sections (world:, env:, sac:, ...), "
                      f"got a {type(data).__name__}")
  return data


def _merged(base: dict, top: dict) -> dict:
  """`base` with `top`'s keys laid over it, section by section (neither is changed)."""
  out = dict(base)
  for key, value in top.items():
    out[key] = (_merged(out[key], value) if isinstance(value, dict) and
                isinstance(out.get(key), dict) else value)
  return out


def _lay_robot_file(data: dict, sets: list[tuple[str, str]]) -> None:
  """Lays the camera and velocity values of the robot file that `robot.name` (in `sets`,
  else in `data`) names over `data`, but under the keys that `sets` gives (RobotConfig)."""
  names = [v for k, v in sets if k == "robot.name"]
  section = data.get("robot")
  name = names[-1] if names else (section.get("name", RobotConfig.name)
                                  if isinstance(section, dict) else RobotConfig.name)
  try:
    robot = robot_spec(str(name))
  except ConfigError as e:
    raise ConfigError(f"robot.name: {e}") from None
  given = {k for k, _ in sets}
  for key, value in robot_files.config_values(robot).items():
    if key not in given:
      _set_nested(data, key, value)


def load_config(path: str | Path | None = None, overrides: Sequence[str] = (),
                base: dict | None = None) -> Config:
  """Loads a config: defaults <- `base` (a mapping, e.g. a run's own config.yaml) <- YAML
  file at `path` <- the robot file's camera and velocity values (RobotConfig) <-
  `overrides` ("section.key=value")."""
  data: dict = _merged(copy.deepcopy(base or {}),
                       read_yaml(path) if path is not None else {})
  sets = []
  for item in overrides:
    if "=" not in item:
      raise ConfigError(f"--set {item!r}: expected section.key=value")
    key, value = item.split("=", 1)
    sets.append((key.strip(), value.strip()))
  _lay_robot_file(data, sets)
  for key, value in sets:
    _set_nested(data, key, value)
  cfg = _build(Config, data, "")
  _check_cross_fields(cfg)
  return cfg


def to_dict(cfg) -> dict:
  """A plain dict of a config (tuples as lists), for YAML/JSON."""
  return json.loads(json.dumps(dataclasses.asdict(cfg)))


def to_yaml(cfg) -> str:
  return yaml.safe_dump(to_dict(cfg), sort_keys=False)


def config_hash(cfg) -> str:
  """A short stable hash of a config (or of its dict, as a policy file records it), to tie
  exported policies to their run."""
  doc = cfg if isinstance(cfg, dict) else to_dict(cfg)
  return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:12]


def add_config_args(parser: argparse.ArgumentParser, default: str | None = None) -> None:
  """Adds `--config FILE` and repeatable `--set section.key=value` to a CLI."""
  parser.add_argument("--config", default=default,
                      help="YAML config file, or the name of a shipped one: "
                      + ", ".join(packaged_configs()))
  parser.add_argument("--set", dest="overrides", action="append", default=[],
                      metavar="SECTION.KEY=VALUE", help="override a config value (repeatable)")


def config_from_args(args: argparse.Namespace, extra: Sequence[str] = ()) -> Config:
  """Loads the config named by `add_config_args`; a bad config is a usage error: one line
  on stderr and exit status 2 (argparse's)."""
  try:
    return load_config(args.config, [*extra, *args.overrides])
  except ConfigError as e:
    print(f"config error: {e}", file=sys.stderr)
    raise SystemExit(2) from None


def enable_compile_cache() -> None:
  """Keeps XLA's compiled programs on disk between runs (JAX's persistent compilation
  cache), so that a second run of the same config starts in seconds, not minutes: in
  $JAX_COMPILATION_CACHE_DIR if set, else ~/.cache/mjxvine/xla ($XDG_CACHE_HOME
  respected); MJXVINE_COMPILE_CACHE=0 turns it off. For the CLIs."""
  import os
  if os.environ.get("MJXVINE_COMPILE_CACHE", "1") == "0":
    return
  import jax
  if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
    return  # jax reads it itself
  root = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
  jax.config.update("jax_compilation_cache_dir", str(root / "mjxvine" / "xla"))


def depth_input_scale(cfg: Config) -> float:
  """The factor (1/m) the networks multiply depth by: [0, camera.max_depth_m] -> [0, 1]."""
  return 1.0 / cfg.camera.max_depth_m


def action_box(cfg: Config) -> tuple[list[float], list[float]]:
  """The vineyard action box ([v_min, -w_max], [v_max, w_max]): [v m/s, w rad/s]."""
  return [cfg.env.v_min, -cfg.env.w_max], [cfg.env.v_max, cfg.env.w_max]


def changed_keys(a: Config, b: Config) -> list[str]:
  """The "section.key" names whose values differ between two configs."""
  return [f"{s.name}.{k}" for s in dataclasses.fields(Config)
          for k, v in vars(getattr(b, s.name)).items() if getattr(getattr(a, s.name), k) != v]


def replace(cfg: Config, **sections: dict) -> Config:
  """Returns `cfg` with fields of sections replaced, e.g. replace(cfg, env={"num_envs": 4})."""
  return dataclasses.replace(
      cfg, **{s: dataclasses.replace(getattr(cfg, s), **kv) for s, kv in sections.items()})


__all__ = [
    "Config", "ConfigError", "WorldConfig", "RobotConfig", "CameraConfig", "EnvConfig",
    "SACConfig", "TrainConfig", "EvalConfig", "load_config", "to_dict", "to_yaml",
    "config_hash", "add_config_args", "config_from_args", "replace", "RobotSpec", "ROBOTS",
    "read_yaml", "robot_spec",
    "ROBOT_NAMES", "SWEEPABLE", "parse_sweep", "enable_compile_cache", "action_box",
    "changed_keys",
    "depth_input_scale",
]
