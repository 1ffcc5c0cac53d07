"""Procedural vineyards: ranges, determinism, the committed test world, MJCF and batching."""

import dataclasses
import json

import jax
import jax.numpy as jp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from mjxvine.worlds import (ROBOTS, batch_models, build_models, build_spec, generate_world,
                            load_test_world, take_world, terrain_height)
from mjxvine.worlds.__main__ import main as worlds_main
from mjxvine.worlds import layout
from mjxvine.worlds.layout import TEST_LANE_SHAPES


def _row_spacings(row_xy):
  return np.diff(np.sort(row_xy[:, 0]))


@pytest.mark.parametrize("kind", ["train", "test"])
@pytest.mark.parametrize("seed", [0, 1, 7])
def test_ranges(cfg, kind, seed):
  w = generate_world(kind, seed, cfg.world)
  assert 1.5 <= w.inter_row_m <= 2.0 and 0.7 <= w.spacing_m <= 1.0
  rows = w.rows()
  if kind == "train":
    assert len(rows) >= 4 and len(w.lanes) == len(rows) - 1
    assert all(l.shape == "straight" for l in w.lanes)
  else:
    assert len(w.lanes) == 5 and tuple(l.shape for l in w.lanes) == TEST_LANE_SHAPES
  jitter = w.spacing_m * layout.JITTER_FRAC
  for row in rows:
    gaps = _row_spacings(row)
    # Neighbours are a spacing apart up to two jitters; a gap is a multiple of spacing.
    assert gaps.min() >= w.spacing_m - 2 * jitter - 1e-9
  wide = [np.max(_row_spacings(r)) / w.spacing_m for r in rows]
  if kind == "test":
    # a wide gap (2-3 missing plants) in rows 3 and 5, which bound lanes 3 and 5
    assert wide[3] > 2.5 and wide[5] > 2.5
    n_missing = sum(int(np.round(g / w.spacing_m)) - 1 for r in rows for g in _row_spacings(r))
    assert n_missing >= 4 + 2 + 2
  else:
    assert max(wide) < 1.5  # no gaps in train worlds
  # plant jitter and shape ranges
  assert np.all(np.abs(w.plant_yaw) <= np.pi)
  assert np.all((w.trunk_height >= 0.6) & (w.trunk_height <= 0.8))
  top = w.canopy_z + w.canopy_half[:, 2]
  assert np.all((top >= 1.6 - 1e-9) & (top <= 1.9 + 1e-9))
  assert np.all((2 * w.canopy_half[:, :2] >= 0.3 - 1e-9) & (2 * w.canopy_half[:, :2] <= 0.5 + 1e-9))
  # terrain bumps of +- amplitude
  assert np.abs(w.terrain).max() == pytest.approx(layout.TERRAIN_AMPLITUDE_M)
  # lanes: the centerline runs between its two rows, ends are the EoRs
  for lane in w.lanes:
    c = lane.centerline
    assert np.all(np.diff(c[:, 0]) > 0)
    np.testing.assert_array_equal(lane.eor_forward, c[-1])
    np.testing.assert_array_equal(lane.eor_reverse, c[0])
    for j, sign in ((lane.left_row, -1), (lane.right_row, 1)):
      r = rows[j]
      y_row = np.interp(c[:, 0], *r[np.argsort(r[:, 0])].T)
      assert np.all(sign * (y_row - c[:, 1]) > 0.5)


@pytest.mark.parametrize("gap_rows, gap_plants", [(2, (2, 3)), (4, (4, 4))])
def test_varied_train_worlds_have_wide_gaps(cfg, gap_rows, gap_plants):
  world_cfg = dataclasses.replace(cfg.world, train_layout="varied",
                                  train_wide_gap_rows=gap_rows, train_wide_gap_plants=gap_plants)
  for seed in range(3):
    w = generate_world("train", seed, world_cfg)
    # the widest spacing of a row, in spacings: a gap of k plants spans k + 1 (+- jitter)
    widest = np.array([_row_spacings(r).max() / w.spacing_m for r in w.rows()])
    wide = widest > 2.5  # wider than a single gap (2 spacings)
    assert wide.sum() == gap_rows, (seed, widest)
    lo, hi = gap_plants
    assert np.all((widest[wide] > lo + 1 - 0.25) & (widest[wide] < hi + 1 + 0.25)), widest
    assert all(l.shape == "varied" for l in w.lanes)


