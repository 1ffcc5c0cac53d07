"""The package's functions stay small at their boundary: none takes more than
`MAX_PARAMETERS` parameters. Parameters that travel together are one typed value instead
(e.g. `rollout.Protocol`, `rollout.PolicySource`, `report.RunSummary`)."""

import ast
from pathlib import Path

from conftest import parse_source

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "mjxvine"
MAX_PARAMETERS = 8

Function = ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda


def parameter_count(node: Function) -> int:
  """Positional (positional-only too) and keyword-only parameters, *args and **kwargs one
  each; a method's `self` or `cls` is not counted."""
  a = node.args
  positional = [p.arg for p in a.posonlyargs + a.args]
  count = len(positional) + len(a.kwonlyargs) + (a.vararg is not None) + (a.kwarg is not None)
  # (a first parameter named so is the instance or class, whatever the decorator)
  return count - (positional[:1] in (["self"], ["cls"]))


def functions(tree: ast.AST, prefix: str = ""):
  """(qualified name, node) of every function and lambda in `tree`, nested ones too:
  Class.method, outer.<locals>.inner, <lambda>."""
  for node in ast.iter_child_nodes(tree):
    if isinstance(node, Function):
      name = prefix + getattr(node, "name", "<lambda>")
      yield name, node
      yield from functions(node, name + ".<locals>.")
    elif isinstance(node, ast.ClassDef):
      yield from functions(node, prefix + node.name + ".")
    else:
      yield from functions(node, prefix)


def too_many_parameters(root: Path = PACKAGE) -> list[str]:
  """"module.py:line name (count)" of each function under `root` over the limit."""
  out = []
  for path in sorted(root.rglob("*.py")):
    tree = parse_source(path.read_text(), filename=str(path))
    for name, node in functions(tree):
      n = parameter_count(node)
      if n > MAX_PARAMETERS:
        out.append(f"{path.relative_to(ROOT)}:{node.lineno} {name} ({n})")
  return out


def test_the_count_follows_the_rule():
  tree = parse_source(
      "def f(a, /, b, *c, d, **e): pass\n"
      "class C:\n"
      "  def m(self, a, b): pass\n"
      "  @classmethod\n"
      "  def k(cls, *, a=1): pass\n"
      "  def s(a, b): pass\n"
      "g = lambda x, y: x\n")
  counts = {name: parameter_count(node) for name, node in functions(tree)}
  assert counts == {"f": 5, "C.m": 2, "C.k": 1, "C.s": 2, "<lambda>": 2}


def test_no_function_takes_more_than_eight_parameters():
  over = too_many_parameters()
  assert not over, (f"functions with more than {MAX_PARAMETERS} parameters (group those "
                    "that travel together into one typed value):\n" + "\n".join(over))
