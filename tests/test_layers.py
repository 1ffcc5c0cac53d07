"""The package's layers (docs/reference.md, Modules): every module of the tree is in the
module map and every entry of the map is a module; imports (inside functions too) run one
way, from a layer to itself or the layers above it; no import cycles; no private name of
one module used by another."""

import ast
import re
from pathlib import Path

from conftest import parse_source

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "mjxvine"
REFERENCE = ROOT / "docs" / "reference.md"


def module_name(path: Path) -> str:
  parts = list(path.relative_to(ROOT).with_suffix("").parts)
  if parts[-1] == "__init__":
    parts.pop()
  return ".".join(parts)


def modules() -> dict[str, Path]:
  return {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def layer_map() -> dict[str, int]:
  """{module: layer} from the rows `| layer | `mjxvine.x` | what |` of the module map."""
  text = REFERENCE.read_text()
  rows = re.findall(r"^\| (\d+) \| `(mjxvine[\w.]*)` \|", text, flags=re.M)
  return {name: int(layer) for layer, name in rows}


def imports(path: Path, name: str, known: set[str]) -> list[tuple[str, list[str]]]:
  """(imported mjxvine module, names taken from it) for every import in the file."""
  tree = parse_source(path.read_text())
  package = name if path.name == "__init__.py" else name.rpartition(".")[0]
  out = []
  for node in ast.walk(tree):
    if isinstance(node, ast.Import):
      out += [(a.name, []) for a in node.names if a.name.split(".")[0] == "mjxvine"]
    elif isinstance(node, ast.ImportFrom):
      base = node.module or ""
      if node.level:
        base = ".".join(package.split(".")[:len(package.split(".")) - node.level + 1]
                        + ([base] if base else []))
      if base.split(".")[0] != "mjxvine":
        continue
      for a in node.names:  # `from pkg import module` imports the module
        sub = f"{base}.{a.name}"
        out.append((sub, []) if sub in known else (base, [a.name]))
  return out


def graph() -> dict[str, list[tuple[str, list[str]]]]:
  mods = modules()
  return {m: imports(p, m, set(mods)) for m, p in mods.items()}


def test_module_map_matches_the_tree():
  mods, layers = set(modules()), layer_map()
  assert not mods - set(layers), f"modules missing from docs/reference.md: {sorted(mods - set(layers))}"
  assert not set(layers) - mods, f"docs/reference.md names no such module: {sorted(set(layers) - mods)}"


def test_imports_follow_the_layers():
  layers = layer_map()
  against = [f"{m} (layer {layers[m]}) imports {dep} (layer {layers[dep]})"
             for m, deps in graph().items() for dep, _ in deps
             if dep in layers and m in layers and layers[dep] > layers[m]]
  assert not against, "imports against the layer order:\n" + "\n".join(sorted(set(against)))
  unknown = {f"{m} imports {dep}" for m, deps in graph().items() for dep, _ in deps
             if dep not in layers}
  assert not unknown, f"imports of no such module: {sorted(unknown)}"


def test_no_import_cycles():
  edges = {m: {d for d, _ in deps if d in graph_nodes() and d != m}
           for m, deps in graph().items()}
  # a package's __init__ importing its own submodules is not a cycle of concepts
  edges = {m: {d for d in ds if not d.startswith(m + ".")} for m, ds in edges.items()}
  cycles, state = [], {}

  def visit(m, stack):
    state[m] = "open"
    for d in sorted(edges.get(m, ())):
      if state.get(d) == "open":
        cycles.append(stack[stack.index(d):] + [d])
      elif d not in state:
        visit(d, stack + [d])
    state[m] = "done"

  for m in sorted(edges):
    if m not in state:
      visit(m, [m])
  assert not cycles, f"import cycles: {cycles}"


def graph_nodes() -> set[str]:
  return set(modules())


def test_no_private_names_across_modules():
  private = [f"{m} takes {dep}.{n}" for m, deps in graph().items() for dep, names in deps
             for n in names if n.startswith("_") and dep != m]
  assert not private, "private names used across modules:\n" + "\n".join(private)
