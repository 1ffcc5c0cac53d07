"""The documentation states the defaults that mjxvine/config.py and the command lines have.

- docs/reference.md (Configs) holds the table of every config key that
  `scripts/config_table.py` generates from config.py: a changed default, range or doc
  text fails until the table is regenerated.
- Statements of a default in the prose of README.md and docs/**/*.md (not
  docs/results/experiment-log.md, which records decisions as they were made, as
  CHANGELOG.md does) are compared with config.py, the command lines' parsers and the
  scripts. The phrases read (KEY: a backticked `section.key`, or a field name of one
  section only, such as `max_depth_m`; V: a number, with a unit or thousands commas, a
  list, true/false, on/off, or a word before `)`, `,`, `:` or `;`):
  * "KEY ... (... default V)", "KEY ... (V by default)", "(KEY, V m by default)";
  * "`KEY: V` by default", "by default ... (`KEY: V`)": the default is V;
  * "(both off by default): `KEY: V` ... and `KEY: V`": the defaults are not those values;
  * "the default stays V" in a paragraph or list item about KEY (its first key);
  * "`--flag` ... (default V)", "`--flag V` (the default)": the argparse default of every
    command line with that flag; flags whose parser default is None (the code resolves
    them: `evaluate --runs`, `--video-fps`) are not compared;
  * "`VAR` ... (default V)", VAR upper case: the `${VAR:-V}` of scripts/*.sh;
  * "`FILE.yaml` (seed N, its default" and "`FILE.yaml` with its default seed, N":
    that config's train.seed.
  Not read: defaults said in words ("relative to the heading by default", "seed 0 by
  default" of `evaluate --world`, which takes test world 0), and the
  parameters of the ROS 2 node (`fov_crop`, `invalid_depth`), which are not config keys.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib.util
import io
import re
from pathlib import Path
from unittest import mock

import pytest
import yaml

from mjxvine.config import Config, load_config
from test_docs import CLIS, ROOT, markdown_paragraphs

SCRIPT = ROOT / "scripts" / "config_table.py"
PROSE = [p for p in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
         if p.name != "experiment-log.md"]


def _config_table_module():
  spec = importlib.util.spec_from_file_location("config_table", SCRIPT)
  mod = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(mod)
  return mod


def test_reference_holds_the_config_table():
  """docs/reference.md's table of config keys is config.py's, as the script prints it."""
  mod = _config_table_module()
  written = mod.written_table((ROOT / "docs" / "reference.md").read_text())
  assert written is not None, f"docs/reference.md: no {mod.BEGIN} ... {mod.END}"
  assert written == mod.table(), (
      "docs/reference.md's config table differs from mjxvine/config.py: run "
      "`python scripts/config_table.py --write`")


def test_the_config_table_has_every_key_once():
  """One row per key of every section, with the key's default as YAML reads it back."""
  mod = _config_table_module()
  rows = mod.rows()
  defaults = {f"{s}.{k}": v for s, sec in dataclasses.asdict(Config()).items()
              for k, v in sec.items()}
  assert [r[0] for r in rows] == list(defaults)
  for key, default, _, _ in rows:
    value = defaults[key]
    assert yaml.safe_load(default) == (list(value) if isinstance(value, tuple) else value), key
  tower = next(k for k in defaults if k.endswith(".conv_impl"))  # xla, shift, native; no dot
  assert f"| `{tower}` | `auto` | auto, xla, shift, native |" in mod.table()


# --- statements of defaults in the prose ----------------------------------------------------

SECTIONS = {f.name: {g.name: g.default for g in dataclasses.fields(type(f.default))}
            for f in dataclasses.fields(Config)}
FIELD_OWNERS = {}
for _section, _fields in SECTIONS.items():
  for _name in _fields:
    FIELD_OWNERS.setdefault(_name, []).append(_section)

