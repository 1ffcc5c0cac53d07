"""The best checkpoint chosen on validation worlds (`mjxvine.choose`, its library
`mjxvine.evaluation.choice`): a tiny run trains
with train.select_worlds, and the trainer scores its best evaluated policies on a
validation world, picks the one with the most successes (then the lower MAE), writes the
record and RUN/selected.npz, which a run dir's best policy then means; an interrupted
selection resumes from its record; bad requests fail in one line."""

import json
import shutil

import jax
import jax.numpy as jp
import numpy as np
import pytest
from test_train import EVAL, _cfg

from mjxvine import choose, select
from mjxvine import train as train_mod
from mjxvine.rundir.checkpoints import restore_actor_params
from mjxvine.config import ConfigError, load_config
from mjxvine.deploy import read_policy_file
from mjxvine.evaluation import choice
from mjxvine.worlds import generate_world

# one validation world, short episodes; the trainer's program is test_train.py's (these
# keys do not shape it)
SELECT = ("train.select_worlds=1", "train.select_candidates=2", "eval.max_steps=12")


@pytest.fixture(scope="module")
def selected_run(tmp_path_factory):
  run = tmp_path_factory.mktemp("selected")
  row = train_mod.train(_cfg(80, *EVAL, *SELECT), run, quiet=True, evaluate_at_end=False)
  return run, row


def test_the_trainer_chooses_on_the_validation_world(selected_run):
  run, row = selected_run
  record = json.loads((run / "selection.json").read_text())
  rows = [json.loads(l) for l in (run / "metrics.jsonl").read_text().splitlines()]
  evals = {r["env_steps"]: r for r in rows if "eval_success_forward" in r}
  assert sorted(evals) == [40, 80]
  # the candidates: the last first; it cannot meet the bar in 12 steps, so the other drives
  assert [c["env_steps"] for c in record["candidates"]] == [80, 40]
  assert record["protocol"]["worlds"] == [100]
  lanes = len(choice.validation_worlds(load_config(run / "config.yaml"))[0].lanes)
  for c in record["candidates"]:
    v = c["validation"]
    # every lane-direction RUNS times, and rows 1F and 4F three times at noise 8 and at 10
    assert v["episodes"] == 2 * lanes * choice.RUNS + 2 * 2 * 3
    assert list(v["worlds"]) == ["100"]
    assert v["worlds"]["100"]["episodes"] == 2 * lanes * choice.RUNS
    assert v["success"] == v["worlds"]["100"]["success"] + sum(
        sum(n.values()) for n in v["noise"].values())
    assert c["trainer"]["eval_mae_m"] == pytest.approx(evals[c["env_steps"]]["eval_mae_m"])
  bar = choice.SUCCESS_BAR
  best = max(record["candidates"], key=lambda c: choice.rank(c["validation"], bar))
  assert record["selected"] == best["env_steps"] == row["selected_env_steps"]
  kept = run / "eval_policies" / f"env{record['selected']}.npz"
  assert (run / "selected.npz").read_bytes() == kept.read_bytes()


def test_a_run_dir_means_its_selected_policy(selected_run):
  run, _ = selected_run
  params, path = restore_actor_params(run)
  assert path == run / "selected.npz"
  arrays, _ = read_policy_file(run / "selected.npz")
  np.testing.assert_array_equal(params["mean"]["kernel"], arrays["mean/kernel"])
  # "last" and the checkpoints themselves are still the orbax checkpoints
  _, item = restore_actor_params(run, "last")
  assert "checkpoints" in item.parts


def _scores(world_success: int, noise8: tuple, noise10: tuple, mae) -> dict:
  """Validation scores of one world of 20 runs and the noise rows at factors 8 and 10."""
  noise = {"8.0": dict(zip(("1F", "4F"), noise8)), "10.0": dict(zip(("1F", "4F"), noise10))}
  return {"worlds": {"100": {"success": world_success, "episodes": 20}}, "noise": noise,
          "success": world_success + sum(noise8) + sum(noise10), "mae_m": mae}


