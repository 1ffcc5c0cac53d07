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
the numbers). --which picks the policy of a run dir: best (default; its chosen
selected.npz where the choice wrote one, else its best checkpoint) or last.

A run dir brings its own config.yaml (an .npz its metadata): camera, networks, world and
env options; --config/--set only override, never what the networks need
(`mjxvine.rundir.settings`). --member K picks a member of a --num-seeds run (default: the
one checkpoints/best follows). --video films the first run of each lane-direction to
OUT/videos/ (`mjxvine.evaluation.video`). The library is `mjxvine.evaluation`.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path

from mjxvine.atomic import check_output
from mjxvine.cli import (CommandParser, add_policy_args, input_error, key_type, member_error,
                         seed_type)
from mjxvine.config import (SENSOR_PRESETS, ConfigError, WorldConfig, add_config_args,
                            enable_compile_cache)
# One error class for every policy problem (`deploy.PolicyFormatError` is a subclass).
from mjxvine.deploy import PolicyError
from mjxvine.evaluation import paper, realism, video
from mjxvine.evaluation.policies import check_policy_file
from mjxvine.evaluation.report import results_markdown, write_results
from mjxvine.evaluation.rollout import (PolicySource, Protocol, all_lanes, parse_lanes,
                                        run_protocol)
from mjxvine.evaluation.video import RenderError, VideoFormat, write_videos
from mjxvine.rundir.checkpoints import WHICH
from mjxvine.rundir.settings import policy_config
from mjxvine.worlds import TEST_WORLD_SEED, world_of


SEASONS = next(f.metadata["choices"] for f in dataclasses.fields(WorldConfig)
               if f.name == "season")


def _size(text: str) -> tuple[int, int]:
  """"480x360" -> (480, 360): even sizes (what H.264 in yuv420p needs), 32..2048 px."""
  try:
    w, h = (int(v) for v in text.lower().split("x"))
  except ValueError:
    raise argparse.ArgumentTypeError(f"{text!r}: expected WIDTHxHEIGHT, e.g. 480x360") from None
  if not (32 <= w <= 2048 and 32 <= h <= 2048 and w % 2 == 0 and h % 2 == 0):
    raise argparse.ArgumentTypeError(f"{text!r}: width and height must be even, 32..2048")
  return w, h


def parser() -> argparse.ArgumentParser:
  """The command line's flags."""
  p = CommandParser(prog="python -m mjxvine.evaluate", description=__doc__)
  add_policy_args(p, WHICH)
  p.add_argument("--noise", type=key_type("eval.noise_factor"), default=None,
                 help="depth noise factor, 0-100 (default: the config's eval.noise_factor, "
                 "which it stands for)")
  p.add_argument("--runs", type=key_type("eval.runs"), default=None,
                 help="runs per lane and direction, 1-1000 as eval.runs (default: the "
                 "config's eval.runs)")
  p.add_argument("--world", default=None, metavar="SEED|FILE",
                 help="test-world seed, a saved world .json or a vineyard file (.geojson "
                 "rows in longitude/latitude, .csv plants in metres: docs/your-vineyard.md; "
                 "every lane, both directions). Default: test world 0")
  p.add_argument("--sweep", choices=("noise", "robots", "rows"), default=None,
                 help="noise, robots: the paper's robustness tables; rows: generated test "
                      "worlds with 80 m rows 1.8-3.0 m apart on slopes of 0-10 %% "
                      "(mjxvine.evaluation.rows; --runs, default 1)")
  p.add_argument("--suite", choices=("paper", "realism"), default=None,
                 help="paper: the paper's whole evaluation (test worlds 0-3 with --runs, "
                      "default 5; the noise and robot tests) in one report "
                      "(mjxvine.evaluation.suite); realism: test worlds 0-3 (and the "
                      "--world vineyard file's block, 2 runs per lane-direction) under each "
                      "factor of the field alone, each season and all together "
                      "(mjxvine.evaluation.realism, docs/sim-to-real.md)")
  p.add_argument("--condition", choices=tuple(realism.CONDITIONS), default=None,
                 help="drive under one of the realism suite's conditions (its config "
                      "values; --set still overrides)")
  p.add_argument("--sensor", choices=tuple(SENSOR_PRESETS), default=None,
                 help="the depth sensor: ideal, d435, d455 (sensor.preset, with the "
                      "preset's values)")
  p.add_argument("--season", choices=SEASONS, default=None,
                 help="the vineyard's season (world.season): classic, spring, summer, winter, "
                      "mixed")
  p.add_argument("--past-end", action="store_true",
                 help="drive every lane on 3 m past its end into the headland and report "
                      "where the end-of-row detector stopped (results.json's row_end: "
                      "docs/evaluation.md, The end of the row)")
  p.add_argument("--seed", type=seed_type, default=0, metavar="N",
                 help="seed of the runs' random draws: their depth noise (the runs of a "
                      "lane differ by it) and the random policy's actions; the starts are "
                      "fixed (default 0)")
  p.add_argument("--out", required=True, metavar="DIR",
                 help="output directory, made if missing: results.json, results.md and "
                      "trajectories.png (--sweep: its <sweep>.md/.json/.png; --suite: "
                      "report.md/.json), videos/; never over an input file, nor inside the "
                      "--policy run directory")
  v = p.add_argument_group("videos (OUT/videos/<lane><dir>.mp4; MuJoCo's renderer, headless "
                           "with EGL or OSMesa)")
  v.add_argument("--video", action="store_true",
                 help="an MP4 of the first run of each lane-direction (or --video-lanes)")
  v.add_argument("--gif", action="store_true", help="a GIF of each (every 4th frame, 320 px "
                 "wide: for a README); with --video as well as the MP4")
  v.add_argument("--video-lanes", default=None, metavar="1F,4R",
                 help="the lane-directions to film (default: all of them)")
  v.add_argument("--video-size", type=_size, default=(480, 360), metavar="WxH",
                 help="frame size in pixels (default 480x360)")
  v.add_argument("--video-fps", type=float, default=None,
                 help="frames per second of the file (default: twice real time, 20)")
  add_config_args(p)
  return p


