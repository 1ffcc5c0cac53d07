"""Top-down maps of vineyards (matplotlib; headless machines fall back to Agg, and the
backend is left to the caller, so that notebooks keep theirs)."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Polygon

from mjxvine.atomic import atomic_path
from mjxvine.worlds.layout import Vineyard
from mjxvine.worlds.robots import RobotSpec

# Neutral styles for the world, so that coloured trajectories drawn on top stand out.
CENTERLINE = dict(color="0.35", ls=":", lw=1.0)
EOR_FORWARD = dict(marker=">", ms=7, mfc="black", mec="black")
EOR_REVERSE = dict(marker="<", ms=7, mfc="white", mec="black")
POST = dict(ls="", marker="s", ms=4, mfc="0.35", mec="black")


def draw_vineyard(ax, world: Vineyard, *, numbers: bool = True, terrain: bool = True):
  """Draws terrain, plants (canopy footprints), lane centerlines, lane numbers and EoRs.

  Returns (legend handles of plants, centreline and EoR markers; the terrain image, for
  a colourbar, or None without terrain).
  """
  image = None
  if terrain:
    xmin, xmax, ymin, ymax = world.terrain_extent
    image = ax.imshow(world.terrain, origin="lower", extent=(xmin, xmax, ymin, ymax),
                      cmap="copper", alpha=0.35, interpolation="bilinear")
  widths = 2 * world.canopy_half[:, :2].mean(axis=1)
  ax.scatter(world.plant_xy[:, 0], world.plant_xy[:, 1], s=(widths * 40) ** 2 / 4,
             c="forestgreen", alpha=0.8, edgecolors="darkgreen", linewidths=0.5)
  if len(world.post_xy):
    ax.plot(world.post_xy[:, 0], world.post_xy[:, 1], **POST)
  for lane in world.lanes:
    c = lane.centerline
    ax.plot(c[:, 0], c[:, 1], **CENTERLINE)
    if numbers:
      ax.text(c[0, 0] - 1.2, c[0, 1], str(lane.id), ha="center", va="center", fontsize=10,
              fontweight="bold", bbox=dict(boxstyle="circle", fc="white", ec="0.3"))
    ax.plot(*lane.eor_forward, ls="", **EOR_FORWARD)
    ax.plot(*lane.eor_reverse, ls="", **EOR_REVERSE)
  ax.set_aspect("equal")
  ax.set_xlabel("x [m]")
  ax.set_ylabel("y [m]")
  ys = world.plant_xy[:, 1]
  ax.set_xlim(-2.5, world.length_m + 1.5)
  ax.set_ylim(ys.min() - 1.5, ys.max() + 1.5)
  handles = [
      Line2D([], [], ls="", marker="o", ms=8, mfc="forestgreen", mec="darkgreen",
             alpha=0.8, label="plants (canopy)"),
      Line2D([], [], **CENTERLINE, label="lane centreline"),
      Line2D([], [], ls="", **EOR_FORWARD, label="EoR forward (+x end)"),
      Line2D([], [], ls="", **EOR_REVERSE, label="EoR reverse (x = 0 end)"),
  ] + ([Line2D([], [], **POST, label="trellis posts")] if len(world.post_xy) else [])
  return handles, image


def draw_pose(ax, robot: RobotSpec, pose, *, fovx_deg: float, max_depth_m: float) -> list:
  """Draws the robot's footprint at pose (x m, y m, yaw rad) and the top view of its depth
  camera's frustum: horizontal FOV `fovx_deg`, out to the z-depth `max_depth_m` (m), from
  the camera `robot.camera_ahead` ahead of the base centre. Returns legend handles."""
  x, y, yaw = (float(v) for v in pose)
  rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
  half = np.array([robot.length, robot.width]) / 2
  corners = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * half
  ax.add_patch(Polygon(corners @ rot.T + [x, y], closed=True, fc="gold", ec="black",
                       lw=1.0, zorder=6))
  ax.annotate("", xy=rot @ [half[0] + 0.35, 0] + [x, y], xytext=(x, y), zorder=7,
              arrowprops=dict(arrowstyle="-|>", color="black", lw=1.2))
  cam = rot @ [robot.camera_ahead, 0] + [x, y]
  # z-depth is measured along the optical axis: the far side is a straight line
  side = max_depth_m * np.tan(np.deg2rad(fovx_deg) / 2)
  far = np.array([[max_depth_m, side], [max_depth_m, -side]]) @ rot.T + cam
  ax.add_patch(Polygon(np.vstack([cam, far]), closed=True, fc="deepskyblue", alpha=0.25,
                       ec="deepskyblue", lw=1.2, zorder=4))
  return [Patch(fc="gold", ec="black", label=f"{robot.name} footprint and heading"),
          Patch(fc="deepskyblue", alpha=0.4, ec="deepskyblue",
                label=f"camera frustum ({fovx_deg:g} deg, {max_depth_m:g} m)")]


def save_map(world: Vineyard, path, title: str | None = None, *, pose=None,
             robot: RobotSpec | None = None, fovx_deg: float = 60.0,
             max_depth_m: float = 5.0) -> None:
  """Writes a top-down PNG map of `world`, with a colourbar of the terrain height (m).
  With `pose` (x, y, yaw) and `robot`: the robot there and its camera frustum."""
  fig, ax = plt.subplots(figsize=(12, 12 * 0.5 * max(0.35, np.ptp(world.plant_xy[:, 1]) /
                                                     world.length_m) + 2.2))
  handles, image = draw_vineyard(ax, world)
  if pose is not None and robot is not None:
    handles += draw_pose(ax, robot, pose, fovx_deg=fovx_deg, max_depth_m=max_depth_m)
  ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
  fig.colorbar(image, ax=ax, location="bottom", fraction=0.04, pad=0.16, shrink=0.5,
               aspect=40, label="terrain height [m]")
  name = (f"{Path(world.frame['source']).name or 'vineyard file'} (rows along +x)"
          if world.frame else f"{world.kind} vineyard, seed {world.seed}")
  ax.set_title(title or f"{name}: inter-row {world.inter_row_m:.2f} m, spacing "
               f"{world.spacing_m:.2f} m")
  with atomic_path(path) as tmp:
    fig.savefig(tmp, dpi=110, bbox_inches="tight")
  plt.close(fig)
