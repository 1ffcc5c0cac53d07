"""What plugs into the training loop (`mjxvine.training.loop`), as brax's `progress_fn`:
after every chunk each hook sees the `Chunk` just trained, in order: the evaluation from
fresh starts (`FreshStartEvaluation`: the best checkpoint, each member's best policy, the
kept policies for the choice on validation worlds), the logs (`ChunkLog`: metrics.jsonl,
TensorBoard, the progress bar) and the checkpoints (`Checkpointing`); at the end of the
loop the evaluation and the checkpoints get their `at_end`."""

from __future__ import annotations

import dataclasses
import datetime
import json
import time
from pathlib import Path
from typing import Any, Callable

import jax
import numpy as np

from mjxvine import atomic
from mjxvine.config import Config
from mjxvine.deploy.export import export_actor, meta_from_config
from mjxvine.evaluation import choice, starts
from mjxvine.rundir.checkpoints import Checkpoints
from mjxvine.rundir.logs import Logger
from mjxvine.networks import describe_conv_impl
from mjxvine.training.distributed import local
from mjxvine.training.programs import starts_params
from mjxvine.agent_file import agent_arrays, agent_path, write_agent


@dataclasses.dataclass
class Chunk:
  """A chunk just trained: `index` chunks are done; `ts` the TrainState after it (its log
  sums are reset by `ChunkLog`), `metrics` its fetched metrics, `seconds` its wall-clock,
  `compile_s` the first chunk's (compilation included); `evals` one dict per member of
  the fresh-start evaluation after it ({} when none ran)."""
  index: int
  ts: Any
  metrics: dict
  seconds: float
  compile_s: float
  evals: list[dict]


def member_scores(out: dict, member: int) -> dict:
  """{"eval_<name>": float} of one member from a `start_evaluator` run's output."""
  return {f"eval_{k}": float(np.reshape(v, (-1,))[member]) for k, v in out.items()}


def eval_line(scores: dict) -> str:
  return (f"forward {scores['eval_success_forward']:.0%}, reverse "
          f"{scores['eval_success_reverse']:.0%}, lateral MAE {scores['eval_mae_m']:.3f} m")


def export_member(cfg: Config, actor, k: int | None, path: Path, chunk: int,
                  env_steps: int) -> None:
  """Writes member k of the (local) actor params, stacked over members, as a policy file;
  k = None: params of a single-member run (no member axis)."""
  meta = {**meta_from_config(cfg), "member": 0 if k is None else k, "chunk": chunk,
          "env_steps": env_steps, "conv_tower": describe_conv_impl(cfg.train.conv_impl)}
  export_actor(actor if k is None else jax.tree.map(lambda x: x[k], actor), path, meta)


class MemberBest:
  """Each member's best actor of a `--num-seeds` / sweep run, chosen by its own evaluations
  from fresh starts (`choice.fresh_start_score`), as a policy file
  RUN_DIR/best_members/member<k>.npz (`python -m mjxvine.evaluate --policy` takes it), its
  scores in RUN_DIR/best_members/scores.json. checkpoints/best follows member 0 alone."""

  def __init__(self, run_dir: Path, cfg: Config):
    self.dir, self.cfg = run_dir / "best_members", cfg
    self.json = self.dir / "scores.json"
    self.scores = json.loads(self.json.read_text()) if self.json.is_file() else {}

  def update(self, chunk: int, env_steps: int, rows: list[dict], actor) -> None:
    score = choice.fresh_start_score
    better = [k for k, row in enumerate(rows) if str(k) not in self.scores
              or score(row) > score(self.scores[str(k)])]
    if not better:
      return
    actor = local(actor)
    for k in better:
      export_member(self.cfg, actor, k, self.dir / f"member{k}.npz", chunk, env_steps)
      self.scores[str(k)] = {"chunk": chunk, "env_steps": env_steps,
                             **{n: v for n, v in rows[k].items() if n != "best"}}
    atomic.write_text(self.json, json.dumps(self.scores, indent=1))