def check_args(p: argparse.ArgumentParser, args) -> None:
  """Exits with `p.error` (status 2, one line) on values or combinations that cannot run
  (--runs and --noise are checked as their config keys while parsing: `cli.key_type`)."""
  if args.video_fps is not None and not (args.video_fps > 0 and math.isfinite(args.video_fps)):
    p.error(f"--video-fps {args.video_fps}: must be a finite number > 0")
  if member_error(args.policy, args.member):
    p.error(member_error(args.policy, args.member))
  filming = args.video or args.gif
  if filming and (args.sweep or args.suite):
    p.error("--video/--gif film the protocol's runs, not a --sweep or --suite")
  if args.sweep and args.suite:
    p.error("--sweep and --suite: choose one (the paper suite includes both sweeps)")
  if args.suite == "realism" and (args.condition or args.sensor or args.season):
    p.error("--suite realism sets its own conditions: drop --condition, --sensor, --season")
  if args.past_end and (args.sweep or args.suite):
    p.error("--past-end drives the protocol's runs: drop --sweep / --suite")
  if args.video_lanes and not filming:
    p.error("--video-lanes: give --video or --gif too")


def say(message: str) -> None:
  """A progress line on stderr (stdout has the tables)."""
  print(message, file=sys.stderr, flush=True)


def run_suite(cfg, args, out: Path) -> None:
  from mjxvine.evaluation.suite import paper_suite
  say(f"evaluating {args.policy}: the paper's suite (compiling first)...")
  paper_suite(cfg, args.policy, out, runs=args.runs or paper.RUNS, seed=args.seed,
              which=args.which, member=args.member)
  print((out / "report.md").read_text())


def run_realism(cfg, args, out: Path) -> None:
  block = args.world if args.world and not args.world.isdigit() else None
  say(f"evaluating {args.policy}: the realism suite, {len(realism.CONDITIONS)} conditions "
      "(a compilation each)...")
  realism.realism_suite(cfg, PolicySource(args.policy, args.which, args.member), out,
                        realism.SuiteRuns(args.runs or paper.RUNS, block=block,
                                          seed=args.seed), say=say)
  print((out / "report.md").read_text())


def condition_overrides(args) -> list[str]:
  """The --set values that --condition, --sensor and --season stand for (before --set)."""
  sets = []
  if args.condition:
    for section, values in realism.CONDITIONS[args.condition].items():
      sets += [f"{section}.{k}={list(v) if isinstance(v, tuple) else v}"
               for k, v in values.items()]
  if args.sensor:
    sets.append(f"sensor.preset={args.sensor}")  # the preset fills the other sensor keys
  if args.season:
    sets.append(f"world.season={args.season}")
  return sets


