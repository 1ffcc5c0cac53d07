"""Every command and code block of the README and docs/ is exercised, so that the
documentation cannot drift from the code: a renamed flag, a removed config key or a moved
file fails here.

Fenced blocks are collected from README.md, CHANGELOG.md and docs/**/*.md:

- ```bash: each command (continuation lines joined, `&&` split, `VAR=value` prefixes
  kept aside) is checked without running anything long: `python -m mjxvine.<cli> ARGS` is
  parsed by that module's own argparse parser (its `main`, stopped right after
  `parse_args`), then its `--config` / `--set` are loaded as a config; `pip install` extras
  must exist in pyproject.toml; scripts, examples and other repository files named must
  exist; `python -c CODE` runs.
- ```python: runs in a temporary folder that holds a small exported `policy.npz`.
- ```yaml: loads as a config file (`mjxvine.config.load_config`), or, when its top-level
  keys are a robot file's (`body`, `wheels`, ...), as a robot file
  (`mjxvine.robot_files`).
- ```csv and ```json: a vineyard file (plants in metres; GeoJSON rows), written to a
  temporary folder and read by `mjxvine.worlds.geo`, which must find lanes in it.
- ```text is not code, and must not hold a file sample in disguise (JSON, a mapping, a
  plant CSV).
File samples (robot YAML, CSV, GeoJSON) are always loaded: a mark before one is a note,
not a skip. The files of examples/ are loaded by their readers too.

An HTML comment on the line before a block marks it:
- `<!-- skip: REASON -->`: not exercised (it needs a GPU, a display, ROS 2, hours);
  reported as skipped with the reason.
- `<!-- no-run: REASON -->` (python): compiled, and its imports run, but not the rest.
- `<!-- slow: REASON -->`: the fast check above, and run for real (bash: at smoke size,
  `--set` overrides appended to training) by the `slow` test.

Inline code spans (single backticks) that hold a `python -m mjxvine...` command are
checked as a bash command is: in the prose of README.md and docs/**/*.md (not CHANGELOG.md,
which records history), and in the comments of experiments/*.yaml, mjxvine/configs/*.yaml,
docs/results/**/recipe.yaml and scripts/*.sh (a run of comment lines is read as one
paragraph). Prose writes commands with placeholders; the rules:
- the module alone (`python -m mjxvine.choose`) names a command line, which must exist;
- `...` stands for arguments left out and is dropped: the rest must still parse, so a
  required flag (`--out`) cannot be left out;
- `[` `]` around arguments mark them optional: they are checked as if given;
- `a|b` gives alternatives, each checked (`--set sac.conv_impl=shift|native` is two
  commands: the text up to the last `=` before the first `|` is shared);
- upper-case words (`POLICY`, `runs/RUN`, `X,Y,YAW`) are placeholders, parsed as the
  literal strings they are (a flag that takes a number needs a number);
- a wrapper before `python` (`/usr/bin/time -v`) is left out.
Commands written as indented code (4 spaces in markdown, `#   python -m ...` in a comment)
are checked the same way.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import importlib
import io
import itertools
import os
import re
import shlex
import subprocess
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path
from unittest import mock

import pytest
from conftest import parse_source

ROOT = Path(__file__).resolve().parent.parent
DOC_FILES = [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").rglob("*.md"))]
MARK = re.compile(r"^<!--\s*(skip|no-run|slow):\s*(.+?)\s*-->\s*$")
FENCE = re.compile(r"^```(\w*)\s*$")
CLIS = {"train": "mjxvine.train", "evaluate": "mjxvine.evaluate", "export": "mjxvine.export",
        "worlds": "mjxvine.worlds.__main__", "bench": "mjxvine.bench.__main__",
        "latency": "mjxvine.latency", "select": "mjxvine.select", "choose": "mjxvine.choose",
        "view": "mjxvine.view"}
# Tools outside the package that documented commands call: only the repository files they
# name are checked.
EXTERNAL = {"tensorboard", "jupyter", "nvidia-smi", "ros2"}
# Appended to training commands when the slow test runs them.
SMOKE_TRAIN = ["--no-eval", "--config", "experiments/smoke.yaml",
               "--set", "train.total_env_steps=64", "--set", "train.eval_every_chunks=0",
               "--set", "sac.warmup_steps=32", "--set", "env.num_envs=4",
               "--set", "sac.batch_size=16", "--set", "sac.buffer_size=256"]


@dataclass(frozen=True)
class Block:
  path: Path
  line: int
  lang: str
  code: str
  mark: str | None = None    # skip | no-run | slow
  reason: str = ""

  @property
  def id(self) -> str:
    return f"{self.path.relative_to(ROOT)}:{self.line}"


def collect(path: Path) -> list[Block]:
  blocks, lines = [], path.read_text().splitlines()
  i = 0
  while i < len(lines):
    m = FENCE.match(lines[i])
    if not m:
      i += 1
      continue
    start, body = i, []
    i += 1
    while i < len(lines) and not lines[i].startswith("```"):
      body.append(lines[i])
      i += 1
    i += 1
    prev = next((lines[k] for k in range(start - 1, -1, -1) if lines[k].strip()), "")
    mark = MARK.match(prev.strip())
    blocks.append(Block(path, start + 1, m.group(1), "\n".join(body) + "\n",
                        mark.group(1) if mark else None, mark.group(2) if mark else ""))
  return blocks


BLOCKS = [b for f in DOC_FILES for b in collect(f)]
CODE = [b for b in BLOCKS if b.lang in ("bash", "python", "yaml", "csv", "json")]


def _skip(block: Block):
  if block.mark == "skip":
    pytest.skip(f"{block.id}: {block.reason}")


# --- bash -------------------------------------------------------------------------------

def commands(code: str) -> list[tuple[dict, list[str]]]:
  """(environment, argv) of every command of a bash block."""
  out = []
  for line in code.replace("\\\n", " ").splitlines():
    tokens = shlex.split(line, comments=True)
    while tokens:
      cut = tokens.index("&&") if "&&" in tokens else len(tokens)
      cmd, tokens = tokens[:cut], tokens[cut + 1:]
      env = {}
      while cmd and re.match(r"^[A-Z_][A-Z0-9_]*=", cmd[0]):
        k, v = cmd.pop(0).split("=", 1)
        env[k] = v
      if cmd:
        out.append((env, cmd))
  return out


class _Parsed(Exception):
  def __init__(self, ns):
    self.ns = ns


def parse_cli(module: str, argv: list[str]) -> argparse.Namespace | None:
  """The namespace `module.main(argv)` parses its arguments into; None for --help."""
  mod = importlib.import_module(module)
  parse = argparse.ArgumentParser.parse_args

  def stop(self, args=None, namespace=None):
    raise _Parsed(parse(self, args, namespace))

  err = io.StringIO()
  with mock.patch.object(argparse.ArgumentParser, "parse_args", stop), \
       contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
    try:
      mod.main(argv)
    except _Parsed as p:
      return p.ns
    except SystemExit as e:
      if e.code == 0 and "--help" in argv:
        return None
      raise AssertionError(f"python -m {module} {shlex.join(argv)}: {err.getvalue()}") from None
  raise AssertionError(f"python -m {module}: main returned without parsing its arguments")


def check_config(module: str, ns: argparse.Namespace) -> None:
  from mjxvine.config import load_config
  from mjxvine.train import DEFAULT_CONFIG
  overrides = list(getattr(ns, "overrides", []) or [])
  if getattr(ns, "resume", None):
    load_config(None, overrides)  # the keys exist; the run's config.yaml is not here
    return
  config = getattr(ns, "config", None)
  if config is None and module == "mjxvine.train":
    config = DEFAULT_CONFIG
  if config is not None or overrides:
    if str(config).startswith("runs/"):  # a run's config.yaml, written by an earlier command
      config = None
    elif config is not None and not Path(config).is_absolute():
      assert (ROOT / config).is_file() or "/" not in str(config), f"no such file: {config}"
    load_config(config, overrides)


def extras() -> set[str]:
  return set(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
             ["optional-dependencies"])


def check_command(env: dict, argv: list[str]) -> None:
  """Checks one command without running anything long (see the module docstring)."""
  prog, args = argv[0], argv[1:]
  if prog in ("python", "python3") and args[:1] == ["-m"]:
    module, rest = args[1], args[2:]
    if module.startswith("mjxvine."):
      name = module.split(".", 1)[1]
      assert name in CLIS, f"python -m {module}: not a command line of mjxvine"
      ns = parse_cli(CLIS[name], rest)
      if ns is not None:
        check_config(CLIS[name].removesuffix(".__main__"), ns)
      return
    if module == "pip":
      assert rest[0] == "install", argv
      for a in rest[1:]:
        m = re.match(r"^\.\[([\w,-]+)\]$", a)
        if m:
          missing = set(m.group(1).split(",")) - extras()
          assert not missing, f"pip install {a}: no such extra in pyproject.toml: {missing}"
      return
    if module == "pytest":
      return
    raise AssertionError(f"python -m {module}: not a documented tool")
  if prog in ("python", "python3") and args[:1] == ["-c"]:
    r = subprocess.run([sys.executable, "-c", args[1]], cwd=ROOT, capture_output=True,
                       text=True, timeout=120, env={**os.environ, **env})
    assert r.returncode == 0, r.stderr[-2000:]
    return
  if prog in ("python", "python3", "bash"):
    assert (ROOT / args[0]).is_file(), f"{prog} {args[0]}: no such file"
    return
  if prog in EXTERNAL:
    for a in args:
      if re.search(r"\.(py|yaml|ipynb|sh)$", a):
        assert (ROOT / a).is_file(), f"{prog}: no such file {a}"
    return
  raise AssertionError(f"{shlex.join(argv)}: unknown command; mark the block "
                       "<!-- skip: REASON --> if it cannot be checked")


@pytest.mark.parametrize("block", [b for b in CODE if b.lang == "bash"], ids=lambda b: b.id)
def test_bash_block(block):
  _skip(block)
  cmds = commands(block.code)
  assert cmds, f"{block.id}: an empty bash block"
  for env, argv in cmds:
    check_command(env, argv)


# --- inline commands in prose and comments ------------------------------------------------

SPAN_DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
COMMENTED = [*sorted((ROOT / "experiments").glob("*.yaml")),
             *sorted((ROOT / "mjxvine" / "configs").glob("*.yaml")),
             *sorted((ROOT / "docs" / "results").rglob("recipe.yaml")),
             *sorted((ROOT / "scripts").glob("*.sh"))]


@dataclass(frozen=True)
class Span:
  path: Path
  line: int
  text: str  # whitespace (line breaks too) collapsed to single spaces

  @property
  def id(self) -> str:
    return f"{self.path.relative_to(ROOT)}:{self.line}"


def markdown_paragraphs(path: Path) -> list[tuple[int, str]]:
  """(first line, text) of each paragraph of a markdown file's prose: fenced blocks left
  out, paragraphs split at blank lines and list items."""
  out, para, start, fenced = [], [], 0, False
  for i, line in enumerate(path.read_text().splitlines(), 1):
    fence = line.startswith("```")
    fenced ^= fence
    if fence or fenced or not line.strip() or re.match(r"^\s*(?:[-*]|\d+\.)\s", line):
      if para:
        out.append((start, "\n".join(para)))
      para = []
      if fence or fenced or not line.strip():
        continue
    if not para:
      start = i
    para.append(line)
  if para:
    out.append((start, "\n".join(para)))
  return out


def comment_paragraphs(path: Path) -> list[tuple[int, str]]:
  """(first line, text) of each run of consecutive comment lines of a YAML or shell file
  (whole-line or trailing `# ...` comments; not a `#!` line)."""
  out, para, start = [], [], 0
  for i, line in enumerate(path.read_text().splitlines(), 1):
    m = None if line.startswith("#!") else re.search(r"(?:^|\s)#\s?(.*)$", line)
    if m:
      if not para:
        start = i
      para.append(m.group(1))
    elif para:
      out.append((start, "\n".join(para)))
      para = []
  if para:
    out.append((start, "\n".join(para)))
  return out


def code_spans(path: Path, paragraphs: list[tuple[int, str]]) -> list[Span]:
  """The inline code spans of `paragraphs`, each at the line where it starts."""
  return [Span(path, start + text[:m.start()].count("\n"), " ".join(m.group(1).split()))
          for start, text in paragraphs for m in re.finditer(r"`([^`]+)`", text)]


def indented_commands(path: Path) -> list[Span]:
  """Commands written as indented code: a markdown line indented by 4 spaces (after a
  blank line or another such line, outside fences), or a comment line whose text is
  indented (`#   python -m ...`); a line ending in a backslash continues on the next."""
  out, lines, fenced, prev_blank, block = [], path.read_text().splitlines(), False, True, []
  comments = path.suffix != ".md"
  for i, line in enumerate(lines + [""], 1):
    fenced ^= line.startswith("```")
    if comments:
      m = re.search(r"(?:^|\s)#(\s{2,}\S.*)$", line)
      code = m.group(1).strip() if m else None
    else:
      code = line.strip() if (not fenced and re.match(r"^ {4,}\S", line)
                              and (prev_blank or block)) else None
    if code is not None and (block or "python -m mjxvine" in code) and "`" not in code:
      block.append((i, code))
      if code.endswith("\\"):
        continue
    if block:
      out.append(Span(path, block[0][0], " ".join(c.rstrip("\\").strip() for _, c in block)))
      block = []
    prev_blank = not line.strip()
  return out


SPANS = [s for f in SPAN_DOCS for s in code_spans(f, markdown_paragraphs(f))] + \
        [s for f in COMMENTED for s in code_spans(f, comment_paragraphs(f))]
COMMAND_SPANS = [s for s in SPANS + [c for f in SPAN_DOCS + COMMENTED
                                     for c in indented_commands(f)]
                 if "python -m mjxvine" in s.text]


def _alternatives(token: str) -> list[str]:
  """`a|b` -> [a, b]; `key=a|b` -> [key=a, key=b]."""
  if "|" not in token:
    return [token]
  first, *rest = token.split("|")
  shared = first[:first.rfind("=") + 1]
  return [first, *(shared + r for r in rest)]


def span_commands(text: str) -> list[tuple[dict, list[str]]]:
  """The commands an inline span stands for, by the rules of the module docstring (none
  for the module alone, which must be a command line)."""
  text = re.sub(r"(?<!\S)\[|\](?!\S)", " ", text)
  out = []
  for env, argv in commands(text):
    argv = [a for a in argv if a != "..."]
    argv = argv[argv.index("python"):] if "python" in argv else argv  # a wrapper left out
    if argv[:2] == ["python", "-m"] and len(argv) == 3:
      assert argv[2].removeprefix("mjxvine.") in CLIS, f"{argv[2]}: not a command line"
      continue
    out += [(env, list(a)) for a in itertools.product(*map(_alternatives, argv))]
  return out


@pytest.mark.parametrize("span", COMMAND_SPANS, ids=lambda s: s.id)
def test_inline_command(span):
  for env, argv in span_commands(span.text):
    try:
      check_command(env, argv)
    except AssertionError as e:
      raise AssertionError(f"{span.id}: `{span.text}`: {e}") from None


def test_inline_commands_are_found():
  """The collection sees the commands of prose and of config comments, a span that runs
  over a line break included, drops a wrapper before `python`, and expands the
  placeholders."""
  assert len(COMMAND_SPANS) >= 30
  assert any(s.path.suffix == ".yaml" for s in COMMAND_SPANS)
  assert any(s.path.suffix == ".md" for s in COMMAND_SPANS)
  text = "Run `python -m mjxvine.evaluate --policy RUN --gif\n--out out/gif` first.\n"
  with mock.patch.object(Path, "read_text", return_value=text):
    spans = code_spans(ROOT / "x.md", markdown_paragraphs(ROOT / "x.md"))
  assert [s.text for s in spans] == ["python -m mjxvine.evaluate --policy RUN --gif --out out/gif"]
  assert [a for _, a in span_commands("/usr/bin/time -v python -m mjxvine.train --out runs/x")] == [
      ["python", "-m", "mjxvine.train", "--out", "runs/x"]]
  assert [a for _, a in span_commands("python -m mjxvine.view ... [--world test|SEED]")] == [
      ["python", "-m", "mjxvine.view", "--world", "test"],
      ["python", "-m", "mjxvine.view", "--world", "SEED"]]
  assert [a[-1] for _, a in span_commands("python -m mjxvine.train --set a.b=c|d")] == [
      "a.b=c", "a.b=d"]


# --- python -----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def policy_dir(tmp_path_factory):
  """A folder with `policy.npz`: a small actor with random weights (40x40 depth)."""
  import jax
  import jax.numpy as jnp
  from mjxvine.deploy import export
  from mjxvine import networks as nw
  from mjxvine.config import load_config
  cfg = load_config(ROOT / "experiments/smoke.yaml", ["sac.hidden=16", "sac.conv_features=4"])
  nets = nw.make_networks_from_config(cfg)
  obs = {"depth": jnp.zeros((1, cfg.camera.height, cfg.camera.width, 1)),
         "state": jnp.zeros((1, 3))}
  actor, _ = nw.init_params(nets, jax.random.PRNGKey(0), obs)
  d = tmp_path_factory.mktemp("docs")
  export.export_actor(actor, d / "policy.npz", export.meta_from_config(cfg))
  return d


def _imports_only(code: str) -> str:
  tree = parse_source(code)
  return ast.unparse([n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))])


def run_python(code: str, folder: Path) -> None:
  old = Path.cwd()
  os.chdir(folder)
  try:
    with contextlib.redirect_stdout(io.StringIO()):
      exec(compile(code, "<doc block>", "exec"), {"__name__": "__doc_block__"})
  finally:
    os.chdir(old)


@pytest.mark.parametrize("block", [b for b in CODE if b.lang == "python"], ids=lambda b: b.id)
def test_python_block(block, policy_dir):
  _skip(block)
  compile(block.code, block.id, "exec")
  if block.mark in ("no-run", "slow"):
    run_python(_imports_only(block.code), policy_dir)
  else:
    run_python(block.code, policy_dir)


# --- file samples: configs, robot files, vineyard files -----------------------------------

def is_robot_file(code: str) -> bool:
  """Whether a YAML sample is a robot file: a mapping of a robot file's top-level keys
  (`name`, `body`, `wheels`, `camera`, `velocity`) with a `body`."""
  import yaml
  from mjxvine.robot_files import SCHEMA
  doc = yaml.safe_load(code)
  return isinstance(doc, dict) and "body" in doc and set(doc) <= {"name", *SCHEMA}


CONFIGS = [b for b in CODE if b.lang == "yaml" and not is_robot_file(b.code)]
SAMPLES = [b for b in CODE if b.lang in ("csv", "json")
           or (b.lang == "yaml" and is_robot_file(b.code))]


@pytest.mark.parametrize("block", CONFIGS, ids=lambda b: b.id)
def test_yaml_block(block, tmp_path):
  _skip(block)
  from mjxvine.config import load_config
  (tmp_path / "c.yaml").write_text(block.code)
  load_config(tmp_path / "c.yaml")


def load_sample(path: Path):
  """The object the real reader makes of a file sample at `path`: a `RobotSpec` of a
  robot file, a `Vineyard` of a vineyard file (its lanes checked for the default robot)."""
  from mjxvine.config import load_config, robot_spec
  from mjxvine.robot_files import read_robot_file
  from mjxvine.worlds import geo
  if path.suffix in (".yaml", ".yml"):
    return read_robot_file(path)
  cfg = load_config()
  return geo.read_vineyard(path, cfg.world, robot_width_m=robot_spec(cfg.robot.name).width)


@pytest.mark.parametrize("block", SAMPLES, ids=lambda b: b.id)
def test_file_sample(block, tmp_path):
  """A file sample is what its reader accepts: a robot file a robot, a CSV or GeoJSON
  vineyard a block with at least one lane."""
  suffix = {"csv": ".csv", "json": ".geojson", "yaml": ".yaml"}[block.lang]
  path = tmp_path / f"sample{suffix}"
  path.write_text(block.code)
  loaded = load_sample(path)
  if block.lang != "yaml":
    assert len(loaded.lanes) >= 1, f"{block.id}: no lane"


@pytest.mark.parametrize("name", sorted(p.name for p in (ROOT / "examples").iterdir()
                                        if p.suffix in (".yaml", ".geojson", ".csv", ".py")))
def test_example_file(name):
  """examples/: robot files and vineyard files load, the ROS 2 parameters are YAML, the
  node compiles."""
  import yaml
  path = ROOT / "examples" / name
  if path.suffix == ".py":
    compile(path.read_text(), str(path), "exec")
  elif path.suffix == ".yaml" and not is_robot_file(path.read_text()):
    assert isinstance(yaml.safe_load(path.read_text()), dict), name
  else:
    assert load_sample(path) is not None


# --- the collection itself ----------------------------------------------------------------

def test_every_block_is_known():
  """Code blocks are bash, python, yaml or text; marks name a reason."""
  for b in BLOCKS:
    assert b.lang in ("bash", "python", "yaml", "csv", "json", "text"), f"{b.id}: ```{b.lang}"
    assert b.mark is None or b.reason
  assert len(CODE) >= 40


def _file_in_disguise(code: str) -> bool:
  """Whether a ```text block holds a file sample: a JSON object, a plant CSV, a YAML
  mapping."""
  import json

  import yaml
  try:
    if isinstance(json.loads(code), dict):
      return True
  except ValueError:
    pass
  if code.lstrip().lower().startswith("row,"):
    return True
  try:
    return isinstance(yaml.safe_load(code), dict)
  except yaml.YAMLError:
    return False


def test_file_samples_are_fenced_by_format():
  """Samples of a file format are fenced as csv, json or yaml, so that they are loaded; the
  guides hold each kind (a CSV, a GeoJSON, a robot file and a config)."""
  hidden = [b.id for b in BLOCKS if b.lang == "text" and _file_in_disguise(b.code)]
  assert not hidden, f"file samples fenced as text: {hidden}"
  assert _file_in_disguise('{"type": "FeatureCollection"}\n')
  assert _file_in_disguise("row,x_m,y_m\nA,0,0\n")
  assert not _file_in_disguise("compiling... done in 12 s\n")
  kinds = {b.lang for b in SAMPLES} | {"config" for _ in CONFIGS[:1]}
  assert kinds == {"csv", "json", "yaml", "config"}, kinds


def test_no_reference_outside_the_repository():
  """The documentation and configs name only files of the repository."""
  pattern = re.compile(r"\.\./shared|\.whl\b|SPEC\.md")
  files = [*DOC_FILES, *(ROOT / "experiments").glob("*.yaml"), *(ROOT / "scripts").glob("*")]
  bad = [f"{f.relative_to(ROOT)}:{i + 1}" for f in files
         for i, line in enumerate(f.read_text().splitlines()) if pattern.search(line)]
  assert not bad


def test_relative_links_exist():
  """Markdown links and images to repository files point at files that exist."""
  link = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
  bad = []
  for f in DOC_FILES:
    for target in link.findall(f.read_text()):
      if re.match(r"^[a-z]+:", target):
        continue
      path = (f.parent / target).resolve()
      if not path.exists():
        bad.append(f"{f.relative_to(ROOT)}: {target}")
  assert not bad


# --- slow: the blocks marked slow, run for real ---------------------------------------------

@pytest.fixture(scope="module")
def slow_dir(policy_dir, tmp_path_factory):
  """One folder for every slow block, in document order: a block may use what an earlier
  one wrote (the getting-started run, then its evaluation and export)."""
  d = tmp_path_factory.mktemp("slow")
  (d / "experiments").symlink_to(ROOT / "experiments")
  (d / "examples").symlink_to(ROOT / "examples")
  (d / "policy.npz").symlink_to(policy_dir / "policy.npz")
  return d


@pytest.mark.slow
@pytest.mark.parametrize("block", [b for b in CODE if b.mark == "slow"], ids=lambda b: b.id)
def test_slow_block_runs(block, slow_dir):
  if block.lang == "python":
    run_python(block.code, slow_dir)
    return
  tmp_path = slow_dir
  for env, argv in commands(block.code):
    if argv[:3] == ["python", "-m", "mjxvine.train"]:
      argv = [*argv, *SMOKE_TRAIN]
    if argv[:3] == ["python", "-m", "mjxvine.evaluate"] and "--runs" not in argv:
      argv = [*argv, "--runs", "1"]
    r = subprocess.run([sys.executable, *argv[1:]], cwd=tmp_path, capture_output=True,
                       text=True, timeout=900, env={**os.environ, **env})
    assert r.returncode == 0, f"{shlex.join(argv)}:\n{r.stderr[-3000:]}"


# The Markdown of the repository stays short: all of it, and the guides' share (docs/*.md,
# CHANGELOG.md and any Markdown outside docs/results/ and README.md).
MAX_MARKDOWN_LINES, MAX_GUIDE_LINES = 5000, 2300
SKIP_DIRS = {".git", ".pytest_cache", ".venv", "venv", "node_modules", "build", "dist"}


def markdown_lines() -> dict[str, int]:
  """Lines of every Markdown file of the repository, by path relative to it."""
  return {str(f.relative_to(ROOT)): len(f.read_text().splitlines())
          for f in ROOT.rglob("*.md")
          if not SKIP_DIRS & set(f.relative_to(ROOT).parts[:-1])
          and not f.relative_to(ROOT).parts[0].endswith(".egg-info")}


def test_the_documentation_stays_short():
  lines = markdown_lines()
  guides = {f: n for f, n in lines.items()
            if f != "README.md" and not f.startswith("docs/results/")}
  assert "docs/training.md" in guides and "CHANGELOG.md" in guides
  assert sum(guides.values()) <= MAX_GUIDE_LINES, sorted(guides.items(), key=lambda x: -x[1])
  assert sum(lines.values()) <= MAX_MARKDOWN_LINES, sorted(lines.items(), key=lambda x: -x[1])[:10]


def test_the_citation_names_the_version():
  """CITATION.cff cites the version the package reports, and the paper it reproduces."""
  import yaml

  import mjxvine
  cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
  assert str(cff["version"]) == mjxvine.__version__
  assert "arXiv:2206.14155" in str(cff["references"])


def test_the_index_lists_every_page():
  """docs/index.md links every page of docs/ and of docs/results/, and every run record's
  README; the tables that commands wrote (results.md, report.md, ...) are listed by their
  folder."""
  index = ROOT / "docs" / "index.md"
  link = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
  linked = {(index.parent / t).resolve() for t in link.findall(index.read_text())}
  pages = [*(ROOT / "docs").glob("*.md"), *(ROOT / "docs" / "results").glob("*.md"),
           *(ROOT / "docs" / "results").glob("*/**/README.md")]
  missing = [str(p.relative_to(ROOT)) for p in pages if p != index and p.resolve() not in linked]
  assert not missing, f"docs/index.md does not link: {missing}"
