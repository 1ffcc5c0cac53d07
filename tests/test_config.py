from pathlib import Path

import pytest

from mjxvine.config import ConfigError, config_hash, load_config, to_yaml


def test_defaults_are_the_spec():
  cfg = load_config()
  assert cfg.world.inter_row_m == (1.5, 2.0)
  assert cfg.world.spacing_m == (0.7, 1.0)
  assert (cfg.camera.width, cfg.camera.height) == (112, 112)
  assert cfg.camera.fovx_deg == 60.0 and cfg.camera.fovy_deg == 46.8
  assert cfg.env.max_steps == 700 and cfg.env.control_dt == 0.1
  assert cfg.sac.learning_rate == 2e-4 and cfg.sac.tau == 5e-3 and cfg.sac.alpha == 0.2


def test_yaml_and_overrides(tmp_path):
  path = tmp_path / "c.yaml"
  path.write_text("env:\n  num_envs: 8\nworld:\n  spacing_m: [0.8, 0.9]\n")
  cfg = load_config(path, ["env.max_steps=50", "robot.name=husky", "sac.auto_alpha=true",
                           "sac.learning_rate=3e-4"])  # YAML 1.1 reads 3e-4 as a string
  assert cfg.env.num_envs == 8 and cfg.env.max_steps == 50
  assert cfg.sac.learning_rate == 3e-4
  assert cfg.world.spacing_m == (0.8, 0.9)
  assert cfg.robot.name == "husky" and cfg.sac.auto_alpha is True
  # The resolved YAML loads back to the same config.
  path2 = tmp_path / "resolved.yaml"
  path2.write_text(to_yaml(cfg))
  assert load_config(path2) == cfg
  assert config_hash(load_config(path2)) == config_hash(cfg)


@pytest.mark.parametrize("override, key", [
    ("env.nope=1", "env.nope"),
    ("nosection.x=1", "nosection"),
    ("world.spacing_m=[-0.5,1.0]", "world.spacing_m"),
    ("world.spacing_m=[1.0,0.7]", "world.spacing_m"),
    ("camera.width=0", "camera.width"),
    ("camera.height=abc", "camera.height"),
    ("env.num_envs=2.5", "env.num_envs"),
    ("robot.name=tank", "robot.name"),
    ("sac.auto_alpha=maybe", "sac.auto_alpha"),
    ("world.inter_row_m=[0.8,2.0]", "world.inter_row_m"),
    ("env.control_dt=0.05", "env.control_dt"),
    ("sac.gamma=1.5", "sac.gamma"),
    ("world.slope_pct=nan", "world.slope_pct"),
    ("world.train_wide_gap_rows=5", "world.train_wide_gap_rows"),  # of 4 rows
    ("world.train_wide_gap_plants=[2,6]", "world.train_wide_gap_plants"),
])
def test_bad_values_name_the_key(override, key):
  with pytest.raises(ConfigError) as e:
    load_config(None, [override])
  assert str(e.value).startswith(key), str(e.value)
  assert "\n" not in str(e.value)


def test_lanes_must_fit_the_robot():
  # Husky (0.67 m) fits 1.5 m rows with 0.5 m canopies, but not 1.1 m ones; Jackal does.
  load_config(None, ["robot.name=husky"])
  load_config(None, ["world.inter_row_m=[1.1,2.0]"])
  with pytest.raises(ConfigError, match="^world.inter_row_m.*husky"):
    load_config(None, ["world.inter_row_m=[1.1,2.0]", "robot.name=husky"])


def test_missing_file_and_bad_yaml(tmp_path):
  with pytest.raises(ConfigError, match="not found"):
    load_config(tmp_path / "missing.yaml")
  bad = tmp_path / "bad.yaml"
  bad.write_text("env: [1, 2\n")
  with pytest.raises(ConfigError, match="not valid YAML"):
    load_config(bad)
  with pytest.raises(ConfigError, match="env: expected a mapping"):
    bad.write_text("env: 3\n")
    load_config(bad)


def test_experiment_configs_load():
  from pathlib import Path
  root = Path(__file__).parent.parent / "experiments"
  files = sorted(root.glob("*.yaml"))
  assert {"paper.yaml", "smoke.yaml"} <= {f.name for f in files}
  for f in files:
    load_config(f)


def test_sweep_grid_and_its_errors():
  from mjxvine.training.iteration import sweep_members
  cfg = load_config(None, ["train.num_seeds=2",
                           "train.sweep=sac.learning_rate=1e-4,1e-3; sac.alpha=0.1"])
  members = sweep_members(cfg)
  assert members == [
      {"seed": 0, "sac.learning_rate": 1e-4, "sac.alpha": 0.1},
      {"seed": 1, "sac.learning_rate": 1e-4, "sac.alpha": 0.1},
      {"seed": 0, "sac.learning_rate": 1e-3, "sac.alpha": 0.1},
      {"seed": 1, "sac.learning_rate": 1e-3, "sac.alpha": 0.1}]
  assert sweep_members(load_config()) == [{"seed": 0}]
  for bad, match in (("sac.gamma=0.9", "cannot be swept"), ("sac.alpha=x", "expected"),
                     ("sac.alpha=-1", "positive")):
    with pytest.raises(ConfigError, match=f"^train.sweep.*{match}"):
      load_config(None, [f"train.sweep={bad}"])


