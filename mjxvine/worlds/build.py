"""MuJoCo models of vineyards, built with `mujoco.MjSpec`.

Scene geoms: the heightfield `terrain` (group 0) and, for every plant slot i, a cylinder
`plant{i}_trunk` and an ellipsoid `plant{i}_canopy` (group 1, contype = conaffinity = 0).
Then the scenery of a world that is not classic (`mjxvine.worlds.seasons`), slots of each
kind in turn, group 1, contype = conaffinity = 0: cylinders `post{i}` and `post_top{i}`
(the lower and upper half of a trellis post; the lower is an obstacle, as trunks are:
`obstacle_geom_ids`) and `cordon{i}`, ellipsoids `lobe{i}`, `shoot{i}` and `tuft{i}`.
Unused slots stay in the model, parked below the terrain at (0, 0, -100), so that all
worlds of a config have the same structure and batch into one `mjx.Model`; a classic world
has no scenery slots. The robot (group 2) and its camera `depth` come from
`robots.add_robot`.
"""

from __future__ import annotations

import math
from typing import Sequence

import mujoco
import numpy as np

from mjxvine.config import PHYSICS_DT_S, Config
from mjxvine.worlds.layout import TERRAIN_AMPLITUDE_M, Vineyard
from mjxvine.worlds.robots import ROBOTS, add_robot
from mjxvine.worlds.seasons import SHAPE_TABLES

PARKED_Z = -100.0
TERRAIN_BASE_M = 0.2  # heightfield base depth under its lowest point
SOLVER_ITERATIONS = 4
SOLVER_LS_ITERATIONS = 8


def _yaw_quat(yaw: float) -> list[float]:
  return [float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))]


def terrain_height(world: Vineyard, x, y):
  """Terrain height (m) at (x, y), bilinear in the heightfield cells (numpy)."""
  xmin, xmax, ymin, ymax = world.terrain_extent
  nrow, ncol = world.terrain.shape
  u = np.clip((np.asarray(x) - xmin) / (xmax - xmin) * (ncol - 1), 0, ncol - 1.000001)
  v = np.clip((np.asarray(y) - ymin) / (ymax - ymin) * (nrow - 1), 0, nrow - 1.000001)
  j, i = np.floor(u).astype(int), np.floor(v).astype(int)
  fu, fv = u - j, v - i
  t = world.terrain
  return (t[i, j] * (1 - fu) * (1 - fv) + t[i, j + 1] * fu * (1 - fv) +
          t[i + 1, j] * (1 - fu) * fv + t[i + 1, j + 1] * fu * fv)


def random_poses(model: mujoco.MjModel, world: Vineyard, n: int, seed: int = 0,
                 tilt: float = 0.05) -> list[mujoco.MjData]:
  """`n` host MjData of `model` (built from `world`) with the robot on random lanes and
  points along them, alternate travel directions, yaw jitter +-0.4 rad and roll and pitch
  uniform in +-`tilt` rad, after `mj_forward` (no physics: the robot hovers 2 cm above
  the terrain at the largest wheel radius of the built-in robots and of `model`'s). Camera
  poses for depth tests and benchmarks."""
  rng = np.random.default_rng(seed)
  wheel = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "wheel0")
  own = [float(model.geom_size[wheel, 0])] if wheel >= 0 else []
  radius = max([r.wheel_radius for r in ROBOTS.values()] + own)
  out = []
  for i in range(n):
    line = world.lanes[i % len(world.lanes)].centerline
    x, y = line[rng.integers(len(line))]
    yaw = rng.uniform(-0.4, 0.4) + (np.pi if i % 2 else 0.0)
    d = mujoco.MjData(model)
    quat = np.zeros(4)
    mujoco.mju_euler2Quat(quat, np.array([*rng.uniform(-tilt, tilt, 2), yaw]), "xyz")
    d.qpos[:3] = [x, y, float(terrain_height(world, x, y)) + radius + 0.02]
    d.qpos[3:7] = quat
    mujoco.mj_forward(model, d)
    out.append(d)
  return out


SLOT_MULTIPLE = 16


