"""The evaluation protocol: metrics on synthetic trajectories, and the oracle on a short
test vineyard."""

import json
from pathlib import Path

import numpy as np
import pytest

from mjxvine.config import load_config
from mjxvine.deploy import read_policy_file
from mjxvine.env import OUTCOMES
from mjxvine.evaluate import main as evaluate_main
from mjxvine.evaluation import geometry, metrics, report, rollout
from mjxvine.evaluation.geometry import distance_to_line, trajectory_errors
from mjxvine.worlds import generate_world


def test_distance_to_line_known_values():
  line = np.stack([np.linspace(0, 10, 41), np.zeros(41)], -1)
  pts = np.array([[1.0, 0.3], [5.05, -0.2], [9.9, 0.0], [12.0, 0.0]])
  np.testing.assert_allclose(distance_to_line(pts, line), [0.3, 0.2, 0.0, 2.0], atol=1e-12)


def test_mae_rmse_of_synthetic_trajectories():
  # a sine-shaped ground truth and a trajectory offset along its normal by a known profile
  x = np.linspace(0, 20, 801)
  y = 0.5 * np.sin(x / 4)
  line = np.stack([x, y], -1)
  tangent = np.gradient(line, axis=0)
  normal = np.stack([-tangent[:, 1], tangent[:, 0]], -1) / np.linalg.norm(tangent, axis=1)[:, None]
  offset = 0.1 * np.sign(np.sin(x))  # |offset| = 0.1 everywhere but at zeros
  traj = line + offset[:, None] * normal
  traj = np.concatenate([[[-1.0, 0.0]], traj, [[21.0, 0.0]]])  # points outside the row
  err = trajectory_errors(traj, line)
  assert len(err) == 801
  assert np.mean(err) == pytest.approx(np.mean(np.abs(offset)), abs=1e-3)
  assert np.sqrt(np.mean(err ** 2)) == pytest.approx(np.sqrt(np.mean(offset ** 2)), abs=1e-3)


@pytest.mark.slow  # over 20 s on a 2-core CPU: the fast suite stays within 12 minutes
def test_oracle_drives_every_test_lane(tmp_path):
  out = tmp_path / "oracle"
  overrides = ["world.test_length_m=8", "camera.width=16",
               "camera.height=12", "eval.max_steps=200"]
  cfg_file = tmp_path / "c.yaml"
  cfg_file.write_text("{}\n")  # the defaults (an empty file is refused)
  argv = ["--policy", "oracle", "--runs", "1", "--world", "3", "--out", str(out),
          "--config", str(cfg_file)]
  for o in overrides:
    argv += ["--set", o]
  assert evaluate_main(argv) == 0
  doc = json.loads((out / "results.json").read_text())
  assert doc["overall"]["success"] == doc["overall"]["runs"] == 10
  assert doc["overall"]["mae_m"] < 0.05
  assert [r["shape"] for r in doc["rows"]][::2] == ["straight", "straight", "hybrid", "curved",
                                                   "curved"]
  assert all(r["outcomes"] == ["success"] for r in doc["rows"])
  assert all(r["metrics_status"] == "full" and r["lane_covered_frac"] == 1.0 for r in doc["rows"])
  assert doc["rows"][0]["lane_covered_m"] == pytest.approx(8.0, abs=0.05)  # the lane's length
  assert doc["overall"]["mae_m"] == doc["overall"]["mae_m_raw"]
  md = (out / "results.md").read_text()
  assert "| 1F | straight | 100% (8.0 m) |" in md and "lane covered" in md
  table = [l for l in md.splitlines() if l.startswith("| ")]
  assert len(table) == 12 and not any("n/a" in l or "(partial)" in l for l in table)
  assert (out / "trajectories.png").stat().st_size > 10_000
  # the world really is the requested one
  world = generate_world("test", 3, load_config(None, overrides).world)
  first = np.asarray(doc["trajectories"][0]["xy"])[0]
  assert abs(first[1] - world.lanes[0].centerline[0, 1]) < 0.1


