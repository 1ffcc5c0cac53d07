"""`python -m mjxvine.view`: the stepping it shows is the evaluator's (checked headless, on
a toy env that compiles in a moment, and on the vineyard in the slow suite), and without
a display it says so in one line."""

from types import SimpleNamespace

import flax.struct
import jax
import jax.numpy as jp
import numpy as np
import pytest
from brax.envs.base import State

from mjxvine import view
from mjxvine.config import load_config
from mjxvine.env import OUTCOMES, VineyardEnv, pure_pursuit
from mjxvine.evaluation import rollout
from mjxvine.worlds import generate_world


def test_without_a_display_it_says_so(monkeypatch, capsys):
  monkeypatch.delenv("DISPLAY", raising=False)
  monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
  monkeypatch.setattr(view.sys, "platform", "linux")
  assert view.main(["--policy", "oracle"]) == 2
  err = capsys.readouterr().err
  assert err.startswith("error: no display") and "--video" in err and err.count("\n") == 1


@flax.struct.dataclass
class _Pipeline:
  qpos: jax.Array


class ToyEnv:
  """A robot on a line: x += v * direction each step; success past |x| = 1 m."""
  cfg = SimpleNamespace(eval=SimpleNamespace(max_steps=40))

  def reset_to(self, key, world, lane, direction):
    qpos = jp.array([0.0, 2.0, 0.1, 1.0, 0.0, 0.0, 0.0]) * jp.array([1, lane, 1, 1, 1, 1, 1])
    return State(pipeline_state=_Pipeline(qpos), obs={"depth": jp.zeros((4, 4, 1)),
                 "state": jp.zeros(3)}, reward=jp.float32(0), done=jp.float32(0), metrics={},
                 info={"outcome": jp.int32(0), "direction": direction})

  def step(self, state, action):
    x = state.pipeline_state.qpos[0] + action[0] * state.info["direction"]
    outcome = jp.where(jp.abs(x) > 1.0, OUTCOMES.index("success"), 0).astype(jp.int32)
    return state.replace(pipeline_state=_Pipeline(state.pipeline_state.qpos.at[0].set(x)),
                         done=(outcome != 0).astype(jp.float32),
                         info=dict(state.info, outcome=outcome))


def _toy_policy(state, key):
  """A speed that depends on the key: equal actions mean equal keys."""
  return jp.array([0.05 + 0.1 * jax.random.uniform(key), 0.0])


def test_drive_is_the_evaluators_stepping():
  env = ToyEnv()
  key = jax.random.PRNGKey(7)
  steps = list(rollout.drive(env, _toy_policy, 3, "R", key))
  starts = rollout.EnvStarts(lanes=[2], directions=[-1.0])
  xy, act, alive, outcome, n, _ = rollout.rollout(env, _toy_policy, starts, key, 40)
  assert len(steps) == int(n[0]) + 1 < 40  # the start, every step, and no more
  assert steps[0][0][1] == 4.0 and np.all(steps[0][1] == 0)  # lane 3 (0-based 2)
  np.testing.assert_allclose(np.stack([q[:2] for q, _, _ in steps[1:]]), xy[:n[0], 0])
  np.testing.assert_allclose(np.stack([a for _, a, _ in steps[1:]]), act[:n[0], 0])
  assert steps[-1][0][0] < -1.0 and OUTCOMES[steps[-1][2]] == OUTCOMES[outcome[0]] == "success"
  assert [OUTCOMES[c] for _, _, c in steps[:-1]] == ["running"] * (len(steps) - 1)
  assert len(list(rollout.drive(env, _toy_policy, 1, "F", key, max_steps=3))) == 4


@pytest.mark.slow
def test_drive_steps_as_the_evaluator_does():
  """The viewer's steps are the protocol's on the vineyard: the same poses and actions."""
  cfg = load_config(None, ["world.test_length_m=8", "camera.width=16", "camera.height=12",
                           "eval.max_steps=20", "env.max_steps=20"])
  world = generate_world("test", 3, cfg.world)
  env = VineyardEnv(cfg, [world])
  policy = pure_pursuit(env)
  key = jax.random.PRNGKey(4)
  steps = list(rollout.drive(env, policy, 2, "R", key, max_steps=20))
  starts = rollout.EnvStarts(lanes=[1], directions=[-1.0])
  xy, act, alive, outcome, n, _ = rollout.rollout(env, policy, starts, key, 20)
  assert len(steps) == int(n[0]) + 1  # the start, then every step
  np.testing.assert_allclose(np.stack([q[:2] for q, _, _ in steps[1:]]), xy[:n[0], 0],
                             atol=1e-6)
  np.testing.assert_allclose(np.stack([a for _, a, _ in steps[1:]]), act[:n[0], 0], atol=1e-6)
  assert OUTCOMES[steps[-1][2]] in ("running", OUTCOMES[int(outcome[0])])
  assert np.linalg.norm(steps[-1][0][:2] - steps[0][0][:2]) > 0.5  # it drove
