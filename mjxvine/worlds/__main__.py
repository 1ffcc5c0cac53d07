"""`python -m mjxvine.worlds`: write a vineyard's MJCF, JSON description and map.

  python -m mjxvine.worlds --kind test --world 0 --robot jackal --out out/test0
  python -m mjxvine.worlds --kind train --world 3 --out out/train3 --depth-at 2,0.9,0
  python -m mjxvine.worlds --kind test --out out/test0 --depth-at 2,0,0 --policy policy.npz
  python -m mjxvine.worlds --world examples/vineyard-block.geojson --out out/block

--world takes a seed (a generated world of --kind) or a file: a vineyard file (.geojson,
.csv) or a saved world .json, as `evaluate --world` and `view --world` do. --depth-at also
draws the robot and its camera frustum on the map (world.png). The depth
image is rendered with the config's camera (--set camera.width=...), or with the image
size, FOVs and max depth that a policy was trained with (--policy FILE.npz).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import mujoco
import numpy as np

from mjxvine.atomic import OutputError, atomic_path, check_output, command_main, write_text
from mjxvine.cli import ROBOT_HELP, CommandParser
from mjxvine.config import add_config_args, config_from_args, short_repr
from mjxvine.deploy import PolicyFormatError, read_policy_file
from mjxvine.worlds.build import build_spec, camera_limits, terrain_height
from mjxvine.worlds.layout import save_world
from mjxvine.worlds.plot import save_map
from mjxvine.worlds.store import world_of

SETTLE_S = 1.0


def place_robot(model: mujoco.MjModel, world, x: float, y: float, yaw: float) -> mujoco.MjData:
  """Puts the robot at (x, y, yaw) on the terrain and lets the physics settle it."""
  data = mujoco.MjData(model)
  r = model.geom_size[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "wheel0"), 0]
  data.qpos[:3] = [x, y, float(terrain_height(world, x, y)) + r + 0.01]
  data.qpos[3:7] = [np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]
  for _ in range(int(SETTLE_S / model.opt.timestep)):
    mujoco.mj_step(model, data)
  return data


def write_depth(model, world, cfg, pose, out: Path) -> None:
  """Renders the depth camera at `pose` and writes depth.npy, depth_noisy.npy,
  camera.json and depth.png into `out`."""
  import jax
  from mujoco import mjx

  from mjxvine import depth as depth_cam

  data = place_robot(model, world, *pose)
  cam = depth_cam.DepthCamera.create(model, cfg.camera, **camera_limits([world], cfg.camera))
  mx, dx = mjx.put_model(model), mjx.put_data(model, data)
  image = np.asarray(jax.jit(lambda m, d: depth_cam.render_depth(cam, m, d))(mx, dx))
  noisy = np.asarray(depth_cam.add_noise(image, jax.random.PRNGKey(0), cfg.camera, 1.0))
  for name, array in (("depth.npy", image), ("depth_noisy.npy", noisy)):
    with atomic_path(out / name) as tmp:
      np.save(tmp, array.astype(np.float32))
  cid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "depth")
  write_text(out / "camera.json", json.dumps({
      "pos": data.cam_xpos[cid].tolist(), "xmat": data.cam_xmat[cid].tolist(),
      "fovx_deg": cfg.camera.fovx_deg, "fovy_deg": cfg.camera.fovy_deg,
      "width": cfg.camera.width, "height": cfg.camera.height,
      "max_depth": cfg.camera.max_depth_m}, indent=1))
  import matplotlib.pyplot as plt
  fig, axes = plt.subplots(1, 2, figsize=(9, 4))
  for ax, img, title in zip(axes, (image, noisy), ("depth (noise-free)", "depth, noise factor 1")):
    im = ax.imshow(img, cmap="viridis_r", vmin=0, vmax=cfg.camera.max_depth_m)
    ax.set_title(title)
    ax.axis("off")
  fig.colorbar(im, ax=axes, label="z-depth [m]", shrink=0.8)
  fig.suptitle(f"camera at x={pose[0]:.2f} y={pose[1]:.2f} yaw={pose[2]:.2f}: "
               f"{cfg.camera.height}x{cfg.camera.width} px, fovx {cfg.camera.fovx_deg:g} deg")
  with atomic_path(out / "depth.png") as tmp:
    fig.savefig(tmp, dpi=100)
  plt.close(fig)


def camera_overrides(policy_file: str | Path) -> list[str]:
  """`--set` overrides of the camera that a policy file was exported for: image size,
  FOVs and max depth from its metadata (`mjxvine.deploy.read_policy_file`)."""
  _, meta = read_policy_file(policy_file)
  try:
    height, width = (int(v) for v in meta["image_size"])
  except (KeyError, TypeError, ValueError):
    raise PolicyFormatError(f"{policy_file}: its metadata has no image_size [H, W]") from None
  out = [f"camera.height={height}", f"camera.width={width}"]
  for key in ("fovx_deg", "fovy_deg", "max_depth_m"):
    if meta.get(key) is not None:
      out.append(f"camera.{key}={meta[key]}")
  return out


MAX_YAW = 2 * np.pi  # one turn either way


def _parse_pose(text: str) -> list[float]:
  """"X,Y,YAW" -> [x m, y m, yaw rad]; ValueError if not three finite numbers with
  |yaw| <= MAX_YAW (where x, y may go: `_check_pose`, once the world is known)."""
  pose = [float(v) for v in text.split(",")]
  if len(pose) != 3 or not np.all(np.isfinite(pose)) or abs(pose[2]) > MAX_YAW:
    raise ValueError(text)
  return pose


def _check_pose(pose: list[float], world) -> str | None:
  """Why the robot cannot stand at `pose` in `world` (None if it can): (x, y) must lie on
  its terrain, `terrain_extent`."""
  xmin, xmax, ymin, ymax = world.terrain_extent
  if xmin <= pose[0] <= xmax and ymin <= pose[1] <= ymax:
    return None
  return (f"--depth-at: ({pose[0]:g}, {pose[1]:g}) is off the world's terrain, x "
          f"{xmin:.2f}..{xmax:.2f} m and y {ymin:.2f}..{ymax:.2f} m")


def parser() -> argparse.ArgumentParser:
  """The command line's flags."""
  p = CommandParser(prog="python -m mjxvine.worlds", description=__doc__)
  p.add_argument("--world", default="0", metavar="SEED|FILE",
                 help="the world: a seed (a generated world of --kind; default 0) or a "
                      "file: a vineyard file (GeoJSON rows in longitude/latitude, a CSV of "
                      "plants in metres: docs/your-vineyard.md) or a saved world .json")
  p.add_argument("--kind", choices=("train", "test"), default="test",
                 help="with a seed as --world: a training world (as the training pool "
                      "draws them) or a test one (the test lanes' shapes; test seed 0 is the "
                      "committed test vineyard). Default: test")
  p.add_argument("--plant-spacing", type=float, default=None, metavar="M",
                 help="with a GeoJSON vineyard file as --world: plant spacing (m) of row "
                      "lines that do not give plant_spacing_m")
  p.add_argument("--robot", default=None, metavar="NAME|FILE.yaml", help=ROBOT_HELP)
  p.add_argument("--out", required=True, metavar="DIR",
                 help="output directory, made if missing: world.xml (MJCF), world.json, "
                      "world.png (the map); with --depth-at the depth images")
  p.add_argument("--depth-at", default=None, metavar="X,Y,YAW",
                 help="also place the robot there (m, m, rad), write its depth image and "
                      "draw it with its camera frustum on the map")
  p.add_argument("--policy", default=None, metavar="FILE.npz",
                 help="use the camera of this exported policy (image size, FOVs, max depth "
                      "from its metadata); --set camera.* still overrides it")
  add_config_args(p)
  return p


