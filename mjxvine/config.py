"""Frozen configuration dataclasses, loaded from YAML with `--set section.key=value` overrides.

Every field carries its allowed range (or choices) in its metadata; `load_config`
rejects unknown keys, wrong types and out-of-range values with one line naming the
key and quoting at most a short prefix of the value (`short_repr`). Config files and
`--set` values are YAML read by one set of rules (`robot_files.yaml_text`): at most 1 MiB,
nested at most 16 deep, no anchors or aliases, scalars as YAML 1.2 reads them (`010` is
10, `1:30` is not a number). Flags that stand for a key take its rule (`check_value`).
Defaults are the paper's setting (docs/design.md).
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
from mjxvine.robot_files import ROBOTS, RobotSpec, clean, short_repr


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
  trunk_height_m: tuple[float, float] = _f((0.6, 0.8), 0.1, 2.0)
  canopy_width_m: tuple[float, float] = _f((0.3, 0.5), 0.05, 2.0)
  canopy_top_m: tuple[float, float] = _f((1.6, 1.9), 0.5, 4.0)
  # Vineyard realism (docs/environment.md, Seasons and the trellis): none in classic worlds.
  season: str = _f("classic", choices=("classic", "spring", "summer", "winter", "mixed"),
                   doc="what the plants look like: classic (the paper's trunk and canopy "
                   "ellipsoid, nothing else), spring (small lobes on the cordon), summer (a "
                   "wall of canopy lobes, shoots into the lanes), winter (bare trunks and "
                   "cordons), the last three with trellis posts; mixed: each world draws "
                   "spring, summer or winter from its seed")
  post_spacing_m: tuple[float, float] = _f((6.4, 8.5), 0.0, 50.0, doc="line posts of "
                                           "the trellis every this along a row (drawn per "
                                           "world), anchor posts at both row ends; [0, 0]: "
                                           "no posts, else at least 1 m (not classic)")
  post_height_m: tuple[float, float] = _f((1.8, 2.2), 0.3, 4.0, doc="post height above "
                                          "the ground, drawn per post (not classic)")
  cordon_height_m: tuple[float, float] = _f((0.9, 1.0), 0.2, 3.0, doc="height of the "
                                            "cordon (fruiting wire) and the trunks' top, "
                                            "drawn per row (not classic; below canopy_top_m)")
  canopy_lobes: tuple[int, int] = _f((3, 5), 1, 12, doc="ellipsoid lobes of a plant's "
                                     "canopy, drawn per plant (spring, summer)")
  shoots_per_plant: tuple[int, int] = _f((1, 2), 0, 8, doc="shoots of a summer plant "
                                         "hanging into the lanes, drawn per plant")
  shoot_reach_m: tuple[float, float] = _f((0.1, 0.35), 0.0, 1.5, doc="how far a summer "
                                          "shoot reaches beyond the canopy's side, drawn "
                                          "per shoot")
  tuft_density_per_m2: float = _f(0.0, 0.0, 10.0, doc="grass and weed tufts per m^2 of "
                                  "lane floor, seen by the camera, driven over (not classic)")
  slope_pct: float = _f(0.0, -30.0, 30.0, doc="terrain gradient along the rows (+x), %")
  cross_slope_pct: float = _f(0.0, -30.0, 30.0, doc="terrain gradient across the rows, %")
  pool_size: int = _f(8, 1, 4096, doc="train worlds in the pool")
  train_files: str = _f("", doc="vineyard files (.geojson, .csv, comma-separated) whose "
                        "blocks join the pool of generated train worlds")
  train_files_share: float = _f(0.5, 0.0, 1.0, doc="share of the training starts in the "
                                "blocks of world.train_files (the rest in the generated "
                                "worlds; without files, every start is in those)")

  MIN_POST_SPACING_M = 1.0  # line posts nearer than this are no trellis (not a key)

  def __post_init__(self):
    lo, hi = self.post_spacing_m
    if hi > 0 and lo < self.MIN_POST_SPACING_M:
      raise ConfigError(f"world.post_spacing_m = {list(self.post_spacing_m)}: [0, 0] (no "
                        f"posts) or a range from at least {self.MIN_POST_SPACING_M:g} m")
    if self.season != "classic" and self.cordon_height_m[1] >= self.canopy_top_m[0]:
      raise ConfigError(f"world.cordon_height_m = {list(self.cordon_height_m)}: must stay "
                        f"below world.canopy_top_m {list(self.canopy_top_m)}")


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
  # The robot's faults (`mjxvine.robot_faults`, docs/your-robot.md): drawn per episode.
  latency_steps: tuple[int, int] = _f((0, 0), 0, 5, doc="control steps between a command "
                                      "and the wheels acting on it, drawn per episode")
  velocity_lag_s: tuple[float, float] = _f((0.0, 0.0), 0.0, 2.0, doc="time constant of "
                                           "the first-order lag of the commanded speed and "
                                           "turn rate, drawn per episode (0: none)")
  mount_pitch_deg: tuple[float, float] = _f((0.0, 0.0), 0.0, 20.0, doc="camera pitch "
                                             "error: its size uniform in [lo, hi], its sign "
                                             "at random, per episode ([0, x]: uniform in "
                                             "+-x; [x, x]: +-x exactly)")
  mount_roll_deg: tuple[float, float] = _f((0.0, 0.0), 0.0, 20.0, doc="camera roll error, "
                                            "as mount_pitch_deg")
  mount_height_m: tuple[float, float] = _f((0.0, 0.0), 0.0, 0.3, doc="camera height error, "
                                            "as mount_pitch_deg")
  yaw_walk_deg: float = _f(0.0, 0.0, 10.0, doc="IMU yaw drift: the state's yaw walks "
                           "randomly by this std per square root of a second")

  @property
  def spec(self) -> RobotSpec:
    """The robot `name` resolves to: body, wheels, camera mount (`robot_files.RobotSpec`,
    read once per file). Every module takes the robot from here."""
    return robot_spec(self.name)


@dataclasses.dataclass(frozen=True)
class CameraConfig:
  """Depth camera (docs/design.md, Camera and noise)."""
  width: int = _f(112, 1, 1024)
  height: int = _f(112, 1, 1024)
  fovx_deg: float = _f(60.0, 1.0, 170.0)
  fovy_deg: float = _f(46.8, 1.0, 170.0)
  max_depth_m: float = _f(5.0, 0.1, 100.0)


# The depth sensor's presets (docs/design.md, The depth sensor): every `sensor.*` key a
# config file or --set does not name takes its preset's value. `ideal` is the paper's camera.
SENSOR_PRESETS = {
    "ideal": dict(stereo_baseline_m=0.0, stereo_focal_px=447.0, stereo_subpixel_px=0.08,
                  min_depth_m=0.0, dropout_rate=(0.0, 0.0), patch_rate=(0.0, 0.0),
                  patch_size_deg=5.0, flying_pixel_rate=0.0, quantum_m=0.0),
    # RealSense D435 at 848 px: B 50 mm, HFOV 87 deg -> f 447 px, subpixel 0.08 px; min-Z
    # f B / 126 px = 0.18 m (0.11 m is at 424x240); outdoor holes (no published vineyard
    # fill rate: ranges, not measurements)
    "d435": dict(stereo_baseline_m=0.050, stereo_focal_px=447.0, stereo_subpixel_px=0.08,
                 min_depth_m=0.18, dropout_rate=(0.01, 0.10), patch_rate=(0.02, 0.10),
                 patch_size_deg=6.0, flying_pixel_rate=0.3, quantum_m=0.001),
    # RealSense D455 at 848 px: B 95 mm, HFOV 87 deg -> f 447 px; min-Z f B / 126 px =
    # 0.34 m (0.52 m at 1280x720)
    "d455": dict(stereo_baseline_m=0.095, stereo_focal_px=447.0, stereo_subpixel_px=0.08,
                 min_depth_m=0.34, dropout_rate=(0.01, 0.08), patch_rate=(0.02, 0.08),
                 patch_size_deg=6.0, flying_pixel_rate=0.3, quantum_m=0.001),
}


@dataclasses.dataclass(frozen=True)
class SensorConfig:
  """The depth sensor's faults on top of the camera's image and noise (docs/design.md, The
  depth sensor; `mjxvine.sensor`). "No return" reads camera.max_depth_m, as a deployed
  policy's preprocessing makes it (`NumpyPolicy(invalid_depth=None)`)."""
  preset: str = _f("ideal", choices=tuple(SENSOR_PRESETS), doc="the camera whose values "
                   "the other sensor keys take unless they are set: ideal (the paper's "
                   "exact image and noise), d435, d455 (RealSense stereo cameras)")
  stereo_baseline_m: float = _f(0.0, 0.0, 1.0, doc="stereo baseline B; the depth error's "
                                "std is z^2 s / (f B) (0: no stereo error)")
  stereo_focal_px: float = _f(447.0, 1.0, 1e5, doc="focal length f, pixels of the "
                              "sensor's native width")
  stereo_subpixel_px: float = _f(0.08, 0.0, 2.0, doc="subpixel accuracy s of the matcher")
  min_depth_m: float = _f(0.0, 0.0, 10.0, doc="nearer than this: no return")
  dropout_rate: tuple[float, float] = _f((0.0, 0.0), 0.0, 1.0, doc="share of single "
                                         "pixels without a return at 0 m and at "
                                         "camera.max_depth_m (linear in between)")
  patch_rate: tuple[float, float] = _f((0.0, 0.0), 0.0, 1.0, doc="share of pixels in "
                                       "patches without a return (spatially correlated), "
                                       "at 0 m and at camera.max_depth_m")
  patch_size_deg: float = _f(5.0, 0.1, 90.0, doc="the patches' size, degrees of view")
  flying_pixel_rate: float = _f(0.0, 0.0, 1.0, doc="share of the pixels on a depth edge "
                                "that read a depth between its two sides")
  quantum_m: float = _f(0.0, 0.0, 0.1, doc="depth step of the output (0.001: millimetres)")


