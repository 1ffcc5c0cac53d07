"""The agent file (`mjxvine.agent_file`) and `train --init` (`mjxvine.training.warm_start`):
names, reading, the shipped agent's actions reproduced, refusals in one line."""

import dataclasses
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjxvine import networks as nw
from mjxvine.agent_file import agent_path, read_agent, write_agent
from mjxvine.config import ConfigError, load_config
from mjxvine.deploy import NumpyPolicy, read_policy_file
from mjxvine.training.warm_start import load_agent, network_shapes, warm_start

SHIPPED = Path("models/jackal.npz")
JACKAL = Path("experiments/jackal.yaml")


def test_a_policy_file_names_its_agent_file():
  assert agent_path("models/jackal.npz") == Path("models/jackal.sac.npz")
  assert agent_path("models/jackal.sac.npz") == Path("models/jackal.sac.npz")
  assert agent_path("runs/x/selected.npz") == Path("runs/x/selected.sac.npz")


def test_damaged_and_foreign_files_are_one_line(tmp_path):
  bad = tmp_path / "bad.sac.npz"
  bad.write_bytes(b"not a zip")
  with pytest.raises(ValueError, match="not a readable agent file"):
    read_agent(bad)
  with pytest.raises(ValueError, match="not an agent file"):
    read_agent(SHIPPED)  # a policy file has no agent format
  nan = tmp_path / "nan.sac.npz"
  write_agent(nan, {"log_alpha": np.float32(np.nan)}, {})
  with pytest.raises(ValueError, match="log_alpha is not a finite"):
    read_agent(nan)


def test_the_shipped_agent_file_reproduces_the_shipped_actions():
  """models/jackal.sac.npz fits experiments/jackal.yaml's networks, and a learner started
  from it acts as models/jackal.npz does, before any update."""
  cfg = load_config("experiments/jackal.yaml")
  nets = nw.make_networks_from_config(cfg)
  h, w = cfg.camera.height, cfg.camera.width
  obs = {"depth": jnp.zeros((1, h, w, 1)), "state": jnp.zeros((1, 3)),
         "lane": jnp.zeros((1, 3))}  # the critics' lane state (sac.privileged_critics)
  assert cfg.sac.privileged_critics
  from mjxvine import sac as sac_lib
  anchored = dataclasses.replace(cfg.sac, anchor_weight=1.0)  # keeps the loaded actor too
  learner = sac_lib.init_state(nets, anchored, jax.random.PRNGKey(7), obs)
  learner = warm_start(learner, str(SHIPPED))
  arrays, meta = read_policy_file(SHIPPED)
  plain = NumpyPolicy(arrays, {**meta, "mirror_average": False})  # one pass, as the actor
  rng = np.random.default_rng(0)
  depth = rng.uniform(0.3, 5.0, (8, h, w, 1)).astype(np.float32)
  depth[:, : h // 3] = 5.0
  state = rng.uniform([0.0, -1.0, -3.0], [0.5, 1.0, 3.0], (8, 3)).astype(np.float32)
  for params in (learner.actor_params, learner.averaged_actor_params,
                 learner.anchor_actor_params):
    mean = nets.actor.apply({"params": params}, {"depth": depth, "state": state})[0]
    got = np.asarray(nw.deterministic_action(mean, nets.action_low, nets.action_high))
    np.testing.assert_allclose(got, plain.action(depth, state), atol=1e-5)
  shapes = network_shapes(cfg)
  assert set(load_agent(str(SHIPPED), shapes)) == set(shapes)


def test_the_anchor_needs_a_loaded_agent(tmp_path):
  with pytest.raises(ConfigError, match="sac.anchor_weight = 0.5: .* train.init_from"):
    load_config("experiments/smoke.yaml", ["sac.anchor_weight=0.5"])
  cfg = load_config("experiments/smoke.yaml", ["sac.anchor_weight=0.5",
                                               f"train.init_from={SHIPPED}"])
  assert cfg.sac.anchor_weight == 0.5


def test_privileged_critics_agent_shapes_include_the_lane_input():
  """An agent file of privileged critics (`sac.privileged_critics`, the recipe's) has 3 more
  inputs in each critic's first layer; a config of critics without them refuses the
  shipped agent."""
  priv = load_config(str(JACKAL))
  plain = load_config(str(JACKAL), ["sac.privileged_critics=false"])
  assert priv.sac.privileged_critics
  plain_shapes, priv_shapes = network_shapes(plain), network_shapes(priv)
  changed = {k for k in plain_shapes if plain_shapes[k] != priv_shapes[k]}
  assert changed == {"critic/critic0/dense0/kernel", "critic/critic1/dense0/kernel",
                     "target_critic/critic0/dense0/kernel",
                     "target_critic/critic1/dense0/kernel"}
  for k in changed:
    assert priv_shapes[k][0] == plain_shapes[k][0] + 3
  with pytest.raises(ConfigError, match="has shape .* the config's networks"):
    load_agent(str(SHIPPED), plain_shapes)


def test_an_agent_of_other_networks_is_refused_in_one_line(tmp_path):
  cfg = load_config("experiments/smoke.yaml")
  with pytest.raises(ConfigError, match="has shape .* the config's networks"):
    load_agent(str(SHIPPED), network_shapes(cfg))
  out = subprocess.run([sys.executable, "-m", "mjxvine.train", "--config",
                        "experiments/smoke.yaml", "--init", str(SHIPPED), "--out",
                        str(tmp_path / "run")], capture_output=True, text=True, timeout=300)
  assert out.returncode == 2, out.stderr
  lines = out.stderr.strip().splitlines()
  assert len(lines) == 1 and lines[0].startswith("config error: train.init_from")
  assert not (tmp_path / "run").exists()


@pytest.mark.slow  # compiles the adapt recipe's trainer on a pool with the 90 m block
def test_the_adapt_guide_command_runs_at_a_tiny_size(tmp_path):
  """docs/adapt.md's command, with its budget, envs and replay cut to a tiny size: it
  starts from the shipped agent and writes a run."""
  tiny = ["train.total_env_steps=64", "env.num_envs=4", "sac.warmup_steps=32",
          "sac.batch_size=16", "sac.buffer_size=256", "train.iters_per_chunk=8",
          "train.eval_every_chunks=0", "train.select_worlds=0", "world.pool_size=1"]
  out = subprocess.run(
      [sys.executable, "-m", "mjxvine.train", "--config", "experiments/adapt.yaml", "--init",
       str(SHIPPED), "--robot", "examples/my_robot.yaml", "--set",
       "world.train_files=examples/vineyard-block.geojson", "--no-eval",
       *sum((["--set", o] for o in tiny), []), "--out", str(tmp_path / "adapt")],
      capture_output=True, text=True, timeout=1800)
  assert out.returncode == 0, out.stderr[-2000:]
  assert "networks and temperature from models/jackal.sac.npz" in out.stderr
  assert (tmp_path / "adapt" / "checkpoints").is_dir()
