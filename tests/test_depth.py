"""Tests of mjxvine.depth: agreement with MuJoCo's C ray caster, conventions, culling,
noise and storage. Small images (24x32) except one 112x112 comparison; compiled
functions are shared through session fixtures (2 CPU cores)."""

from __future__ import annotations

import math
import types
from functools import partial

import jax
import jax.numpy as jp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from mjxvine import depth
from mjxvine.config import CameraConfig, Config, replace

SMALL = CameraConfig(height=24, width=32)

try:  # the real vineyards, once mjxvine.worlds is there
  from mjxvine.worlds import build_model, generate_world, random_poses
  HAVE_WORLDS = True
except ImportError:  # pragma: no cover
  HAVE_WORLDS = False


# ------------------------------------------------------------------ scenes

def make_scene(seed: int, slots: int = 40, extras: str = "") -> mujoco.MjModel:
  """A small vineyard with the conventions of mjxvine.worlds: hfield `terrain` (group 0),
  plant slots `plant{i}_trunk` (cylinder) / `plant{i}_canopy` (ellipsoid, yawed) in group
  1 (unused ones parked at z = -100), a free robot of group-2 geoms with camera `depth`.

  extras: "shapes" adds a capsule and a sphere; "wall" adds a flat disc (a wide cylinder
  cap) facing +x at x = 3; "robot_group1" adds a group-1 geom on the robot in view.
  """
  rng = np.random.default_rng(seed)
  spec = mujoco.MjSpec()
  sx, sy, nrow, ncol = 7.5, 5.0, 41, 61  # 0.25 m cells
  coarse = rng.uniform(-1, 1, (11, 16))
  yy, xx = np.linspace(0, 10, nrow), np.linspace(0, 15, ncol)
  fine = np.array([np.interp(xx, np.arange(16), row) for row in coarse])
  fine = np.array([np.interp(yy, np.arange(11), col) for col in fine.T]).T
  flat = "wall" in extras
  data = np.zeros_like(fine) if flat else (fine - fine.min()) / (fine.max() - fine.min())
  spec.add_hfield(name="terrain", nrow=nrow, ncol=ncol, size=[sx, sy, 0.1, 0.2],
                  userdata=data.ravel().tolist())
  spec.worldbody.add_geom(name="terrain", type=mujoco.mjtGeom.mjGEOM_HFIELD,
                          hfieldname="terrain", pos=[0, 0, -0.05], group=0)
  ground = lambda x, y: -0.05 + 0.1 * data[int(round((y + sy) / 0.25)), int(round((x + sx) / 0.25))]
  plants = []
  for row_y in () if flat else (-1.75, 0.0, 1.75):
    x = -6.0 + rng.uniform(0, 0.5)
    while x < 6.0 and len(plants) < slots:
      plants.append((x + rng.triangular(-0.08, 0, 0.08), row_y + rng.triangular(-0.08, 0, 0.08)))
      x += rng.uniform(0.7, 1.0)
  for i in range(slots):
    common = dict(group=1, contype=0, conaffinity=0)
    if i < len(plants):
      x, y = plants[i]
      h, top, c = rng.uniform(0.6, 0.8), rng.uniform(1.6, 1.9), rng.uniform(0.3, 0.4)
      yaw = rng.uniform(-np.pi, np.pi)
      z0 = ground(x, y) - 0.02
      tpos, cpos = [x, y, z0 + h / 2], [x, y, z0 + top - c]
      tsize, csize = [0.04, h / 2, 0], [rng.uniform(0.15, 0.25), rng.uniform(0.1, 0.2), c]
    else:
      tpos = cpos = [0, 0, -100]
      tsize, csize, yaw = [0.04, 0.35, 0], [0.2, 0.2, 0.4], 1.0
    quat = [math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)]
    spec.worldbody.add_geom(name=f"plant{i}_trunk", type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                            pos=tpos, size=tsize, quat=quat, **common)
    spec.worldbody.add_geom(name=f"plant{i}_canopy", type=mujoco.mjtGeom.mjGEOM_ELLIPSOID,
                            pos=cpos, size=csize, quat=quat, **common)
  if "shapes" in extras:
    spec.worldbody.add_geom(name="capsule", type=mujoco.mjtGeom.mjGEOM_CAPSULE, group=1,
                            size=[0.15, 0.4, 0], pos=[2.5, 0.6, 0.3],
                            quat=[0.8, 0.3, 0.5, 0.1], contype=0, conaffinity=0)
    spec.worldbody.add_geom(name="sphere", type=mujoco.mjtGeom.mjGEOM_SPHERE, group=1,
                            size=[0.3, 0, 0], pos=[3.5, -0.8, 0.2], contype=0, conaffinity=0)
    spec.worldbody.add_geom(name="tilted_cyl", type=mujoco.mjtGeom.mjGEOM_CYLINDER, group=1,
                            size=[0.2, 0.3, 0], pos=[2.0, -0.4, 0.25], contype=0,
                            conaffinity=0, quat=[0.9, 0.0, 0.43, 0.0])
  if flat:
    spec.worldbody.add_geom(name="wall", type=mujoco.mjtGeom.mjGEOM_CYLINDER, group=1,
                            size=[20.0, 0.5, 0], pos=[3.5, 0, 0],
                            quat=[0.7071068, 0, -0.7071068, 0], contype=0, conaffinity=0)
  robot = spec.worldbody.add_body(name="robot", pos=[0, 0, 0.2])
  robot.add_freejoint()
  robot.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.25, 0.2, 0.1], group=2)
  # A group-2 geom right in front of the lens: the camera must look through it.
  robot.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.1, 0, 0], pos=[0.5, 0, 0.15],
                 group=2)
  if "robot_group1" in extras:
    robot.add_geom(type=mujoco.mjtGeom.mjGEOM_ELLIPSOID, size=[0.05, 0.2, 0.1],
                   pos=[0.6, 0, 0.15], group=1, contype=0, conaffinity=0)
  robot.add_camera(name="depth", pos=[0.21, 0, 0.06], xyaxes=[0, -1, 0, 0, 0, 1])
  return spec.compile()