def test_bad_policy_and_world_fail_in_one_line(tmp_path, capsys):
  assert evaluate_main(["--policy", str(tmp_path / "nope.npz"), "--out", str(tmp_path)]) == 2
  assert "policy not found" in capsys.readouterr().err
  assert evaluate_main(["--policy", "oracle", "--world", "lane9", "--out", str(tmp_path)]) == 2
  assert "give a seed or a world .json file" in capsys.readouterr().err


def test_lane_progress():
  line = np.stack([np.linspace(0, 10, 41), 0.2 * np.sin(np.linspace(0, 3, 41))], -1)
  length = geometry.arc_length(line)
  assert length > 10.0
  fwd = line[:13]  # a forward run that stopped at x = 3
  assert geometry.lane_progress(fwd, line, "F") == pytest.approx(
      geometry.arc_length(line[:13]), abs=1e-9)
  rev = line[::-1][:9]  # a reverse run from x = 10 to x = 8
  assert geometry.lane_progress(rev, line, "R") == pytest.approx(
      geometry.arc_length(line[-9:]), abs=1e-9)
  # wobbling back does not lower the furthest point; outside the lane's ends clamps
  assert geometry.lane_progress(np.concatenate([fwd, fwd[:3]]), line, "F") == pytest.approx(
      geometry.lane_progress(fwd, line, "F"))
  assert geometry.lane_progress(np.array([[-1.0, 0.0], [12.0, 0.0]]), line, "F") == pytest.approx(
      length)
  straight = np.stack([np.linspace(0, 10, 41), np.zeros(41)], -1)  # off-centre: its projection
  assert geometry.lane_progress(np.array([[0.5, 0.4], [4.2, -0.3]]), straight, "F") == (
      pytest.approx(4.2))
  assert geometry.lane_progress(np.array([[9.5, 0.4], [4.2, -0.3]]), straight, "R") == (
      pytest.approx(5.8))
  assert geometry.lane_progress(np.zeros((0, 2)), line, "R") == 0.0


def _row(outcomes, covered_frac, lane=1, direction="F"):
  codes = [OUTCOMES.index(o) for o in outcomes]
  errs = [np.full(10, 0.1) for _ in outcomes]
  acts = [np.tile([0.4, 0.0], (10, 1)) for _ in outcomes]
  row = metrics.group_metrics(errs, acts, codes, [10] * len(codes), 0.1,
                              [24.0 * f for f in covered_frac], covered_frac)
  row.update(lane=lane, direction=direction, shape="straight", outcomes=list(outcomes))
  return row


def _doc(rows, overall):
  return {"policy": "p", "robot": "jackal", "noise": 1.0, "rows": rows, "overall": overall,
          "wall_s": 1.0, "world": {}, "trajectories": []}


def test_metrics_of_failed_runs_are_not_reported_as_comparable():
  full = _row(["success", "success"], [1.0, 1.0])
  partial = _row(["success", "collision"], [1.0, 0.25], direction="R")
  none = _row(["collision", "timeout"], [0.1, 0.2], lane=2)
  assert [r["metrics_status"] for r in (full, partial, none)] == ["full", "partial", "n/a"]
  assert none["mae_m"] is None and none["rmse_m"] is None
  assert none["mae_m_raw"] == pytest.approx(0.1) and none["rmse_m_raw"] == pytest.approx(0.1)
  assert partial["mae_m"] == pytest.approx(0.1)
  assert none["lane_covered_frac"] == pytest.approx(0.15)
  assert none["lane_covered_m"] == pytest.approx(3.6)
  overall = _row(["success"] * 3 + ["collision"] * 3, [1, 1, 1, 0.25, 0.1, 0.2])
  overall.update(metrics.mean_of_rows([full, partial, none]))
  assert overall["mae_m_rows"] == pytest.approx(0.1) and overall["rows_status"] == "partial"
  md = report.results_markdown(_doc([full, partial, none], overall))
  lines = {l.split("|")[1].strip(): l for l in md.splitlines() if l.startswith("| ")}
  assert "| 100% (24.0 m) | 0.100 (0.076) | 0.100 (0.089) |" in lines["1F"]
  assert "| 62% (15.0 m) | 0.100 (partial) (0.131) | 0.100 (partial) (0.141) |" in lines["1R"]
  assert "| 15% (3.6 m) | n/a (0.068) | n/a (0.076) |" in lines["2F"]
  assert "0.100 (partial) (0.114)" in lines["overall"]
  assert "lane covered" in lines["test row"]
  assert metrics.metrics_status(0, 0) == "n/a"
  nothing = _row(["collision"], [0.05])
  assert "MAE/RMSE n/a" in report.figure_title(_doc([nothing], nothing))