PHYSICS_DT_S = 0.02  # the MJX timestep: env.control_dt / this physics steps a control step


@dataclasses.dataclass(frozen=True)
class EnvConfig:
  """Task, reward and termination (docs/design.md, Observation and action; Reward and
  terminations)."""
  num_envs: int = _f(1, 1, 1 << 20)
  control_dt: float = _f(0.1, 0.02, 1.0, doc="seconds per action, a multiple of PHYSICS_DT_S")
  max_steps: int = _f(700, 1, 100000, doc="episode limit T (a truncation) on rows up "
                      "to 24 m, in proportion on longer ones (`lanes.lane_steps`)")
  v_min: float = _f(0.0, 0.0, 5.0, doc="lowest commanded speed, m/s (0: the paper's box; "
                    "> 0: the robot cannot stop in the row, so time-outs cannot be "
                    "waited out)")
  v_max: float = _f(0.5, 0.01, 5.0, doc="linear speed box [v_min, v_max] m/s")
  w_max: float = _f(1.0, 0.01, 10.0, doc="angular speed box [-w_max, w_max] rad/s")
  past_end_m: float = _f(0.0, 0.0, 20.0, doc="0: an episode succeeds at the end of the "
                         "row; > 0: only this far past its end line (m), anywhere "
                         "sideways (`evaluate --past-end` drives into the headland)")
  start_yaw_jitter_deg: float = _f(10.0, 0.0, 90.0)
  start_lateral_jitter_m: float = _f(0.1, 0.0, 1.0)
  yaw_reference: str = _f("start", choices=("start", "world"),
                          doc="the state's yaw: relative to the heading at the episode start "
                          "(a robot zeroing its IMU at the row entrance; this project's "
                          "default) or the world yaw (the paper's input)")
  heading_reward: str = _f("paper", choices=("paper", "speed_weighted"),
                           doc="r_h as in the paper, or scaled by the forward speed / v_max "
                           "(no heading reward for standing still facing the EoR)")
  train_noise_factor: tuple[float, float] = _f(
      (0.0, 0.0), 0.0, 100.0, doc="training episodes draw their depth noise factor k "
      "from this range (domain randomisation; as train_noise_draw says); [0, 0]: "
      "the paper's factor 1 always. Evaluation uses eval.noise_factor (or the noise "
      "sweep's)")
  train_noise_draw: str = _f("uniform", choices=("uniform", "log_uniform"),
                             doc="how train_noise_factor's k is drawn: uniformly, or "
                             "log-uniformly (as many episodes in [1, 2] as in [5, 10]: "
                             "most see a usable image, some a near-blind one; needs lo > 0)")