def pose(model, x, y, yaw, z=0.14, roll=0.0, pitch=0.0):
  d = mujoco.MjData(model)
  quat = np.zeros(4)
  mujoco.mju_euler2Quat(quat, np.array([roll, pitch, yaw]), "xyz")
  d.qpos[:3] = [x, y, z]
  d.qpos[3:7] = quat
  mujoco.mj_forward(model, d)
  return d


def scene_poses(model, n, seed):
  """Poses in the two lanes (y = +-0.875), either direction, small tilts."""
  rng = np.random.default_rng(seed)
  return [pose(model, rng.uniform(-4, 4), rng.choice([-0.875, 0.875]) + rng.uniform(-0.2, 0.2),
               rng.uniform(-0.5, 0.5) + (np.pi if i % 2 else 0.0), 0.14 + rng.uniform(0, 0.05),
               *rng.uniform(-0.08, 0.08, 2)) for i in range(n)]


def silhouette(ref: np.ndarray, step: float = 0.05) -> np.ndarray:
  """Pixels whose reference depth differs by more than `step` m from a 4-neighbour."""
  edge = np.zeros(ref.shape, bool)
  dv = np.abs(np.diff(ref, axis=0)) > step
  dh = np.abs(np.diff(ref, axis=1)) > step
  edge[1:] |= dv
  edge[:-1] |= dv
  edge[:, 1:] |= dh
  edge[:, :-1] |= dh
  return edge


def compare(img, ref):
  """(fraction within 1 cm, pixels off by > 5 cm away from silhouette edges, max error)."""
  err = np.abs(np.asarray(img, np.float64) - ref)
  return float(np.mean(err < 0.01)), int(np.sum((err > 0.05) & ~silhouette(ref))), float(err.max())


# ------------------------------------------------------------------ fixtures

@pytest.fixture(scope="session")
def synth():
  """Three synthetic worlds of one structure, one camera, one compiled renderer."""
  models = [make_scene(s) for s in range(3)]
  cam = depth.DepthCamera.create(models[0], SMALL)
  render = jax.jit(partial(depth.render_depth_info, cam))
  return models, cam, render


