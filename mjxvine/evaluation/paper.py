"""The paper's tests as data, and the paper's own figures (docs/design.md, Evaluation
protocol): what the suite (`suite`), the sweeps (`sweeps`), the checkpoint choice on
validation worlds (`choice`) and the reports drive and print beside our numbers.

Lanes are 1-based, directions "F" (forward, from the lane's first centreline point) and
"R" (reverse); a "row" of a table is a lane-direction such as "4F".
"""

from __future__ import annotations

# The protocol: every lane of a test world in both directions, RUNS runs each. On test
# world 0, the paper's vineyard, that is its table: 5 lanes x 2 directions x 5 runs.
DIRECTIONS = ("F", "R")
RUNS = 5
# The test worlds of the suite: 0 is the paper's, 1-3 are drawn by the same generator and
# never used in training.
SUITE_WORLDS = (0, 1, 2, 3)

# The noise test: lanes 1 (straight) and 4 (curved) of world 0, forward, NOISE_RUNS runs
# at each depth noise factor.
NOISE_LANES = (1, 4)
NOISE_SHAPES = ("straight", "curved")  # of NOISE_LANES; PAPER_NOISE's column order
NOISE_DIRECTION = "F"
NOISE_RUNS = 3
NOISE_FACTORS = (1, 2, 4, 6, 8, 10)

# The robot test: the noise test's rows and runs on each robot, at the config's noise
# (the policy was trained on the Jackal).
ROBOTS = ("jackal", "husky")
ROBOT_LANES = NOISE_LANES
ROBOT_DIRECTION = NOISE_DIRECTION
ROBOT_RUNS = NOISE_RUNS

# The paper's table: lane-direction -> (MAE m, RMSE m, v m/s, v_std, w rad/s, w_std,
# successes of RUNS); "overall" is the mean of the rows (successes: the sum).
PAPER = {
    "1F": (0.076, 0.089, 0.493, 0.020, -0.027, 0.538, 5), "1R": (0.131, 0.141, 0.478, 0.053, -0.030, 0.623, 5),
    "2F": (0.068, 0.076, 0.488, 0.037, -0.028, 0.642, 5), "2R": (0.087, 0.105, 0.489, 0.037, -0.001, 0.610, 5),
    "3F": (0.120, 0.154, 0.497, 0.003, -0.012, 0.353, 5), "3R": (0.100, 0.130, 0.494, 0.017, -0.036, 0.610, 2),
    "4F": (0.164, 0.191, 0.468, 0.079, -0.008, 0.687, 5), "4R": (0.081, 0.097, 0.484, 0.059, -0.014, 0.493, 5),
    "5F": (0.112, 0.145, 0.486, 0.057, -0.005, 0.571, 3), "5R": (0.201, 0.233, 0.445, 0.122, -0.042, 0.656, 5),
    "overall": (0.114, 0.136, 0.482, 0.048, -0.020, 0.578, 45),
}
PAPER_RUNS = RUNS * (len(PAPER) - 1)  # the runs of the paper's overall row: 50
# noise factor -> successes of NOISE_RUNS (straight, curved); the factors the sweep drives
PAPER_NOISE = {2: (3, 3), 4: (3, 3), 6: (3, 3), 8: (2, 3), 10: (0, 0)}
# (robot, row) -> (successes of ROBOT_RUNS, MAE m, RMSE m), and the mean time to the EoR (s)
PAPER_ROBOTS = {("jackal", "1F"): (3, 0.079, 0.088), ("husky", "1F"): (3, 0.081, 0.098),
                ("jackal", "4F"): (3, 0.085, 0.101), ("husky", "4F"): (2, 0.112, 0.138)}
PAPER_ROBOT_TIMES = {("jackal", "1F"): 78, ("husky", "1F"): 69, ("jackal", "4F"): 78,
                     ("husky", "4F"): 88}


def noise_rows() -> list[tuple[int, str]]:
  """The noise test's lane-directions: [(1, "F"), (4, "F")]."""
  return [(lane, NOISE_DIRECTION) for lane in NOISE_LANES]


def robot_rows() -> list[tuple[int, str]]:
  """The robot test's lane-directions: [(1, "F"), (4, "F")]."""
  return [(lane, ROBOT_DIRECTION) for lane in ROBOT_LANES]


def weak_rows(min_fraction: float = 0.8) -> list[str]:
  """The paper's rows with fewer than `min_fraction` of their runs successful, as
  "3R 2/5"."""
  return [f"{key} {p[6]}/{RUNS}" for key, p in PAPER.items()
          if key != "overall" and p[6] < min_fraction * RUNS]
