"""The env step's cost follows what is near the robot, not the vineyard's size: the
physics steps no plant geoms, the camera and the collision check read fixed-size sets of
plants near the robot (`mjxvine.nearby`), and those sets miss nothing in reach.

Structural checks (shapes of the traced program, brute force over points), no timings:
`python -m mjxvine.bench env --block 12x200` times it."""

import dataclasses
from collections import Counter

import jax
import jax.numpy as jp
import numpy as np
import pytest
from jax.extend.core import jaxprs_in_params
from mujoco import mjx

from mjxvine import depth
from mjxvine.config import load_config
from mjxvine.env import VineyardEnv, training_env
from mjxvine.nearby import MARGIN_M, NearbyIndex
from mjxvine.worlds import generate_world, layout, random_poses

TINY = ["camera.width=8", "camera.height=6", "env.max_steps=20"]
# Plants every metre exactly (and no jitter: `layout.JITTER_FRAC` patched), all of one size:
# any two windows of the rows hold as many.
REGULAR = ["world.spacing_m=[1.0, 1.0]", "world.inter_row_m=[2.0, 2.0]",
           "world.trunk_height_m=[0.7, 0.7]", "world.canopy_width_m=[0.4, 0.4]",
           "world.canopy_top_m=[1.8, 1.8]", "world.train_rows=4", "world.train_length_m=72"]
PLANT_FIELDS = ("plant_xy", "plant_yaw", "plant_row", "trunk_height", "canopy_half", "canopy_z")


def _points(worlds, rows, length, seed):
  """Plant-like points (Wd, P, 2): rows 2 m apart, a point every ~0.9 m, jittered; the
  last world has fewer (the rest not kept), as pool worlds with gaps."""
  rng = np.random.default_rng(seed)
  x, y = np.meshgrid(np.arange(0.0, length, 0.9), np.arange(rows) * 2.0)
  base = np.stack([x.ravel(), y.ravel()], -1)
  xy = base[None] + rng.uniform(-0.1, 0.1, (worlds, len(base), 2))
  keep = np.ones(xy.shape[:2], bool)
  keep[-1, ::7] = False
  return xy, keep


def test_nearby_returns_every_point_in_reach_ascending():
  xy, keep = _points(3, 6, 60.0, seed=0)
  for reach in (0.9, 3.0, 8.0):
    index = NearbyIndex.build(xy, keep, reach)
    near = jax.jit(index.near)
    rng = np.random.default_rng(1)
    for q in rng.uniform([-10, -10], [70, 20], (60, 2)):
      for world in range(3):
        ids = np.asarray(near(world, jp.asarray(q, jp.float32)))
        assert ids.shape == (index.size,) and np.all(np.diff(ids) >= 0)
        inside = keep[world] & np.all(np.abs(xy[world] - q) <= reach, -1)
        found = set(ids[ids < index.count].tolist())
        assert set(np.flatnonzero(inside).tolist()) <= found  # none missed
        assert keep[world][list(found)].all()  # none that was left out
  assert index.reach == 8.0 + MARGIN_M


def test_nearby_queries_do_not_grow_with_the_rows_length():
  short, long_ = (NearbyIndex.build(*_points(1, 6, length, seed=2), 8.0)
                  for length in (40.0, 400.0))
  assert long_.count > 9 * short.count
  assert long_.size <= short.size + 12 * long_.window[0]  # the jitter: a point per run
  assert long_.size < long_.count / 5


@pytest.fixture(scope="module")
def envs():
  """(a regular 4-row world of 72 m, [training envs on it with the plants of x < 30 m
  only, and on it]): the same terrain, lanes and plant density, 2.4 times the plants."""
  cfg = load_config("experiments/smoke.yaml", TINY + REGULAR)
  with pytest.MonkeyPatch.context() as patch:
    patch.setattr(layout, "JITTER_FRAC", 0.0)
    world = generate_world("train", 0, cfg.world)
  keep = world.plant_xy[:, 0] < 30.0
  short = dataclasses.replace(world, **{f: getattr(world, f)[keep] for f in PLANT_FIELDS})
  return world, [training_env(cfg, [w]) for w in (short, world)]


def _shapes(jaxpr) -> Counter:
  """(primitive, output shapes) of every equation of a jaxpr, nested ones included."""
  out = Counter()
  for eqn in jaxpr.eqns:
    out[(eqn.primitive.name, tuple(tuple(v.aval.shape) for v in eqn.outvars))] += 1
    for sub in jaxprs_in_params(eqn.params):
      out += _shapes(sub)
  return out


def test_the_env_step_is_the_same_program_with_more_plants(envs):
  _, envs = envs
  short, long_ = (e.env for e in envs)
  assert len(long_.worlds[0].plant_xy) > 2 * len(short.worlds[0].plant_xy)
  # the physics model has no plant geoms: the same in both, and much smaller
  assert short.physics_model(0).ngeom == long_.physics_model(0).ngeom < 10
  # the camera and the collision check read as many plants in both, fewer than all
  assert short._near_plants.size == long_._near_plants.size < short._near_plants.count
  assert short._near_trunks.size == long_._near_trunks.size < short._near_trunks.count
  programs = [_shapes(jax.make_jaxpr(
      lambda k, e=e: e.step_batch(e.reset_batch(k, 2), jp.zeros((2, 2))))(
          jax.random.PRNGKey(0)).jaxpr) for e in envs]
  # every array that reset and step (auto-reset included) compute has the same shape in
  # both: none grows with the number of plants (the plant tables are constants, read by
  # gathers of a fixed size)
  assert programs[0] == programs[1]


def test_the_camera_sees_what_it_saw_with_every_plant(envs):
  world, envs = envs
  env: VineyardEnv = envs[1].env
  cam, m = env.camera, env.world_model(0)
  datas = random_poses(env.mj_model, world, 8, seed=3)
  dx = jax.tree.map(lambda *x: jp.stack(x), *[mjx.put_data(env.mj_model, d) for d in datas])

  def both(d):
    full = depth.render_depth_info(cam, m, d)
    ids = env._near_plants.near(0, d.cam_xpos[cam.cam_id, :2])
    near = depth.render_depth_info(cam, m, d, env._plants.take(ids, 0), env._terrain_ref[0])
    return full, near

  (full, info_full), (near, info_near) = jax.jit(jax.vmap(both))(dx)
  assert np.all(np.asarray(info_full["seen"]) > 0)
  np.testing.assert_array_equal(info_near["seen"], info_full["seen"])
  # the same primitives: equal but for float32 rounding of the poses (host vs MJX)
  np.testing.assert_allclose(near, full, atol=1e-3)
