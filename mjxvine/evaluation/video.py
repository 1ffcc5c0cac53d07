"""Videos of evaluation runs: MuJoCo's own renderer (`mujoco.Renderer`) from a camera that
follows the robot, the depth image the policy saw as an inset, and a small overlay (lane,
v, w, offset from the centreline, outcome).

    frames = render_frames(model, track)          # a `Track` from `rollout.run_protocol`
    write_video(frames, mp4="run.mp4", gif="run.gif", fps=20)
    # MP4 needs imageio-ffmpeg (it bundles ffmpeg); the GIF only Pillow

Headless: `choose_gl` picks EGL, then OSMesa (MUJOCO_GL) when no display is set and the
user did not choose; without any GL it raises `RenderError`, one line saying what to
install. Software GL (Mesa llvmpipe) is slow with shadows and reflections, so they are off.
The conv tower reads every pixel of the depth image (edge padding, `tower.tower_pad`):
the inset is the whole image, the size the network sees. `write_videos` renders the
tracks of a protocol run to files, as `evaluate --video` and `train.video` do.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import importlib
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Iterable, Iterator, NamedTuple

import numpy as np

from mjxvine import atomic
from mjxvine.formatting import first_line

GL_BACKENDS = ("egl", "osmesa")  # headless, in order of preference
INSTALL_GL = ("no OpenGL for headless rendering: install EGL (Debian/Ubuntu: apt-get install "
              "libegl1 libgl1-mesa-dri) or OSMesa (apt-get install libosmesa6), or set "
              "MUJOCO_GL to a working backend")
INSTALL_FFMPEG = ("MP4 videos need imageio-ffmpeg (it bundles ffmpeg): pip install "
                  "'mjxvine[video]' (or pip install imageio-ffmpeg); --gif needs only Pillow")


class RenderError(RuntimeError):
  """Rendering or writing a video is not possible here; the message says what to install."""


@contextlib.contextmanager
def _child_processes():
  """Silences JAX's warning on fork: these children (the GL probe, ffmpeg) exec another
  program at once, which is safe in a multithreaded process."""
  with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called",
                            category=RuntimeWarning)
    yield


# ---------------------------------------------------------------------------- OpenGL
_PROBE = """
import mujoco
m = mujoco.MjModel.from_xml_string("<mujoco><worldbody><geom size='.1'/></worldbody></mujoco>")
r = mujoco.Renderer(m, 8, 8)
r.update_scene(mujoco.MjData(m))
r.render()
"""


def _works(backend: str) -> bool:
  """Whether MuJoCo renders with `backend`: tried in a child process, because a failed GL
  library cannot be unloaded from this one (and PyOpenGL binds one platform)."""
  env = dict(os.environ, MUJOCO_GL=backend, PYOPENGL_PLATFORM=backend)
  try:
    with _child_processes():
      out = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True,
                           timeout=120)
  except (OSError, subprocess.TimeoutExpired):
    return False
  return out.returncode == 0


@functools.lru_cache(maxsize=1)
def choose_gl() -> str:
  """The OpenGL backend MuJoCo renders with in this process: MUJOCO_GL if the user set it,
  "glfw" (a window system) when a display is set, else the first of EGL and OSMesa that
  works, installed for this process and its children. RenderError when none does."""
  if os.environ.get("MUJOCO_GL"):
    return os.environ["MUJOCO_GL"]
  if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
    return "glfw"
  for backend in GL_BACKENDS:
    if _works(backend):
      _use(backend)
      return backend
  raise RenderError(INSTALL_GL)


def _use(backend: str) -> None:
  """Makes `mujoco.Renderer` use `backend`. MuJoCo reads MUJOCO_GL when it is imported
  (by then, in this process, it chose glfw), so its context class is replaced as well."""
  os.environ["MUJOCO_GL"] = backend
  os.environ.setdefault("PYOPENGL_PLATFORM", backend)
  from mujoco.rendering.classic import gl_context
  gl_context.GLContext = importlib.import_module(f"mujoco.{backend}").GLContext


# ---------------------------------------------------------------------------- frames
@dataclasses.dataclass(frozen=True)
class Track:
  """One evaluation run, frame by frame: frame 0 is the start, frame t the state after t
  control steps (T + 1 frames for a run of T steps).

  qpos (T + 1, nq): MuJoCo positions (free joint first: x, y, z m, quaternion w x y z).
  depth (T + 1, h, w): the noisy depth image (m) the policy saw at each frame.
  action (T + 1, 2): [v m/s, w rad/s] of the step that led to the frame (0 at the start).
  offset (T + 1,): lateral offset from the lane centreline (m, left of travel positive).
  """
  lane: int
  direction: str
  qpos: np.ndarray
  depth: np.ndarray
  action: np.ndarray
  offset: np.ndarray
  outcome: str
  control_dt: float
  max_depth_m: float

  @property
  def label(self) -> str:
    return f"{self.lane}{self.direction}"

  def __len__(self) -> int:
    return len(self.qpos)


def _yaw(qpos: np.ndarray) -> np.ndarray:
  w, x, y, z = qpos[:, 3], qpos[:, 4], qpos[:, 5], qpos[:, 6]
  return np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def chase_azimuths(qpos: np.ndarray, smoothing: float = 0.85) -> np.ndarray:
  """Camera azimuths (deg) that follow the robot's heading, smoothed so that the view does
  not shake with every turn: (T,) from qpos (T, nq)."""
  yaw = np.unwrap(_yaw(qpos))
  out = np.empty_like(yaw)
  acc = yaw[0]
  for i, y in enumerate(yaw):
    acc = smoothing * acc + (1 - smoothing) * y
    out[i] = acc
  return np.degrees(out)


@functools.lru_cache(maxsize=1)
def _lut() -> np.ndarray:
  from matplotlib import colormaps
  return (colormaps["magma"](np.linspace(0, 1, 256))[:, :3] * 255).astype(np.uint8)


def _colourise(depth: np.ndarray, max_depth: float) -> np.ndarray:
  """Depth (h, w) m -> RGB uint8 (h, w, 3): near bright, far (and no return) dark."""
  lut = _lut()
  idx = np.clip((1.0 - np.nan_to_num(depth, nan=max_depth) / max_depth) * 255, 0, 255)
  return lut[idx.astype(np.uint8)]


@functools.lru_cache(maxsize=8)
def _font(size: int):
  from PIL import ImageFont
  try:
    return ImageFont.load_default(size=size)  # FreeType: scalable
  except TypeError:  # an old Pillow: the fixed bitmap font
    return ImageFont.load_default()


def compose(scene: np.ndarray, track: Track, t: int) -> np.ndarray:
  """Frame `t`: the rendered scene (H, W, 3) uint8 with the depth inset (top right) and
  the text overlay (top left). Returns a new (H, W, 3) uint8 array."""
  from PIL import Image, ImageDraw
  frame = scene.copy()
  height, width = frame.shape[:2]
  depth = track.depth[t]
  scale = max(1, int(0.36 * height) // depth.shape[0])
  inset = np.repeat(np.repeat(_colourise(depth, track.max_depth_m), scale, 0), scale, 1)
  ih, iw = inset.shape[:2]
  if ih + 4 <= height and iw + 4 <= width:
    frame[2:ih + 6, width - iw - 6:width - 2] = 255  # a white frame around it
    frame[4:ih + 4, width - iw - 4:width - 4] = inset
  img = Image.fromarray(frame)
  draw = ImageDraw.Draw(img, "RGBA")
  size = max(10, height // 26)
  font = _font(size)
  v, w = track.action[t]
  last = t == len(track) - 1
  lines = [f"lane {track.label}   t {t * track.control_dt:5.1f} s",
           f"v {v:4.2f} m/s   w {w:+5.2f} rad/s",
           f"offset {track.offset[t]:+5.2f} m",
           track.outcome if last else "running"]
  box = (4, 4, 4 + int(size * 11.5), 8 + len(lines) * (size + 3))
  draw.rectangle(box, fill=(0, 0, 0, 140))
  for i, line in enumerate(lines):
    colour = (255, 255, 255) if i < 3 else ((120, 220, 120) if line == "success" else
                                            (255, 120, 100) if last else (200, 200, 200))
    draw.text((8, 6 + i * (size + 3)), line, fill=colour, font=font)
  if ih + 4 <= height and iw + 4 <= width:
    label = f"policy input {depth.shape[0]}x{depth.shape[1]}"
    draw.text((width - iw - 4, ih + 8), label, fill=(255, 255, 255), font=_font(max(9, size - 3)),
              stroke_width=1, stroke_fill=(0, 0, 0))
  return np.asarray(img)


def render_frames(model, track: Track, width: int = 480, height: int = 360,
                  distance: float = 3.2, elevation: float = -22.0) -> Iterator[np.ndarray]:
  """The frames (height, width, 3) uint8 of `track` in `model` (the MjModel of its world),
  one per entry of the track, from a camera `distance` m behind the robot, looking down by
  `-elevation` deg, following its (smoothed) heading."""
  import mujoco
  choose_gl()
  model = render_model(model, width, height)
  data = mujoco.MjData(model)
  camera = mujoco.MjvCamera()
  camera.type = mujoco.mjtCamera.mjCAMERA_FREE
  camera.distance, camera.elevation = distance, elevation
  azimuths = chase_azimuths(track.qpos)
  try:
    renderer = mujoco.Renderer(model, height, width)
  except Exception as e:  # noqa: BLE001 - GL libraries fail in many ways
    raise RenderError(f"{INSTALL_GL} ({type(e).__name__}: {first_line(e)})") from None
  try:
    for t in range(len(track)):
      data.qpos[:] = track.qpos[t]
      mujoco.mj_kinematics(model, data)
      heading = np.radians(azimuths[t])
      camera.lookat[:] = track.qpos[t, :3] + [0.8 * np.cos(heading), 0.8 * np.sin(heading), 0.2]
      camera.azimuth = azimuths[t]
      renderer.update_scene(data, camera)
      for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION):
        renderer.scene.flags[flag] = 0  # software GL: each costs several times the frame
      yield compose(renderer.render(), track, t)
  finally:
    renderer.close()


def render_model(model, width: int, height: int):
  """A copy of `model` set up for fast offscreen frames: a buffer of at least width x
  height, no multisampling, and coarser spheres and ellipsoids (12 slices, 6 stacks).
  On software GL (Mesa llvmpipe) this renders a vineyard about 5x faster, at a look that
  a video of a run does not miss."""
  import copy
  model = copy.copy(model)
  vis = model.vis
  vis.global_.offwidth = max(vis.global_.offwidth, width)
  vis.global_.offheight = max(vis.global_.offheight, height)
  vis.quality.offsamples = 0
  vis.quality.numslices = min(vis.quality.numslices, 12)
  vis.quality.numstacks = min(vis.quality.numstacks, 6)
  # without shadows the scene's one light leaves the rows dark: a brighter headlight
  vis.headlight.ambient = np.maximum(vis.headlight.ambient, 0.3)
  vis.headlight.diffuse = np.maximum(vis.headlight.diffuse, 0.5)
  return model


# ---------------------------------------------------------------------------- files
def check_mp4() -> None:
  """RenderError (what to install) when MP4s cannot be written here."""
  try:
    import imageio_ffmpeg
    imageio_ffmpeg.get_ffmpeg_exe()
  except (ImportError, RuntimeError):
    raise RenderError(INSTALL_FFMPEG) from None


def _mp4_writer(path: Path, width: int, height: int, fps: float):
  """A started imageio-ffmpeg generator that takes (height, width, 3) uint8 frames and
  writes an H.264 MP4 that browsers and players read (yuv420p)."""
  try:
    import imageio_ffmpeg
  except ImportError:
    raise RenderError(INSTALL_FFMPEG) from None
  writer = imageio_ffmpeg.write_frames(str(path), (width, height), fps=fps, codec="libx264",
                                       pix_fmt_out="yuv420p", macro_block_size=2, quality=7,
                                       ffmpeg_log_level="error")
  with _child_processes():
    writer.send(None)  # starts ffmpeg
  return writer


def write_video(frames: Iterable[np.ndarray], mp4: str | Path | None = None,
                gif: str | Path | None = None, fps: float = 20.0, gif_every: int = 4,
                gif_width: int = 320, gif_colors: int = 96) -> int:
  """Writes frames (H, W, 3) uint8 (H, W even) in one pass: an MP4 at `mp4` (needs
  imageio-ffmpeg; RenderError without it) and/or a looping GIF at `gif` (Pillow only; every
  `gif_every`-th frame at `gif_width` px in `gif_colors` colours: a 50 s run at 320x240
  is about 2.7 MB, small enough for a README). Returns the number of frames rendered."""
  from PIL import Image
  if mp4 is None and gif is None:
    raise ValueError("write_video: give mp4 and/or gif")
  for path in (mp4, gif):
    if path is not None:
      Path(path).parent.mkdir(parents=True, exist_ok=True)
  writer, images, count = None, [], 0
  # both files written whole or not at all: a failed render keeps an earlier video
  with contextlib.ExitStack() as files:
    mp4_tmp = files.enter_context(atomic.atomic_path(mp4)) if mp4 is not None else None
    try:
      for frame in frames:
        if mp4 is not None:
          if writer is None:
            writer = _mp4_writer(mp4_tmp, frame.shape[1], frame.shape[0], fps)
          writer.send(np.ascontiguousarray(frame))
        if gif is not None and count % gif_every == 0:
          img = Image.fromarray(frame)
          if img.width != gif_width:
            img = img.resize((gif_width, round(img.height * gif_width / img.width)),
                             Image.Resampling.BILINEAR)
          images.append(img.quantize(colors=gif_colors, method=Image.Quantize.MEDIANCUT))
        count += 1
    finally:
      if writer is not None:
        writer.close()
  if gif is not None and images:
    with atomic.atomic_path(gif) as tmp:
      images[0].save(tmp, save_all=True, append_images=images[1:], loop=0,
                     duration=round(1000 * gif_every / fps), optimize=True)
  return count


def count_frames(path: str | Path) -> int:
  """The number of frames of a video file (MP4 via imageio-ffmpeg, GIF via Pillow)."""
  path = Path(path)
  if path.suffix == ".gif":
    from PIL import Image
    with Image.open(path) as img:
      return img.n_frames
  import imageio_ffmpeg
  reader = imageio_ffmpeg.read_frames(str(path))
  with _child_processes():
    next(reader)  # starts ffmpeg; the metadata
  return sum(1 for _ in reader)


# ---------------------------------------------------------------------------- runs
def video_after_train(world) -> list[tuple[int, str]]:
  """The runs `train.video` films on `world` (a `Vineyard`): a straight lane forward and a
  curved one in reverse (1F and 4R of the test world)."""
  return [(1, "F"), (min(4, len(world.lanes)), "R")]


class VideoFormat(NamedTuple):
  """The files `write_videos` writes: an MP4 and/or a GIF per run, `fps` frames per second
  (None: twice real time), frames `size` = (width, height) px."""
  mp4: bool = True
  gif: bool = False
  fps: float | None = None
  size: tuple[int, int] = (480, 360)


def write_videos(tracks, world, cfg, out: Path, form: VideoFormat = VideoFormat(), *,
                 say=print) -> list[Path]:
  """Renders each `Track` of `world` (a `Vineyard`; `cfg` its `Config`) to
  out/<lane><dir>.mp4 (and .gif), as `form` says; returns the files written."""
  from mjxvine.worlds import build_models
  model = build_models([world], cfg)[0]
  fps = 2.0 / cfg.env.control_dt if form.fps is None else form.fps
  written = []
  for track in tracks:
    t0 = time.time()
    paths = {k: out / f"{track.label}.{k}" for k, on in (("mp4", form.mp4), ("gif", form.gif))
             if on}
    n = write_video(render_frames(model, track, *form.size), fps=fps, **paths)
    written += list(paths.values())
    say(f"  {' and '.join(str(p) for p in paths.values())}: {n} frames ({track.outcome}) "
        f"in {time.time() - t0:.0f} s")
  return written