def test_trajectories_figure(tmp_path):
  """A figure of successful forward and failed reverse runs is written (whether it reads
  well is checked by eye)."""
  world = generate_world("test", 3, load_config(None, ["world.test_length_m=8"]).world)
  trajs = []
  for lane in world.lanes:
    c = lane.centerline
    for direction, outcome, part in (("F", "success", c), ("R", "collision", c[::-1][:12])):
      trajs.append({"lane": lane.id, "direction": direction, "outcome": outcome,
                    "xy": (part + [0.0, 0.1 if direction == "F" else -0.1]).tolist()})
  overall = _row(["success"] * 5 + ["collision"] * 5, [1.0] * 5 + [0.3] * 5)
  doc = dict(_doc([], overall), trajectories=trajs)
  report.plot_trajectories(doc, world, tmp_path / "t.png")
  assert (tmp_path / "t.png").stat().st_size > 10_000
  assert "(partial: only some runs reached the EoR)" in report.figure_title(doc)


def test_bad_runs_noise_and_policy_file(tmp_path, capsys):
  for flags, message in ((["--runs", "0"], "--runs: eval.runs = 0: must be in [1, 1000]"),
                         (["--noise", "-1"],
                          "--noise: eval.noise_factor = -1.0: must be in [0.0, 100.0]")):
    with pytest.raises(SystemExit) as e:
      evaluate_main(["--policy", "oracle", "--out", str(tmp_path), *flags])
    assert e.value.code == 2 and message in capsys.readouterr().err
  (tmp_path / "corrupt.npz").write_bytes(b"\x80\x04 not a policy at all" * 20)
  assert evaluate_main(["--policy", str(tmp_path / "corrupt.npz"), "--out", str(tmp_path)]) == 2
  err = capsys.readouterr().err
  assert "corrupt.npz: not a valid policy file" in err and "allow_pickle" not in err
  assert len(err.splitlines()) == 1
  with pytest.raises(ValueError, match="runs=0"):
    rollout.evaluate(load_config(), rollout.PolicySource("oracle"),
                     generate_world("test", 0, load_config().world),
                     rollout.Protocol(runs=0, noise_factor=1.0))


@pytest.mark.slow  # over 20 s on a 2-core CPU: the fast suite stays within 12 minutes
def test_paper_suite_oracle(tmp_path):
  """The whole suite in one call on two short test worlds: every table is there, the
  privileged oracle drives every run to the end of its row, and the overall figure is
  the mean of the rows (the paper's convention)."""
  from mjxvine.evaluation.paper import NOISE_FACTORS
  from mjxvine.evaluation.suite import paper_suite
  cfg = load_config(None, ["world.test_length_m=8", "camera.width=16", "camera.height=12",
                           "eval.max_steps=200"])
  report = paper_suite(cfg, "oracle", tmp_path, runs=1, worlds=(2, 3))
  for w in ("2", "3"):
    o, rows = report["worlds"][w]["overall"], report["worlds"][w]["rows"]
    assert o["success"] == o["runs"] == 10 and o["rows_status"] == "full"
    assert o["mae_m_rows"] == pytest.approx(np.mean([r["mae_m"] for r in rows]))
    assert (tmp_path / f"world{w}" / "trajectories.png").is_file()
  assert sorted(report["noise"], key=float) == [str(k) for k in NOISE_FACTORS]
  assert all(r["success"] == r["runs"] == 3 for k in report["noise"].values()
             for r in k.values())
  assert sorted(report["robots"]) == ["husky_1F", "husky_4F", "jackal_1F", "jackal_4F"]
  assert all(r["success"] == 3 for r in report["robots"].values())
  md = (tmp_path / "report.md").read_text()
  assert "| 2 | 10/10 | none |" in md and "## Robots" in md and "## Test world 3" in md


