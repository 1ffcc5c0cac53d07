"""Vineyard realism (`mjxvine.worlds.seasons`): classic worlds and models as they were,
trellis posts where the config puts them and in the env's collision check, each season's
shapes, tufts out of the physics and the collisions, seeds, the camera against MuJoCo's
`mj_multiRay` on a summer and a winter world, a vineyard file's season and post spacing,
and bad keys refused in one line. Small worlds, small images (2 CPU cores)."""

import json
import re
from functools import partial

import jax
import jax.numpy as jp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from mjxvine import depth
from mjxvine.config import ConfigError, WorldConfig, load_config
from mjxvine.worlds import (build_model, build_spec, camera_limits, generate_world,
                            load_test_world, load_world, obstacle_geom_ids, plant_geom_ids,
                            plant_slots_for, random_poses, save_world, terrain_height)
from mjxvine.worlds import layout, seasons
from mjxvine.worlds.build import PARKED_Z, SCENERY
from mjxvine.worlds.geo import local_to_lonlat, read_vineyard, write_csv, write_geojson
from mjxvine.worlds.layout import WorldFileError

SMALL = ["world.train_length_m=8", "world.test_length_m=10", "camera.width=32",
         "camera.height=24"]
# every realism key away from its default: none of them may change a classic world
REALISM = ["world.post_spacing_m=[3.0, 4.0]", "world.post_height_m=[2.0, 2.4]",
           "world.cordon_height_m=[0.8, 0.9]", "world.canopy_lobes=[4, 6]",
           "world.shoots_per_plant=[2, 3]", "world.shoot_reach_m=[0.2, 0.5]",
           "world.tuft_density_per_m2=3.0"]
SCENERY_NAME = re.compile(rf"({'|'.join(SCENERY)})\d+$")
ORIGIN = (7.62, 44.70)


def config(season: str, *more: str):
  return load_config(None, [f"world.season={season}", *SMALL, *more])


def names(model) -> list[str]:
  return [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or "" for g in range(model.ngeom)]


def ids(model, prefix: str) -> np.ndarray:
  return np.array([g for g, n in enumerate(names(model)) if re.fullmatch(rf"{prefix}\d+", n)])


def live(model, geoms) -> np.ndarray:
  """Of `geoms`, those not parked below the terrain."""
  return np.asarray([g for g in geoms if model.geom_pos[g, 2] > PARKED_Z / 2], int)


# --- classic: the default, and today's worlds --------------------------------------------

def test_classic_is_the_default_and_builds_the_same_worlds_and_models():
  default, classic = load_config(), load_config(None, ["world.season=classic", *REALISM])
  assert default.world.season == "classic" and WorldConfig().season == "classic"
  for kind, seed in (("train", 0), ("test", 3)):
    a, b = (generate_world(kind, seed, c.world) for c in (default, classic))
    assert json.dumps(a.to_json()) == json.dumps(b.to_json())
    assert not set(seasons.SCENERY_FIELDS) & set(b.to_json())  # its world file as before
    assert build_spec(a, default).to_xml() == build_spec(b, classic).to_xml()
    model = build_model(b, classic)
    assert not any(SCENERY_NAME.match(n) for n in names(model))
    slots = plant_slots_for([b])
    trunks = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"plant{i}_trunk")
              for i in range(slots)]
    np.testing.assert_array_equal(plant_geom_ids(model, slots)[0], trunks)
    assert camera_limits([b]) == {}
  committed = load_test_world(default.world)
  assert json.dumps(load_test_world(classic.world).to_json()) == json.dumps(committed.to_json())


