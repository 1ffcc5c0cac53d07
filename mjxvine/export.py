"""`python -m mjxvine.export`: a trained actor as a numpy-only .npz policy file, or ONNX.

    python -m mjxvine.export --policy RUN_DIR [--out policy.npz] [--config FILE]
    python -m mjxvine.export --policy RUN_DIR --which last      # not the best checkpoint
    python -m mjxvine.export --policy RUN_DIR --format onnx [--out policy.onnx]
    python -m mjxvine.export --policy policy.npz --format onnx   # convert a policy file

A run's best policy (--which best, the default) is the one its choice of checkpoint wrote
(RUN_DIR/selected.npz) where there is one, else RUN_DIR/checkpoints/best/<step>/; --which
last is the newest RUN_DIR/checkpoints/<step>/; a run without a best checkpoint gives its
last one (`mjxvine.rundir.checkpoints`). The run's config.yaml gives the metadata;
--config FILE and --set only override it, and not what the networks were trained for
(image size, depth range, network sizes, action box: `mjxvine.rundir.settings`). Of a run
that trained several members (--num-seeds, sweeps), --member K picks one (default: the
one checkpoints/best follows, member 0). The file format: `mjxvine.deploy.export`; the
ONNX graph: `mjxvine.deploy.onnx`. Beside an .npz it writes the policy's agent file
(`<name>.sac.npz`: critics, targets and temperature too, what `train --init` continues
from; `mjxvine.agent_file`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mjxvine import config as config_lib
from mjxvine.agent_file import agent_path, checkpoint_agent, write_agent
from mjxvine.atomic import OutputError, check_output, write_bytes
from mjxvine.cli import MEMBER_HELP, WHICH_HELP, CommandParser, member_error, member_type
from mjxvine.deploy.export import actor_arrays, check_actor_fits, export_actor, meta_from_config
from mjxvine.deploy.numpy_policy import PolicyError
from mjxvine.deploy.onnx import export_onnx
from mjxvine.rundir import EXIT_USAGE, EXIT_WRITE, run_record
from mjxvine.rundir.checkpoints import WHICH, restore_actor_params, run_dir_of
from mjxvine.rundir.settings import policy_config


def _fail(message: str, code: int = EXIT_USAGE) -> int:
  """One line on stderr; exit 2 for usage and input errors (argparse's), 4 for a failed
  write."""
  print(f"export error: {message}", file=sys.stderr)
  return code


def parser() -> argparse.ArgumentParser:
  p = CommandParser(prog="python -m mjxvine.export", description=__doc__)
  p.add_argument("--policy", required=True, metavar="RUN|FILE",
                 help="a run dir, its checkpoints/ dir or one orbax checkpoint step (see "
                      "--which); with --format onnx also an exported .npz policy file")
  p.add_argument("--which", choices=WHICH, default="best", help=WHICH_HELP)
  p.add_argument("--member", type=member_type, default=None, metavar="K", help=MEMBER_HELP)
  p.add_argument("--out", default=None, metavar="FILE",
                 help="output file, .npz or .onnx as the format (default RUN_DIR/policy.npz "
                      "or RUN_DIR/policy.onnx; for an .npz input, the same name with .onnx); "
                      "never an input (the policy file, the run directory's files); written "
                      "whole or not at all, so a failed export keeps the previous file")
  p.add_argument("--format", choices=FORMATS, default=None,
                 help="npz (numpy-only mjxvine.deploy) or onnx (needs the onnx package); "
                      "default: --out's suffix, else npz")
  p.add_argument("--preprocess", action="store_true",
                 help="onnx: in the graph, map invalid depth (NaN, inf, <= 0) to the "
                      "maximum range (or --invalid-depth) and clip to [0, max_depth]")
  p.add_argument("--invalid-depth", type=float, default=None, metavar="M",
                 help="with --preprocess: what invalid pixels become, metres (default: "
                      "the camera's max_depth_m, as the simulator renders no return)")
  config_lib.add_config_args(p)
  return p


FORMATS = ("npz", "onnx")


def out_format(out: str | None, fmt: str | None) -> str:
  """The output's format: --out's suffix (.npz, .onnx) and --format agreeing, either one
  alone, else npz. ValueError (one line) for another suffix or a conflict: an .onnx name
  holding an .npz file is read as what it is not."""
  if out is None or Path(out).is_dir():  # (a directory: check_output says so)
    return fmt or "npz"
  suffix = Path(out).suffix
  if suffix[1:] not in FORMATS:
    raise ValueError(f"--out {out}: give a .npz or .onnx file name (its suffix says the "
                     "format)")
  if fmt is not None and fmt != suffix[1:]:
    raise ValueError(f"--out {out}: a {suffix} name, but --format {fmt}: give a .{fmt} name "
                     f"or --format {suffix[1:]}")
  return suffix[1:]


def _run_of(src: Path) -> Path:
  """The run directory that --policy SRC (a run, its checkpoints/ or a step) lies in."""
  return run_dir_of(src) or (src.parent if src.name == "checkpoints" else src)


def _write(write, out: Path, what: str) -> int | None:
  """Runs `write()`; a failed write (a full disk, ...) is one line and exit 4."""
  try:
    write()
  except OSError as e:
    return _fail(f"could not write {out} ({e.strerror or type(e).__name__}); {what}",
                 EXIT_WRITE)
  return None


def convert_file(args, src: Path) -> int:
  """An .npz policy file -> its ONNX graph (as the file is: flags that would change or
  pick something else are refused, not ignored)."""
  if src.suffix != ".npz":
    return _fail(f"--policy {src}: a file, but not an .npz policy file (give a run "
                 "directory, or an .npz written by python -m mjxvine.export)")
  if args.format != "onnx":
    return _fail(f"{src} is a file; an .npz policy converts only to --format onnx")
  if args.config or args.overrides:
    return _fail(f"--config/--set: {src} converts to ONNX as it is (its metadata is its "
                 "config); they apply to a run directory's export")
  if member_error(str(src), args.member):
    return _fail(member_error(str(src), args.member))
  if args.which != "best":
    return _fail(f"--which {args.which}: a policy file is one policy; --which picks a run "
                 "directory's checkpoint")
  out = Path(args.out) if args.out else src.with_suffix(".onnx")
  try:
    check_output(out, "--out", inputs=[(src, "the --policy file")])
  except OutputError as e:
    return _fail(str(e))
  try:
    failed = _write(lambda: export_onnx(src, out, preprocess=args.preprocess,
                                        invalid_depth=args.invalid_depth),
                    out, "any previous file there is unchanged")
  except PolicyError as e:
    return _fail(str(e))
  if failed is None:
    print(f"wrote {out} (from {src})", file=sys.stderr)
  return failed or 0


def export_run(args, src: Path) -> int:
  """A run's checkpoint -> a policy file (.npz or ONNX), checked against its config."""
  if not src.exists():
    return _fail(f"no such {'policy file' if src.suffix == '.npz' else 'run directory'}: {src}")
  run = _run_of(src)
  # never over what it reads: in the run directory only its own policy.npz / .onnx
  inputs = dict(inputs=[(run, "the run directory of --policy"),
                        (args.config, "the --config file")],
                own=[run / f"policy.{f}" for f in FORMATS])
  if args.out:
    try:
      check_output(args.out, "--out", **inputs)
    except OutputError as e:
      return _fail(str(e))
  try:
    actor, item = restore_actor_params(src, args.which, args.member)
    # the run's own config.yaml (image size, FOVs, action box); --config/--set override
    cfg, source = policy_config(src, args.config, args.overrides, args.which)
    check_actor_fits(actor, cfg)
  except config_lib.ConfigError as e:
    print(f"config error: {e}", file=sys.stderr)
    return EXIT_USAGE
  except (FileNotFoundError, KeyError, ValueError) as e:  # no, or a damaged, checkpoint
    return _fail(e.args[0] if e.args else str(e))  # a KeyError's str() is quoted
  run_dir = run_dir_of(item) or (src if (src / "config.yaml").is_file() else None)
  out = Path(args.out) if args.out else (run_dir or src) / f"policy.{args.format}"
  meta = meta_from_config(cfg)
  tower = run_record(run_dir).get("conv_tower") if run_dir else None
  if tower:  # the tower it trained with, as its run recorded it
    meta["conv_tower"] = tower
  try:
    check_output(out, "--out", **inputs)
    if args.format == "onnx":
      arrays = actor_arrays(actor, meta)
      write = lambda: export_onnx(arrays, out, preprocess=args.preprocess,
                                  invalid_depth=args.invalid_depth)
    else:
      write = lambda: _export_with_agent(actor, out, meta, item, args.member)
    failed = _write(write, out, "any previous file there is unchanged")
  except OutputError as e:
    return _fail(str(e))
  except ValueError as e:  # no conv tower, or arrays that do not fit the metadata
    return _fail(f"{item}: {e}")
  if failed is None:
    print(f"wrote {out} (from {item}, config {source})", file=sys.stderr)
  return failed or 0


def _export_with_agent(actor, out: Path, meta: dict, item: Path, member) -> None:
  """The policy file, and beside it its agent file (`mjxvine.agent_file`: what `train
  --init` continues from): the chosen policy's, copied, or the orbax checkpoint's. Where
  there is none, an agent file left there by an earlier export is removed: it belongs to
  another policy."""
  export_actor(actor, out, meta)
  agent, why = agent_path(out), None
  if item.suffix == ".npz":  # RUN/selected.npz: its agent file where the run wrote one
    if agent_path(item).is_file():
      write_bytes(agent, agent_path(item).read_bytes())
    else:
      why = f"{item} has none beside it"
  else:
    try:
      write_agent(agent, checkpoint_agent(item, member), meta)
    except ValueError as e:  # a checkpoint of the actor alone (release 0.2.0)
      why = str(e)
  if why is None:
    print(f"wrote {agent} (the agent file: train --init continues from it)", file=sys.stderr)
  elif agent.is_file():
    agent.unlink()
    print(f"no agent file ({why}): removed the earlier {agent}", file=sys.stderr)


def main(argv=None) -> int:
  """The CLI. Exit codes: 0 written, 2 a bad argument or input (one line), 4 a failed
  write (the previous file, if any, unchanged)."""
  p = parser()
  args = p.parse_args(argv)
  if args.invalid_depth is not None and not args.preprocess:
    p.error("--invalid-depth: give --preprocess too")
  try:
    args.format = out_format(args.out, args.format)
  except ValueError as e:
    return _fail(str(e))
  src = Path(args.policy)
  return convert_file(args, src) if src.is_file() else export_run(args, src)


if __name__ == "__main__":
  from mjxvine.atomic import command_main
  # SIGINT / SIGTERM: 130 / 143 in one line, the outputs of the unfinished set removed
  command_main(main)