@dataclasses.dataclass(frozen=True)
class SACConfig:
  """Soft Actor-Critic (docs/design.md, SAC hyper-parameters)."""
  learning_rate: float = _f(2e-4, 1e-7, 1.0)
  gamma: float = _f(0.99, 0.0, 1.0)
  n_step: int = _f(1, 1, 64, doc="the critics learn from n-step returns: the discounted "
                   "rewards of up to n consecutive steps of an episode, then the bootstrapped "
                   "value (uncorrected for the policy's change, as in DrQ-v2; 1: the paper's "
                   "one-step target)")
  tau: float = _f(5e-3, 0.0, 1.0, doc="the target critics' Polyak rate per gradient step")
  tau_late: float = _f(0.0, 0.0, 1.0, doc="the target critics' rate from a quarter of "
                       "train.total_env_steps on, where epsilon reaches its floor (0: tau "
                       "throughout); jackal.yaml slows the target five times")
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
  eps_start: float = _f(1.0, 0.0, 1.0, doc="epsilon-greedy's initial probability of a "
                        "uniform action; it decays as the paper's 0.992 per episode with "
                        "the budget train.total_env_steps counted as 1500 episodes over all "
                        "envs together, so that it reaches eps_min at the same fraction of "
                        "the budget for any number of envs")
  eps_min: float = _f(0.05, 0.0, 1.0)
  hidden: int = _f(256, 1, 8192)
  conv_features: int = _f(32, 1, 1024)
  grad_steps_per_iter: int = _f(1, 1, 1 << 16, doc="gradient steps per training iteration")
  actor_ema_tau: float = _f(0.0, 0.0, 1.0, doc="the actor that is evaluated, kept as best "
                            "and exported is a Polyak average of the learning actor, moved "
                            "by this rate every gradient step (0: the learning actor "
                            "itself); acting during training always uses the learning actor")
  anchor_weight: float = _f(0.0, 0.0, 1e4, doc="with train.init_from: the actor's loss "
                            "adds this times the mean squared distance between its "
                            "test-time action and the loaded actor's on the same replay "
                            "states (actions scaled to [-1, 1]), so that fine-tuning keeps "
                            "the loaded driving where the new experience does not pay to "
                            "change it (0: no pull)")
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
  critic_layer_norm: bool = _f(False, doc="LayerNorm before each hidden ReLU of the "
                               "critics (not the paper's; the actor, and so the exported "
                               "policy, unchanged)")
  privileged_critics: bool = _f(False, doc="the critics also read the simulator's lane "
                                "state (obs['lane']: lateral offset / half lane width, "
                                "heading error in rad, distance to the row's end / 10 m), "
                                "an asymmetric actor-critic; the actor, and so the exported "
                                "policy, still sees only the depth and the state vector")
  reward_scale: float = _f(1.0, 1e-6, 1e6, doc="rewards are multiplied by this before the "
                           "replay (1: the paper; returns are logged unscaled)")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
  seed: int = _f(0, 0, 2**31 - 1)
  total_env_steps: int = _f(1_050_000, 1, 1 << 40)
  iters_per_chunk: int = _f(100, 1, 1 << 20, doc="iterations per chunk between host logs")
  conv_impl: str = _f("auto", choices=("auto", "xla", "shift", "native"),
                      doc="how the learner computes the conv tower (the same parameters "
                      "and numbers to float32 rounding; evaluation and export use XLA's): "
                      "native = the whole tower as the hand-written CPU kernel "
                      "(mjxvine.native, x86-64 Linux with a C++ compiler); shift = "
                      "XLA's convs but the first as a sum of slices; auto = native on the "
                      "CPU where it builds, else shift, and xla elsewhere")
  checkpoint_every_chunks: int = _f(10, 1, 1 << 20)
  init_from: str = _f("", doc="start from a trained agent: a policy file with its agent "
                      "file beside it (models/jackal.npz -> models/jackal.sac.npz) or the "
                      "agent file; its warm-up drives with that actor "
                      "(mjxvine.training.warm_start)")
  save_replay: bool = _f(False)
  num_seeds: int = _f(1, 1, 1024)
  sweep: str = _f("", doc="grid of hyper-parameters trained at once with the seeds (vmap), "
                  "e.g. 'sac.learning_rate=1e-4,1e-3; sac.alpha=0.1,0.2'")
  devices: int = _f(0, 0, 1 << 16, doc="devices the envs, replay and batches are split over "
                    "(0: all; see mjxvine.training.parallel)")
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
                          "validation worlds (test-kind worlds of seeds 100 and up, never "
                          "a test table's) among train.select_candidates evaluated "
                          "policies, the last first, after training, for each member "
                          "(mjxvine.evaluation.choice; writes their policies as "
                          "train.keep_eval_policies does; 0: the best fresh-start "
                          "evaluation is the best checkpoint)")
  select_candidates: int = _f(4, 1, 1024, doc="evaluated policies scored on the "
                              "validation worlds at most: the last, then (when it misses "
                              "the bar) the best others by the weaker direction's "
                              "fresh-start success, then the lower MAE")
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
  sensor: SensorConfig = SensorConfig()
  env: EnvConfig = EnvConfig()
  sac: SACConfig = SACConfig()
  train: TrainConfig = TrainConfig()
  eval: EvalConfig = EvalConfig()