def test_every_season_dresses_the_same_layout():
  plain = generate_world("test", 3, config("classic").world)
  for season in ("spring", "summer", "winter"):
    world = generate_world("test", 3, config(season).world)
    assert world.season == season
    for name in ("plant_xy", "plant_row", "plant_yaw", "terrain", "row_y0"):
      np.testing.assert_array_equal(getattr(world, name), getattr(plain, name), err_msg=name)
    for a, b in zip(world.lanes, plain.lanes):
      np.testing.assert_array_equal(a.centerline, b.centerline)
  # the committed test world, dressed
  summer = load_test_world(load_config(None, ["world.season=summer"]).world)
  np.testing.assert_array_equal(summer.plant_xy, load_test_world(WorldConfig()).plant_xy)
  assert summer.season == "summer" and len(summer.lobes)


def test_the_same_seed_gives_the_same_world_and_another_seed_another():
  cfg = config("summer", "world.tuft_density_per_m2=2")
  a, b, c = (generate_world("train", s, cfg.world) for s in (4, 4, 5))
  for name in ("post_xy", "post_height", "post_radius", *seasons.SHAPE_TABLES):
    np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    if name not in ("post_radius", "cordons"):  # (two radii; no summer cordons)
      assert not np.array_equal(getattr(a, name), getattr(c, name)), name
  assert build_spec(a, cfg).to_xml() == build_spec(b, cfg).to_xml()
  mixed = config("mixed").world
  drawn = [generate_world("train", s, mixed).season for s in range(12)]
  assert drawn == [generate_world("train", s, mixed).season for s in range(12)]
  assert set(drawn) == set(seasons.DRAWN_SEASONS)


# --- posts ---------------------------------------------------------------------------------

def _row_of(world, xy):
  return world.plant_row[np.argmin(np.linalg.norm(world.plant_xy - xy, axis=1))]


def test_posts_stand_at_the_configured_spacing_with_anchors_at_the_row_ends():
  cfg = load_config(None, ["world.season=winter", "world.post_spacing_m=[5.0, 5.0]",
                           "world.post_height_m=[2.0, 2.2]"])
  world = generate_world("train", 2, cfg.world)
  gap = seasons.ANCHOR_GAP_SPACINGS * world.spacing_m
  rows = [_row_of(world, p) for p in world.post_xy]
  for j in range(world.num_rows):
    p = world.plant_xy[world.plant_row == j]
    p = p[np.argsort(p[:, 0])]
    mine = np.flatnonzero(np.asarray(rows) == j)
    anchors = mine[world.post_radius[mine] == seasons.ANCHOR_POST_RADIUS_M]
    ends = [p[0] - gap * (p[1] - p[0]) / np.linalg.norm(p[1] - p[0]),
            p[-1] + gap * (p[-1] - p[-2]) / np.linalg.norm(p[-1] - p[-2])]
    np.testing.assert_allclose(world.post_xy[anchors], ends, atol=1e-12)
    line = mine[world.post_radius[mine] == seasons.LINE_POST_RADIUS_M]
    xy = world.post_xy[line]
    mids = (p[1:] + p[:-1]) / 2  # each line post midway between two plants of its row
    assert all(np.linalg.norm(mids - q, axis=1).min() < 1e-12 for q in xy)
    arc = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert len(line) == int(np.floor((arc.sum() + 2 * gap) / 5.0 - 0.5))
    along = np.concatenate([[-gap], np.sort(xy[:, 0]) - p[0, 0]])
    np.testing.assert_array_less(np.abs(np.diff(along) - 5.0), arc.max() + 0.05)
  assert np.all((world.post_height >= 2.0) & (world.post_height <= 2.2))
  # in the model: cylinders on the terrain, among the obstacles
  model = build_model(world, cfg)
  posts = ids(model, "post")
  obstacles = obstacle_geom_ids(model, plant_slots_for([world]))
  assert set(posts) <= set(obstacles) and set(posts) <= set(plant_geom_ids(
      model, plant_slots_for([world]))[0])
  assert not set(ids(model, "post_top")) & set(obstacles)
  ground = terrain_height(world, world.post_xy[:, 0], world.post_xy[:, 1])
  h = world.post_height
  for half, z in (("post", h / 4), ("post_top", 3 * h / 4)):  # two halves on the ground
    used = ids(model, half)[:len(world.post_xy)]
    np.testing.assert_array_equal(model.geom_type[used], mujoco.mjtGeom.mjGEOM_CYLINDER)
    np.testing.assert_allclose(model.geom_pos[used, :2], world.post_xy)
    np.testing.assert_allclose(model.geom_size[used, :2],
                               np.stack([world.post_radius, h / 4], -1))
    np.testing.assert_allclose(model.geom_pos[used, 2], ground + z, atol=1e-9)
  assert not len(generate_world("train", 2, config("winter", "world.post_spacing_m=[0, 0]")
                                .world).post_xy)