def test_rank_puts_the_bar_first_then_the_lower_mae():
  bar = 0.95
  every = _scores(20, (3, 3), (3, 3), 0.05)       # drives every run, 5 cm off centre
  paper_noise = _scores(19, (2, 3), (0, 0), 0.04)  # 19/20 and the paper's noise test
  assert choice.meets_bar(every, bar) and choice.meets_bar(paper_noise, bar)
  assert choice.rank(paper_noise, bar) > choice.rank(every, bar)  # both meet it: MAE
  # every run driven, but further off centre than the test target allows (or no MAE):
  # below the bar, and above those that fail runs
  off_centre = _scores(20, (3, 3), (3, 3), choice.MAE_BAR_M + 0.01)
  assert not choice.meets_bar(off_centre, bar)
  assert choice.meets_bar(_scores(20, (3, 3), (3, 3), choice.MAE_BAR_M), bar)
  assert choice.rank(every, bar) > choice.rank(off_centre, bar)
  assert choice.rank(off_centre, bar) > choice.rank(_scores(18, (3, 3), (3, 3), 0.01), bar)
  # below the bar: a world at 18/20 (90 %), or the curved noise row short of the paper's at 8
  short = [_scores(18, (3, 3), (3, 3), 0.01), _scores(20, (3, 2), (3, 3), 0.01)]
  for s in short:
    assert not choice.meets_bar(s, bar)
    assert choice.rank(every, bar) > choice.rank(s, bar)
  # among those below it, the successes, then the lower MAE; no MAE ranks last
  assert choice.rank(short[1], bar) > choice.rank(short[0], bar)
  assert choice.rank(_scores(18, (3, 3), (3, 3), 0.05), bar) < choice.rank(short[0], bar)
  assert choice.rank(_scores(0, (0, 0), (0, 0), None), bar) < choice.rank(
      _scores(0, (0, 0), (0, 0), 1.0), bar)
  # bar 0: the noise rows still ask the paper's successes
  assert not choice.meets_bar(_scores(0, (1, 3), (0, 0), 0.01), 0.0)


def test_fresh_start_score_orders_the_weaker_direction_then_mae():
  def row(fwd, rev, mae):
    return {"eval_success_forward": fwd, "eval_success_reverse": rev, "eval_mae_m": mae}
  assert choice.fresh_start_score(row(1.0, 0.5, 0.1)) < choice.fresh_start_score(
      row(0.6, 0.6, 0.2))
  assert choice.fresh_start_score(row(0.5, 0.5, 0.1)) > choice.fresh_start_score(
      row(0.5, 0.9, 0.2))
  evals = {40: row(0.5, 0.5, 0.1), 80: row(0.5, 0.5, 0.1), 120: row(0.9, 0.8, 0.3),
           160: row(0.1, 0.1, 0.5)}
  # the last first, then the others best first, the earlier of equals first; only kept
  assert choice.candidates(evals, {40, 80, 120, 160}, 3) == [160, 120, 40]
  assert choice.candidates(evals, {40, 80, 120}, 3) == [120, 40, 80]
  assert choice.candidates(evals, {80, 120, 160}, 1) == [160]
  assert choice.candidates(evals, {80}, 3) == [80]


def test_validation_cases_are_the_paper_noise_rows():
  from mjxvine.evaluation import paper
  worlds = [generate_world("test", 3, load_config(None, ["world.test_length_m=8"]).world)]
  cases, tables, noise = choice.validation_cases(worlds, 2, 1.0, (8, 10))
  lanes = len(worlds[0].lanes)
  assert list(tables[0]) == list(range(4 * lanes))
  assert cases[:3] == [(0, 1, "F", 1.0), (0, 1, "F", 1.0), (0, 1, "R", 1.0)]
  assert sorted(noise) == [8.0, 10.0]
  assert [cases[i][1:] for i in noise[8.0]] == [
      (lane, "F", 8.0) for lane in paper.NOISE_LANES for _ in range(paper.NOISE_RUNS)]