def test_curved_lanes_wander(cfg):
  w = generate_world("test", 0, cfg.world)
  wander = [np.ptp(l.centerline[:, 1]) for l in w.lanes]
  assert wander[0] < 0.1 and wander[1] < 0.1          # straight
  assert 0.2 < wander[2] and wander[4] > 0.5          # hybrid, curved (~0.7 m)
  half = len(w.lanes[2].centerline) // 2
  assert np.ptp(w.lanes[2].centerline[: half // 2, 1]) < np.ptp(w.lanes[2].centerline[half:, 1])


def test_determinism_by_seed(cfg):
  a, b = generate_world("test", 3, cfg.world), generate_world("test", 3, cfg.world)
  c = generate_world("test", 4, cfg.world)
  for name in ("plant_xy", "plant_yaw", "canopy_half", "terrain"):
    np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
  assert not np.array_equal(a.terrain, c.terrain)
  assert build_spec(a, cfg).to_xml() == build_spec(b, cfg).to_xml()


def test_committed_test_world_is_seed_0(cfg):
  """The committed file was generated on one machine. Draws of the seeded RNG and plain
  IEEE arithmetic on them are exact on every machine; results of LAPACK (the centrelines'
  polynomial fit) and of numpy's vectorised sin/cos (the y offsets of curved rows) can
  differ in the last bits from one CPU to another: those are compared to 1e-9 m."""
  committed, fresh = load_test_world(cfg.world), generate_world("test", 0, cfg.world)
  for name in ("plant_row", "plant_yaw", "trunk_height", "canopy_half", "canopy_z",
               "terrain", "row_y0"):
    np.testing.assert_array_equal(getattr(committed, name), getattr(fresh, name), err_msg=name)
  np.testing.assert_array_equal(committed.plant_xy[:, 0], fresh.plant_xy[:, 0])
  np.testing.assert_allclose(committed.plant_xy[:, 1], fresh.plant_xy[:, 1], rtol=0, atol=1e-9)
  assert (committed.inter_row_m, committed.spacing_m) == (fresh.inter_row_m, fresh.spacing_m)
  assert [(l.id, l.shape, l.left_row, l.right_row) for l in committed.lanes] == [
      (l.id, l.shape, l.left_row, l.right_row) for l in fresh.lanes]
  for a, b in zip(committed.lanes, fresh.lanes):
    np.testing.assert_array_equal(a.centerline[:, 0], b.centerline[:, 0])  # a linspace
    np.testing.assert_allclose(a.centerline, b.centerline, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.eor_forward, b.eor_forward, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.eor_reverse, b.eor_reverse, rtol=0, atol=1e-9)


def test_model_structure(cfg):
  w = generate_world("train", 0, cfg.world)
  m = build_models([w], cfg)[0]
  groups = {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, i): m.geom_group[i]
            for i in range(m.ngeom)}
  assert groups["terrain"] == 0 and groups["plant0_trunk"] == 1 and groups["chassis"] == 2
  plants = [i for i in range(m.ngeom) if m.geom_group[i] == 1]
  assert np.all(m.geom_contype[plants] == 0) and np.all(m.geom_conaffinity[plants] == 0)
  assert m.nu == 4 and m.nq == 7 + 4
  assert mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, "depth") >= 0
  # The terrain surface in MuJoCo matches the layout's heights.
  d = mujoco.MjData(m)
  mujoco.mj_forward(m, d)
  x, y = 3.3, w.lanes[1].centerline[10, 1]
  dist = mujoco.mj_ray(m, d, np.array([x, y, 2.0]), np.array([0, 0, -1.0]),
                       np.array([1, 0, 0, 0, 0, 0], np.uint8), 1, -1, np.zeros(1, np.int32))
  assert 2.0 - dist == pytest.approx(terrain_height(w, x, y), abs=2e-3)