def test_new_choices_are_checked():
  assert load_config(None, ["env.yaw_reference=world"]).env.yaw_reference == "world"
  with pytest.raises(ConfigError, match="^env.yaw_reference"):
    load_config(None, ["env.yaw_reference=sideways"])
  with pytest.raises(ConfigError, match="^sac.reward_scale"):
    load_config(None, ["sac.reward_scale=0"])
  assert load_config(None, ["sac.mirror_augment=true"]).sac.mirror_augment


def test_removed_keys_are_one_line_naming_the_release_that_had_them(tmp_path):
  """A config file or --set that names a key of an earlier release fails in one line
  naming the key and the release; a run's or a policy's recorded config (`base`) drops
  it at the value that kept it off, moves a renamed one, and refuses one that was on."""
  from mjxvine.config import MOVED_KEYS, RELEASE_WITH_REMOVED, REMOVED_KEYS
  assert len(REMOVED_KEYS) >= 27 and "0.2.0" in RELEASE_WITH_REMOVED
  for key in ("sac.image_shift_px", "env.start_along", "train.chunk_loop", "sac.conv_impl"):
    with pytest.raises(ConfigError, match=f"^{key}: (removed|renamed).*0.2.0") as e:
      load_config(None, [f"{key}=1"])
    assert "\n" not in str(e.value)
    (tmp_path / "old.yaml").write_text(f"{key.split('.')[0]}:\n  {key.split('.')[1]}: 1\n")
    with pytest.raises(ConfigError, match=f"^{key}: "):
      load_config(tmp_path / "old.yaml")
  recorded = {"sac": {"image_shift_px": 0, "conv_impl": "native", "eps_decay": 0.992},
              "env": {"start_along": [0.0, 0.6]}}
  cfg = load_config(None, (), recorded)
  assert cfg.train.conv_impl == "native" and MOVED_KEYS["sac.conv_impl"] == "train.conv_impl"
  with pytest.raises(ConfigError, match="^sac.image_shift_px = 2: .*0.2.0"):
    load_config(None, (), {"sac": {"image_shift_px": 2}})


def test_shipped_configs_match_experiments():
  """mjxvine/configs/ (package data: what an installed `python -m mjxvine.train` uses) is a
  copy of experiments/*.yaml: edit experiments/, then `cp experiments/*.yaml mjxvine/configs/`."""
  from pathlib import Path
  from mjxvine.config import PACKAGED_CONFIGS, packaged_configs, resolve_config_path
  repo = sorted(p.name for p in Path("experiments").glob("*.yaml"))
  assert packaged_configs() == repo
  for name in repo:
    assert (PACKAGED_CONFIGS / name).read_text() == (Path("experiments") / name).read_text(), name
  assert resolve_config_path("cpu") == PACKAGED_CONFIGS / "cpu.yaml"
  assert resolve_config_path("experiments/cpu.yaml") == Path("experiments/cpu.yaml")


def test_train_without_config_uses_the_packaged_default(tmp_path, monkeypatch, capsys):
  """`python -m mjxvine.train` from a folder with no experiments/ (as after a non-editable
  install) trains the shipped default.yaml and says so."""
  import tomllib
  from pathlib import Path
  from mjxvine import train as train_mod
  from mjxvine.config import PACKAGED_CONFIGS
  data = tomllib.loads((Path(__file__).parent.parent / "pyproject.toml").read_text())
  assert "configs/*.yaml" in data["tool"]["setuptools"]["package-data"]["mjxvine"]
  assert train_mod.DEFAULT_CONFIG == PACKAGED_CONFIGS / "default.yaml"
  seen = {}
  monkeypatch.setattr(train_mod, "train", lambda cfg, run_dir, **kw: seen.update(cfg=cfg) or {})
  monkeypatch.chdir(tmp_path)
  assert train_mod.main(["--out", "r"]) == 0
  assert capsys.readouterr().out.startswith(f"config: {train_mod.DEFAULT_CONFIG} (the default")
  assert seen["cfg"] == load_config(train_mod.DEFAULT_CONFIG)


def test_a_run_of_the_earlier_release_loads_as_its_own_config():
  """A run's config.yaml written by 0.2.0 (every key, removed ones at their off values)
  loads as a run's own config (`load_run_config`: resume, choose), not as a config file."""
  from mjxvine.config import load_run_config
  record = Path(__file__).resolve().parents[1] / "docs/results/default-run/config.yaml"
  assert "terrain_bump_m" in record.read_text()  # a 0.2.0 record
  with pytest.raises(ConfigError, match="removed"):
    load_config(record)
  cfg = load_run_config(record, ["train.total_env_steps=100"])
  assert cfg.env.v_min == 0.3 and cfg.train.total_env_steps == 100
  with pytest.raises(ConfigError, match="^env.start_along = 5: "):
    load_config(None, (), {"env": {"start_along": 5}})
  with pytest.raises(ConfigError, match="^train: expected a mapping"):
    load_config(None, (), {"sac": {"conv_impl": "xla"}, "train": 3})
