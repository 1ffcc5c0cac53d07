"""Videos of runs: frames of a tiny world rendered headless (EGL or OSMesa), the overlay
and the depth inset, MP4 and GIF files decoded back to their frame counts, and the one
line that says what to install when there is no OpenGL."""

import numpy as np
import pytest

from mjxvine import evaluate
from mjxvine.evaluation import video
from mjxvine.config import load_config
from mjxvine.worlds import build_models, generate_world


@pytest.fixture(scope="module")
def gl():
  try:
    return video.choose_gl()
  except video.RenderError as e:
    pytest.skip(f"no OpenGL for headless rendering here: {e}")


def _track(world, frames=5):
  """A synthetic run along lane 1: qpos from the model's start, moving 0.1 m a frame."""
  import mujoco
  cfg = load_config(None, ["world.test_length_m=8"])
  model = build_models([world], cfg)[0]
  data = mujoco.MjData(model)
  mujoco.mj_forward(model, data)
  line = world.lanes[0].centerline
  qpos = np.tile(data.qpos, (frames, 1))
  qpos[:, :2] = line[0] + np.arange(frames)[:, None] * [0.1, 0.0]
  qpos[:, 2] = 0.15
  depth = np.tile(np.linspace(0.5, 5.0, 12)[None, :], (frames, 8, 1)).astype(np.float32)
  action = np.tile([0.5, 0.1], (frames, 1))
  offset = np.linspace(0.0, 0.2, frames)
  return model, video.Track(1, "F", qpos, depth, action, offset, "collision", 0.1, 5.0)


def test_frames_of_a_tiny_world_decode_to_their_count(gl, tmp_path):
  world = generate_world("test", 3, load_config(None, ["world.test_length_m=8"]).world)
  model, track = _track(world)
  frames = list(video.render_frames(model, track, width=160, height=120))
  assert len(frames) == 5 and frames[0].shape == (120, 160, 3) and frames[0].dtype == np.uint8
  assert frames[0].std() > 10  # a scene, not a blank buffer
  # the inset (top right, 3x scale of the 8x12 image): near bright on the left, far dark
  inset = frames[0][4:28, 160 - 36 - 4:160 - 4].astype(float).mean(axis=(0, 2))
  assert inset[:6].mean() > inset[-6:].mean() + 50
  assert not np.array_equal(frames[0], frames[-1])  # the camera follows the robot
  n = video.write_video(iter(frames), mp4=tmp_path / "a.mp4", gif=tmp_path / "a.gif", fps=10)
  assert n == 5
  assert video.count_frames(tmp_path / "a.mp4") == 5
  assert video.count_frames(tmp_path / "a.gif") == 2  # every 4th frame: 0 and 4


def test_without_opengl_it_says_what_to_install(monkeypatch, tmp_path, capsys):
  monkeypatch.delenv("MUJOCO_GL", raising=False)
  monkeypatch.delenv("DISPLAY", raising=False)
  monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
  monkeypatch.setattr(video, "_works", lambda backend: False)
  video.choose_gl.cache_clear()
  try:
    with pytest.raises(video.RenderError, match="apt-get install libegl1 libgl1-mesa-dri"):
      video.choose_gl()
    # the CLI: one line, before any rollout
    assert evaluate.main(["--policy", "oracle", "--out", str(tmp_path), "--video"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: no OpenGL for headless rendering") and err.count("\n") == 1
    assert not (tmp_path / "results.json").exists()
  finally:
    video.choose_gl.cache_clear()


def test_train_video_needs_the_closing_runs():
  from mjxvine.config import ConfigError
  assert load_config(None, ["train.video=true"]).train.video
  with pytest.raises(ConfigError, match="train.video = true: .*eval.runs_after_train >= 1"):
    load_config(None, ["train.video=true", "eval.runs_after_train=0"])