@pytest.mark.parametrize("robot", ["jackal", "husky"])
def test_robot_drives_on_terrain(cfg, robot):
  """The C physics: the robot rests on its wheels and drives straight at the commanded speed."""
  from mjxvine.config import replace
  c = replace(cfg, robot={"name": robot})
  spec = ROBOTS[robot]
  w = generate_world("train", 0, c.world)
  m = build_models([w], c)[0]
  d = mujoco.MjData(m)
  from mjxvine.worlds.robots import wheel_speeds
  for _ in range(50):
    mujoco.mj_step(m, d)
  x0 = d.qpos[0]
  d.ctrl[:] = wheel_speeds(0.4, 0.0, spec)
  for _ in range(250):
    mujoco.mj_step(m, d)
  speed = (d.qpos[0] - x0) / (250 * m.opt.timestep)
  assert 0.3 < speed < 0.45
  ground = terrain_height(w, d.qpos[0], d.qpos[1])
  assert abs(d.qpos[2] - ground - spec.wheel_radius) < 0.05


def test_worlds_cli(tmp_path):
  for kind, robot in (("train", "jackal"), ("test", "husky")):
    out = tmp_path / f"{kind}_{robot}"
    assert worlds_main(["--kind", kind, "--world", "0", "--robot", robot, "--out", str(out)]) == 0
    m = mujoco.MjModel.from_xml_path(str(out / "world.xml"))
    mjx.put_model(m)
    doc = json.loads((out / "world.json").read_text())
    assert doc["kind"] == kind and doc["robot"] == robot and doc["seed"] == 0
    assert set(doc["lanes"][0]) == {"id", "shape", "left_row", "right_row", "centerline",
                                    "eor_forward", "eor_reverse", "width_m"}
    assert doc["lanes"][0]["width_m"] == pytest.approx(doc["inter_row_m"], abs=1e-4)
    assert len(doc["row_y0"]) == len(doc["lanes"]) + 1
    assert len(doc["plant_xy"]) == len(doc["plant_row"]) == sum(
        mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, i).endswith("_trunk") and
        m.geom_pos[i, 2] > -50 for i in range(m.ngeom))
    assert (out / "world.png").stat().st_size > 10_000


@pytest.mark.slow  # compiles mjx.step (~20 s on 2 cores)
def test_batch_of_different_worlds_steps(cfg):
  """Two different worlds in one mjx.Model: fields really differ, and each world steps as
  MuJoCo's C physics steps it."""
  worlds = [generate_world("train", s, cfg.world) for s in (0, 1)]
  models = build_models(worlds, cfg)
  mx, axes = batch_models(models)
  assert axes.geom_pos == 0 and axes.hfield_data == 0 and axes.body_mass is None
  assert not np.allclose(mx.geom_pos[0], mx.geom_pos[1])
  assert not np.allclose(mx.hfield_data[0], mx.hfield_data[1])
  datas = []
  for m in models:
    d = mujoco.MjData(m)
    d.ctrl[:] = 3.0
    mujoco.mj_forward(m, d)
    datas.append(d)
  dx = jax.tree.map(lambda *x: jp.stack(x), *[mjx.put_data(m, d) for m, d in zip(models, datas)])
  step = jax.jit(jax.vmap(mjx.step, in_axes=(axes, 0)))
  for _ in range(10):
    dx = step(mx, dx)
  for i, (m, d) in enumerate(zip(models, datas)):
    for _ in range(10):
      mujoco.mj_step(m, d)
    np.testing.assert_allclose(dx.qpos[i, :3], d.qpos[:3], atol=2e-3)
    np.testing.assert_allclose(take_world(mx, axes, i).geom_pos, m.geom_pos, atol=1e-6)
  assert not np.allclose(dx.qpos[0, :3], dx.qpos[1, :3])