# ---------------------------------------------------------------------------- a run's own config
# A run trained with another image size (34x36) and smaller networks than the defaults: its
# config.yaml and a best checkpoint laid out as `checkpoint.Checkpoints` writes them.
RUN_SETTINGS = ["camera.height=34", "camera.width=36", "sac.hidden=16", "sac.conv_features=4",
                "world.test_length_m=8", "eval.max_steps=12",
                "eval.runs=1"]


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
  """(root, run dir name): root/run holds config.yaml and checkpoints/best/1 of a 34x36
  actor with hidden 16 and 4 conv features."""
  import jax
  import jax.numpy as jp
  import orbax.checkpoint as ocp

  from mjxvine import networks as nw
  from mjxvine.config import to_yaml
  root = tmp_path_factory.mktemp("runs")
  run = root / "run"
  cfg = load_config(None, RUN_SETTINGS)
  run.mkdir()
  (run / "config.yaml").write_text(to_yaml(cfg))
  nets = nw.make_networks_from_config(cfg)
  obs = {"depth": jp.zeros((1, 34, 36, 1)), "state": jp.zeros((1, 3))}
  actor, _ = nw.init_params(nets, jax.random.PRNGKey(3), obs)
  actor = jax.tree.map(np.asarray, actor)
  actor["mean"]["bias"] = np.array([2.0, 0.0], np.float32)  # drive forward at once
  manager = ocp.CheckpointManager((run / "checkpoints" / "best").resolve(),
                                  options=ocp.CheckpointManagerOptions(create=True))
  manager.save(1, args=ocp.args.StandardSave({"learner": {"policy_params": actor}}))
  manager.wait_until_finished()
  manager.close()
  return root, "run"


def test_a_run_is_evaluated_filmed_and_exported_with_its_own_config(small_run, monkeypatch,
                                                                    capsys):
  """evaluate, export and evaluate of the export, with relative paths and no --config:
  the networks, camera and world come from the run's config.yaml; the export's results
  equal the run's; the video of a run decodes to one frame per step plus the start."""
  from mjxvine import export
  from mjxvine.evaluation import video
  root, run = small_run
  monkeypatch.chdir(root)
  try:
    video.choose_gl()
  except video.RenderError as e:
    pytest.skip(f"no OpenGL for headless rendering here: {e}")
  film = ["--video", "--gif", "--video-lanes", "2R", "--video-size", "160x120"]
  assert evaluate_main(["--policy", run, "--out", "ev", *film]) == 0
  doc = json.loads(Path("ev/results.json").read_text())
  assert doc["overall"]["runs"] == 10 and Path("ev/trajectories.png").is_file()
  traj = next(t for t in doc["trajectories"] if (t["lane"], t["direction"]) == (2, "R"))
  assert 1 <= len(traj["xy"]) <= 12  # the run's own eval.max_steps
  assert video.count_frames("ev/videos/2R.mp4") == len(traj["xy"]) + 1
  assert video.count_frames("ev/videos/2R.gif") == (len(traj["xy"]) + 4) // 4  # every 4th
  assert sorted(p.name for p in Path("ev/videos").iterdir()) == ["2R.gif", "2R.mp4"]
  assert "(config: run/config.yaml)" in capsys.readouterr().err

  assert export.main(["--policy", run, "--out", "p.npz"]) == 0
  _, meta = read_policy_file("p.npz")
  assert meta["image_size"] == [34, 36] and meta["max_depth_m"] == 5.0
  assert evaluate_main(["--policy", "p.npz", "--out", "ev2", *film]) == 0
  doc2 = json.loads(Path("ev2/results.json").read_text())
  assert [t["xy"] for t in doc2["trajectories"]] == [t["xy"] for t in doc["trajectories"]]
  assert [r["outcomes"] for r in doc2["rows"]] == [r["outcomes"] for r in doc["rows"]]


