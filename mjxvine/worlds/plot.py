"""Top-down maps of vineyards (matplotlib; headless machines fall back to Agg, and the
backend is left to the caller, so that notebooks keep theirs)."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

from mjxvine.worlds.layout import Vineyard


def draw_vineyard(ax, world: Vineyard, *, numbers: bool = True, terrain: bool = True) -> None:
  """Draws terrain, plants (canopy footprints), lane centerlines, lane numbers and EoRs."""
  if terrain:
    xmin, xmax, ymin, ymax = world.terrain_extent
    ax.imshow(world.terrain, origin="lower", extent=(xmin, xmax, ymin, ymax), cmap="copper",
              alpha=0.35, interpolation="bilinear")
  widths = 2 * world.canopy_half[:, :2].mean(axis=1)
  ax.scatter(world.plant_xy[:, 0], world.plant_xy[:, 1], s=(widths * 40) ** 2 / 4,
             c="forestgreen", alpha=0.8, edgecolors="darkgreen", linewidths=0.5,
             label="plants")
  for lane in world.lanes:
    c = lane.centerline
    ax.plot(c[:, 0], c[:, 1], "--", color="0.4", lw=0.8)
    if numbers:
      ax.text(c[0, 0] - 1.2, c[0, 1], str(lane.id), ha="center", va="center", fontsize=10,
              fontweight="bold", bbox=dict(boxstyle="circle", fc="white", ec="0.3"))
    ax.plot(*lane.eor_forward, marker=">", color="tab:red", ms=6)
    ax.plot(*lane.eor_reverse, marker="<", color="tab:blue", ms=6)
  ax.set_aspect("equal")
  ax.set_xlabel("x [m]")
  ax.set_ylabel("y [m]")
  ys = world.plant_xy[:, 1]
  ax.set_xlim(-2.5, world.length_m + 1.5)
  ax.set_ylim(ys.min() - 1.5, ys.max() + 1.5)


def save_map(world: Vineyard, path, title: str | None = None) -> None:
  """Writes a top-down PNG map of `world`."""
  fig, ax = plt.subplots(figsize=(12, 12 * 0.5 * max(0.35, np.ptp(world.plant_xy[:, 1]) /
                                                     world.length_m) + 1.5))
  draw_vineyard(ax, world)
  ax.plot([], [], ">", color="tab:red", label="EoR forward")
  ax.plot([], [], "<", color="tab:blue", label="EoR reverse")
  ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
  ax.set_title(title or f"{world.kind} vineyard, seed {world.seed}: inter-row "
               f"{world.inter_row_m:.2f} m, spacing {world.spacing_m:.2f} m")
  fig.tight_layout()
  fig.savefig(path, dpi=110, bbox_inches="tight")
  plt.close(fig)