def test_worlds_cli_depth_at(tmp_path):
  out = tmp_path / "depth"
  args = ["--kind", "train", "--world", "0", "--out", str(out), "--depth-at", "3.0,-0.9,0.1",
          "--set", "camera.width=32", "--set", "camera.height=24"]
  assert worlds_main(args) == 0
  depth = np.load(out / "depth.npy")
  noisy = np.load(out / "depth_noisy.npy")
  cam = json.loads((out / "camera.json").read_text())
  assert depth.shape == noisy.shape == (24, 32) and depth.dtype == np.float32
  assert cam["width"] == 32 and cam["height"] == 24 and len(cam["xmat"]) == 9
  assert 0 <= depth.min() and depth.max() <= 5.0 and not np.array_equal(depth, noisy)
  # the robot settled on the terrain at the asked pose; the camera looks along +x (yaw 0.1)
  assert abs(cam["pos"][0] - 3.0 - 0.21 * np.cos(0.1)) < 0.05
  forward = -np.asarray(cam["xmat"]).reshape(3, 3)[:, 2]
  assert forward[0] > 0.95
  # the bottom rows see the ground close by, the top rows see farther
  assert depth[-1].mean() < depth[0].mean()
  assert (out / "depth.png").stat().st_size > 5000
  assert (out / "world.png").stat().st_size > 10_000  # with the robot and its frustum


def test_worlds_cli_depth_at_policy_camera(tmp_path, capsys):
  """--policy FILE.npz renders at the policy's image size and FOVs; a bad file or pose is
  one line and exit status 2."""
  from mjxvine.deploy import FORMAT_VERSION
  policy = tmp_path / "policy.npz"
  meta = {"format_version": FORMAT_VERSION, "image_size": [20, 28], "fovx_deg": 70.0,
          "fovy_deg": 52.0, "max_depth_m": 4.0}
  np.savez(policy, **{"__meta__": np.array(json.dumps(meta))})
  out = tmp_path / "depth"
  assert worlds_main(["--kind", "train", "--world", "0", "--out", str(out), "--depth-at",
                      "3.0,-0.9,0.1", "--policy", str(policy)]) == 0
  cam = json.loads((out / "camera.json").read_text())
  assert (cam["height"], cam["width"], cam["fovx_deg"], cam["max_depth"]) == (20, 28, 70.0, 4.0)
  assert np.load(out / "depth.npy").shape == (20, 28)
  capsys.readouterr()
  (tmp_path / "bad.npz").write_text("not a policy")
  assert worlds_main(["--out", str(out), "--policy", str(tmp_path / "bad.npz")]) == 2
  assert "bad.npz: not a valid policy file" in capsys.readouterr().err
  with pytest.raises(SystemExit) as e:
    worlds_main(["--out", str(out), "--depth-at", "3,1"])
  assert e.value.code == 2 and "expected X,Y,YAW" in capsys.readouterr().err


def test_mjx_backend_fields_are_where_batching_reads_them(cfg):
  """`batch_models` reads one private attribute of MJX (`mjx.Model._impl`); this fails,
  naming the installed MJX, as soon as a release moves it or the field it unifies."""
  from mjxvine.worlds.batch import mjx_backend_fields
  model = build_models([generate_world("train", 0, cfg.world)], cfg)[0]
  impl = mjx_backend_fields(mjx.put_model(model))
  assert np.asarray(impl.geom_rbound_hfield).shape == (model.ngeom,)

  class NoBackend:
    pass

  with pytest.raises(RuntimeError, match="mujoco-mjx .*needs updating"):
    mjx_backend_fields(NoBackend())
