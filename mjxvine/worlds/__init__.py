"""Procedural vineyards and robots as MuJoCo / MJX models (docs/design.md, World layout;
Robots)."""

from mjxvine.worlds.batch import batch_models, take_world
from mjxvine.worlds.build import (build_model, build_models, build_spec, camera_limits,
                                  obstacle_geom_ids,
                                  plant_geom_ids, plant_slots_for, random_poses,
                                  scenery_slots_for, terrain_height)
from mjxvine.worlds.layout import (Lane, Vineyard, WorldFileError, generate_world, load_world,
                                   save_world, world_extent)
from mjxvine.worlds.robots import ROBOTS, RobotSpec, robot_spec, wheel_speeds
from mjxvine.worlds.store import (TEST_WORLD_SEED, load_test_world, make_world, pool_worlds,
                                  world_of)

__all__ = [
    "Lane", "Vineyard", "WorldFileError", "generate_world", "load_world", "save_world",
    "world_extent",
    "build_model", "build_models", "build_spec", "plant_slots_for", "plant_geom_ids",
    "obstacle_geom_ids", "scenery_slots_for", "camera_limits",
    "terrain_height", "random_poses", "batch_models", "take_world", "ROBOTS", "RobotSpec",
    "robot_spec", "wheel_speeds", "load_test_world", "TEST_WORLD_SEED", "make_world", "pool_worlds", "world_of",
]