def test_a_selection_resumes_from_its_record(selected_run, tmp_path, monkeypatch, capsys):
  run, _ = selected_run
  copy = tmp_path / "copy"
  shutil.copytree(run, copy)
  (copy / "selected.npz").unlink()
  record = json.loads((copy / "selection.json").read_text())
  record["selected"] = None
  (copy / "selection.json").write_text(json.dumps(record))
  # every candidate is in the record: nothing is driven again
  monkeypatch.setattr(choice, "score_policy", lambda *a, **k: pytest.fail("scored again"))
  assert choose.main(["--policy", str(copy)]) == 0
  again = json.loads((copy / "selection.json").read_text())
  assert again["selected"] == json.loads((run / "selection.json").read_text())["selected"]
  assert (copy / "selected.npz").read_bytes() == (run / "selected.npz").read_bytes()
  assert "selected the policy of" in capsys.readouterr().out
  # under another sensor (or robot faults) the record's scores no longer hold
  driven = []
  monkeypatch.setattr(choice, "score_policy", lambda cfg, path, *a, **k: driven.append(
      cfg.sensor.preset) or {**_scores(0, (0, 0), (0, 0), None), "episodes": 32})
  assert choose.main(["--policy", str(copy), "--set", "sensor.preset=d435"]) == 0
  assert driven == ["d435", "d435"]


def test_bad_requests_fail_in_one_line(selected_run, tmp_path, capsys):
  run, _ = selected_run
  assert choose.main(["--policy", str(tmp_path)]) == 2
  assert "no config.yaml" in capsys.readouterr().err
  assert select.main(["--policy", str(tmp_path)]) == 2  # the old name still answers
  assert "no config.yaml" in capsys.readouterr().err
  assert choose.main(["--policy", str(run), "--set", "train.select_worlds=0"]) == 2
  assert "train.select_worlds = 0" in capsys.readouterr().err
  empty = tmp_path / "empty"
  empty.mkdir()
  shutil.copy(run / "config.yaml", empty / "config.yaml")
  assert choose.main(["--policy", str(empty)]) == 2
  assert "no evaluated policy" in capsys.readouterr().err
  with pytest.raises(ConfigError, match="train.select_world_seed"):
    load_config("experiments/smoke.yaml", ["train.select_world_seed=3"])
  assert choose.main(["--policy", str(run), "--member", "1"]) == 2
  assert "--member 1: the run trained 1 member(s), 0 to 0" in capsys.readouterr().err


@pytest.mark.slow  # a vmapped 2-member trainer compiles: over 20 s on a 2-core CPU
def test_each_member_of_a_seeds_run_chooses_its_own(tmp_path, capsys):
  """`--num-seeds 2` with train.select_worlds: each member keeps its own evaluated policies,
  is scored on the validation world from its own fresh-start evaluations, and gets its own
  choice, which `--member K` of a run dir then means."""
  run = tmp_path / "seeds"
  row = train_mod.train(_cfg(80, *EVAL, *SELECT, "train.num_seeds=2"), run, quiet=True,
                        evaluate_at_end=False)
  rows = [json.loads(l) for l in (run / "metrics.jsonl").read_text().splitlines()]
  for k in (0, 1):
    kept = choice.kept_policies(run, k)
    assert sorted(kept) == [40, 80]
    record = json.loads((run / "selected_members" / f"selection{k}.json").read_text())
    evals = {r["env_steps"]: r for r in rows if r["member"] == k and "eval_mae_m" in r}
    assert {c["env_steps"]: c["trainer"]["eval_mae_m"] for c in record["candidates"]} == {
        s: evals[s]["eval_mae_m"] for s in evals}
    chosen = run / "selected_members" / f"member{k}.npz"
    assert chosen.read_bytes() == kept[record["selected"]].read_bytes()
    params, path = restore_actor_params(run, member=k)
    assert path == chosen
    np.testing.assert_array_equal(params["mean"]["kernel"],
                                  read_policy_file(chosen)[0]["mean/kernel"])
  # the members' kept policies differ: each member exports its own actor
  a, b = (read_policy_file(choice.kept_policies(run, k)[80])[0]["mean/kernel"] for k in (0, 1))
  assert not np.array_equal(a, b)
  assert row["selected_env_steps"] == json.loads(
      (run / "selected_members" / "selection0.json").read_text())["selected"]
  assert not (run / "selection.json").exists() and restore_actor_params(run)[1] == (
      run / "selected_members" / "member0.npz")
  # the command line chooses again for one member, from its record (nothing driven again)
  assert choose.main(["--policy", str(run), "--member", "1"]) == 0
  assert "member 1: selected the policy of" in capsys.readouterr().out