@pytest.fixture(scope="session")
def shapes():
  model = make_scene(5, slots=16, extras="shapes robot_group1")
  cam = depth.DepthCamera.create(model, SMALL)
  return model, cam, jax.jit(partial(depth.render_depth_info, cam))


def check_agreement(model, cam, render, datas, min_frac=0.995):
  total, bad, worst = [], 0, 0.0
  for d in datas:
    img, info = render(mjx.put_model(model), mjx.put_data(model, d))
    frac, nbad, err = compare(img, depth.reference_depth(model, d, cam))
    assert int(info["dropped"]) == 0 and int(info["tile_overflow"]) == 0, info
    total.append(frac)
    bad += nbad
    worst = max(worst, err)
  assert np.mean(total) >= min_frac, (total, worst)
  assert bad == 0
  return float(np.mean(total))


# ------------------------------------------------------------------ tests

def test_reference_agreement_synthetic(synth):
  models, cam, render = synth
  for i, model in enumerate(models):
    check_agreement(model, cam, render, scene_poses(model, 4, i))


def test_batched_worlds_vmap(synth):
  """One mjx.Model holding several worlds (batched fields), vmapped with in_axes."""
  models, cam, _ = synth
  puts = [mjx.put_model(m) for m in models]
  flat = [jax.tree_util.tree_flatten(p) for p in puts]
  leaves, axes = [], []
  for group in zip(*(f[0] for f in flat)):
    same = all(np.array_equal(np.asarray(group[0]), np.asarray(x)) for x in group[1:])
    leaves.append(group[0] if same else jp.stack(group))
    axes.append(None if same else 0)
  batched, in_axes = flat[0][1].unflatten(leaves), flat[0][1].unflatten(axes)
  assert in_axes.hfield_data == 0 and in_axes.geom_size == 0
  datas = [scene_poses(m, 1, 10 + i)[0] for i, m in enumerate(models)]
  dx = jax.tree.map(lambda *x: jp.stack(x), *[mjx.put_data(m, d) for m, d in zip(models, datas)])
  imgs = jax.jit(jax.vmap(partial(depth.render_depth, cam), in_axes=(in_axes, 0)))(batched, dx)
  assert imgs.shape == (3, cam.height, cam.width) and imgs.dtype == jp.float32
  for img, m, d in zip(imgs, models, datas):
    frac, bad, _ = compare(img, depth.reference_depth(m, d, cam))
    assert frac >= 0.995 and bad == 0