def _yaml_value(key: str, text: str) -> Any:
  """A `--set` value (or a string where a number was due) read as YAML, by the rules of
  every YAML here (`robot_files.yaml_text`: YAML 1.2 scalars, no aliases)."""
  return robot_files.yaml_text(text, f"{key} = {short_repr(text)}", ConfigError)


def _coerce(key: str, value: Any, tp: Any, meta: dict) -> Any:
  """Converts `value` (from YAML or a `--set` string) to `tp`, checking its range."""
  origin = typing.get_origin(tp)
  if origin is tuple:
    if isinstance(value, str):
      value = _yaml_value(key, value)
    item_types = typing.get_args(tp)
    if not isinstance(value, (list, tuple)) or len(value) != len(item_types):
      raise ConfigError(f"{key} = {short_repr(value)}: expected a list of "
                        f"{len(item_types)} numbers")
    out = tuple(_coerce(key, v, t, meta) for v, t in zip(value, item_types))
    if any(a > b for a, b in zip(out, out[1:])):
      raise ConfigError(f"{key} = {list(out)}: the range must be increasing [min, max]")
    return out
  if isinstance(value, str) and tp is not str:
    value = _yaml_value(key, value)
  if tp is bool:
    if not isinstance(value, bool):
      raise ConfigError(f"{key} = {short_repr(value)}: expected true or false")
    return value
  if tp is int:
    if isinstance(value, bool) or not (isinstance(value, int) or
                                       (isinstance(value, float) and value.is_integer())):
      raise ConfigError(f"{key} = {short_repr(value)}: expected an integer")
    value = int(value)
  elif tp is float:
    if isinstance(value, str):  # YAML 1.1 reads "3e-4" (no dot) as a string
      try:
        value = float(value)
      except ValueError:
        pass
    if isinstance(value, bool) or not isinstance(value, (int, float)):
      raise ConfigError(f"{key} = {short_repr(value)}: expected a number")
    value = float(value)
    if not math.isfinite(value):
      raise ConfigError(f"{key} = {short_repr(value)}: expected a finite number")
  elif tp is str:
    value = str(value)
  lo, hi, choices = meta.get("lo"), meta.get("hi"), meta.get("choices")
  if choices is not None and value not in choices:
    raise ConfigError(f"{key} = {short_repr(value)}: must be one of {', '.join(choices)}")
  if lo is not None and not (lo <= value <= hi):
    raise ConfigError(f"{key} = {short_repr(value)}: must be in [{lo}, {hi}]")
  return value


