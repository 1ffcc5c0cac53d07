"""Rows of real length: the protocol's time limit follows the row, lanes of different
lengths share one env, and the oracle finishes a 100 m row and a block of unequal rows."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from mjxvine.config import load_config
from mjxvine.episodes import OUTCOMES
from mjxvine.evaluation import rollout
from mjxvine.worlds import generate_world, make_world
from mjxvine.worlds.blocks import BlockFrame, vineyard_from_rows

TINY = ["camera.width=16", "camera.height=12"]
EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "vineyard-block.geojson"


def _block(cfg, lengths=(40.0, 46.0, 43.0), inter_row=2.4, bend=0.6):
  """Three gently bending rows of unequal lengths, plants every metre, 25 deg from east."""
  a = np.deg2rad(25.0)
  rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
  rows = []
  for j, (length, start) in enumerate(zip(lengths, (0.0, -3.0, 1.5))):
    x = np.arange(start, start + length, 1.0)
    y = j * inter_row + bend * np.sin(np.pi * x / 46.0) ** 2
    rows.append(np.stack([x, y], -1) @ rot.T)
  return vineyard_from_rows(rows, cfg.world, robot_width_m=0.43, frame=BlockFrame("block"))


def test_the_time_limit_follows_the_row(cfg):
  paper = generate_world("test", 0, cfg.world)
  assert rollout.lane_steps(cfg, paper, 1) == cfg.eval.max_steps == 700  # the paper's rows
  short = generate_world("test", 0, load_config(None, ["world.test_length_m=10"]).world)
  assert rollout.lane_steps(cfg, short, 1) == 700  # never below the paper's limit
  long = generate_world("test", 0, load_config(None, ["world.test_length_m=100"]).world)
  assert rollout.lane_steps(cfg, long, 1) == 2917  # 700 steps per 24 m


def test_a_block_has_lanes_of_its_own_lengths_and_widths(cfg):
  world = _block(cfg)
  assert len(world.lanes) == 2
  lengths = [l.centerline[-1, 0] - l.centerline[0, 0] for l in world.lanes]
  # where each pair of rows runs side by side: rows 0-1 over x 0..39 m, rows 1-2 1.5..42 m
  np.testing.assert_allclose(lengths, [39.0, 40.5], atol=0.1)
  np.testing.assert_allclose([world.lane_width(l) for l in world.lanes], 2.4, atol=0.05)
  assert world.lanes[0].centerline[0, 0] == pytest.approx(0.0, abs=1e-9)
  assert abs(world.frame["heading_deg"] - 25.0) < 1.0


@pytest.mark.slow  # two envs compiled and 6000 oracle steps: over 20 s on a 2-core CPU
def test_the_oracle_finishes_a_100_m_row_and_the_example_block(cfg):
  long_cfg = load_config(None, [*TINY, "world.test_length_m=100"])
  long = generate_world("test", 0, long_cfg.world)
  doc = rollout.evaluate(long_cfg, rollout.PolicySource("oracle"), long,
                         rollout.Protocol(runs=1, noise_factor=1.0, lanes=[1], directions=("F",)))
  (row,) = doc["rows"]
  assert row["outcomes"] == ["success"] and row["lane_length_m"] > 99.9
  assert row["time_to_eor_s"] > 700 * long_cfg.env.control_dt  # past the paper's limit
  assert row["mae_m"] < 0.05

  # the example block read from its GeoJSON: lanes of 87-90.5 m, each to its own end
  block_cfg = load_config(None, TINY)
  block = make_world(str(EXAMPLE), block_cfg.world, robot_width_m=0.43)
  doc = rollout.evaluate(block_cfg, rollout.PolicySource("oracle"), block,
                         rollout.Protocol(runs=1, noise_factor=1.0, lanes=[1, 8]))
  assert [r["outcomes"] for r in doc["rows"]] == [["success"]] * 4
  for r in doc["rows"]:
    lane = block.lanes[r["lane"] - 1]
    assert r["lane_covered_frac"] == 1.0
    assert r["lane_length_m"] == pytest.approx(
        float(np.linalg.norm(np.diff(lane.centerline, axis=0), axis=1).sum()))
  assert {round(r["lane_length_m"]) for r in doc["rows"]} == {87, 91}
  assert doc["overall"]["mae_m"] < 0.06


def _pool_with_block(tmp_path, extra=()):
  from mjxvine.worlds import save_world
  cfg = load_config(None, TINY)
  path = tmp_path / "block.json"
  save_world(_block(cfg), path)
  return load_config(None, [*TINY, "world.pool_size=2", f"world.train_files={path}", *extra])


def test_vineyard_files_join_the_pool_of_train_worlds(tmp_path):
  from mjxvine.env import LaneTable
  from mjxvine.worlds import batch_models, build_models, pool_worlds
  cfg = _pool_with_block(tmp_path)
  worlds = pool_worlds(cfg)
  assert [w.kind for w in worlds] == ["train", "train", "file"]
  assert len({w.terrain.shape for w in worlds}) == 1  # one heightfield shape for the batch
  sizes = {(round(w.terrain_extent[1] - w.terrain_extent[0], 6),
            round(w.terrain_extent[3] - w.terrain_extent[2], 6)) for w in worlds}
  assert len(sizes) == 1
  model, axes = batch_models(build_models(worlds, cfg))
  assert axes.hfield_data == 0 and model.hfield_data.shape[0] == 3
  lanes = LaneTable(worlds)
  assert not lanes.uniform
  assert np.asarray(lanes.samples)[2, :2].tolist() == [len(l.centerline) for l in worlds[2].lanes]
  np.testing.assert_allclose(np.asarray(lanes.width_m)[2, :2],
                             [l.width_m for l in worlds[2].lanes], atol=1e-6)
  # episode limits per lane: the generated 20 m rows keep env.max_steps, the block's
  # rows of 39 and 40.5 m get theirs
  limits = LaneTable(worlds, 700).max_steps
  assert np.asarray(limits)[:2].tolist() == [[700] * 3] * 2
  lengths = [l.centerline[-1, 0] - l.centerline[0, 0] for l in worlds[2].lanes]
  assert np.asarray(limits)[2, :2].tolist() == [int(np.ceil(700 * x / 24 - 1e-6))
                                                for x in lengths]
  assert 1137 <= np.asarray(limits)[2, :2].min() and np.asarray(limits)[2, :2].max() <= 1183
  assert LaneTable(worlds[:2], 700).static_max_steps == 700
  with pytest.raises(FileNotFoundError, match="world.train_files"):
    pool_worlds(load_config(None, [f"world.train_files={tmp_path / 'nope.geojson'}"]))


def test_the_blocks_of_files_get_their_share_of_the_starts(tmp_path):
  """world.train_files_share of the random starts are in the file's block (the pool's last
  world), the rest spread over the generated ones; evaluation's reset_to is unchanged."""
  import jax
  from mjxvine.env import VineyardEnv
  env = VineyardEnv(_pool_with_block(tmp_path, ["world.train_files_share=0.25"]))
  assert env.file_worlds == 1 and len(env.worlds) == 3
  keys = jax.random.split(jax.random.PRNGKey(0), 4000)
  worlds = np.asarray(jax.jit(jax.vmap(lambda k: env.sample_pose(k)["world"]))(keys))
  share = np.mean(worlds == 2)
  assert abs(share - 0.25) < 4 * np.sqrt(0.25 * 0.75 / 4000), share
  assert abs(np.mean(worlds == 0) - 0.375) < 0.04 and abs(np.mean(worlds == 1) - 0.375) < 0.04


