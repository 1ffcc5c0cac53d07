"""The best checkpoint, chosen on validation worlds after training.

  python -m mjxvine.choose --policy RUN_DIR            # what the trainer does at its end
  python -m mjxvine.choose --policy RUN_DIR --set train.select_candidates=6
  python -m mjxvine.choose --policy RUN_DIR --every   # the validation curve: every policy

(`python -m mjxvine.select`, its old name, still answers.)

The fresh-start evaluations during training (`mjxvine.evaluation.starts`, 2 x
train.eval_starts starts on the training rows) are a noisy yardstick: two checkpoints that
score alike there can differ from 0 to 100 % on test-kind worlds. With
`train.select_worlds` > 0 the trainer keeps every evaluated policy
(RUN/eval_policies/env<steps>.npz) and, after training, drives the last of them, then (when
it misses the bar below) the `train.select_candidates - 1` best of the others by the
fresh-start rule (`choice.fresh_start_score`: the weaker direction's success, then the
lower MAE) through a validation protocol:

- every lane-direction of `train.select_worlds` validation worlds, test-kind worlds of seeds
  100 and up (test tables use seeds below 100), 2 runs each, at `eval.noise_factor`;
- rows 1F and 4F of the first validation world at noise factors 8 and 10, 3 runs each (the
  noise test's rows and runs).

One batched rollout per candidate (`rollout.rollout_cases`, rollout seed 0: the same
cases and keys for every candidate). When the last policy meets the bar within 0.04 m of
the centreline it is chosen and no other drives; once a candidate has met the bar, a
later one stops as soon as it cannot (`stopped_early` in the record). The candidates
that meet the bar (at least 95 % of the validation worlds' runs, an MAE of at most 0.06
m, and the noise rows at least as often as the paper's) rank first, by the lower MAE
(the mean over the validation worlds of each world's mean of rows); the others after
them, by their successes, then the MAE (`choice.rank`). RUN/selection.json records every
candidate's scores and the choice, and is written after each candidate, so an
interrupted selection resumes; RUN/selected.npz is the chosen policy, which a run dir's
"best" policy means from then on (`checkpoints.selected_policy`: `evaluate --policy
RUN`, `export --policy RUN`).
Of a run of several members (`--num-seeds`, sweeps) each member chooses its own, from its own
evaluations and kept policies: RUN/selected_members/member<k>.npz and selection<k>.json
(`evaluate --policy RUN --member K`).
No test world is driven. The library is `mjxvine.evaluation.choice`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from mjxvine.atomic import command_main
from mjxvine.cli import CommandParser, input_error
from mjxvine.config import ConfigError, add_config_args, load_config, load_run_config
from mjxvine.rundir import RunDirBusy, RunLock


def parser(prog: str = "python -m mjxvine.choose") -> argparse.ArgumentParser:
  """The command line's flags."""
  p = CommandParser(prog=prog, description=__doc__)
  p.add_argument("--policy", required=True, type=Path, metavar="RUN",
                 help="the run directory whose best policy to choose (its config.yaml and "
                      "RUN/eval_policies/)")
  p.add_argument("--every", action="store_true",
                 help="drive every kept policy, in the order of training, none stopped "
                 "early: the run's validation curve in selection.json (the choice among "
                 "them as usual)")
  p.add_argument("--member", type=int, default=None, metavar="K",
                 help="of a run of several members (--num-seeds, --sweep): choose for "
                 "member K alone (default: for each member)")
  add_config_args(p)
  return p


def main(argv=None, prog: str = "python -m mjxvine.choose") -> int:
  """The CLI: 0 chosen, 2 a bad argument, config or run directory, or a run in use (one
  line); stopped by SIGINT / SIGTERM (`atomic.command_main`): 130 / 143, selection.json
  kept (a new choice goes on from it) and the earlier selected.npz as it was."""
  args = parser(prog).parse_args(argv)
  run_dir = args.policy
  try:
    if not (run_dir / "config.yaml").is_file():
      raise FileNotFoundError(f"--policy {run_dir}: no config.yaml (not a run directory)")
    cfg = (load_config(args.config, args.overrides) if args.config else
           load_run_config(run_dir / "config.yaml", args.overrides))
    # the run's one writer, as the trainer is (its own choice writes the same files)
    with RunLock(run_dir):
      from mjxvine.training.iteration import sweep_members  # (jax: after the cheap checks)
      count = len(sweep_members(cfg))
      if args.member is not None and not 0 <= args.member < count:
        raise ValueError(f"--member {args.member}: the run trained {count} member(s), 0 "
                         f"to {count - 1}")
      from mjxvine.evaluation import choice
      chosen = (args.member,) if args.member is not None and count > 1 else None
      for k in chosen or choice.member_ids(count):
        choice.select(cfg, run_dir, member=k, every=args.every)
  except (ConfigError, FileNotFoundError, ValueError, RunDirBusy) as e:
    return input_error(e)
  return 0


if __name__ == "__main__":
  command_main(main, keep_outputs=True)  # selection.json: what a new choice goes on from