def check_value(key: str, value: Any) -> Any:
  """`value` (a flag's text or number) as the config key `key` ("section.name") takes it:
  converted and range-checked by the key's own rule, or ConfigError ("key = value: ...").
  The flags that stand for a key go through it (`cli.key_type`): one rule for both."""
  section, _, name = key.partition(".")
  cls = typing.get_type_hints(Config)[section]
  field = {f.name: f for f in dataclasses.fields(cls)}[name]
  return _coerce(key, value, typing.get_type_hints(cls)[name], dict(field.metadata))


# Keys that earlier releases had, with the value that kept their behaviour off (the
# code's constant now). A config file or --set naming one is refused in one line; a run's
# or a policy's own recorded config (`load_config(base=...)`) drops it at that value.
RELEASE_WITH_REMOVED = "mjxvine 0.2.0 (commit df22916)"
REMOVED_KEYS = {
    "world.plant_slots": 0, "world.terrain_bump_m": 1.0, "world.terrain_cell_m": 0.25,
    "world.terrain_margin_m": 4.0, "world.test_seed": 0,
    "env.heading_target": "eor", "env.heading_lookahead_m": 2.0, "env.yaw_offset_deg": 0.0,
    "env.yaw_reference_jitter_deg": 20.0, "env.start_along": [0.0, 0.6],
    "env.start_directions": "both", "env.collision_margin_m": 0.05,
    "sac.lr_end_fraction": 1.0, "sac.tau_late_from": 0.25, "sac.log_std_min": -20.0,
    "sac.log_std_max": 2.0, "sac.compute_dtype": "float32", "sac.image_shift_px": 0,
    "sac.actor_mean_init_scale": 1.0, "sac.reuse_critic_features": False,
    "sac.eps_decay": 0.992, "sac.eps_budget_episodes": 1500.0,
    "train.chunk_loop": "auto", "train.select_world_seed": 100, "train.select_runs": 2,
    "train.select_success_bar": 0.95, "train.select_noise_factors": [8.0, 10.0],
    "world.trunk_radius_m": 0.04, "world.terrain_amplitude_m": 0.05,
    "camera.noise_sigma_m": 0.2, "camera.noise_clip_m": 0.5, "env.heading_weight": 0.6,
    "env.progress_weight": 35.0, "env.success_reward": 1000.0,
    "env.collision_reward": -500.0, "env.reverse_reward": -500.0,
    "env.yaw_limit_deg": 85.0, "env.success_radius_m": 0.4, "env.physics_dt": PHYSICS_DT_S,
    "world.jitter_frac": 0.1, "world.curve_amplitude_m": 0.7, "world.train_seed": 0,
    "robot.wheel_kv": 1.0, "robot.wheel_armature": 0.005, "robot.wheel_friction": 0.8,
    "camera.noise_factor": 1.0, "env.pose_reset_every": 10, "train.max_minutes": 0.0,
}
MOVED_KEYS = {"sac.conv_impl": "train.conv_impl"}