@pytest.mark.slow  # compiles the env on a mixed pool: over 20 s on a 2-core CPU
def test_the_oracle_drives_every_lane_of_a_mixed_pool(tmp_path):
  import jax
  from mjxvine.env import VineyardEnv, pure_pursuit
  cfg = _pool_with_block(tmp_path, [])
  env = VineyardEnv(cfg)
  drive = pure_pursuit(env)
  keys = jax.random.split(jax.random.PRNGKey(0), 64)
  state = jax.jit(jax.vmap(lambda k: env.reset(k, None, (0.0, 0.9))))(keys)
  assert set(np.asarray(state.info["pose"]["world"]).tolist()) == {0, 1, 2}

  @jax.jit
  def step(state):
    action = jax.vmap(drive)(state, keys)
    return jax.vmap(env.step)(state, action)

  ended = np.zeros(64, np.int32)
  for _ in range(120):
    state = step(state)
    out = np.asarray(state.info["outcome"])
    ended = np.where(ended == 0, out, ended)
  names = {OUTCOMES[o] for o in ended.tolist()}
  assert names <= {"running", "success"}, names  # no collision, no lane left, in any world
  on_block = np.asarray(state.info["pose"]["world"]) == 2
  moved = np.linalg.norm(np.asarray(state.pipeline_state.qpos[:, :2]) -
                         np.asarray(state.info["pose"]["xy"]), axis=1)
  assert on_block.sum() >= 10 and np.all(moved[on_block & (ended == 0)] > 4.0)  # 120 steps


def test_worlds_of_one_batch_keep_their_heights(tmp_path):
  """A flat-ish generated world batched with a sloped block keeps its own heights: MuJoCo
  rescales heightfield data to [0, 1], which the pinned corners make the identity."""
  import mujoco
  from mjxvine.worlds import build_models, pool_worlds, terrain_height
  cfg = _pool_with_block(tmp_path)
  worlds = pool_worlds(cfg)
  sloped = dataclasses.replace(worlds[2], terrain=worlds[2].terrain + 0.05 * np.arange(
      worlds[2].terrain.shape[1])[None, :])
  worlds = [worlds[0], sloped]
  for world, model in zip(worlds, build_models(worlds, cfg)):
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    xy = world.lanes[0].centerline[len(world.lanes[0].centerline) // 2]
    # the height MuJoCo's heightfield has there: a ray straight down onto the terrain
    geomid = np.zeros(1, np.int32)
    dist = mujoco.mj_ray(model, data, np.array([xy[0], xy[1], 50.0]), np.array([0, 0, -1.0]),
                         np.array([1, 0, 0, 0, 0, 0], np.uint8), 1, -1, geomid)
    assert 50.0 - dist == pytest.approx(float(terrain_height(world, *xy)), abs=2e-3)


def test_lanes_of_one_length_but_staggered_starts(cfg):
  """A slanted block whose lanes are equally long but start at different x: the static
  path of the lane table takes the lanes' own extent, not the block's length."""
  from mjxvine.env import LaneTable
  rows = [np.stack([np.arange(30.0) + 2.0 * j, np.full(30, 2.4 * j)], -1) for j in range(3)]
  block = vineyard_from_rows(rows, cfg.world, robot_width_m=0.43,
                             frame=BlockFrame(heading_rad=0.0))
  lanes = LaneTable([block])
  assert lanes.uniform and block.length_m == pytest.approx(29.0)  # lane 2 ends at x = 29
  assert lanes.static_length_m == pytest.approx(27.0)  # lanes: x 0..27 and 2..29
