"""A run's logs: metrics.jsonl (one JSON row per member and chunk), TensorBoard events
(tb/) and a progress bar (`Logger`); the learning curve drawn from metrics.jsonl
(`plot_learning_curve`); both cut back to the checkpoint a resume starts from
(`truncate_metrics`, `clear_events`)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

from mjxvine import atomic
from mjxvine.formatting import fmt


def truncate_metrics(path: Path, env_steps: int) -> int:
  """Keeps the rows of metrics.jsonl at `path` up to `env_steps` (those the restored
  checkpoint has seen; 0: none), rewriting the file atomically. Returns the rows dropped."""
  if not path.is_file():
    return 0
  lines = [l for l in path.read_text().splitlines() if l.strip()]
  keep = []
  for line in lines:
    try:
      row = json.loads(line)
    except json.JSONDecodeError:
      continue  # a line cut short by a kill
    if row.get("env_steps", 0) <= env_steps:
      keep.append(line)
  if len(keep) == len(lines):
    return 0
  atomic.write_text(path, "".join(l + "\n" for l in keep))
  return len(lines) - len(keep)


def clear_events(tb_dir: Path) -> None:
  """Removes the TensorBoard event files of a run that starts afresh in the same dir."""
  for f in Path(tb_dir).glob("events.out.tfevents.*"):
    f.unlink()


class Logger:
  """metrics.jsonl + TensorBoard (tensorboardX) + a progress line."""

  def __init__(self, run_dir: Path, total: int, start: int, enabled: bool = True,
               purge_step: int | None = None):
    """`purge_step`: on a resume, the first env step after the restored checkpoint;
    TensorBoard drops the events of the stopped run from there on."""
    self.enabled = enabled
    if not enabled:
      return
    from tensorboardX import SummaryWriter
    from tqdm import tqdm
    self.jsonl = open(run_dir / "metrics.jsonl", "a")
    self.tb = SummaryWriter(str(run_dir / "tb"), purge_step=purge_step)
    self.bar = tqdm(total=total, initial=start, unit="step", dynamic_ncols=True,
                    mininterval=2.0, file=sys.stderr)
    self.last_eval = ""

  def log(self, row: dict) -> None:
    if not self.enabled:
      return
    self.jsonl.write(json.dumps(row) + "\n")
    self.jsonl.flush()
    for k, v in row.items():
      if isinstance(v, (int, float)) and k != "env_steps" and v is not None and math.isfinite(v):
        self.tb.add_scalar(k, v, row["env_steps"])
    self.tb.flush()
    self.bar.n = row["env_steps"]
    if "eval_success_forward" in row:
      self.last_eval = (f" | eval F {row['eval_success_forward']:.2f} "
                        f"R {row['eval_success_reverse']:.2f}")
    self.bar.set_postfix_str(
        f"sps {row['sps']:.0f} ups {row['ups']:.0f} ret {fmt(row['return_mean'], 2)} "
        f"succ {fmt(row['success_rate'], 2)} eps {row['eps']:.2f} alpha {row['alpha']:.3f} "
        f"Lq {row['critic_loss']:.3g} Lpi {row['actor_loss']:.3g}{self.last_eval}",
        refresh=True)

  def close(self):
    if not self.enabled:
      return
    self.enabled = False
    self.bar.close()
    self.tb.close()
    self.jsonl.close()


def _smooth(y: np.ndarray, width: int) -> np.ndarray:
  """Moving average over the last `width` finite values (NaN where none yet)."""
  out = np.full(len(y), np.nan)
  for i in range(len(y)):
    window = y[max(0, i - width + 1):i + 1]
    window = window[np.isfinite(window)]
    if window.size:
      out[i] = window.mean()
  return out


def plot_learning_curve(run_dir: Path) -> None:
  """learning_curve.png from metrics.jsonl: training episodes (with exploration), the
  deterministic evaluations per direction, losses and the exploration schedule."""
  import matplotlib.pyplot as plt
  rows = [json.loads(l) for l in (run_dir / "metrics.jsonl").read_text().splitlines() if l]
  if not rows:
    return
  members = sorted({r.get("member", r.get("seed", 0)) for r in rows})
  fig, axes = plt.subplots(2, 3, figsize=(15, 7.5))
  axes = axes.ravel()
  width = max(1, len(rows) // len(members) // 15)
  for s in members:
    rs = [r for r in rows if r.get("member", r.get("seed", 0)) == s]
    x = np.array([r["env_steps"] for r in rs])
    col = lambda k: np.array([np.nan if r.get(k) is None else r[k] for r in rs], float)
    label = ", ".join(f"{k.split('.')[-1]} {v:g}" for k, v in rs[0].items()
                      if k.startswith("sac.")) or f"seed {rs[0].get('seed', s)}"
    if any(k.startswith("sac.") for k in rs[0]):
      label += f", seed {rs[0].get('seed', 0)}"
    colour = f"C{s % 10}"

    def curve(ax, key, lab, style="-", c=colour, smooth=True):
      y = col(key)
      if smooth and width > 1:
        ax.plot(x, y, style, color=c, alpha=0.25, lw=0.8)
        y = _smooth(y, width)
      ax.plot(x, y, style, color=c, label=lab)

    curve(axes[0], "return_mean", label)
    curve(axes[1], "success_rate", f"training ({label})")
    evaluated = np.isfinite(col("eval_success_forward"))
    for key, style, name in (("eval_success_forward", "o-", "forward"),
                             ("eval_success_reverse", "s--", "reverse")):
      if evaluated.any():
        axes[2].plot(x[evaluated], col(key)[evaluated], style, color=colour, ms=4,
                     label=f"{name} ({label})" if len(members) > 1 else name)
    if evaluated.any():
      axes[3].plot(x[evaluated], col("eval_mae_m")[evaluated], "o-", color=colour, ms=4,
                   label=label)
    learned = col("critic_loss") > 0  # 0 before learning starts: not a loss
    for ax, key in ((axes[4], "critic_loss"), (axes[5], "actor_loss")):
      y = np.where(learned, col(key), np.nan)
      ax.plot(x, y, color=colour, label=label)
    if s == members[0]:
      twin = axes[0].twinx()
      twin.plot(x, col("eps"), ":", color="0.4", label="epsilon")
      twin.plot(x, col("alpha") / max(np.nanmax(col("alpha")), 1e-12), "-.", color="0.6",
                label="alpha / max")
      twin.set_ylim(0, 1.05)
      twin.set_ylabel("epsilon, alpha / max alpha")
      twin.legend(loc="lower right", fontsize=7)
  titles = [("training episodes (with exploration): return", "episode return"),
            ("training episodes (with exploration): success", "success rate"),
            ("deterministic policy, fresh starts: success", "success rate"),
            ("deterministic policy, fresh starts: lateral MAE", "MAE (m)"),
            ("critic loss (once learning)", "loss"), ("actor loss (once learning)", "loss")]
  for ax, (title, ylabel) in zip(axes, titles):
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("env steps")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
  for ax in (axes[1], axes[2]):
    ax.set_ylim(-0.03, 1.03)
  axes[4].set_yscale("log")
  if axes[2].lines:
    axes[2].legend(fontsize=7)
  if len(members) > 1:
    axes[0].legend(fontsize=7, loc="upper left")
  fig.tight_layout()
  with atomic.atomic_path(run_dir / "learning_curve.png") as tmp:
    fig.savefig(tmp, dpi=100)
  plt.close(fig)