def _removed_key_error(key: str) -> ConfigError:
  if key in MOVED_KEYS:
    return ConfigError(f"{key}: renamed {MOVED_KEYS[key]} after {RELEASE_WITH_REMOVED}")
  return ConfigError(f"{key}: removed after {RELEASE_WITH_REMOVED}, which has it "
                     "(CHANGELOG.md, Removed: what to use instead)")


def _recorded(base: dict) -> dict:
  """A run's or a policy's recorded config with the keys of earlier releases dropped
  (at the value that kept them off) or moved; ConfigError for one that was on."""
  out = {s: dict(v) if isinstance(v, dict) else v for s, v in base.items()}
  for key, off in REMOVED_KEYS.items():
    section, name = key.split(".")
    if isinstance(out.get(section), dict) and name in out[section]:
      value = out[section].pop(name)
      if value != off and not (isinstance(value, (list, tuple)) and list(value) == off):
        raise ConfigError(f"{key} = {short_repr(value)}: the run was trained with a key "
                          f"removed after {RELEASE_WITH_REMOVED}, which reproduces it")
  for key, new in MOVED_KEYS.items():
    (section, name), (new_section, new_name) = key.split("."), new.split(".")
    if isinstance(out.get(section), dict) and name in out[section]:
      value = out[section].pop(name)
      if isinstance(out.setdefault(new_section, {}), dict):
        out[new_section].setdefault(new_name, value)
  return out


