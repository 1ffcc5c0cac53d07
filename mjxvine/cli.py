"""What the command lines (`python -m mjxvine.<command>`) share: how a parser is made,
and the help of the flags that several commands take, so that one flag means one thing."""

from __future__ import annotations

import argparse
from pathlib import Path


class CommandParser(argparse.ArgumentParser):
  """An `ArgumentParser` that takes a long option only by its whole name (`--see` is not
  `--seed`: an abbreviation would silently change meaning when a flag is added) and prints
  its description as written (a module docstring's usage examples). Sub-command parsers
  (`add_subparsers`) are made of this class too, so they inherit both."""

  def __init__(self, *args, **kwargs):
    kwargs.setdefault("allow_abbrev", False)
    kwargs.setdefault("formatter_class", argparse.RawDescriptionHelpFormatter)
    super().__init__(*args, **kwargs)


def key_type(key: str):
  """An argparse `type` for a flag that stands for the config key `key`: its value is
  converted and range-checked as the key's (`config.check_value`), so that a flag and its
  key take the same values; a bad one is argparse's error line (exit 2)."""
  def convert(text: str):
    from mjxvine.config import ConfigError, check_value  # config reads the robot files
    try:
      return check_value(key, text)
    except ConfigError as e:
      raise argparse.ArgumentTypeError(str(e)) from None
  convert.__name__ = key  # argparse's name for it
  return convert


def int_range(lo: int, hi: int):
  """An argparse `type`: a decimal integer in [lo, hi] (flags that stand for no key)."""
  def convert(text: str) -> int:
    from mjxvine.robot_files import short_repr
    try:
      value = int(text, 10)
    except ValueError:
      raise argparse.ArgumentTypeError(f"{short_repr(text)}: expected an integer") from None
    if not lo <= value <= hi:
      raise argparse.ArgumentTypeError(f"{value}: must be in [{lo}, {hi}]")
    return value
  convert.__name__ = "integer"
  return convert


MAX_MEMBER = 1023  # members are 0-based, at most config.MAX_MEMBERS of them
member_type = int_range(0, MAX_MEMBER)  # --member K of evaluate, view, export
seed_type = int_range(0, 2**31 - 1)  # --seed N of every command, as train.seed


def member_error(policy: str, member: int | None) -> str | None:
  """Why `--member` cannot be given with `policy` (None when it can): oracle, random and a
  policy file are one policy, member 0; only a run directory has several."""
  if member is None or member == 0:
    return None
  if policy in ("oracle", "random"):
    return f"--member {member}: the {policy} policy has no members"
  if Path(policy).suffix == ".npz" or Path(policy).is_file():
    return (f"--member {member}: a policy file holds one policy (member 0); --member picks "
            "a member of a run directory")
  return None


# --which of evaluate, view and export: what `rundir.checkpoints.restore_actor_params`
# (`selected_policy`, then `checkpoint_item`) resolves.
WHICH_HELP = (
    "with a run dir as --policy, which of its policies: best (default): the policy its "
    "choice of checkpoint wrote (RUN/selected.npz with RUN/selection.json; of member K "
    "of a run of several, RUN/selected_members/memberK.npz), where one was written; else "
    "the highest step under RUN/checkpoints/best/; else, in a run without one, the newest "
    "step under RUN/checkpoints/. last: the newest step under RUN/checkpoints/ (never a "
    "chosen policy)")

MEMBER_HELP = ("of a run that trained several members (--num-seeds, --sweep): which one, "
               "0-based (default: the one checkpoints/best follows, member 0)")

ROBOT_HELP = ("a built-in robot (jackal, husky) or a robot file (docs/your-robot.md); sets "
              "robot.name (default: the config's)")
# ... of the commands that drive a trained policy (evaluate, view)
ROBOT_POLICY_HELP = (ROBOT_HELP + "; its camera and speed limits may not change a trained "
                     "policy's")

POLICY_HELP = ("oracle, random, a run dir or a .npz policy file; a run dir's config.yaml "
               "(an .npz's metadata) gives the camera, networks and env options, "
               "--config/--set only override")


def add_policy_args(p: argparse.ArgumentParser, which: tuple[str, ...]) -> None:
  """--policy, --which (of `which`), --member and --robot: the flags of the commands that
  drive a trained policy (evaluate, view)."""
  p.add_argument("--policy", required=True, metavar="RUN|FILE", help=POLICY_HELP)
  p.add_argument("--which", choices=which, default="best", help=WHICH_HELP)
  p.add_argument("--member", type=member_type, default=None, metavar="K", help=MEMBER_HELP)
  p.add_argument("--robot", default=None, metavar="NAME|FILE.yaml", help=ROBOT_POLICY_HELP)


def input_error(e: Exception, stream=None) -> int:
  """A refused input as one line on stderr ("config error: ..." for a config, "error: ..."
  otherwise); returns the exit status, 2."""
  import sys  # pylint: disable=import-outside-toplevel
  from mjxvine.config import ConfigError  # config reads the robot files
  prefix = "config error" if isinstance(e, ConfigError) else "error"
  print(f"{prefix}: {e}", file=stream or sys.stderr)
  return 2

