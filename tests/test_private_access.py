"""No module reads another module's private attributes: `obj._x` (obj not self/cls) in src/
only where this module defines `_x` itself (an attribute it assigns, a method, a class or
module name), e.g. a class reaching into another instance of itself; and no
`from relayrl.x import _y`. Names no relayrl module defines are third-party ones (torch's
`_foreach_*`, an env's internals): not this rule's.
Tests may reach in."""

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "relayrl"


def _defined(tree: ast.AST) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            names.add(node.attr)
        elif isinstance(node, ast.alias):
            names.add(node.asname or node.name.split(".")[-1])
    return names


def _private_reads(path: Path, tree: ast.AST, ours: set[str]) -> list[str]:
    own = _defined(tree)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("relayrl"):
            found += [f"{path.relative_to(SRC.parent)}:{node.lineno}: import {a.name}" for a in node.names
                      if a.name.startswith("_") and not a.name.startswith("__")]
        if not isinstance(node, ast.Attribute):
            continue
        attr = node.attr
        if not attr.startswith("_") or attr.startswith("__") or attr in own or attr not in ours:
            continue
        if isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"):
            continue
        found.append(f"{path.relative_to(SRC.parent)}:{node.lineno}: .{attr}")
    return found


def test_no_module_reads_another_modules_private_attributes():
    trees = {path: ast.parse(path.read_text(), str(path)) for path in sorted(SRC.rglob("*.py"))}
    ours = set().union(*(_defined(tree) for tree in trees.values()))
    found = [hit for path, tree in trees.items() for hit in _private_reads(path, tree, ours)]
    assert not found, "private attributes read across modules:\n" + "\n".join(found)