def test_an_override_of_what_the_networks_need_is_one_line(small_run, monkeypatch, capsys):
  from mjxvine import export
  root, run = small_run
  monkeypatch.chdir(root)
  assert evaluate_main(["--policy", run, "--out", "x", "--set", "camera.width=40"]) == 2
  err = capsys.readouterr().err
  assert err == ("config error: camera.width = 40: the policy was trained with 36 "
                 "(run/config.yaml); its networks fit only that (drop the override)\n")
  assert export.main(["--policy", run, "--out", "x.npz", "--set", "sac.hidden=64"]) == 2
  assert "sac.hidden = 64: the policy was trained with 16" in capsys.readouterr().err
  assert not Path("x").exists() and not Path("x.npz").exists()
  # what does not touch the networks may change: the config says so
  from mjxvine.rundir.settings import policy_config
  cfg, source = policy_config(run, overrides=["eval.max_steps=30", "robot.name=husky"])
  assert (cfg.camera.height, cfg.camera.width, cfg.sac.hidden) == (34, 36, 16)
  assert cfg.eval.max_steps == 30 and cfg.robot.name == "husky"
  assert source == "run/config.yaml with --set eval.max_steps=30, --set robot.name=husky"


def test_signed_offsets_and_lane_lists():
  line = np.stack([np.linspace(0, 10, 11), np.zeros(11)], -1)
  pts = np.array([[2.0, 0.3], [5.0, -0.2]])
  np.testing.assert_allclose(geometry.signed_offsets(pts, line, "F"), [0.3, -0.2])
  np.testing.assert_allclose(geometry.signed_offsets(pts, line, "R"), [-0.3, 0.2])
  assert rollout.parse_lanes("1F, 4r", 5) == [(1, "F"), (4, "R")]
  for bad in ("6F", "1X", "F"):
    with pytest.raises(ValueError, match="not a lane-direction"):
      rollout.parse_lanes(bad, 5)


def test_cases_are_built_group_by_group():
  cases = rollout.Cases()
  first = cases.add(0, [(1, "F"), (2, "R")], 1.0, 2)
  second = cases.add(1, [(4, "F")], 8.0, 1)
  assert list(first) == [0, 1, 2, 3] and list(second) == [4]
  assert cases == [(0, 1, "F", 1.0), (0, 1, "F", 1.0), (0, 2, "R", 1.0), (0, 2, "R", 1.0),
                   (1, 4, "F", 8.0)]
  world = generate_world("test", 3, load_config(None, ["world.test_length_m=8"]).world)
  assert rollout.all_lanes(world) == [(lane, d) for lane in range(1, len(world.lanes) + 1)
                                      for d in ("F", "R")]


def test_the_papers_figures():
  """The paper's overall row is the mean of its rows (successes: the sum), as ours."""
  from mjxvine.evaluation import paper
  rows = [v for k, v in paper.PAPER.items() if k != "overall"]
  overall = paper.PAPER["overall"]
  for i in (0, 1, 2, 3, 4, 5):
    assert np.mean([r[i] for r in rows]) == pytest.approx(overall[i], abs=1e-3)
  assert sum(r[6] for r in rows) == overall[6] and paper.PAPER_RUNS == 50
  assert paper.weak_rows() == ["3R 2/5", "5F 3/5"]
  assert paper.noise_rows() == paper.robot_rows() == [(1, "F"), (4, "F")]
  assert set(paper.PAPER_NOISE) <= set(paper.NOISE_FACTORS)
  assert set(paper.PAPER_ROBOTS) == set(paper.PAPER_ROBOT_TIMES) == {
      (r, f"{lane}F") for r in paper.ROBOTS for lane in paper.ROBOT_LANES}