WRITES = ("world.xml", "world.json", "world.png", "depth.npy", "depth_noisy.npy",
          "camera.json", "depth.png")  # what --out gets


def main(argv=None) -> int:
  """The CLI: 0 written, 2 a bad argument, world file or policy file (one line); stopped
  by SIGINT / SIGTERM (`atomic.command_main`): 130 / 143, nothing of the set written."""
  p = parser()
  args = p.parse_args(argv)
  pose = None
  if args.depth_at:
    try:
      pose = _parse_pose(args.depth_at)
    except ValueError:
      p.error(f"--depth-at {short_repr(args.depth_at)}: expected X,Y,YAW (three finite "
              "numbers: m, m, rad with |YAW| <= 2 pi)")
  extra = [f"robot.name={args.robot}"] if args.robot else []
  if args.policy:
    try:
      extra += camera_overrides(args.policy)
    except PolicyFormatError as e:
      print(f"error: {e}", file=sys.stderr)
      return 2
  cfg = config_from_args(args, extra)
  try:
    # a seed, a vineyard file or a saved world, as `evaluate --world` reads it
    world = world_of(args.world, cfg, kind=args.kind, flag="--world",
                     plant_spacing_m=args.plant_spacing)
    if pose is not None and _check_pose(pose, world):
      p.error(_check_pose(pose, world))
    # after a bad file: nothing made; never over its own --world, --policy, ... files
    out = check_output(args.out, "--out", directory=True, writes=WRITES, inputs=[
        (args.world, "the --world file"), (args.policy, "the --policy file"),
        (args.config, "the --config file"), (args.robot, "the --robot file")])
  except (OutputError, ValueError, FileNotFoundError) as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  spec = build_spec(world, cfg)
  model = spec.compile()
  write_text(out / "world.xml", spec.to_xml())
  save_world(world, out / "world.json", robot=cfg.robot.name)  # what --world FILE.json reads
  save_map(world, out / "world.png", pose=pose, robot=cfg.robot.spec,
           fovx_deg=cfg.camera.fovx_deg, max_depth_m=cfg.camera.max_depth_m)
  if pose is not None:  # the whole set before a line says it is there
    write_depth(model, world, cfg, pose, out)
  name = (f"vineyard {args.world}" if Path(args.world).is_file() else
          f"{args.kind} world seed {args.world}")
  print(f"{name} ({cfg.robot.name}): {len(world.plant_xy)} plants, "
        f"{len(world.lanes)} lanes, inter-row {world.inter_row_m:.2f} m, spacing "
        f"{world.spacing_m:.2f} m -> {out}/world.xml, world.json, world.png")
  if world.season != "classic":
    print(f"  {world.season}: {len(world.post_xy)} posts, {len(world.cordons)} cordons, "
          f"{len(world.lobes)} canopy lobes, {len(world.shoots)} shoots, "
          f"{len(world.tufts)} tufts")
  if world.frame:
    for lane in world.lanes:
      line = lane.centerline
      print(f"  lane {lane.id}: {line[-1, 0] - line[0, 0]:.1f} m long, "
            f"{world.lane_width(lane):.2f} m wide")
  if pose is not None:
    print(f"depth at {pose} ({cfg.camera.height}x{cfg.camera.width}, fovx "
          f"{cfg.camera.fovx_deg:g} deg) -> {out}/depth.npy, depth_noisy.npy, camera.json, "
          "depth.png")
  return 0


if __name__ == "__main__":
  command_main(main)