def plant_slots_for(worlds: Sequence[Vineyard]) -> int:
  """Plant slots that fit every world of `worlds`: the largest plant count rounded up to
  a multiple of 16 (fewer geoms make MJX faster)."""
  need = max(len(w.plant_xy) for w in worlds)
  return -(-need // SLOT_MULTIPLE) * SLOT_MULTIPLE


# geom name prefixes, in order: a post is two cylinders, its lower and upper half (so that
# no camera primitive is much taller than a canopy: the camera's reach, and with it the
# primitives it reads per step, follows the largest), the lower one an obstacle
SCENERY = ("post", "post_top", *(name[:-1] for name in SHAPE_TABLES))
_GT = mujoco.mjtGeom
_SCENERY_GEOM = {"post": _GT.mjGEOM_CYLINDER, "post_top": _GT.mjGEOM_CYLINDER,
                 "cordon": _GT.mjGEOM_CYLINDER, "lobe": _GT.mjGEOM_ELLIPSOID,
                 "shoot": _GT.mjGEOM_ELLIPSOID, "tuft": _GT.mjGEOM_ELLIPSOID}
_SCENERY_RGBA = {"post": [0.45, 0.4, 0.35, 1], "post_top": [0.45, 0.4, 0.35, 1],
                 "cordon": [0.35, 0.22, 0.1, 1], "lobe": [0.2, 0.5, 0.15, 1],
                 "shoot": [0.3, 0.6, 0.2, 1], "tuft": [0.45, 0.55, 0.2, 1]}
_PARKED_SIZE = {"post": [0.04, 0.5, 0], "post_top": [0.04, 0.5, 0],
                "cordon": [0.035, 0.4, 0]}  # ellipsoids: [0.1] * 3


def scenery_slots_for(worlds: Sequence[Vineyard]) -> dict[str, int]:
  """Slots of each kind of scenery (`SCENERY`) that fit every world of `worlds`: the
  largest count, rounded up to a multiple of 16 (0 where no world has any)."""
  need = {k: max(len(_scenery_table(w, k)) for w in worlds) for k in SCENERY}
  return {k: -(-n // SLOT_MULTIPLE) * SLOT_MULTIPLE for k, n in need.items()}


def _scenery_table(world: Vineyard, kind: str) -> np.ndarray:
  """`world`'s shapes of `kind` as (n, 10) rows [x, y, z above the ground, size (3),
  quat (4)]; posts as the lower or upper halves (`post_top`) of vertical cylinders on the
  ground (a fixed yaw of 1 rad: see the parked slots in `build_spec`)."""
  if kind not in ("post", "post_top"):
    return getattr(world, kind + "s")
  n = len(world.post_xy)
  h = world.post_height
  z = h / 4 if kind == "post" else 3 * h / 4
  return np.concatenate([world.post_xy, z[:, None], world.post_radius[:, None],
                         (h / 4)[:, None], np.zeros((n, 1)),
                         np.tile(_yaw_quat(1.0), (n, 1))], 1)


def terrain_span(world: Vineyard) -> float:
  """The half-range (m) of `world`'s heightfield: its largest |height| (at least the
  bumps' amplitude, and 0.1 mm)."""
  return max(TERRAIN_AMPLITUDE_M, float(np.abs(world.terrain).max()), 1e-4)


def build_spec(world: Vineyard, cfg: Config, plant_slots: int | None = None,
               terrain_span_m: float | None = None, plants: bool = True,
               scenery_slots: dict[str, int] | None = None) -> mujoco.MjSpec:
  """The MjSpec of `world` with the robot of `cfg.robot` at the start of lane 1, forward.

  `plant_slots` (default: `plant_slots_for([world])`) fixes the number of plant geom
  pairs, `scenery_slots` (default: `scenery_slots_for([world])`) those of each kind of
  scenery, and `terrain_span_m` (default `terrain_span(world)`) the heightfield's
  height range, so that worlds built with the same values batch together. `plants=False`
  leaves the plant and scenery geoms out (the env's physics model: they take part in no
  contact, and MJX would pose every one of them at every physics step).
  """
  spec = mujoco.MjSpec()
  # the same for all worlds (names are static); a robot file's name, not its path
  spec.modelname = f"vineyard_{cfg.robot.spec.name}"
  spec.option.timestep = PHYSICS_DT_S
  spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
  spec.option.iterations = SOLVER_ITERATIONS
  spec.option.ls_iterations = SOLVER_LS_ITERATIONS
  spec.stat.extent = 10.0
  spec.visual.map.zfar = 200.0

  spec.add_texture(name="grid", type=mujoco.mjtTexture.mjTEXTURE_2D,
                   builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER, width=256, height=256,
                   rgb1=[0.45, 0.38, 0.28], rgb2=[0.40, 0.34, 0.25])
  mat = spec.add_material(name="soil", texrepeat=[20, 20])
  mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "grid"
  spec.worldbody.add_light(name="sun", pos=[0, 0, 30], dir=[0.2, 0.2, -1],
                           type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)

  # Terrain: MuJoCo mixes friction by max, so the wheels' friction decides. Heights span
  # exactly [-amp, amp] (two far corners, in the margin, pinned), so MuJoCo's [0, 1]
  # rescaling of the data is exact and the same for every world of a batch.
  xmin, xmax, ymin, ymax = world.terrain_extent
  amp = terrain_span(world) if terrain_span_m is None else terrain_span_m
  nrow, ncol = world.terrain.shape
  hfield = spec.add_hfield(name="terrain", nrow=nrow, ncol=ncol,
                           size=[(xmax - xmin) / 2, (ymax - ymin) / 2, 2 * amp, TERRAIN_BASE_M])
  data = (world.terrain + amp) / (2 * amp)
  if data[0, 0] != 0.0 or data[-1, -1] != 1.0:  # generated worlds come pinned: unchanged
    data = data.copy()
    data[0, 0], data[-1, -1] = 0.0, 1.0
  hfield.userdata = data.ravel().tolist()
  spec.worldbody.add_geom(name="terrain", type=mujoco.mjtGeom.mjGEOM_HFIELD,
                          hfieldname="terrain", pos=[(xmin + xmax) / 2, (ymin + ymax) / 2, -amp],
                          group=0, material="soil", friction=[0.1, 0.005, 0.0001])

  _add_plants(spec, world, plant_slots_for([world]) if plant_slots is None else plant_slots,
              plants)
  slots = scenery_slots_for([world]) if scenery_slots is None else scenery_slots
  for kind in SCENERY if plants else ():
    _add_scenery(spec, world, kind, slots.get(kind, 0))

  robot = cfg.robot.spec
  max_wheel = 1.5 * (cfg.env.v_max + cfg.env.w_max * robot.track_slip * robot.track / 2) / robot.wheel_radius
  add_robot(spec, robot, fovy_deg=cfg.camera.fovy_deg, max_wheel_speed=max_wheel)
  start = world.lanes[0].centerline[2]
  chassis = spec.body("chassis")
  chassis.pos = [start[0], start[1],
                 float(terrain_height(world, start[0], start[1])) + robot.wheel_radius + 0.01]
  return spec


def _add_plants(spec: mujoco.MjSpec, world: Vineyard, slots: int, plants: bool) -> None:
  """`slots` plant slots of a trunk cylinder and a canopy ellipsoid each: the world's
  plants, then parked ones (none where not `plants`)."""
  n = len(world.plant_xy)
  if n > slots:
    raise ValueError(f"plant_slots = {slots}: the world has {n} plants")
  ground = terrain_height(world, world.plant_xy[:, 0], world.plant_xy[:, 1])
  for i in range(slots if plants else 0):
    if i < n:
      x, y = world.plant_xy[i]
      h, z0 = world.trunk_height[i], ground[i]
      trunk_pos, canopy_pos = [x, y, z0 + h / 2], [x, y, z0 + world.canopy_z[i]]
      trunk_size, canopy_size = [world.trunk_radius, h / 2, 0], world.canopy_half[i].tolist()
      quat = _yaw_quat(world.plant_yaw[i])
    else:
      trunk_pos = canopy_pos = [0, 0, PARKED_Z]
      # A non-identity quat: MJX keeps a static per-geom "same frame" flag, and it must
      # not depend on which slots are in use.
      trunk_size, canopy_size, quat = [0.04, 0.35, 0], [0.2, 0.2, 0.4], _yaw_quat(1.0)
    if i < n and world.season != "classic":
      canopy_pos = [x, y, PARKED_Z]  # the canopy is lobes (or none): its slot stays parked
    common = dict(group=1, contype=0, conaffinity=0, quat=quat)
    spec.worldbody.add_geom(name=f"plant{i}_trunk", type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                            pos=trunk_pos, size=trunk_size, rgba=[0.35, 0.22, 0.1, 1], **common)
    spec.worldbody.add_geom(name=f"plant{i}_canopy", type=mujoco.mjtGeom.mjGEOM_ELLIPSOID,
                            pos=canopy_pos, size=canopy_size, rgba=[0.2, 0.5, 0.15, 1], **common)


def _add_scenery(spec: mujoco.MjSpec, world: Vineyard, kind: str, slots: int) -> None:
  """`slots` geoms `{kind}{i}` of `world`'s scenery of `kind`, on its terrain; the
  unused ones parked."""
  table = _scenery_table(world, kind)
  if len(table) > slots:
    raise ValueError(f"{kind} slots = {slots}: the world has {len(table)}")
  ground = terrain_height(world, table[:, 0], table[:, 1])
  for i in range(slots):
    if i < len(table):
      pos, size, quat = [*table[i, :2], ground[i] + table[i, 2]], table[i, 3:6], table[i, 6:]
    else:  # (a non-identity quat, as the parked plant slots)
      pos, size, quat = [0, 0, PARKED_Z], _PARKED_SIZE.get(kind, [0.1] * 3), _yaw_quat(1.0)
    spec.worldbody.add_geom(name=f"{kind}{i}", type=_SCENERY_GEOM[kind], pos=pos,
                            size=list(size), quat=list(quat), rgba=_SCENERY_RGBA[kind],
                            group=1, contype=0, conaffinity=0)


def build_model(world: Vineyard, cfg: Config, plant_slots: int | None = None,
                terrain_span_m: float | None = None, plants: bool = True,
                scenery_slots: dict[str, int] | None = None) -> mujoco.MjModel:
  """Compiles the MuJoCo model of `world` with the robot and camera of `cfg` (`plants`,
  slots: see `build_spec`)."""
  return build_spec(world, cfg, plant_slots, terrain_span_m, plants, scenery_slots).compile()


def build_models(worlds: Sequence[Vineyard], cfg: Config,
                 plants: bool = True) -> list[mujoco.MjModel]:
  """Models of `worlds` with a common number of plant and scenery slots and terrain
  height range, ready for `batch_models` (`plants`: see `build_spec`)."""
  slots, scenery = plant_slots_for(worlds), scenery_slots_for(worlds)
  span = max(terrain_span(w) for w in worlds)
  return [build_model(w, cfg, slots, span, plants, scenery) for w in worlds]


CLASSIC_MAX_PRIMS = 64  # `depth.DepthCamera`'s default, ample for two primitives a plant
CANOPY_TILE_SLOTS = 12  # primitives a tile of canopy lobes needs (the default 8 overflows)
# The most camera primitives in view over 48 lane poses (tilts to 0.05-0.1 rad; the
# 60 x 46.8 deg, 5 m camera) were those of 16-18 m^2 of the vineyard: classic 21 at 1.2 a
# m^2, summer 66 at 3.9 and 87 at 5.5, winter with 2 tufts a m^2 60 at 3.5 (a tuft
# counting as `TUFT_WEIGHT` primitives: they lie near the camera). A fifth to spare:
VIEW_M2 = 21.0
TUFT_WEIGHT = 1.4
PRIM_STEP = 16  # max_prims rounds up to a multiple of this


def camera_limits(worlds: Sequence[Vineyard], camera=None) -> dict[str, int]:
  """The keyword arguments of `depth.DepthCamera.create` that the scenery of `worlds`
  needs so that the camera's culling leaves out nothing in view (`render_depth_info`:
  dropped 0): none where every world is classic (its defaults); else max_prims for the
  camera primitives per m^2 of the densest world (`VIEW_M2`; a plant's m^2 is its
  spacing times the inter-row distance), scaled by the ground the view of `camera` (a
  CameraConfig; default the paper's) covers, at least `CLASSIC_MAX_PRIMS`, and
  `CANOPY_TILE_SLOTS` primitives a tile where a world has canopy lobes (what they cost:
  docs/results/realism.md, The env step with everything on)."""
  if all(w.season == "classic" for w in worlds):
    return {}
  def per_m2(w):
    prims = len(w.plant_xy) * (1 if w.season != "classic" else 2) + sum(
        len(_scenery_table(w, k)) * (TUFT_WEIGHT if k == "tuft" else 1) for k in SCENERY)
    return prims / max(len(w.plant_xy) * w.spacing_m * w.inter_row_m, 1e-9)
  view = 1.0 if camera is None else (math.tan(math.radians(camera.fovx_deg) / 2)
                                     * camera.max_depth_m ** 2 / (math.tan(math.pi / 6) * 25))
  need = VIEW_M2 * max(map(per_m2, worlds)) * view
  limits = {"max_prims": max(CLASSIC_MAX_PRIMS, PRIM_STEP * math.ceil(need / PRIM_STEP))}
  if any(len(w.lobes) for w in worlds):
    limits["tile_slots"] = CANOPY_TILE_SLOTS
  return limits


def obstacle_geom_ids(model: mujoco.MjModel, slots: int) -> np.ndarray:
  """Geom ids of the vertical cylinders that the robot must not touch: the `slots` plant
  trunks in slot order, then every trellis post slot (`post{i}`, a post's lower half)."""
  posts = []
  while (g := mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"post{len(posts)}")) >= 0:
    posts.append(g)
  return np.concatenate([plant_geom_ids(model, slots, posts=False)[0],
                         np.asarray(posts, np.int64)]).astype(np.int64)


def plant_geom_ids(model: mujoco.MjModel, slots: int,
                   posts: bool = True) -> tuple[np.ndarray, np.ndarray]:
  """Geom ids of the plant trunks (slots,) and canopies (slots,), in slot order. With
  `posts` the trunks' ids are followed by the trellis posts' (`obstacle_geom_ids`: the
  trunk table of the env's collision check holds every obstacle)."""
  ids = [[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"plant{i}_{part}")
          for i in range(slots)] for part in ("trunk", "canopy")]
  trunks = obstacle_geom_ids(model, slots) if posts else np.asarray(ids[0])
  return trunks, np.asarray(ids[1])