def test_zdepth_convention_flat_wall():
  """A flat wall facing the camera at a known distance reads that distance in every
  pixel (z-depth, not ray length); flat ground reads h / tan(angle below the axis)."""
  model = make_scene(0, slots=16, extras="wall")
  cfg = CameraConfig(height=24, width=32)
  cam = depth.DepthCamera.create(model, cfg)
  d = pose(model, 0.0, 0.0, 0.0, z=0.2)
  img, _ = jax.jit(partial(depth.render_depth_info, cam))(mjx.put_model(model),
                                                         mjx.put_data(model, d))
  img = np.asarray(img)
  cx = d.cam_xpos[cam.cam_id][0]
  wall = 3.5 - 0.5 - cx  # cylinder axis along x, cap at x = 3.0
  cz = d.cam_xpos[cam.cam_id][2]
  eta = (1 - 2 * (np.arange(cam.height) + 0.5) / cam.height) * cam.tan_y
  ground = np.where(eta < 0, (cz + 0.05) / np.maximum(-eta, 1e-9), np.inf)  # terrain z=-0.05
  expect = np.minimum(np.minimum(wall, ground), cam.max_depth)[:, None] * np.ones((1, cam.width))
  np.testing.assert_allclose(img, expect, atol=2e-4)
  assert np.allclose(img[: cam.height // 2], wall, atol=2e-4)  # the wall, everywhere above
  np.testing.assert_allclose(img, depth.reference_depth(model, d, cam), atol=2e-4)


def test_pixel_convention():
  cam = depth.DepthCamera.create(make_scene(0, slots=16), CameraConfig(height=4, width=6))
  rays = cam.pixel_rays()
  tx, ty = math.tan(math.radians(30)), math.tan(math.radians(23.4))
  assert rays.shape == (4, 6, 3) and np.all(rays[..., 2] == -1)
  np.testing.assert_allclose(rays[0, 0, :2], [-tx * 5 / 6, ty * 3 / 4], rtol=1e-6)  # top left
  np.testing.assert_allclose(rays[3, 5, :2], [tx * 5 / 6, -ty * 3 / 4], rtol=1e-6)


def test_orientation_left_top():
  """An object to the camera's left shows in the left columns; rows run top-down."""
  model = make_scene(0, slots=16, extras="wall")
  cam = depth.DepthCamera.create(model, SMALL)
  render = jax.jit(partial(depth.render_depth, cam))
  # Looking along +x, +y is to the left: turn the robot so the wall is at its right.
  d = pose(model, 0.0, 0.0, 0.3, z=0.2)
  img = np.asarray(render(mjx.put_model(model), mjx.put_data(model, d)))
  # Turned left (yaw > 0), the wall (perpendicular to x) is nearer on the right side.
  assert img[2, -1] < img[2, 0]
  assert img[-1].mean() < img[0].mean()  # bottom rows see the ground, nearer


def test_shapes_and_robot_excluded(shapes):
  """Capsules, spheres, tilted cylinders agree with mj_multiRay; the robot's own geoms
  (group 2, and even group 1 ones on its bodies) are never seen."""
  model, cam, render = shapes
  datas = [pose(model, 0.0, y, yaw, roll=r) for y, yaw, r in
           [(0.0, 0.0, 0.0), (0.2, 0.2, 0.05), (-0.3, -0.2, -0.05)]]
  for d in datas:
    img, info = render(mjx.put_model(model), mjx.put_data(model, d))
    ref = depth.reference_depth(model, d, cam)
    # the reference sees the group-1 geom on the robot: exclude the robot body by hand
    robot = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "robot")
    rot = d.cam_xmat[cam.cam_id].reshape(3, 3)
    rays = cam.pixel_rays().reshape(-1, 3).astype(np.float64) @ rot.T
    norm = np.linalg.norm(rays, axis=1)
    gid, dist = np.zeros(len(rays), np.int32), np.zeros(len(rays))
    mujoco.mj_multiRay(model, d, d.cam_xpos[cam.cam_id].copy(), (rays / norm[:, None]).ravel(),
                       np.array([1, 1, 0, 0, 0, 0], np.uint8), 1, robot, gid, dist, None,
                       len(rays), 1e9)
    ref_ex = np.minimum(np.where(dist >= 0, dist / norm, np.inf), cam.max_depth).reshape(ref.shape)
    assert np.any(ref < ref_ex - 0.1)  # the robot's group-1 geom is in view...
    frac, bad, _ = compare(img, ref_ex)  # ...and we do not see it
    assert frac >= 0.995 and bad == 0
    assert np.all(np.asarray(img) > 0.5)  # nothing of the robot right in front of the lens
  names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) for g in cam.prim_geom]
  assert {"capsule", "sphere", "tilted_cyl"} <= set(names)


def test_culling_same_as_no_culling(synth):
  """Looking down a row with many plants in view: the culled renderer equals testing
  every primitive in every pixel; too small a top_k is reported, and changes the image."""
  models, cam, render = synth
  model = models[0]
  full = depth.DepthCamera.create(model, SMALL, max_prims=10 ** 6, tile=(SMALL.height, SMALL.width),
                                  tile_slots=cam.prim_geom.size)
  tight = depth.DepthCamera.create(model, SMALL, max_prims=4)
  render_full = jax.jit(partial(depth.render_depth_info, full))
  render_tight = jax.jit(partial(depth.render_depth_info, tight))
  mx = mjx.put_model(model)
  changed = 0
  for i, d in enumerate(scene_poses(model, 3, 20) + [pose(model, -5.5, 0.9, 0.05)]):
    dx = mjx.put_data(model, d)
    img, info = render(mx, dx)
    ref, _ = render_full(mx, dx)
    assert int(info["seen"]) > 8  # culling matters: many primitives in view
    assert int(info["dropped"]) == 0 and int(info["tile_overflow"]) == 0
    np.testing.assert_allclose(img, ref, atol=1e-5)
    img_t, info_t = render_tight(mx, dx)
    assert int(info_t["dropped"]) == int(info["seen"]) - 4
    changed += int(np.any(np.abs(np.asarray(img_t) - np.asarray(ref)) > 0.05))
  assert changed > 0