def _with_a_third_policy(run, tmp_path):
  """A copy of the selected run with a kept policy at 60 env steps whose fresh-start
  evaluation is the best of the three (so the candidates are 80, the last, then 60, 40)."""
  copy = tmp_path / "three"
  shutil.copytree(run, copy)
  (copy / "selection.json").unlink()
  shutil.copy(copy / "eval_policies" / "env40.npz", copy / "eval_policies" / "env60.npz")
  best = {"member": 0, "env_steps": 60, "eval_success_forward": 1.0,
          "eval_success_reverse": 1.0, "eval_mae_m": 0.01}
  with open(copy / "metrics.jsonl", "a") as f:
    f.write(json.dumps(best) + "\n")
  return copy


# MAE 0.05 m + steps / 10^4 (the last, 80: 0.058 m), or 0.03 m less
@pytest.mark.parametrize("meeting, mae0, every, driven, stopping, chosen", [
    ({80}, 0.02, False, [80], [False], 80),                  # meets it within 0.04 m: alone
    ({80, 40}, 0.05, False, [80, 60, 40], [False, True, True], 40),  # not: the others drive
    ({60}, 0.05, False, [80, 60, 40], [False, False, True], 60),  # after 60 met it, 40 may stop
    ({60}, 0.05, True, [40, 60, 80], [False, False, False], 60),  # every one, in order, whole
])
def test_the_last_drives_first_and_a_candidate_stops_once_it_cannot_win(
    selected_run, tmp_path, monkeypatch, meeting, mae0, every, driven, stopping, chosen):
  run = _with_a_third_policy(selected_run[0], tmp_path)
  calls = []

  def score(cfg, path, worlds, runs, noise_factors=(), below_bar_stops=False):
    steps = int(path.stem[3:])
    calls.append((steps, below_bar_stops))
    return {**_scores(20 if steps in meeting else 10, (3, 3), (3, 3), mae0 + steps / 1e4),
            "episodes": 32}

  monkeypatch.setattr(choice, "score_policy", score)
  cfg = load_config(run / "config.yaml", ["train.select_candidates=3"])
  record = choice.select(cfg, run, say=lambda *a: None, every=every)
  assert calls == list(zip(driven, stopping))
  assert [c["env_steps"] for c in record["candidates"]] == driven
  assert record["selected"] == chosen
  assert (run / "selected.npz").read_bytes() == (
      run / "eval_policies" / f"env{chosen}.npz").read_bytes()


def test_a_rollout_stops_when_asked_and_unfinished_runs_time_out():
  from test_view import ToyEnv
  from mjxvine.env import OUTCOMES
  from mjxvine.evaluation import rollout

  def crawl(state, key):  # 5 mm per step: no run ends within 200 steps
    return jp.array([0.005, 0.0])

  starts = rollout.EnvStarts(lanes=[0, 1], directions=[1.0, -1.0])
  seen = []

  def stop(outcome):
    seen.append(outcome.copy())
    return True

  key = jax.random.PRNGKey(0)
  _, _, alive, outcome, steps, _ = rollout.rollout(ToyEnv(), crawl, starts, key, 200, stop=stop)
  assert len(seen) == 1 and list(seen[0]) == [0, 0]  # asked once, after the first chunk
  assert alive.shape[0] == rollout.CHUNK_STEPS and list(steps) == [rollout.CHUNK_STEPS] * 2
  assert [OUTCOMES[c] for c in outcome] == ["timeout", "timeout"]
  _, _, alive, _, _, _ = rollout.rollout(ToyEnv(), crawl, starts, key, 200)
  assert alive.shape[0] == 200  # without a stop: to the limit