def _build(cls, data: dict, prefix: str):
  if not isinstance(data, dict):
    raise ConfigError(f"{prefix.rstrip('.') or 'config'}: expected a mapping, got "
                      f"{short_repr(data)}")
  hints = typing.get_type_hints(cls)
  names = {f.name: f for f in dataclasses.fields(cls)}
  for key in data:
    if key not in names and f"{prefix}{key}" in {**REMOVED_KEYS, **MOVED_KEYS}:
      raise _removed_key_error(f"{prefix}{key}")
    if key not in names:
      raise ConfigError(f"{prefix}{clean(str(key), 80)}: unknown key (known: "
                        f"{', '.join(names)})")
  kwargs = {}
  for name, field in names.items():
    tp, key = hints[name], prefix + name
    if dataclasses.is_dataclass(tp):
      kwargs[name] = _build(tp, data.get(name, {}) or {}, key + ".")
    elif name in data:
      kwargs[name] = _coerce(key, data[name], tp, dict(field.metadata))
  return cls(**kwargs)


def _check_cross_fields(cfg: Config) -> None:
  robot = cfg.robot.spec
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
  steps = cfg.env.control_dt / PHYSICS_DT_S
  if abs(steps - round(steps)) > 1e-6:
    raise ConfigError(f"env.control_dt = {cfg.env.control_dt}: must be a multiple of the "
                      f"physics step, {PHYSICS_DT_S} s")
  grid = parse_sweep(cfg.train.sweep)
  members = cfg.train.num_seeds * math.prod(len(v) for v in grid.values())
  if members > MAX_MEMBERS:
    raise ConfigError(f"train.sweep: {members} members with train.num_seeds = "
                      f"{cfg.train.num_seeds}; at most {MAX_MEMBERS} train at once")
  if cfg.train.video and cfg.eval.runs_after_train < 1:
    raise ConfigError("train.video = true: films the closing test-world runs, which need "
                      "eval.runs_after_train >= 1 (got 0)")
  if cfg.sac.anchor_weight > 0 and not cfg.train.init_from:
    raise ConfigError(f"sac.anchor_weight = {cfg.sac.anchor_weight}: pulls the actor "
                      "towards a loaded one, which needs train.init_from (--init)")
  rows = cfg.sac.buffer_size // cfg.env.num_envs
  if cfg.sac.n_step >= rows:
    raise ConfigError(f"sac.n_step = {cfg.sac.n_step}: must be below the steps per env "
                      f"that the replay holds (sac.buffer_size // env.num_envs = {rows})")


# Hyper-parameters that a vmapped sweep may vary (they live in the learner state).
SWEEPABLE = ("sac.learning_rate", "sac.alpha")
MAX_MEMBERS = 1024  # seeds x sweep grid trained at once (as train.num_seeds' bound)


def parse_sweep(text: str) -> dict[str, tuple[float, ...]]:
  """'sac.learning_rate=1e-4,1e-3; sac.alpha=0.1' -> {"sac.learning_rate": (1e-4, 1e-3),
  "sac.alpha": (0.1,)}; raises ConfigError naming train.sweep on a bad entry. Entries of
  one key combine their values ('sac.alpha=0.1; sac.alpha=0.2' is 'sac.alpha=0.1,0.2'), a
  value given again is dropped (it would train the same member twice); different keys
  make a grid."""
  out: dict[str, tuple[float, ...]] = {}
  for item in filter(None, (x.strip() for x in text.split(";"))):
    key, _, values = item.partition("=")
    key = key.strip()
    if key not in SWEEPABLE:
      raise ConfigError(f"train.sweep: {short_repr(key)} cannot be swept (sweepable: "
                        f"{', '.join(SWEEPABLE)})")
    try:
      vals = tuple(float(v) for v in values.split(","))
    except ValueError:
      raise ConfigError(f"train.sweep: {short_repr(item)}: expected {key}=v1,v2,...") from None
    if not all(math.isfinite(v) and v > 0 for v in vals):
      raise ConfigError(f"train.sweep: {short_repr(item)}: values must be positive numbers")
    out[key] = tuple(dict.fromkeys(out.get(key, ()) + vals))
  return out