def run_sweep(cfg, args, world, out: Path) -> None:
  from mjxvine.evaluation import sweeps
  if args.sweep == "rows":
    from mjxvine.evaluation.rows import sweep_rows
    say(f"evaluating {args.policy} on long rows (one compilation per grid point)...")
    sweep_rows(cfg, PolicySource(args.policy, args.which, args.member), out,
               runs=args.runs or 1, seed=args.seed, say=say)
    print((out / "rows.md").read_text())
    return
  sweep = sweeps.sweep_noise if args.sweep == "noise" else sweeps.sweep_robots
  sweep(cfg, args.policy, world, out, args.seed, args.which, args.member)
  print((out / f"{args.sweep}.md").read_text())


def run_tables(cfg, source: str, args, world, out: Path) -> None:
  """The protocol on `world`: results.* under `out`, the table on stdout, and the videos."""
  filming = args.video or args.gif
  noise = cfg.eval.noise_factor if args.noise is None else args.noise
  runs = cfg.eval.runs if args.runs is None else args.runs
  lanes = parse_lanes(args.video_lanes, len(world.lanes)) if args.video_lanes else \
      all_lanes(world)
  say(f"evaluating {args.policy} (config: {source}): {len(world.lanes) * 2 * runs} runs "
      f"on the {world.kind} world (compiling first)...")
  doc, tracks = run_protocol(cfg, PolicySource(args.policy, args.which, args.member), world,
                             Protocol(runs, noise, seed=args.seed, past_end=args.past_end),
                             video=lanes if filming else ())
  write_results(doc, world, out)
  print(results_markdown(doc))
  if tracks:
    say(f"rendering {len(tracks)} video(s) to {out / 'videos'}/ ...")
    write_videos(tracks, world, cfg, out / "videos",
                 VideoFormat(args.video, args.gif, args.video_fps, args.video_size), say=say)


# what evaluate may write in --out (every mode's: a file read from there may be none of them)
WRITES = ("results.json", "results.md", "trajectories.png", "videos/", "report.json",
          "report.md", *(f"world{s}/" for s in paper.SUITE_WORLDS),
          *(f"{sweep}.{ext}" for sweep in ("noise", "robots", "rows")
            for ext in ("md", "json", "png")))


def _inputs(args) -> list[tuple]:
  """(path, what) of the files and run directory the flags name (`outputs.check_not_input`):
  --out may write over none of them."""
  from mjxvine.rundir.checkpoints import run_dir_of
  policy = Path(args.policy)
  run = run_dir_of(policy) or (policy.parent if policy.name == "checkpoints" else policy)
  return [(run, "the run directory of --policy") if run.is_dir() else
          (policy, "the --policy file"), (args.world, "the --world file"),
          (args.config, "the --config file"), (args.robot, "the --robot file")]


def run(args) -> int:
  """What the checked flags ask for; 2 with one line on stderr when it cannot be done."""
  extra = [f"robot.name={args.robot}"] if args.robot else []
  extra += condition_overrides(args)
  try:
    if args.policy not in ("oracle", "random"):  # fail before the worlds are built
      check_policy_file(args.policy, args.which)
    try:
      cfg, source = policy_config(args.policy, args.config, [*extra, *args.overrides],
                                  args.which)
    except ConfigError as e:
      return input_error(e)
    world = world_of(args.world or str(TEST_WORLD_SEED), cfg)
    if args.video_lanes:  # a bad lane is one line before anything is built
      parse_lanes(args.video_lanes, len(world.lanes))
    if args.video or args.gif:  # before the rollout: no GL, no ffmpeg is one line
      video.choose_gl()
      if args.video:
        video.check_mp4()
    out = check_output(args.out, "--out", directory=True,  # before the first rollout
                       inputs=_inputs(args), writes=WRITES)
    if args.suite == "paper":
      run_suite(cfg, args, out)
    elif args.suite == "realism":
      run_realism(cfg, args, out)
    elif args.sweep:
      run_sweep(cfg, args, world, out)
    else:
      run_tables(cfg, source, args, world, out)
  except (PolicyError, FileNotFoundError, ValueError, RenderError) as e:  # OutputError too
    return input_error(e)
  return 0


def main(argv=None) -> int:
  p = parser()
  args = p.parse_args(argv)
  enable_compile_cache()
  check_args(p, args)
  return run(args)


if __name__ == "__main__":
  from mjxvine.atomic import command_main
  # SIGINT / SIGTERM: 130 / 143 in one line, the outputs of the unfinished set removed
  command_main(main)