def test_the_env_collision_check_reads_the_posts_and_not_the_tufts():
  from mjxvine.env import COLLISION_MARGIN_M, VineyardEnv
  cfg = load_config("experiments/smoke.yaml", [
      "camera.width=8", "camera.height=6", "world.season=winter",
      "world.tuft_density_per_m2=2", "world.post_spacing_m=[3.0, 3.0]"])
  world = generate_world("train", 1, cfg.world)
  env = VineyardEnv(cfg, [world])
  table = np.asarray(env._trunks[0])
  for xy, r in zip(world.post_xy, world.post_radius):  # every post in the trunk table
    assert np.min(np.abs(table[:, :2] - xy).sum(1) + np.abs(table[:, 3] - r)) < 1e-5
  clear = lambda xy: float(env.plant_clearance(0, jp.asarray(xy, jp.float32), 0.0))
  assert clear(world.post_xy[0]) < COLLISION_MARGIN_M  # on a post: a collision
  obstacles = np.concatenate([world.plant_xy, world.post_xy])
  far = [t[:2] for t in world.tufts if np.linalg.norm(obstacles - t[:2], axis=1).min() > 0.6]
  assert far and all(clear(xy) > COLLISION_MARGIN_M for xy in far[:5])  # tufts: none


# --- seasons -------------------------------------------------------------------------------

def _check_common(world, model):
  """Posts, trunks up to the cordon, the single canopy parked, all of group 1 without
  contacts."""
  assert len(world.post_xy) >= 2 * world.num_rows
  cordon = world.trunk_height
  for j in range(world.num_rows):  # a cordon height per row
    assert np.ptp(cordon[world.plant_row == j]) == 0
  assert np.all((cordon >= 0.9) & (cordon <= 1.0))
  canopies = plant_geom_ids(model, plant_slots_for([world]))[1]
  assert not len(live(model, canopies))
  scenery = [g for g, n in enumerate(names(model)) if SCENERY_NAME.match(n)]
  assert np.all(model.geom_group[scenery] == 1)
  assert np.all(model.geom_contype[scenery] == 0) and np.all(model.geom_conaffinity[scenery] == 0)


def _axis(quat: np.ndarray, column: int) -> np.ndarray:
  """Column `column` of the rotation of each quaternion (n, 4)."""
  out = []
  for q in quat:
    m = np.zeros(9)
    mujoco.mju_quat2Mat(m, q)
    out.append(m.reshape(3, 3)[:, column])
  return np.array(out)