_KEY = r"`(?P<key>[a-z_]+(?:\.[a-z_0-9]+)?)(?:(?::\s*|=)(?P<span_value>[^`]*))?`"
_NUM = r"-?(?:\d{1,3}(?:,\d{3})+|\d+)(?:\.\d+)?(?:e-?\d+)?"
_VALUE = rf"(?:\[[^\]]*\]|{_NUM}|true|false|on|off)"
_WORD_VALUE = rf"(?:{_VALUE}|[\w.-]+(?=[):,;]))"
_UNIT = r"(?:\s(?:m|s|%|deg|m/s))?"
PATTERNS = {
    # KEY ... (... default V)  /  KEY ... (V by default)  /  (KEY, V m by default)
    "key": re.compile(
        rf"(?:{_KEY}[^`()]{{0,40}}?\((?:[^()`]*?\bdefault:?\s+(?P<v1>{_WORD_VALUE})"
        rf"|\s*(?P<v2>{_VALUE}){_UNIT}\s+by default\))"
        rf"|\({_KEY.replace('key>', 'key2>').replace('span_value>', 'sv2>')},\s*"
        rf"(?P<v3>{_VALUE}){_UNIT}\s+by default\))"),
    # `KEY: V` by default
    "key_value": re.compile(rf"{_KEY}\s+by default\b"),
    # by default ... (`KEY: V`)
    "by_default_key_value": re.compile(rf"\bby default\b[^`.()]{{0,30}}\({_KEY}\)"),
    # (both off by default): `KEY: V` ... `KEY: V`
    "off": re.compile(r"\((?:both|all) (?P<onoff>off|on) by default\):?"
                      r"(?P<rest>(?:[^.]|\.(?!\s))*)"),
    # the default stays V
    "stays": re.compile(rf"\b[Tt]he default (?:stays|is) (?P<v>{_VALUE})"),
    # `--flag` ... (default V)  /  `--flag V` (the default)
    "flag": re.compile(rf"`(?P<flag>--[a-z][\w-]*)(?: (?P<span_value>[^`]+))?`[^`()]{{0,30}}?"
                       rf"\((?:the )?default(?::?\s+(?P<v>{_WORD_VALUE}))?"),
    # `VAR` ... (default V)
    "variable": re.compile(rf"`(?P<var>[A-Z][A-Z0-9_]*)`[^`()]{{0,30}}?\(default "
                           rf"(?P<v>{_WORD_VALUE})"),
    # `FILE.yaml` (seed N, its default  /  `FILE.yaml` with its default seed, N
    "seed": re.compile(r"`(?P<file>[\w/.-]+\.yaml)` (?:\(seed (?P<v1>\d+), its default"
                       r"|with its default seed, (?P<v2>\d+))"),
}


@dataclasses.dataclass(frozen=True)
class Statement:
  where: str
  kind: str      # config | not_config | flag | variable | seed
  subject: str   # section.key, --flag, VAR or FILE.yaml
  value: str

  def __str__(self):
    return f"{self.where}: {self.subject} {self.kind} {self.value}"


def _config_key(name: str) -> str | None:
  """section.key of a span's name: a dotted key, or a field name of one section only."""
  if "." in name:
    section, key = name.split(".", 1)
    return name if key in SECTIONS.get(section, {}) else None
  owners = FIELD_OWNERS.get(name, [])
  return f"{owners[0]}.{name}" if len(owners) == 1 else None


def statements(path: Path) -> list[Statement]:
  """Every statement of a default in `path`'s prose (the module docstring's phrases)."""
  out = []
  for start, para in markdown_paragraphs(path):
    text = para.replace("\n", " ")  # offsets kept: the line of a match is still countable

    def where(m):
      return f"{path.relative_to(ROOT)}:{start + para[:m.start()].count(chr(10))}"

    keys = [k for k in (_config_key(m.group("key")) for m in re.finditer(_KEY, text)) if k]
    for m in PATTERNS["key"].finditer(text):
      key = _config_key(m.group("key") or m.group("key2"))
      if key:
        out.append(Statement(where(m), "config", key, m.group("v1") or m.group("v2")
                             or m.group("v3")))
    for name in ("key_value", "by_default_key_value"):
      for m in PATTERNS[name].finditer(text):
        key = _config_key(m.group("key"))
        if key and m.group("span_value"):
          out.append(Statement(where(m), "config", key, m.group("span_value")))
    for m in PATTERNS["off"].finditer(text):
      for k in re.finditer(_KEY, m.group("rest")):
        key = _config_key(k.group("key"))
        if key and k.group("span_value"):
          kind = "config" if m.group("onoff") == "on" else "not_config"
          out.append(Statement(where(m), kind, key, k.group("span_value")))
    for m in PATTERNS["stays"].finditer(text):
      if keys:
        out.append(Statement(where(m), "config", keys[0], m.group("v")))
    for m in PATTERNS["flag"].finditer(text):
      value = m.group("v") or m.group("span_value")
      if value:
        out.append(Statement(where(m), "flag", m.group("flag"), value))
    for m in PATTERNS["variable"].finditer(text):
      out.append(Statement(where(m), "variable", m.group("var"), m.group("v")))
    for m in PATTERNS["seed"].finditer(text):
      out.append(Statement(where(m), "seed", m.group("file"), m.group("v1") or m.group("v2")))
  return out


STATEMENTS = [s for p in PROSE for s in statements(p)]


def _read(text: str):
  """A stated value as Python: on/off as booleans, numbers without thousands commas."""
  text = text.strip()
  if text in ("on", "off"):
    return text == "on"
  if re.fullmatch(_NUM, text):
    text = text.replace(",", "")
  return yaml.safe_load(text)


def _same(stated, default) -> bool:
  if isinstance(default, (tuple, list)):
    return (isinstance(stated, (tuple, list)) and len(stated) == len(default)
            and all(_same(a, b) for a, b in zip(stated, default)))
  if isinstance(default, bool) or isinstance(stated, bool):
    return stated is default
  if isinstance(default, (int, float)):
    return isinstance(stated, (int, float)) and float(stated) == float(default)
  return str(stated) == str(default)


class _Parser(Exception):
  def __init__(self, parser):
    self.parser = parser


