"""`python -m mjxvine.export`: a trained actor as a numpy-only .npz policy file, or ONNX.

    python -m mjxvine.export --checkpoint RUN_DIR [--out policy.npz] [--config FILE]
    python -m mjxvine.export --checkpoint RUN_DIR --which last      # not the best checkpoint
    python -m mjxvine.export --checkpoint RUN_DIR --format onnx [--out policy.onnx]
    python -m mjxvine.export --checkpoint policy.npz --format onnx   # convert a policy file

A run's checkpoint is RUN_DIR/checkpoints/best/<step>/ (the best one; --which best, the
default) or the newest RUN_DIR/checkpoints/<step>/ (--which last); a run without a best
checkpoint gives its last one (`mjxvine.rundir.checkpoints`). The run's config.yaml gives
the metadata; --config FILE and --set only override it, and not what the networks were
trained for (image size, depth range, network sizes, action box: `mjxvine.rundir.settings`).
Of a run that trained several members (--seeds, sweeps), --member K picks one (default:
the one checkpoints/best follows, member 0). The file format: `mjxvine.deploy.export`; the
ONNX graph: `mjxvine.deploy.onnx`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mjxvine import config as config_lib
from mjxvine.atomic import OutputError, check_output
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
  p = argparse.ArgumentParser(prog="python -m mjxvine.export", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--checkpoint", required=True,
                 help="run dir, its checkpoints/ dir or one orbax checkpoint step (see "
                      "--which); with --format onnx also an exported .npz policy file")
  p.add_argument("--which", choices=WHICH, default="best",
                 help="which checkpoint of a run: best (the highest step under "
                      "RUN/checkpoints/best/; the last step when the run has none) or "
                      "last (the newest step under RUN/checkpoints/). Default: best")
  p.add_argument("--format", choices=("npz", "onnx"), default="npz",
                 help="npz (numpy-only mjxvine.deploy) or onnx (needs the onnx package)")
  p.add_argument("--out", default=None,
                 help="output file (default RUN_DIR/policy.npz or RUN_DIR/policy.onnx; "
                      "for an .npz input, the same name with .onnx); written whole or not "
                      "at all, so a failed export keeps the previous file")
  p.add_argument("--member", type=int, default=None,
                 help="of a run that trained several members (--seeds, sweeps): which "
                      "one to export (default: the one checkpoints/best follows, "
                      "member 0)")
  p.add_argument("--preprocess", action="store_true",
                 help="onnx: in the graph, map invalid depth (NaN, inf, <= 0) to the "
                      "maximum range (or --invalid-depth) and clip to [0, max_depth]")
  p.add_argument("--invalid-depth", type=float, default=None, metavar="M",
                 help="with --preprocess: what invalid pixels become, metres (default: "
                      "the camera's max_depth_m, as the simulator renders no return)")
  config_lib.add_config_args(p)
  return p


def _write(write, out: Path, what: str) -> int | None:
  """Runs `write()`; a failed write (a full disk, ...) is one line and exit 4."""
  try:
    write()
  except OSError as e:
    return _fail(f"could not write {out} ({e.strerror or type(e).__name__}); {what}",
                 EXIT_WRITE)
  return None


def convert_file(args, src: Path) -> int:
  """An .npz policy file -> its ONNX graph."""
  if src.suffix != ".npz":
    return _fail(f"--checkpoint {src}: a file, but not an .npz policy file (give a run "
                 "directory, or an .npz written by python -m mjxvine.export)")
  if args.format != "onnx":
    return _fail(f"{src} is a file; an .npz policy converts only to --format onnx")
  out = Path(args.out) if args.out else src.with_suffix(".onnx")
  try:
    check_output(out, "--out")
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
  if args.out:
    try:
      check_output(args.out, "--out")
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
    check_output(out, "--out")
    if args.format == "onnx":
      arrays = actor_arrays(actor, meta)
      write = lambda: export_onnx(arrays, out, preprocess=args.preprocess,
                                  invalid_depth=args.invalid_depth)
    else:
      write = lambda: export_actor(actor, out, meta)
    failed = _write(write, out, "any previous file there is unchanged")
  except OutputError as e:
    return _fail(str(e))
  except ValueError as e:  # no conv tower, or arrays that do not fit the metadata
    return _fail(f"{item}: {e}")
  if failed is None:
    print(f"wrote {out} (from {item}, config {source})", file=sys.stderr)
  return failed or 0


def main(argv=None) -> int:
  """The CLI. Exit codes: 0 written, 2 a bad argument or input (one line), 4 a failed
  write (the previous file, if any, unchanged)."""
  p = parser()
  args = p.parse_args(argv)
  if args.invalid_depth is not None and not args.preprocess:
    p.error("--invalid-depth: give --preprocess too")
  src = Path(args.checkpoint)
  return convert_file(args, src) if src.is_file() else export_run(args, src)


if __name__ == "__main__":
  sys.exit(main())