def test_summer_is_a_wall_of_lobes_with_shoots_into_the_lanes(monkeypatch):
  # straight rows and one canopy size: a shape's row line and canopy need no owner
  monkeypatch.setattr(layout, "JITTER_FRAC", 0.0)
  cfg = config("summer", "world.shoot_reach_m=[0.2, 0.3]",
               "world.canopy_width_m=[0.4, 0.4]", "world.canopy_top_m=[1.8, 1.8]")
  world = generate_world("train", 0, cfg.world)
  model = build_model(world, cfg)
  _check_common(world, model)
  assert not len(world.cordons)
  plants = len(world.plant_xy)
  assert 3 * plants <= len(world.lobes) <= 5 * plants and plants <= len(world.shoots) <= 2 * plants
  row_y = lambda xy: world.plant_xy[np.argmin(np.abs(world.plant_xy[:, 1] - xy[1])), 1]
  cordon = lambda xy: world.trunk_height[np.argmin(np.abs(world.plant_xy[:, 1] - xy[1]))]
  lobes = world.lobes  # between the cordon and the canopy's top, no wider than the canopy
  assert all(l[2] - l[5] >= cordon(l) - 1e-9 and l[2] + l[5] <= 1.8 + 1e-9 for l in lobes)
  assert np.all(lobes[:, 4] <= 0.2 + 1e-9)
  # a shoot's lower end reaches 0.2-0.3 m beyond the canopy's side into the lane
  shoots = world.shoots
  axis = _axis(shoots[:, 6:], 0)
  assert np.all(axis[:, 2] < 0) and np.all(shoots[:, 4:6] == seasons.SHOOT_RADIUS_M)
  tip = shoots[:, :3] + axis * shoots[:, 3:4]
  beyond = np.array([abs(t[1] - row_y(s)) for t, s in zip(tip, shoots)]) - 0.2
  assert np.all((beyond > 0.2 - 1e-9) & (beyond < 0.3 + 1e-9)), beyond
  assert np.all(tip[:, 2] < shoots[:, 2])
  for kind, table in (("lobe", world.lobes), ("shoot", world.shoots)):
    used = ids(model, kind)[:len(table)]
    np.testing.assert_array_equal(model.geom_type[used], mujoco.mjtGeom.mjGEOM_ELLIPSOID)
    np.testing.assert_allclose(model.geom_size[used], table[:, 3:6])


def test_winter_is_bare_trunks_and_cordons_and_spring_small_lobes_on_them():
  cfg = config("winter")
  world = generate_world("train", 0, cfg.world)
  model = build_model(world, cfg)
  _check_common(world, model)
  assert not len(world.lobes) and not len(world.shoots)
  c = world.cordons  # a horizontal cylinder per plant along its row, at the trunk's top
  assert len(c) == len(world.plant_xy)
  np.testing.assert_allclose(c[:, :2], world.plant_xy)
  np.testing.assert_allclose(c[:, 2], world.trunk_height)
  heading, spacing = seasons.row_directions(world)
  axis = _axis(c[:, 6:], 2)
  np.testing.assert_allclose(axis, np.stack([np.cos(heading), np.sin(heading), 0 * heading],
                                            -1), atol=1e-12)
  np.testing.assert_allclose(c[:, 4], spacing / 2)
  used = ids(model, "cordon")[:len(c)]
  np.testing.assert_array_equal(model.geom_type[used], mujoco.mjtGeom.mjGEOM_CYLINDER)
  # spring: the same cordons, and small lobes just above them
  spring = generate_world("train", 0, config("spring").world)
  _check_common(spring, build_model(spring, config("spring")))
  assert not len(spring.shoots) and len(spring.cordons) == len(spring.plant_xy)
  lobes = spring.lobes
  for k, (lo, hi) in enumerate(seasons.SPRING_LOBE_M):
    assert np.all((lobes[:, 3 + k] >= lo) & (lobes[:, 3 + k] <= hi))
  near = [np.argmin(np.linalg.norm(spring.plant_xy - l[:2], axis=1)) for l in lobes]
  rise = lobes[:, 2] - spring.trunk_height[near]
  assert np.all((rise >= 0.05) & (rise <= 0.3))


