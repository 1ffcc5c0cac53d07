"""The evaluation's lane geometry (numpy, closest points on the centreline's segments)
agrees with the env's JAX lane frame (`env.lane_frame`, nearest sample): lateral offsets,
distances and along-lane coordinates on the straight, hybrid and curved lanes of two test
worlds, both directions, within the sampling's curvature error (not bit for bit)."""

import jax
import jax.numpy as jp
import numpy as np
import pytest

from mjxvine.config import load_config
from mjxvine.env import lane_frame
from mjxvine.evaluation import geometry
from mjxvine.worlds import generate_world


def _points_near(line: np.ndarray, rng, n: int = 40) -> np.ndarray:
  """n points (n, 2) within 0.5 m of the centreline `line` (k, 2), away from its ends."""
  idx = rng.integers(5, len(line) - 5, n)
  tangent = line[idx + 1] - line[idx - 1]
  tangent /= np.linalg.norm(tangent, axis=1)[:, None]
  normal = np.stack([-tangent[:, 1], tangent[:, 0]], -1)
  return (line[idx] + rng.uniform(-0.5, 0.5, (n, 1)) * normal
          + rng.uniform(-0.1, 0.1, (n, 1)) * tangent)


@pytest.mark.parametrize("seed", [0, 3])
def test_numpy_geometry_equals_the_envs_lane_frame(seed):
  world = generate_world("test", seed, load_config().world)
  assert {lane.shape for lane in world.lanes} >= {"straight", "curved"}
  rng = np.random.default_rng(seed)
  for lane in world.lanes:
    line = lane.centerline
    pts = _points_near(line, rng)
    start = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
    for direction, sign in (("F", 1.0), ("R", -1.0)):
      index, _, lateral, along = jax.vmap(lambda p: lane_frame(
          jp.asarray(line, jp.float32), p, jp.float32(sign)))(jp.asarray(pts, jp.float32))
      lateral = np.asarray(lateral)
      np.testing.assert_allclose(geometry.signed_offsets(pts, line, direction), lateral,
                                 atol=2e-3, err_msg=f"{lane.shape} {direction}")
      np.testing.assert_allclose(geometry.distance_to_line(pts, line), np.abs(lateral),
                                 atol=2e-3)
      # along-lane from line[0]: the nearest sample's arc length and the step past it
      s = start[np.asarray(index)] + sign * np.asarray(along)
      np.testing.assert_allclose(geometry.along_line(pts, line), s, atol=5e-3)
