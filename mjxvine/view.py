"""Watch a policy drive, live, in MuJoCo's interactive viewer.

    python -m mjxvine.view --policy runs/RUN                       # lane 1F of the test world
    python -m mjxvine.view --policy policy.npz --world test --lane 4R
    python -m mjxvine.view --policy oracle --world train --lane 2F --noise 0
    python -m mjxvine.view --policy oracle --robot husky --lane 3R

The policy drives one env with the evaluator's own stepping (`rollout.drive`: the same
reset, policy call and control step as the protocol, one env), in real time
(one control step per `env.control_dt` of wall clock, when the machine keeps up); each
pose is shown in `mujoco.viewer.launch_passive`. When an episode ends the outcome is
printed and, after a pause, the lane starts again (close the window or Ctrl-C to stop).
A run directory brings its own config.yaml, as in `mjxvine.evaluate`; --robot drives
another robot, as there. The viewer needs a
display; without one the CLI says so in one line (`evaluate --video` films headless).
On macOS run it with `mjpython` (MuJoCo's launcher for the passive viewer).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from mjxvine.cli import (CommandParser, add_policy_args, input_error, key_type, member_error,
                         seed_type)
from mjxvine.rundir.checkpoints import WHICH

NO_DISPLAY = ("no display: the interactive viewer needs a desktop session (DISPLAY or "
              "WAYLAND_DISPLAY); to watch a run headless, film it: python -m mjxvine.evaluate "
              "--policy P --video --video-lanes 1F --out OUT")


def has_display() -> bool:
  """Whether a window can be opened (Linux: an X or Wayland display; elsewhere assumed)."""
  if sys.platform != "linux":
    return True
  return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _world(spec: str, cfg):
  """--world: "test" (the config's test world), "train" (its first training world), a
  test-world seed, a world .json file or a vineyard file (.geojson, .csv)."""
  from mjxvine.worlds import TEST_WORLD_SEED, generate_world, make_world, world_of
  if spec == "test":
    return make_world(str(TEST_WORLD_SEED), cfg.world)
  if spec == "train":
    return generate_world("train", 0, cfg.world)
  return world_of(spec, cfg)


def parser() -> argparse.ArgumentParser:
  """The command line's flags."""
  p = CommandParser(prog="python -m mjxvine.view", description=__doc__)
  add_policy_args(p, WHICH)
  p.add_argument("--world", default="test", metavar="test|train|SEED|FILE",
                 help="test (default), train, a test-world seed, a world .json file or a "
                      "vineyard file (.geojson, .csv: docs/your-vineyard.md)")
  p.add_argument("--lane", default="1F", help="lane and direction, e.g. 4R (default 1F)")
  p.add_argument("--noise", type=key_type("eval.noise_factor"), default=None,
                 help="depth noise factor, 0-100 (default: the config's eval.noise_factor, "
                 "which it stands for)")
  p.add_argument("--seed", type=seed_type, default=0, metavar="N",
                 help="seed of the episodes' random draws: their depth noise and the random "
                      "policy's actions, new for each repeat of the lane; the start is fixed "
                      "(default 0)")
  p.add_argument("--once", action="store_true", help="drive the lane once, then exit")
  from mjxvine.config import add_config_args
  add_config_args(p)
  return p


def load(args):
  """(env, policy, its name, config source, world, (lane, direction)) of the flags; the
  env has the one world and the protocol's episode limit."""
  from mjxvine.config import replace
  from mjxvine.env import VineyardEnv
  from mjxvine.evaluation.policies import check_policy_file, load_policy
  from mjxvine.evaluation.rollout import parse_lanes
  from mjxvine.rundir.settings import policy_config
  if args.policy not in ("oracle", "random"):
    check_policy_file(args.policy, args.which)
  extra = [f"robot.name={args.robot}"] if args.robot else []  # as evaluate applies it
  cfg, source = policy_config(args.policy, args.config, [*extra, *args.overrides],
                              args.which)
  world = _world(args.world, cfg)
  ((lane, direction),) = parse_lanes(args.lane, len(world.lanes))
  noise = cfg.eval.noise_factor if args.noise is None else args.noise
  cfg = replace(cfg, env={"max_steps": cfg.eval.max_steps})  # per lane: `lanes.lane_steps`
  env = VineyardEnv(cfg, [world], noise_factor=noise)
  policy, name = load_policy(args.policy, env, args.which, args.member)
  return env, policy, name, source, world, (lane, direction)


def watch(env, policy, lane: int, direction: str, seed: int, once: bool) -> int:
  """Shows `policy` driving `lane` in `direction` in the passive viewer, in real time,
  again and again (`once`: one episode) until the window is closed."""
  import jax
  import mujoco
  import mujoco.viewer

  from mjxvine.env import OUTCOMES
  from mjxvine.evaluation.rollout import drive
  model = env.mj_model
  data = mujoco.MjData(model)
  dt = env.cfg.env.control_dt
  key = jax.random.PRNGKey(seed)
  with mujoco.viewer.launch_passive(model, data) as viewer:
    # a camera that follows the robot (the body of the free joint); the mouse still moves it
    viewer.cam.type = mujoco.mjtCamera.mjCAMERA_TRACKING
    viewer.cam.trackbodyid = int(model.jnt_bodyid[0])
    viewer.cam.distance, viewer.cam.elevation = 4.0, -25.0
    while viewer.is_running():
      key, k = jax.random.split(key)
      t_next, steps, code = time.perf_counter(), 0, 0
      for qpos, action, code in drive(env, policy, lane, direction, k):
        if not viewer.is_running():
          return 0
        data.qpos[:] = qpos
        mujoco.mj_forward(model, data)
        viewer.sync()
        steps += 1
        t_next += dt
        time.sleep(max(0.0, t_next - time.perf_counter()))
      print(f"lane {lane}{direction}: {OUTCOMES[code]} after {steps - 1} steps "
            f"({(steps - 1) * dt:.1f} s)", file=sys.stderr, flush=True)
      if once:
        return 0
      time.sleep(2.0)
  return 0


def main(argv=None) -> int:
  p = parser()
  args = p.parse_args(argv)  # --noise is checked as eval.noise_factor here
  if not has_display():  # before anything is built: one line
    print(f"error: {NO_DISPLAY}", file=sys.stderr)
    return 2
  if member_error(args.policy, args.member):
    p.error(member_error(args.policy, args.member))

  from mjxvine.config import ConfigError, enable_compile_cache
  from mjxvine.deploy import PolicyError
  enable_compile_cache()
  try:
    env, policy, name, source, world, (lane, direction) = load(args)
  except (ConfigError, PolicyError, FileNotFoundError, ValueError) as e:
    return input_error(e)
  print(f"{name} (config: {source}) on lane {lane}{direction} of the {world.kind} world; "
        f"compiling the step (a minute on a CPU)...", file=sys.stderr, flush=True)
  return watch(env, policy, lane, direction, args.seed, args.once)


if __name__ == "__main__":
  from mjxvine.atomic import command_main
  # SIGINT / SIGTERM: 130 / 143 in one line, the outputs of the unfinished set removed
  command_main(main)