def test_tufts_lie_on_the_lane_floors_without_contacts_and_out_of_the_physics():
  cfg = config("summer", "world.tuft_density_per_m2=3")
  world = generate_world("test", 0, cfg.world)
  area = sum((l.centerline[-1, 0] - l.centerline[0, 0])
             * (world.lane_width(l) - 2 * seasons.TUFT_ROW_CLEARANCE_M) for l in world.lanes)
  assert abs(len(world.tufts) - 3 * area) < 4 * np.sqrt(3 * area)  # Poisson
  for t in world.tufts:  # within a lane, clear of the rows
    lane = min(world.lanes, key=lambda l: abs(np.interp(t[0], *l.centerline.T) - t[1]))
    assert abs(np.interp(t[0], *lane.centerline.T) - t[1]) <= (
        world.lane_width(lane) / 2 - seasons.TUFT_ROW_CLEARANCE_M + 1e-9)
  assert np.all(world.tufts[:, 2] == 0)  # centred on the ground: a dome shows
  model = build_model(world, cfg)
  tufts = ids(model, "tuft")
  assert len(live(model, tufts)) == len(world.tufts)
  assert np.all(model.geom_contype[tufts] == 0) and np.all(model.geom_conaffinity[tufts] == 0)
  assert not set(tufts) & set(obstacle_geom_ids(model, plant_slots_for([world])))
  cam = depth.DepthCamera.create(model, cfg.camera)
  assert set(tufts) <= set(cam.prim_geom.tolist())  # seen by the camera
  physics = build_model(world, cfg, plants=False)
  assert not any(SCENERY_NAME.match(n) or n.startswith("plant") for n in names(physics))
  assert physics.ngeom == build_model(generate_world("test", 0, config("classic").world),
                                      cfg, plants=False).ngeom


# --- the camera against mj_multiRay -------------------------------------------------------

def _reference(model, data, cam):
  """mj_multiRay's z-depth image and geom id per pixel."""
  return depth.reference_hits(model, data, cam)


def _silhouette(ref, step=0.05):
  edge = np.zeros(ref.shape, bool)
  dv, dh = np.abs(np.diff(ref, axis=0)) > step, np.abs(np.diff(ref, axis=1)) > step
  edge[1:] |= dv
  edge[:-1] |= dv
  edge[:, 1:] |= dh
  edge[:, :-1] |= dh
  return edge


@pytest.mark.parametrize("season,kinds", [("summer", ("post", "lobe", "shoot", "tuft")),
                                          ("winter", ("post", "cordon", "tuft"))])
def test_the_camera_sees_posts_lobes_shoots_and_tufts_as_mj_multiray_does(season, kinds):
  """As tests/test_depth.py: at least 99.5 % of pixels within 1 cm, none off by more
  than 5 cm away from silhouette edges; every kind of shape is hit by 20 pixels or more,
  99 % of them within 1 cm (silhouette edges included: most of a lobe's pixels are)."""
  cfg = config(season, "world.tuft_density_per_m2=2", "world.post_spacing_m=[2.5, 3.0]")
  world = generate_world("test", 1, cfg.world)
  model = build_model(world, cfg)
  cam = depth.DepthCamera.create(model, cfg.camera, **camera_limits([world], cfg.camera))
  datas = random_poses(model, world, 12, seed=2)
  dx = jax.tree.map(lambda *x: jp.stack(x), *[mjx.put_data(model, d) for d in datas])
  images, info = jax.jit(jax.vmap(partial(depth.render_depth_info, cam, mjx.put_model(model))))(dx)
  assert np.all(np.asarray(info["dropped"]) == 0), info["seen"]
  kind_of = {g: SCENERY_NAME.match(n).group(1).replace("post_top", "post")
             for g, n in enumerate(names(model)) if SCENERY_NAME.match(n)}
  fracs, hits, agree = [], {k: 0 for k in kinds}, {k: 0 for k in kinds}
  for img, d in zip(np.asarray(images), datas):
    ref, geom = _reference(model, d, cam)
    err = np.abs(img - ref)
    fracs.append(np.mean(err < 0.01))
    edge = _silhouette(ref)
    assert not np.any((err > 0.05) & ~edge)
    kind = np.vectorize(lambda g: kind_of.get(int(g), ""))(geom)
    for k in kinds:
      hits[k] += int((kind == k).sum())
      agree[k] += int(((kind == k) & (err < 0.01)).sum())
  assert np.mean(fracs) >= 0.995, fracs
  assert min(hits.values()) >= 20, hits
  assert all(agree[k] >= 0.99 * hits[k] for k in kinds), (hits, agree)