class FreshStartEvaluation:
  """Every `train.eval_every_chunks` chunks and after the last, the deterministic policy of
  every member drives `train.eval_starts` fresh starts per direction (the same starts
  each time). Keeps the state of all members as checkpoints/best when member 0's scores
  are the best so far, each member's actor as best_members/member<k>.npz when its own
  are (`MemberBest`), and, for the choice on validation worlds, every evaluated policy
  (of each member: `choice.policy_file`)."""
  phase = "fresh_start_evaluations"  # of the run's profile (`training.profile`)

  def __init__(self, cfg: Config, run_dir: Path, start_eval, ckpt: Checkpoints, seeds: int,
               total_chunks: int, primary: bool, say: Callable):
    self.cfg, self.run_dir, self.start_eval, self.ckpt = cfg, run_dir, start_eval, ckpt
    self.seeds, self.total_chunks, self.primary, self.say = seeds, total_chunks, primary, say
    self.key = jax.random.PRNGKey(cfg.train.seed + 1)  # the same starts at every evaluation
    # read once: every process decides on the same scores (process 0 rewrites the file)
    self.best = ckpt.best_scores()
    self.member_best = MemberBest(run_dir, cfg) if seeds > 1 and primary else None
    self.evaluated = -1  # the chunk index of the last evaluation

  def evaluate(self, ts, chunk_index: int) -> list[dict]:
    """The scores of every member after `chunk_index` chunks; keeps the best policies."""
    t0 = time.time()
    out = self.start_eval(starts_params(ts.learner.averaged_actor_params, starts.ACTOR, self.seeds),
                          self.key)
    rows = [member_scores(out, s) for s in range(self.seeds)]
    steps = int(np.max(ts.env_steps))
    if self.best is None or choice.fresh_start_score(rows[0]) > choice.fresh_start_score(
        self.best):
      scores = {"env_steps": steps, **rows[0]}
      self.ckpt.save_best(chunk_index, ts, scores)
      self.best = {"chunk": chunk_index, **scores}
      rows[0]["best"] = True
    if self.member_best is not None:
      self.member_best.update(chunk_index, steps, rows, ts.learner.averaged_actor_params)
    if (self.cfg.train.keep_eval_policies or self.cfg.train.select_worlds) and self.primary:
      learner = local(ts.learner)
      for k in choice.member_ids(self.seeds):  # each member's own, with its agent file
        path = choice.policy_file(self.run_dir, steps, k)
        export_member(self.cfg, learner.averaged_actor_params, k, path, chunk_index, steps)
        one = learner if k is None else jax.tree.map(lambda x, k=k: x[k], learner)
        write_agent(agent_path(path), agent_arrays(one), meta_from_config(self.cfg))
    self.say(f"evaluated {2 * self.cfg.train.eval_starts} fresh starts in "
             f"{time.time() - t0:.0f} s: {eval_line(rows[0])}"
             + (" (new best)" if rows[0].get("best") else ""))
    self.evaluated = chunk_index
    return rows

  def after_chunk(self, chunk: Chunk) -> None:
    every = self.cfg.train.eval_every_chunks
    if (every and chunk.index % every == 0) or chunk.index == self.total_chunks:
      chunk.evals = self.evaluate(chunk.ts, chunk.index)

  def at_end(self, ts, chunk_index: int) -> dict:
    """Member 0's scores of the last policy when the loop stopped early ({} otherwise)."""
    return self.evaluate(ts, chunk_index)[0] if self.evaluated != chunk_index else {}


class ChunkLog:
  """One metrics.jsonl row per member and chunk (`row`), also to TensorBoard and the
  progress bar; then the TrainState's log sums are reset for the next chunk."""
  phase = "logs"

  def __init__(self, cfg: Config, members: list[dict], logger: Logger):
    self.cfg, self.members, self.logger = cfg, members, logger
    self.steps_per_chunk = cfg.env.num_envs * cfg.train.iters_per_chunk
    self.last_row = {}  # member 0's

  def after_chunk(self, chunk: Chunk) -> None:
    ts = chunk.ts
    host = jax.device_get((ts.env_steps, ts.episodes, ts.log_episodes, ts.log_return,
                           ts.log_success, ts.log_timeout, ts.log_speed, ts.log_terms))
    evals = chunk.evals or [{}] * len(self.members)
    for s, member in enumerate(self.members):
      row = self.row(member, s, chunk, host, evals[s])
      if s == 0:
        self.last_row = row
      self.logger.log(row)
    chunk.ts = ts.reset_log()

  def row(self, member: dict, s: int, chunk: Chunk, host, evals: dict) -> dict:
    """The metrics.jsonl row of member `s` after the chunk: `host` the fetched counters
    and sums of the TrainState."""
    get = (lambda x: np.reshape(x, (-1,))[s])
    eps_done = int(get(host[2]))
    per_episode = lambda x: float(get(x) / eps_done) if eps_done else None
    steps_per_chunk, dt = self.steps_per_chunk, chunk.seconds
    row = {
        **member, "member": s,
        "chunk": chunk.index, "env_steps": int(get(host[0])),
        "episodes": int(get(host[1])),
        "return_mean": per_episode(host[3]), "success_rate": per_episode(host[4]),
        "timeout_rate": per_episode(host[5]), "v_mean": float(get(host[6])) / steps_per_chunk,
        "sps": steps_per_chunk / dt,
        "ups": self.cfg.train.iters_per_chunk * self.cfg.sac.grad_steps_per_iter / dt,
        "chunk_s": dt, "compile_s": chunk.compile_s,
        "wall": datetime.datetime.now().isoformat(timespec="seconds"),
        **evals,
    }
    row.update({k: float(get(v)) / steps_per_chunk for k, v in host[7].items()})
    row.update({k: float(get(v)) for k, v in chunk.metrics.items() if k != "finite"})
    return row


class Checkpointing:
  """A checkpoint every `train.checkpoint_every_chunks` chunks and after the last; at the
  end of a loop that stopped early (a signal), one of where it stopped."""
  phase = "checkpoints"

  def __init__(self, ckpt: Checkpoints, every: int, total_chunks: int, saved: int):
    self.ckpt, self.every, self.total_chunks, self.saved = ckpt, every, total_chunks, saved

  def after_chunk(self, chunk: Chunk) -> None:
    if chunk.index % self.every == 0 or chunk.index == self.total_chunks:
      self.ckpt.save(chunk.index, chunk.ts)
      self.saved = chunk.index

  def at_end(self, ts, chunk_index: int) -> None:
    if self.saved != chunk_index:
      self.ckpt.save(chunk_index, ts)
      self.saved = chunk_index