def _set_nested(data: dict, dotted: str, value: str) -> None:
  parts = dotted.split(".")
  node = data
  for p in parts[:-1]:
    node = node.setdefault(p, {})
    if not isinstance(node, dict):
      raise ConfigError(f"{clean(dotted, 80)}: {clean(p, 80)} is not a section")
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
  `path` may also name a shipped experiment config (`resolve_config_path`). The file is
  read by the rules of every YAML here (`robot_files.load_yaml`: at most 1 MiB, nested at
  most 16 deep, no anchors or aliases, YAML 1.2 scalars)."""
  path = resolve_config_path(path)
  shown = clean(str(path))
  if not path.is_file():
    raise ConfigError(f"config file not found: {shown} (shipped configs: "
                      f"{', '.join(packaged_configs())})")
  data = robot_files.load_yaml(path, shown, ConfigError, "config")
  if data is None:
    # An empty file is more likely a mistake than a wish for the defaults (a 112x112
    # run with a multi-GB replay): "{}" says the latter.
    raise ConfigError(f"{shown}: empty (write {{}} to train the defaults)")
  if not isinstance(data, dict):
    raise ConfigError(f"{shown}: expected a mapping of sections (world:, env:, sac:, ...), "
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


def _lay_sensor_preset(data: dict, named: set[str]) -> None:
  """Fills the `sensor` keys with `data`'s preset's values: those missing, and, where the
  config file or --set names the preset (`named`: the sensor keys they name), every one
  they do not name (over a recorded run's values)."""
  sensor = data.get("sensor")
  if sensor is None:
    sensor = data["sensor"] = {}
  if not isinstance(sensor, dict):
    return  # _build names the fault
  preset = sensor.get("preset", SensorConfig.preset)
  if preset not in SENSOR_PRESETS:
    _coerce("sensor.preset", preset, str, {"choices": tuple(SENSOR_PRESETS)})  # raises
  for key, value in SENSOR_PRESETS[preset].items():
    if key not in sensor or ("preset" in named and key not in named):
      sensor[key] = list(value) if isinstance(value, tuple) else value


def load_config(path: str | Path | None = None, overrides: Sequence[str] = (),
                base: dict | None = None) -> Config:
  """Loads a config: defaults <- `base` (a mapping, e.g. a run's own config.yaml) <- YAML
  file at `path` <- the robot file's camera and velocity values (RobotConfig) <-
  `overrides` ("section.key=value")."""
  own = read_yaml(path) if path is not None else {}
  data: dict = _merged(_recorded(copy.deepcopy(base or {})), own)
  sets = []
  for item in overrides:
    if "=" not in item:
      raise ConfigError(f"--set {short_repr(item)}: expected section.key=value")
    key, value = item.split("=", 1)
    sets.append((key.strip(), value.strip()))
  _lay_robot_file(data, sets)
  for key, value in sets:
    _set_nested(data, key, value)
  named = {k.split(".", 1)[1] for k, _ in sets if k.startswith("sensor.")}
  if isinstance(own.get("sensor"), dict):
    named |= set(own["sensor"])
  _lay_sensor_preset(data, named)
  cfg = _build(Config, data, "")
  _check_cross_fields(cfg)
  return cfg


def load_run_config(path: str | Path, overrides: Sequence[str] = ()) -> Config:
  """A run's own recorded config.yaml (`path`) with `overrides`: read as a recorded config
  (`load_config(base=...)`), so that a run of an earlier release, whose file lists keys
  since removed at the values that kept them off, still loads."""
  return load_config(None, overrides, read_yaml(path))


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
    "read_yaml", "robot_spec", "check_value", "short_repr", "MAX_MEMBERS",
    "ROBOT_NAMES", "SWEEPABLE", "parse_sweep", "enable_compile_cache", "action_box",
    "changed_keys",
    "depth_input_scale",
]