# --- vineyard files ------------------------------------------------------------------------

def _rows_geojson(path, meta, rows=3, length=20.5, width=2.5):
  features = [{"type": "Feature", "properties": {"name": f"R{j + 1}"},
               "geometry": {"type": "LineString", "coordinates": local_to_lonlat(
                   np.array([[0.0, j * width], [length, j * width]]), ORIGIN).tolist()}}
              for j in range(rows)]
  path.write_text(json.dumps({"type": "FeatureCollection", "mjxvine": meta,
                              "features": features}))
  return path


def read(path, cfg=WorldConfig()):
  return read_vineyard(path, cfg, robot_width_m=0.43)


def test_a_vineyard_file_sets_its_season_and_post_spacing(tmp_path):
  path = _rows_geojson(tmp_path / "b.geojson", {"plant_spacing_m": 1.0, "season": "winter",
                                                "post_spacing_m": 5.0})
  world = read(path)  # a classic config: the file's season comes first
  assert world.season == "winter" and world.frame["post_spacing_m"] == [5.0, 5.0]
  assert len(world.cordons) == len(world.plant_xy) and not len(world.lobes)
  # plants every metre, 0-20 m: anchors at -0.5 and 20.5, line posts at 4.5, 9.5, 14.5
  for j in range(3):
    x = np.sort(world.post_xy[[_row_of(world, p) == j for p in world.post_xy], 0])
    np.testing.assert_allclose(x - world.plant_xy[world.plant_row == j, 0].min(),
                               [-0.5, 4.5, 9.5, 14.5, 20.5], atol=1e-6)
  # written back (GeoJSON and CSV), read back the same
  again = read(write_geojson(world, tmp_path / "again.geojson"))
  assert again.season == "winter" and again.frame["post_spacing_m"] == [5.0, 5.0]
  np.testing.assert_allclose(again.post_xy, world.post_xy, atol=1e-4)
  np.testing.assert_allclose(again.trunk_height, world.trunk_height, atol=1e-6)
  csv = read(write_csv(world, tmp_path / "again.csv"))
  assert csv.season == "winter" and csv.frame["post_spacing_m"] == [5.0, 5.0]
  assert len(csv.post_xy) == len(world.post_xy)
  # a range, none, the config's season where the file names none, mixed from the seed
  ranged = read(_rows_geojson(tmp_path / "r.geojson", {"plant_spacing_m": 1.0,
                                                       "season": "summer",
                                                       "post_spacing_m": [6.0, 8.0]}))
  assert ranged.season == "summer" and 2 * 3 < len(ranged.post_xy) <= 5 * 3
  none = read(_rows_geojson(tmp_path / "n.geojson", {"plant_spacing_m": 1.0,
                                                     "season": "spring", "post_spacing_m": 0}))
  assert none.season == "spring" and not len(none.post_xy)
  plain = _rows_geojson(tmp_path / "p.geojson", {"plant_spacing_m": 1.0})
  assert read(plain).season == "classic"
  assert read(plain, config("summer").world).season == "summer"
  mixed = _rows_geojson(tmp_path / "m.geojson", {"plant_spacing_m": 1.0, "season": "mixed"})
  assert read(mixed).season in seasons.DRAWN_SEASONS
  # a CSV's columns
  text = "row,x_m,y_m,season,post_spacing_m\n" + "".join(
      f"{r},{x},{2.5 * j},{'summer' if j + x == 0 else ''},{'4' if j + x == 0 else ''}\n"
      for j, r in enumerate("AB") for x in range(12))
  (tmp_path / "c.csv").write_text(text)
  block = read(tmp_path / "c.csv")
  assert block.season == "summer" and block.frame["post_spacing_m"] == [4.0, 4.0]


