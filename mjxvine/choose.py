"""The best checkpoint, chosen on validation worlds after training.

  python -m mjxvine.choose RUN_DIR            # what the trainer does at its end
  python -m mjxvine.choose RUN_DIR --set train.select_candidates=6

(`python -m mjxvine.select`, its old name, still answers.)

The fresh-start evaluations during training (`mjxvine.evaluation.starts`, 2 x
train.eval_starts starts on the training rows) are a noisy yardstick: two checkpoints that
score alike there can differ from 0 to 100 % on test-kind worlds. With
`train.select_worlds` > 0 the trainer keeps every evaluated policy
(RUN/eval_policies/env<steps>.npz) and, after training, drives the
`train.select_candidates` best of them by the fresh-start rule
(`choice.fresh_start_score`: the weaker direction's success, then the lower MAE) through a
validation protocol:

- every lane-direction of `train.select_worlds` validation worlds, test-kind worlds of seeds
  `train.select_world_seed` (100 or more: test tables use seeds below 100) and up,
  `train.select_runs` runs each, at `eval.noise_factor`;
- rows 1F and 4F of the first validation world at each of `train.select_noise_factors`,
  3 runs each (the noise test's rows and runs).

One batched rollout per candidate (`rollout.rollout_cases`, rollout seed 0: the same
cases and keys for every candidate). The candidates that meet the bar (at least
`train.select_success_bar` of the validation worlds' runs, and the noise rows at least as
often as the paper's) rank first, by the lower MAE (the mean over the validation worlds
of each world's mean of rows); the others after them, by their successes, then the MAE
(`choice.rank`). RUN/selection.json records every candidate's scores and the choice,
and is written after each candidate, so an interrupted selection resumes; RUN/selected.npz
is the chosen policy, which a run dir's "best" policy means from then on
(`checkpoints.selected_policy`: `evaluate --policy RUN`, `export --checkpoint RUN`).
Of a run of several members (`--seeds`, sweeps) each member chooses its own, from its own
evaluations and kept policies: RUN/selected_members/member<k>.npz and selection<k>.json
(`evaluate --policy RUN --member K`).
No test world is driven. The library is `mjxvine.evaluation.choice`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mjxvine.config import ConfigError, add_config_args, load_config


def main(argv=None, prog: str = "python -m mjxvine.choose") -> int:
  p = argparse.ArgumentParser(prog=prog, description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("run_dir", type=Path)
  p.add_argument("--member", type=int, default=None, metavar="K",
                 help="of a run of several members (--seeds, sweeps): choose for member K "
                 "alone (default: for each member)")
  add_config_args(p)
  args = p.parse_args(argv)
  try:
    if not (args.run_dir / "config.yaml").is_file():
      raise FileNotFoundError(f"{args.run_dir}: no config.yaml (not a run directory)")
    cfg = load_config(args.config or str(args.run_dir / "config.yaml"), args.overrides)
    from mjxvine.training.iteration import sweep_members  # (jax: after the cheap checks)
    count = len(sweep_members(cfg))
    if args.member is not None and not 0 <= args.member < count:
      raise ValueError(f"--member {args.member}: the run trained {count} member(s), 0 to "
                       f"{count - 1}")
    from mjxvine.evaluation import choice
    chosen = (args.member,) if args.member is not None and count > 1 else None
    for k in chosen or choice.member_ids(count):
      choice.select(cfg, args.run_dir, member=k)
  except ConfigError as e:
    print(f"config error: {e}", file=sys.stderr)
    return 2
  except (FileNotFoundError, ValueError) as e:
    print(f"select error: {e}", file=sys.stderr)
    return 2
  return 0


if __name__ == "__main__":
  sys.exit(main())