def _parser(module: str) -> argparse.ArgumentParser:
  """The parser `module.main` builds (its `parse_args` stopped before it parses)."""
  def stop(self, args=None, namespace=None):
    raise _Parser(self)

  mod = importlib.import_module(module)
  with mock.patch.object(argparse.ArgumentParser, "parse_args", stop), \
       contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
    try:
      mod.main([])
    except _Parser as p:
      return p.parser
  raise AssertionError(f"{module}: main returned without parsing its arguments")


def _flag_actions(parser: argparse.ArgumentParser, prog: str):
  """(command, action) of every option of `parser` and of its sub-commands' parsers."""
  for action in parser._actions:
    if isinstance(action, argparse._SubParsersAction):
      for name, sub in action.choices.items():
        yield from _flag_actions(sub, f"{prog} {name}")
    elif action.option_strings:
      yield prog, action


@pytest.fixture(scope="module")
def flag_defaults() -> dict[str, list[tuple[str, argparse.Action]]]:
  """flag -> (command, its action) for every command line of mjxvine."""
  out = {}
  for module in sorted(set(CLIS.values())):
    for prog, action in _flag_actions(_parser(module), module):
      for flag in action.option_strings:
        out.setdefault(flag, []).append((prog, action))
  return out


def _check(s: Statement, flag_defaults) -> str | None:
  """None if the statement is right, else why not; "skip: ..." if it cannot be compared."""
  if s.kind in ("config", "not_config"):
    section, key = s.subject.split(".")
    default = SECTIONS[section][key]
    same = _same(_read(s.value), default)
    if same != (s.kind == "config"):
      return f"{s.subject}'s default is {default!r}"
    return None
  if s.kind == "flag":
    actions = flag_defaults.get(s.subject)
    assert actions, f"{s.where}: {s.subject}: no command line has this flag"
    known = [(prog, a) for prog, a in actions if a.default is not None]
    if not known:
      return "skip: the parser's default is None (the code resolves it)"
    if not any(_same((a.type or str)(s.value) if a.type else s.value, a.default)
               for _, a in known):
      return "the parsers' defaults: " + ", ".join(f"{p}: {a.default!r}" for p, a in known)
    return None
  if s.kind == "variable":
    found = {m.group(1) for f in (ROOT / "scripts").glob("*.sh")
             for m in re.finditer(r"\$\{" + s.subject + r":-([^}]*)\}", f.read_text())}
    assert found, f"{s.where}: no script gives ${{{s.subject}:-...}}"
    if not any(_same(_read(s.value), _read(v)) for v in found):
      return f"the scripts' default: {', '.join(sorted(found))}"
    return None
  if s.kind == "seed":
    seed = load_config(ROOT / s.subject if "/" in s.subject else s.subject).train.seed
    return None if seed == int(s.value) else f"{s.subject}: train.seed is {seed}"
  raise AssertionError(s.kind)


def test_stated_defaults_are_the_code_defaults(flag_defaults):
  """Every statement of a default in the prose (module docstring) holds."""
  wrong = [f"{s}: {why}" for s in STATEMENTS
           if (why := _check(s, flag_defaults)) and not why.startswith("skip")]
  assert not wrong, "\n".join(wrong)


def test_the_statements_are_found():
  """The phrases of the docs are read: each kind at least once, and the regexes pick the
  key and value out of their forms (a regression here would let wrong defaults pass)."""
  kinds = {s.kind for s in STATEMENTS}
  assert kinds == {"config", "not_config", "flag", "variable", "seed"}, kinds
  assert len(STATEMENTS) >= 15
  text = ("- `sac.mirror_augment` (off by default): x. `world.train_wide_gap_rows` random "
          "rows (2 by default), of `env.train_noise_factor: [lo, hi]` (a range, default\n"
          "[0, 0]) and (`max_depth_m`, 5 m by default). `env.yaw_reference: start` by "
          "default. Mirroring (both off by default): `sac.mirror_average: true` "
          "and `sac.critic_layer_norm: true`.\n\n- `sac.target_entropy` (with "
          "`sac.auto_alpha`) is ... The default stays -2.\n\n`--rounds` times (default 3, "
          "about 1 s each); `--which best` (the default); `STEPS` env steps (default "
          "80,000); `experiments/cpu.yaml` (seed 0, its default.\n")
  with mock.patch.object(Path, "read_text", return_value=text):
    found = {(s.kind, s.subject, s.value) for s in statements(ROOT / "x.md")}
  assert found == {
      ("config", "sac.mirror_augment", "off"), ("config", "world.train_wide_gap_rows", "2"),
      ("config", "env.train_noise_factor", "[0, 0]"), ("config", "camera.max_depth_m", "5"),
      ("config", "env.yaw_reference", "start"),
      ("not_config", "sac.mirror_average", "true"),
      ("not_config", "sac.critic_layer_norm", "true"),
      ("config", "sac.target_entropy", "-2"), ("flag", "--rounds", "3"),
      ("flag", "--which", "best"), ("variable", "STEPS", "80,000"),
      ("seed", "experiments/cpu.yaml", "0")}, found