def test_tiles_keep_their_nearest_overlaps_in_order():
  """The running count that gives each tile its slots is the cumulative sum of its
  overlaps, for K of every shape (blocks of about sqrt(K), the last one short)."""
  rng = np.random.default_rng(0)
  for k in (1, 5, 64, 144, 150):
    over = rng.random((7, k)) < 0.3
    np.testing.assert_array_equal(np.asarray(depth._running_count(jp.asarray(over))),
                                  np.cumsum(over, axis=1))


def test_unsupported_geoms_raise():
  spec = mujoco.MjSpec()
  spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[1, 1, 1], group=1)
  body = spec.worldbody.add_body(name="robot")
  body.add_freejoint()
  body.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.1, 0, 0], group=2)
  body.add_camera(name="depth")
  with pytest.raises(ValueError, match="unsupported"):
    depth.DepthCamera.create(spec.compile(), SMALL)
  with pytest.raises(ValueError, match="no camera"):
    depth.DepthCamera.create(make_scene(0, slots=16), SMALL, camera="nope")


# ------------------------------------------------------------------ noise and storage

def _spec_noise_std(d, k, sigma=0.2, clip=0.5, max_depth=5.0, n=2_000_000):
  """Std of the noisy depth (docs/design.md, Camera and noise) at true depth d, by numpy
  Monte Carlo."""
  rng = np.random.default_rng(0)
  n1 = np.clip(rng.normal(0, sigma, n), -clip, clip)
  n2 = np.clip(rng.normal(0, 1, n) * d / 10, -clip, clip)
  return np.clip(d + k * (n1 + n2), 0, max_depth).std()


def test_noise_statistics_and_clipping():
  cfg = CameraConfig()
  clean = jp.full((256, 256), 2.0, jp.float32)
  noisy = jax.jit(partial(depth.add_noise, cfg_or_params=cfg))(clean, jax.random.key(0))
  diff = np.asarray(noisy - clean)
  # n1 ~ clip(N(0, 0.2), +-0.5), n2 ~ clip(N(0, 0.2), +-0.5) at d = 2 m, independent
  assert abs(diff.mean()) < 0.005 and abs(diff.std() - _spec_noise_std(2.0, 1.0)) < 0.005
  assert np.abs(diff).max() <= 1.0 + 1e-6  # each term clipped to +-0.5

  # noise factor as a traced override; k = 0 is the identity
  f = jax.jit(lambda k, key: depth.add_noise(clean, key, cfg, noise_factor=k))
  d4 = np.asarray(f(jp.float32(4.0), jax.random.key(1)) - clean)
  assert abs(d4.std() - _spec_noise_std(2.0, 4.0)) < 0.02
  np.testing.assert_array_equal(np.asarray(f(jp.float32(0.0), jax.random.key(1))), clean)
  # the depth-proportional term alone (sigma = 0): std 0.25 at 2.5 m, clipped
  no_n1 = types.SimpleNamespace(max_depth=cfg.max_depth_m, noise_sigma=0.0,
                                noise_clip=depth.NOISE_CLIP_M, noise_factor=1.0)
  zero = np.asarray(depth.add_noise(jp.full((256, 256), 2.5), jax.random.key(2), no_n1))
  assert abs((zero - 2.5).std() - _spec_noise_std(2.5, 1.0, sigma=0.0)) < 0.005
  # output clipped to [0, max_depth]
  big = np.asarray(depth.add_noise(jp.linspace(0, 5, 4096).reshape(64, 64), jax.random.key(3),
                                   cfg, noise_factor=10.0))
  assert big.min() == 0.0 and big.max() == 5.0
  # explicit keys: same key same noise, another key other noise
  a = depth.add_noise(clean, jax.random.key(7), cfg)
  np.testing.assert_array_equal(a, depth.add_noise(clean, jax.random.key(7), cfg))
  assert not np.array_equal(a, depth.add_noise(clean, jax.random.key(8), cfg))


