"""The package's import graph: the library never imports the command line (``ngp_warp.cli``),
and no modules import each other in a cycle, counting imports inside functions too."""

import ast
from pathlib import Path

ROOT = Path(__file__).parents[1] / "ngp_warp"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path, modules: set[str]) -> set[str]:
    """The package's modules that ``path`` imports (anywhere in it)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        found |= {n for n in names if n in modules}
    return found


def graph() -> dict[str, set[str]]:
    paths = {module_name(p): p for p in ROOT.rglob("*.py")}
    return {name: imports(path, set(paths)) - {name} for name, path in paths.items()}


def test_the_library_never_imports_the_command_line():
    offenders = {m: sorted(i for i in deps if i.startswith("ngp_warp.cli"))
                 for m, deps in graph().items() if not m.startswith("ngp_warp.cli")}
    assert not {m: d for m, d in offenders.items() if d}


def test_no_import_cycles():
    edges = graph()
    for deps in edges.values():  # a package's __init__ re-exporting its modules is not a cycle
        deps.discard("ngp_warp")
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == 1:
                raise AssertionError("import cycle: " + " -> ".join(path[path.index(nxt):] + [node, nxt]))
            if nxt not in state:
                visit(nxt, path + [node])
        state[node] = 2

    for node in sorted(edges):
        if node not in state:
            visit(node, [])