@pytest.mark.parametrize("meta,words", [
    ({"season": "autumn"}, ["mjxvine.season", "'autumn'", "one of classic"]),
    ({"season": 3}, ["mjxvine.season", "3"]),
    ({"post_spacing_m": 0.5}, ["mjxvine.post_spacing_m", "0.5"]),
    ({"post_spacing_m": [8.0, 6.0]}, ["mjxvine.post_spacing_m", "[8.0, 6.0]"]),
    ({"post_spacing_m": "7"}, ["mjxvine.post_spacing_m"])])
def test_a_bad_season_or_post_spacing_in_a_file_is_one_line(tmp_path, meta, words):
  path = _rows_geojson(tmp_path / "bad.geojson", {"plant_spacing_m": 1.0, **meta})
  with pytest.raises(WorldFileError) as e:
    read(path)
  msg = str(e.value)
  assert "\n" not in msg and str(path) in msg and all(w in msg for w in words), msg


def test_a_csv_says_one_season_for_its_block(tmp_path):
  csv = tmp_path / "bad.csv"
  csv.write_text("row,x_m,y_m,season\nA,0,0,summer\nA,5,0,winter\nB,0,2.5,\nB,5,2.5,\n")
  with pytest.raises(WorldFileError, match=r"line 3: season 'winter' differs from 'summer' "
                                           r"on line 2") as e:
    read(csv)
  assert "\n" not in str(e.value)


# --- config and world files --------------------------------------------------------------

@pytest.mark.parametrize("override,key", [
    ("world.season=autumn", "world.season"),
    ("world.post_spacing_m=[0.5, 3.0]", "world.post_spacing_m"),
    ("world.post_spacing_m=[4.0, 3.0]", "world.post_spacing_m"),
    ("world.post_height_m=[2.0, 9.0]", "world.post_height_m"),
    ("world.cordon_height_m=[0.9, 1.7]", "world.cordon_height_m"),
    ("world.canopy_lobes=[0, 3]", "world.canopy_lobes"),
    ("world.shoots_per_plant=[1, 20]", "world.shoots_per_plant"),
    ("world.shoot_reach_m=[-0.1, 0.3]", "world.shoot_reach_m"),
    ("world.tuft_density_per_m2=-1", "world.tuft_density_per_m2")])
def test_a_bad_season_or_range_is_one_line_naming_the_key(override, key):
  with pytest.raises(ConfigError) as e:
    load_config(None, ["world.season=summer", override])
  assert str(e.value).startswith(f"{key} = ") and "\n" not in str(e.value), str(e.value)


def test_a_dressed_world_file_reads_back_exactly(tmp_path):
  world = generate_world("train", 3, config("summer", "world.tuft_density_per_m2=1").world)
  save_world(world, tmp_path / "w.json")
  again = load_world(tmp_path / "w.json")
  assert again.season == "summer"
  for name in seasons.SCENERY_FIELDS[1:] + ("trunk_height", "canopy_half", "canopy_z"):
    np.testing.assert_array_equal(getattr(again, name), getattr(world, name), err_msg=name)
  doc = json.loads((tmp_path / "w.json").read_text())
  doc["season"] = "autumn"
  (tmp_path / "bad.json").write_text(json.dumps(doc))
  with pytest.raises(WorldFileError, match="season 'autumn'"):
    load_world(tmp_path / "bad.json")


def test_a_block_dressed_beyond_the_limits_is_refused_in_one_line():
  from mjxvine.worlds.blocks import vineyard_from_rows
  from mjxvine.worlds.limits import MAX_SCENERY
  rows = [np.stack([np.arange(0.0, 300.0), np.full(300, 2.5 * j)], -1) for j in range(40)]
  cfg = load_config(None, ["world.season=summer", "world.tuft_density_per_m2=10"]).world
  with pytest.raises(WorldFileError, match=rf"summer puts \d+ posts and shapes on it; a "
                                           rf"block has at most {MAX_SCENERY}") as e:
    vineyard_from_rows(rows, cfg, robot_width_m=0.43)
  assert "\n" not in str(e.value)
