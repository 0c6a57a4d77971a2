"""The package's two floors: the library never imports the lab, no cycles."""

import ast
import pathlib

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "clipgs_jax"
LAB = "clipgs_jax.lab"


def _module(path: pathlib.Path) -> str:
  parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
  return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports() -> dict[str, set[str]]:
  """{module: the clipgs_jax modules it imports}, from the source."""
  modules = {_module(p): p for p in PACKAGE.rglob("*.py")}
  out = {}
  for name, path in modules.items():
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
      if isinstance(node, ast.ImportFrom) and node.module:
        for alias in node.names:
          full = f"{node.module}.{alias.name}"
          found.add(full if full in modules else node.module)
      elif isinstance(node, ast.Import):
        found.update(alias.name for alias in node.names)
    out[name] = {m for m in found if m in modules and m != name}
  return out


def test_the_library_never_imports_the_lab():
  imports = _imports()
  assert any(LAB in m for m in imports), "no lab package found"
  bad = {m: sorted(i for i in deps if i.startswith(LAB))
         for m, deps in imports.items() if not m.startswith(LAB)}
  assert not {m: d for m, d in bad.items() if d}


def test_no_import_cycles():
  imports = _imports()
  done, path = set(), []

  def visit(module):
    if module in path:
      raise AssertionError(" -> ".join(path[path.index(module):] + [module]))
    if module in done:
      return
    path.append(module)
    for dep in sorted(imports[module]):
      visit(dep)
    path.pop()
    done.add(module)

  for module in sorted(imports):
    visit(module)
  # The check can fail: the modules import each other.
  assert len(done) > 30 and imports["clipgs_jax.run"]
