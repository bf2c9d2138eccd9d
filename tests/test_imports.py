"""The package's import structure: every module imports on its own, in a fresh
interpreter, and no two modules import each other (directly or round a longer loop),
counting the imports inside functions too (issue 12: "no import cycle left")."""

import ast
import os
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import robo3d

PACKAGE = Path(robo3d.__file__).resolve().parent


def _modules() -> list[str]:
    return sorted(m.name for m in pkgutil.walk_packages([str(PACKAGE)], "robo3d."))


def _module_file(name: str) -> Path:
    rel = Path(*name.split(".")[1:])
    path = PACKAGE / rel
    return path / "__init__.py" if path.is_dir() else path.with_suffix(".py")


def import_graph() -> dict[str, set[str]]:
    """``module -> robo3d modules it imports`` from the source (module-level and
    function-level ``import``/``from ... import``; ``from pkg import name`` counts as
    importing ``pkg.name`` when that is a module, else ``pkg``)."""
    modules = set(_modules()) | {"robo3d"}
    graph: dict[str, set[str]] = {}
    for name in modules:
        path = _module_file(name) if name != "robo3d" else PACKAGE / "__init__.py"
        is_pkg = path.name == "__init__.py"
        package = name if is_pkg else name.rsplit(".", 1)[0]
        edges: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")
                    base = base[: len(base) - (node.level - 1)]
                    mod = ".".join(base + ([node.module] if node.module else []))
                else:
                    mod = node.module or ""
                targets = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in modules else mod
                           for a in node.names]
            for t in targets:
                while t and t not in modules:  # a name inside a module: the module
                    t = t.rpartition(".")[0]
                if t and t != name:
                    edges.add(t)
        graph[name] = edges
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` (``[a, b, ..., a]``), or None. A package importing its
    own submodule (``robo3d.x`` -> ``robo3d.x.y``) is no cycle by itself; the edge from
    a submodule to its package ``__init__`` is left out, as Python imports the package
    first anyway."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> list[str] | None:
        state[n] = 1
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if n.startswith(m + "."):  # submodule -> its package: not an import order
                continue
            if state.get(m) == 1:
                return stack[stack.index(m):] + [m]
            if m not in state:
                found = visit(m)
                if found:
                    return found
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state:
            found = visit(n)
            if found:
                return found
    return None


# Run in a fresh interpreter: load the third-party libraries the package uses (their
# start-up is most of the cost and says nothing about robo3d's own import order), then
# fork one child per robo3d module, which imports that module alone: a child starts
# with no robo3d module loaded, so a module that works only because another one was
# imported first fails in it.
_ISOLATED_IMPORTS = """
import importlib, os, sys, traceback
for lib in sys.argv[1].split(","):
    try:
        importlib.import_module(lib)
    except Exception:
        pass
failed = 0
for name in sys.argv[2].split(","):
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(r)
        try:
            importlib.import_module(name)
            code = 0
        except BaseException:
            os.write(w, traceback.format_exc().strip().splitlines()[-1].encode())
            code = 1
        os._exit(code)
    os.close(w)
    with os.fdopen(r, "rb") as f:
        msg = f.read().decode(errors="replace")
    _, status = os.waitpid(pid, 0)
    if status:
        failed += 1
        print(f"{name}: {msg or status}")
sys.exit(1 if failed else 0)
"""


def _third_party(graph_modules: list[str]) -> list[str]:
    """Top-level names of the non-robo3d libraries the package imports at module level
    (those inside functions are loaded lazily, by the child that needs them)."""
    libs: set[str] = set()
    for name in graph_modules:
        tree = ast.parse(_module_file(name).read_text(encoding="utf-8"))
        for node in tree.body:
            if isinstance(node, ast.Import):
                libs.update(a.name.split(".")[0] for a in node.names)
            elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
                libs.add(node.module.split(".")[0])
    return sorted(lib for lib in libs if lib != "robo3d" and lib not in sys.builtin_module_names)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")
def test_every_module_imports_alone():
    modules = _modules()
    p = subprocess.run([sys.executable, "-c", _ISOLATED_IMPORTS, ",".join(_third_party(modules)),
                        ",".join(modules)], capture_output=True, text=True, timeout=300,
                       cwd=PACKAGE.parent)
    assert p.returncode == 0, ("modules that do not import alone:\n" + p.stdout
                               + p.stderr[-2000:])


def test_no_import_cycle():
    cycle = find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_cycle_finder_finds_a_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None
    assert find_cycle({"p": {"p.x"}, "p.x": {"p"}}) is None