def test_quantize_roundtrip_bound():
  max_depth = 5.0
  x = np.concatenate([np.random.default_rng(0).uniform(0, max_depth, 100_000),
                      [0.0, max_depth, 1e-7, max_depth - 1e-6]]).astype(np.float32)
  q = depth.quantize_depth(x, max_depth)
  assert q.dtype == jp.uint16 and q.shape == x.shape
  back = depth.dequantize_depth(q, max_depth)
  assert back.dtype == jp.float32
  bound = max_depth / 131070 + 1e-6
  assert np.abs(np.asarray(back) - x).max() <= bound
  assert int(q.max()) == 65535 and int(q.min()) == 0
  np.testing.assert_array_equal(
      depth.quantize_depth(np.array([-1.0, 9.0, np.nan, np.inf]), max_depth), [0, 65535, 0, 65535])
  q8 = depth.quantize_depth(x, max_depth, jp.uint8)
  assert q8.dtype == jp.uint8
  assert np.abs(np.asarray(depth.dequantize_depth(q8, max_depth)) - x).max() <= max_depth / 510 + 1e-6


# ------------------------------------------------------------------ the real vineyards

needs_worlds = pytest.mark.skipif(not HAVE_WORLDS, reason="mjxvine.worlds not available")


@needs_worlds
@pytest.mark.parametrize("kind,robot", [("train", "jackal"), ("test", "jackal"),
                                        ("train", "husky"), ("test", "husky")])
def test_reference_agreement_worlds(kind, robot):
  cfg = replace(Config(), camera={"height": 24, "width": 32}, robot={"name": robot})
  world = generate_world(kind, 3, cfg.world)
  model = build_model(world, cfg)
  cam = depth.DepthCamera.create(model, cfg.camera)
  render = jax.jit(partial(depth.render_depth_info, cam))
  check_agreement(model, cam, render, random_poses(model, world, 4, seed=1, tilt=0.08))


@needs_worlds
def test_reference_agreement_on_slopes():
  """An 80 m test world on a 10 % slope along its rows and 5 % across: the camera sees the
  ground rise metres away, and the refinement the slope turns on keeps it on mj_multiRay."""
  cfg = replace(Config(), camera={"height": 24, "width": 32},
                world={"slope_pct": 10.0, "cross_slope_pct": 5.0, "test_length_m": 80.0})
  world = generate_world("test", 3, cfg.world)
  model = build_model(world, cfg)
  cam = depth.DepthCamera.create(model, cfg.camera)
  assert cam.terrain_refine == 3 and cam.hfield_size[2] > 8.0  # +-4.4 m of slope
  render = jax.jit(partial(depth.render_depth_info, cam))
  check_agreement(model, cam, render, random_poses(model, world, 6, seed=1, tilt=0.08))


@needs_worlds
def test_reference_agreement_112():
  """Full-size images of a train world, a batch of poses."""
  cfg = Config()
  world = generate_world("train", 0, cfg.world)
  model = build_model(world, cfg)
  cam = depth.DepthCamera.create(model, cfg.camera)
  datas = random_poses(model, world, 2, seed=4)
  dx = jax.tree.map(lambda *x: jp.stack(x), *[mjx.put_data(model, d) for d in datas])
  imgs, info = jax.jit(jax.vmap(partial(depth.render_depth_info, cam), in_axes=(None, 0)))(
      mjx.put_model(model), dx)
  assert imgs.shape == (2, 112, 112)
  assert np.all(np.asarray(info["dropped"]) == 0) and np.all(np.asarray(info["tile_overflow"]) == 0)
  for img, d in zip(imgs, datas):
    frac, bad, _ = compare(img, depth.reference_depth(model, d, cam))
    assert frac >= 0.995 and bad == 0
