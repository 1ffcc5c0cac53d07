"""The closing report of a training run: the best policy from fresh starts of the training
rows beside the drive-straight and random baselines, the test world (the paper's
protocol, for information), and where the run's files are."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, NamedTuple

import jax

from mjxvine.config import Config
from mjxvine.formatting import fmt
from mjxvine.rundir.checkpoints import Checkpoints, restore_actor_params
from mjxvine.training.distributed import local
from mjxvine.training.hooks import eval_line, member_scores
from mjxvine.training.programs import starts_params


def summary_line(row: dict, best: dict | None) -> str:
  """The last training figures and the best checkpoint's, in one line."""
  text = (f"return {fmt(row.get('return_mean'), 2)}, training success "
          f"{fmt(row.get('success_rate'), 2)} (with exploration)")
  if best is not None:
    text += f"; best checkpoint (chunk {best['chunk']}): {eval_line(best)}"
  return text


class RunSummary(NamedTuple):
  """A trained run at its end, as the closing report reads it."""
  run_dir: Path
  sac: Any  # the learner (`sac.SAC`): its networks drive the test world
  ckpt: Checkpoints
  ts: Any  # the last TrainState, every member
  seeds: int  # members trained at once
  best: dict | None  # the best fresh-start scores (member 0, best.json); None: none yet
  selected: int | None = None  # env steps of the policy chosen on validation worlds


def baselines(cfg: Config, run: RunSummary, row: dict, say: Callable, start_eval, eval_key):
  """The best checkpoint's actor (all members), after printing its fresh-start scores
  (`run.best`, not None) beside the baselines' from the same starts (`start_eval` with
  `eval_key`; added to `row` as straight_* and random_*). Every process enters the
  restore and the evaluations (collectives over all devices)."""
  from mjxvine.evaluation import starts
  ts, best, seeds = run.ts, run.best, run.seeds
  actor = ts.learner.averaged_actor_params
  restored = run.ckpt.restore(ts, best=True)
  if restored is not None:
    actor = restored[1].learner.averaged_actor_params
  say(f"\nbest policy (chunk {best['chunk']}, {best['env_steps']} env steps) from "
      f"{2 * cfg.train.eval_starts} fresh starts on the training rows: {eval_line(best)}")
  for name, policy in starts.BASELINES.items():
    out = start_eval(starts_params(actor, policy, seeds), eval_key)
    scores = member_scores(out, 0)
    row.update({f"{name}_{k}": v for k, v in scores.items()})
    say(f"  the same starts, {'driving straight' if name == 'straight' else name}: "
        f"{eval_line(scores)}")
  return actor


def test_world(cfg: Config, run_dir: Path, sac, actor, which: str, seeds: int, row: dict,
               say: Callable) -> None:
  """The actor on the test world (`eval.runs_after_train` runs per lane-direction), its
  report in RUN/eval/ and, with `train.video`, its videos."""
  from mjxvine.evaluation import report, rollout, video
  from mjxvine.evaluation.policies import actor_policy, averaging_mirror
  from mjxvine.worlds import load_test_world
  runs = cfg.eval.runs_after_train
  world = load_test_world(cfg.world)
  say(f"evaluating the best policy on the test world ({len(world.lanes) * 2 * runs} runs, "
      f"the paper's protocol; for information)...")
  source = rollout.PolicySource(
      "checkpoint", policy=actor_policy(sac.nets, actor, mirror=averaging_mirror(cfg)))
  doc, tracks = rollout.run_protocol(
      cfg, source, world, rollout.Protocol(runs, cfg.eval.noise_factor),
      video=video.video_after_train(world) if cfg.train.video else ())
  member = ", member 0" if seeds > 1 else ""
  doc["policy"] = f"{run_dir} ({which}, train.seed {cfg.train.seed}{member})"
  report.write_results(doc, world, run_dir / "eval")
  row["eval_test_success"] = doc["overall"]["success"]
  row["eval_test_runs"] = doc["overall"]["runs"]
  say(report.results_markdown(doc))
  if tracks:  # train.video
    say(f"filming the best policy's runs to {run_dir / 'eval' / 'videos'}/ ...")
    try:
      video.write_videos(tracks, world, cfg, run_dir / "eval" / "videos", say=say)
    except video.RenderError as e:  # no GL or no ffmpeg here: the run itself is fine
      say(f"no videos: {e}")


def closing_report(cfg: Config, run: RunSummary, row: dict, say: Callable, start_eval,
                   eval_key, primary: bool = True) -> None:
  """Prints the best policy's evaluation on fresh starts beside the baselines
  (`baselines`), evaluates it on the test world (`test_world`; process 0 alone, on its own
  device) and names the files of the run. With `run.selected` (the env steps of the
  policy chosen on validation worlds: RUN/selected.npz, `mjxvine.evaluation.choice`) the
  test world drives that policy instead of checkpoints/best."""
  run_dir, seeds, selected = run.run_dir, run.seeds, run.selected
  actor = run.ts.learner.averaged_actor_params
  if run.best is not None:
    actor = baselines(cfg, run, row, say, start_eval, eval_key)
  actor = local(actor)
  if seeds > 1:
    actor = jax.tree.map(lambda x: x[0], actor)
  runs = cfg.eval.runs_after_train
  if not primary:
    return
  which = "best checkpoint"
  if selected is not None:
    actor, _ = restore_actor_params(run_dir)  # RUN/selected.npz
    which = f"policy selected on validation worlds, {selected} env steps"
  if runs > 0:
    test_world(cfg, run_dir, run.sac, actor, which, seeds, row, say)
  say(f"wrote {run_dir}/: open learning_curve.png first" +
      (", then eval/trajectories.png and eval/results.md" if runs > 0 else "") +
      "; metrics.jsonl and tb/ (tensorboard --logdir) hold every chunk, checkpoints/ the "
      "last and best policies (python -m mjxvine.export --policy " + f"{run_dir})")
