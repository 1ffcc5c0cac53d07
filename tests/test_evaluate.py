"""The evaluation protocol: metrics on synthetic trajectories, and the oracle on a short
test vineyard."""

import json

import numpy as np
import pytest

from mjxvine.config import load_config
from mjxvine.evaluate import distance_to_line, main as evaluate_main, trajectory_errors
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


def test_oracle_drives_every_test_lane(tmp_path):
  out = tmp_path / "oracle"
  overrides = ["world.test_length_m=8", "world.test_seed=3", "camera.width=16",
               "camera.height=12", "env.max_steps=200"]
  cfg_file = tmp_path / "c.yaml"
  cfg_file.write_text("")
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
  assert "| 1F | straight |" in (out / "results.md").read_text()
  assert (out / "trajectories.png").stat().st_size > 10_000
  # the world really is the requested one
  world = generate_world("test", 3, load_config(None, overrides).world)
  first = np.asarray(doc["trajectories"][0]["xy"])[0]
  assert abs(first[1] - world.lanes[0].centerline[0, 1]) < 0.1


def test_bad_policy_and_world_fail_in_one_line(tmp_path, capsys):
  assert evaluate_main(["--policy", str(tmp_path / "nope.npz"), "--out", str(tmp_path)]) == 2
  assert "policy not found" in capsys.readouterr().err
  assert evaluate_main(["--policy", "oracle", "--world", "lane9", "--out", str(tmp_path)]) == 2
  assert "unknown world" in capsys.readouterr().err
