"""A run's orbax checkpoints: the one owner of their layout, writing and reading.

    RUN_DIR/checkpoints/<chunk>/default/        the last 3 TrainStates (`Checkpoints.save`)
    RUN_DIR/checkpoints/best/<chunk>/default/   the best evaluated one (`Checkpoints.save_best`)
    RUN_DIR/best.json                           its evaluation scores

`Checkpoints` writes them and restores a whole TrainState (the trainer's resume);
`checkpoint_item` picks the step a run's "best" or "last" policy is read from and
`restore_actor_params` reads one member's actor params without a template (`python -m mjxvine.export`,
`mjxvine.evaluation.policies`).

jax and orbax are imported where they are used, so that the export CLI's .npz -> ONNX
conversion and evaluate's argument checks do not load them.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from mjxvine import atomic
from mjxvine.formatting import first_line

WHICH = ("best", "last")  # which checkpoint of a run: see `checkpoint_item`


class Checkpoints:
  """Orbax checkpoints of the TrainState under RUN_DIR/checkpoints/<chunk>, written
  atomically (orbax finalises a step only once complete), and the best evaluated one
  under RUN_DIR/checkpoints/best/<chunk> (its scores in RUN_DIR/best.json). Restoring
  falls back to the previous step, with a message, when the newest is corrupt or
  partial."""

  def __init__(self, run_dir: Path, save_replay: bool, clean: bool = False):
    """`clean`: first remove the temporary step directories a killed or failed save left
    (only the one writer of the run dir may: see `mjxvine.rundir.RunLock`)."""
    import orbax.checkpoint as ocp
    self.ocp = ocp
    self.dir = (run_dir / "checkpoints").resolve()
    self.best_json = run_dir / "best.json"
    self.save_replay = save_replay
    self.primary = True
    if clean:
      self.removed = remove_partial_steps(self.dir)
    options = lambda keep: ocp.CheckpointManagerOptions(max_to_keep=keep, create=True)
    self.manager = ocp.CheckpointManager(self.dir, options=options(3))
    self.best_manager = ocp.CheckpointManager(self.dir / "best", options=options(1))

  def _payload(self, ts) -> dict:
    """{"learner": LearnerState, "state": {index: array}}: the learner keeps its field
    names (`restore_actor_params` finds `actor_params` there); the rest is flattened,
    because orbax cannot store the zero-size arrays of MJX data."""
    import jax
    rest = ts.replace(learner=None, buffer=None if not self.save_replay else ts.buffer)
    leaves = jax.tree.leaves(rest)
    return {"learner": ts.learner,
            "state": {f"{i:05d}": x for i, x in enumerate(leaves) if x.size > 0}}

  def _unpayload(self, payload: dict, template):
    import jax
    rest = template.replace(learner=None,
                            buffer=None if not self.save_replay else template.buffer)
    leaves, treedef = jax.tree.flatten(rest)
    leaves = [payload["state"].get(f"{i:05d}", x) for i, x in enumerate(leaves)]
    ts = jax.tree.unflatten(treedef, leaves).replace(learner=payload["learner"])
    return ts if self.save_replay else ts.replace(buffer=template.buffer)

  def save(self, step: int, ts) -> None:
    """Writes step `step` and waits until it is complete. A failed write (disk full, ...)
    raises `mjxvine.rundir.WriteError` in one line; the earlier steps stay intact."""
    self._save(self.manager, step, ts, f"checkpoint {step}")

  def save_best(self, step: int, ts, scores: dict) -> None:
    """Keeps `ts` as the best checkpoint, with its evaluation `scores`."""
    self._save(self.best_manager, step, ts, f"best checkpoint {step}", force=True)
    if self.primary:
      atomic.write_text(self.best_json, json.dumps({"chunk": step, **scores}))

  def _save(self, manager, step: int, ts, what: str, **kw) -> None:
    from mjxvine.rundir import write_failure
    try:
      with _orbax_quiet():
        manager.save(step, args=self.ocp.args.StandardSave(self._payload(ts)), **kw)
        manager.wait_until_finished()
    except Exception as e:  # noqa: BLE001 - orbax and tensorstore fail in many types
      error = write_failure(manager.directory, what, e)
      if self.primary:
        remove_partial_steps(Path(manager.directory))  # give the space back
      raise error from None

  def best_scores(self) -> dict | None:
    """The scores of the best checkpoint so far (None before the first evaluation)."""
    if not self.best_json.is_file() or self.best_manager.latest_step() is None:
      return None
    return json.loads(self.best_json.read_text())

  def restore(self, template, best: bool = False):
    """(step, TrainState) of the newest intact checkpoint (or the best one), restored onto
    `template` (a fresh TrainState of the same config), or None when there is none.
    A step that cannot be restored is said in one line and, by the run's one writer,
    moved aside to RUN_DIR/checkpoints-broken/ (`move_aside`), so the next save does not
    sit beside it."""
    import jax
    manager = self.best_manager if best else self.manager
    abstract = jax.tree.map(
        lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding),
        self._payload(template))
    for step in sorted(manager.all_steps(), reverse=True):
      try:
        payload = manager.restore(step, args=self.ocp.args.StandardRestore(abstract))
      except Exception as e:  # noqa: BLE001 - any failure means this step is unusable
        what = "best checkpoint" if best else "checkpoint"
        moved = self.move_aside(manager, step) if self.primary else None
        print(f"{what} {step} is corrupt or partial ({type(e).__name__}: "
              f"{first_line(e)})" + (f"; moved to {moved}" if moved else "")
              + ("; trying the previous one" if not best else ""), file=sys.stderr)
        continue
      return step, self._unpayload(payload, template)
    return None

  def move_aside(self, manager, step: int) -> Path | None:
    """Moves a broken step out of its manager's directory (to
    RUN_DIR/checkpoints-broken/[best-]<step>), where nothing reads it but a person;
    returns where, or None when it could not be moved."""
    import shutil
    source = Path(manager.directory) / str(step)
    aside = self.dir.parent / "checkpoints-broken"
    target = aside / (f"best-{step}" if manager is self.best_manager else str(step))
    try:
      aside.mkdir(exist_ok=True)
      if target.exists():
        shutil.rmtree(target)
      shutil.move(str(source), str(target))
      manager.reload()
    except OSError:
      return None
    return target


def remove_partial_steps(manager_dir: Path) -> list[Path]:
  """Removes the temporary step directories ("<step>.orbax-checkpoint-tmp*") that orbax
  leaves when a save is killed or fails, under a CheckpointManager dir and its best/.
  Returns those removed. Finished steps are never touched."""
  import shutil
  removed = []
  for d in (Path(manager_dir), Path(manager_dir) / "best"):
    for tmp in d.glob("*.orbax-checkpoint-tmp*") if d.is_dir() else ():
      shutil.rmtree(tmp, ignore_errors=True)
      removed.append(tmp)
  return removed


class _orbax_quiet:
  """Silences orbax's own logging (absl) during a save: a failed write makes it log
  hundreds of lines of tracebacks for one cause, which `Checkpoints._save` reports in
  one line instead."""

  def __enter__(self):
    import logging
    self.loggers = [logging.getLogger(n) for n in ("absl", "orbax", "asyncio")]
    self.levels = [l.level for l in self.loggers]
    for l in self.loggers:
      l.setLevel(logging.CRITICAL)

  def __exit__(self, *exc):
    for l, level in zip(self.loggers, self.levels):
      l.setLevel(level)


def _item_of(step: Path) -> Path | None:
  """The orbax item dir of a step dir: itself when it holds _METADATA, else its item
  subdir ("default" for a CheckpointManager step); None when there is none."""
  if (step / "_METADATA").is_file():
    return step
  items = sorted(p for p in step.iterdir() if (p / "_METADATA").is_file()) if step.is_dir() else []
  return next((p for p in items if p.name == "default"), items[0] if items else None)


def _steps(manager: Path) -> dict[int, Path]:
  """{step: item dir} of the finished steps of a CheckpointManager dir (numeric subdirs;
  orbax writes a step under a temporary name and renames it once complete)."""
  if not manager.is_dir():
    return {}
  found = {int(p.name): _item_of(p) for p in manager.iterdir() if p.name.isdigit()}
  return {step: item for step, item in found.items() if item is not None}


def checkpoint_item(path: str | Path, which: str = "best") -> Path:
  """The absolute orbax item dir to restore from a run dir, its `checkpoints` dir (or
  `checkpoints/best`), a step dir or an item dir (one holding _METADATA: used as is).

  which="best": the highest step under checkpoints/best/, else the last regular step;
  which="last": the highest step directly under checkpoints/ (never best/). The path is
  made absolute (orbax refuses relative ones). FileNotFoundError "no such run directory:
  PATH" when `path` does not exist, and one naming `path` when it holds no checkpoint.
  """
  if which not in WHICH:
    raise ValueError(f"which={which!r}: expected one of {', '.join(WHICH)}")
  given = Path(path)
  path = given.expanduser().resolve()
  if not path.exists():
    raise FileNotFoundError(f"no such run directory: {given}")
  item = _item_of(path)
  if item is not None:
    return item
  root = path / "checkpoints" if (path / "checkpoints").is_dir() else path
  steps = (_steps(root / "best") if which == "best" else {}) or _steps(root)
  if not steps:
    raise FileNotFoundError(f"{given}: no orbax checkpoint inside (no checkpoints/<step>/ "
                            "with a _METADATA file)")
  return steps[max(steps)]


def run_dir_of(item: Path) -> Path | None:
  """The run dir of a checkpoint item (the parent of its `checkpoints` dir), or None."""
  return next((p.parent for p in item.parents if p.name == "checkpoints"), None)


def _find_key(tree: Any, key: str) -> Any:
  """The first value under `key` in a nested dict (breadth first), or None."""
  level = [tree]
  while level:
    nxt = []
    for node in level:
      if isinstance(node, dict):
        if key in node:
          return node[key]
        nxt.extend(node.values())
    level = nxt
  return None


def best_member(run_dir: Path | None) -> int:
  """The member of a `--num-seeds` / sweep run that checkpoints/best follows: the trainer keeps
  the best evaluation of member 0 (RUN_DIR/best.json may name another as "member")."""
  if run_dir is not None and (run_dir / "best.json").is_file():
    try:
      return int(json.loads((run_dir / "best.json").read_text()).get("member", 0))
    except (ValueError, TypeError, AttributeError):
      pass
  return 0


def num_members(actor: Any) -> int | None:
  """How many members a restored actor holds: the leading axis of its stacked params (a
  `--num-seeds` / sweep run), None for a single actor (its mean head's kernel is 2-D)."""
  head = _find_key(actor, "mean")
  if not isinstance(head, dict) or "kernel" not in head:
    return None
  return head["kernel"].shape[0] if np.ndim(head["kernel"]) == 3 else None


def select_member(actor: Any, member: int | None, run_dir: Path | None = None) -> Any:
  """One member's params of a restored actor: `member` (None: `best_member(run_dir)`) of
  stacked params; a single actor as it is (member None or 0). ValueError naming the
  range when `member` is not a member of the run."""
  import jax
  count = num_members(actor)
  if count is None:
    if member not in (None, 0):
      raise ValueError(f"member {member}: this run trained one member (0)")
    return actor
  member = best_member(run_dir) if member is None else member
  if not 0 <= member < count:
    raise ValueError(f"member {member}: this run trained {count} members (0 to {count - 1})")
  return jax.tree.map(lambda x: np.asarray(x)[member], actor)


def unflatten_params(arrays: dict) -> dict:
  """{"a/b/c": array} (a policy file's flax paths) -> the nested params dict."""
  tree: dict = {}
  for name, value in arrays.items():
    node = tree
    *parents, leaf = name.split("/")
    for p in parents:
      node = node.setdefault(p, {})
    node[leaf] = value
  return tree


# Written by `mjxvine.evaluation.choice` in a run dir: the validation worlds' choice of the
# best policy; of a run of several members (--num-seeds, sweeps), one choice per member.
SELECTION_JSON = "selection.json"
SELECTED_POLICY = "selected.npz"
SELECTED_MEMBERS = "selected_members"  # RUN/selected_members/{selection<k>.json, member<k>.npz}


def selection_files(run_dir: str | Path, member: int | None = None) -> tuple[Path, Path]:
  """(the selection record, the chosen policy file) of a run (`member` None) or of one
  member of a run of several."""
  run = Path(run_dir)
  if member is None:
    return run / SELECTION_JSON, run / SELECTED_POLICY
  return (run / SELECTED_MEMBERS / f"selection{member}.json",
          run / SELECTED_MEMBERS / f"member{member}.npz")


def selected_policy(path: str | Path, which: str = "best",
                    member: int | None = None) -> Path | None:
  """The policy chosen on validation worlds (`mjxvine.evaluation.choice`) when `path` is a
  run dir (or its checkpoints dir) whose choice was made and `which` is "best": RUN/
  selected.npz, or of a run of several members RUN/selected_members/member<k>.npz (member
  None: member 0, which checkpoints/best follows); else None."""
  if which != "best":
    return None
  path = Path(path).expanduser()
  run = path.parent if path.name == "checkpoints" else path
  options = ([selection_files(run)] if member in (None, 0) else []) + [
      selection_files(run, member or 0)]
  return next((npz for record, npz in options if record.is_file() and npz.is_file()), None)


def restore_tree(item: Path) -> dict:
  """The nested dict of numpy arrays of one orbax checkpoint item, from its own metadata (no
  TrainState template); ValueError in one line for a damaged one."""
  import jax
  import orbax.checkpoint as ocp
  ckpt = ocp.PyTreeCheckpointer()
  try:
    tree_meta = ckpt.metadata(item).item_metadata
    tree_meta = getattr(tree_meta, "tree", tree_meta)
    restore_args = jax.tree.map(lambda _: ocp.RestoreArgs(restore_type=np.ndarray), tree_meta)
    return ckpt.restore(item, args=ocp.args.PyTreeRestore(restore_args=restore_args))
  except Exception as e:  # noqa: BLE001 - orbax fails in many ways on damaged files
    raise ValueError(f"{item}: not a readable orbax checkpoint ({type(e).__name__}: "
                     f"{first_line(e)})") from None


def restore_actor_params(path: str | Path, which: str = "best",
                         member: int | None = None) -> tuple[Any, Path]:
  """(actor params, item dir) of the checkpoint that `checkpoint_item(path, which)` picks;
  of a run dir whose best policy was chosen on validation worlds, (its params, the chosen
  policy file) for which="best" (`selected_policy`, of `member`).

  The params are the actor's flax "params" dict of numpy arrays of one member: of a run
  that trained several (`--num-seeds`, sweeps; saved with a leading members axis), `member`,
  by default the one checkpoints/best follows (`best_member`). No TrainState template is
  needed: the tree comes from the checkpoint's own metadata. Raises FileNotFoundError (see
  `checkpoint_item`), ValueError (a damaged checkpoint, a member the run does not have)
  and KeyError (no `actor_params` entry).
  """
  chosen = selected_policy(path, which, member)
  if chosen is not None:
    from mjxvine.deploy import read_policy_file
    return unflatten_params(read_policy_file(chosen)[0]), chosen
  item = checkpoint_item(path, which)
  tree = restore_tree(item)
  # the evaluated actor (`LearnerState.averaged_actor_params`; "policy_params" in
  # checkpoints of mjxvine 0.2.0); older checkpoints had only the learning actor
  actor = _find_key(tree, "averaged_actor_params")
  if actor is None:
    actor = _find_key(tree, "policy_params")
  if actor is None:
    actor = _find_key(tree, "actor_params")
  if actor is None:
    raise KeyError(f"{item}: the checkpoint has no 'actor_params' entry")
  try:
    return select_member(actor, member, run_dir_of(item)), item
  except ValueError as e:
    raise ValueError(f"{run_dir_of(item) or item}: {e}") from None
