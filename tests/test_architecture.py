"""The layout's rules (README "Where things are"), checked on the source with the ast module:

- which package may import which (``ALLOWED``): the core imports no adapter, no application, and none of
  zenoh, pymavlink, OpenCV, sockets, threads or processes; nothing in onboard imports groundsim or bench;
- no import cycles between modules, function-local and dynamic imports included (a cycle hidden in a
  function or behind ``__import__("x.y")`` / ``importlib.import_module("x.y")`` is still a cycle);
- no dynamic import of a project module by a literal name (a plain ``import`` says the same and the
  checker reads it; loading a plug-in the user names is not literal and stays allowed).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("onboard", "groundsim", "bench")

# room -> the rooms (and third-party top-level modules) it may import; a room is the longest matching prefix
ALLOWED = {
    "onboard.core": {"onboard.core"},
    "onboard.imaging": {"onboard.core", "onboard.imaging"},
    "onboard.estimation": {"onboard.core", "onboard.estimation"},
    "onboard.pipeline": {"onboard.core", "onboard.imaging", "onboard.estimation", "onboard.pipeline"},
    "onboard.io": {"onboard.core", "onboard.pipeline", "onboard.estimation", "onboard.io"},
    "onboard.app": {"onboard"},
    "onboard": {"onboard"},  # the entry-point shims
    "groundsim.world": {"onboard.core", "groundsim.world"},
    "groundsim.io": {"onboard.core", "onboard.io", "groundsim.world", "groundsim.io"},
    "groundsim.evaluation": {"onboard", "groundsim.world", "groundsim.io", "groundsim.evaluation"},
    "groundsim.app": {"onboard", "groundsim"},
    "groundsim": {"groundsim", "onboard.core"},  # the entry-point shim (and its BLAS environment)
    "bench": {"onboard", "groundsim", "bench"},
}
# third-party or standard modules a room must not import
FORBIDDEN = {
    "onboard.core": {
        "zenoh",
        "pymavlink",
        "cv2",
        "av",
        "mcap",
        "foxglove",
        "socket",
        "threading",
        "multiprocessing",
        "subprocess",
        "asyncio",
    },
    "onboard.imaging": {"zenoh", "pymavlink", "socket", "threading", "multiprocessing", "subprocess"},
    "onboard.estimation": {"zenoh", "pymavlink", "cv2", "socket", "threading", "multiprocessing", "subprocess"},
    "onboard.pipeline": {"zenoh", "pymavlink", "socket", "threading", "multiprocessing", "subprocess"},
    "groundsim.world": {"zenoh", "pymavlink", "socket", "threading", "multiprocessing", "subprocess"},
}
# onboard must install and run without the simulator's packages
ONBOARD_NEVER = {"groundsim", "bench", "jsbsim", "matplotlib", "tqdm", "dask", "pandas", "pyarrow"}
# (module, imported module) pairs exempt from ALLOWED: none
EXCEPTIONS: set[tuple[str, str]] = set()


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for p in sorted((REPO / pkg).rglob("*.py")):
            rel = p.relative_to(REPO).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = p
    return out


MODULES = _modules()


def _literal_dynamic_import(node: ast.AST) -> str | None:
    """The module name of ``__import__("x.y", ...)`` or ``importlib.import_module("x.y")`` (also
    ``import_module("x.y")`` imported from importlib) when its first argument is a string literal."""
    if not isinstance(node, ast.Call) or not node.args:
        return None
    f = node.func
    if isinstance(f, ast.Name):
        name = f.id
    elif isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) and f.value.id == "importlib":
        name = f.attr
    else:
        return None
    arg = node.args[0]
    if name in ("__import__", "import_module") and isinstance(arg, ast.Constant) and isinstance(arg.value, str):
        return arg.value
    return None


def _imports(mod: str, path: Path, dynamic: bool = True) -> list[tuple[str, int]]:
    """Every imported module name (absolute; relative ones resolved), function-local ones included, and
    (``dynamic``) the literal names given to ``__import__`` / ``importlib.import_module``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    pkg = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = pkg.split(".")[: len(pkg.split(".")) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            out.append((base, node.lineno))
            # ``from pkg import module`` imports the module
            out += [(f"{base}.{a.name}", node.lineno) for a in node.names if f"{base}.{a.name}" in MODULES]
        elif dynamic and (name := _literal_dynamic_import(node)) is not None:
            out.append((name, node.lineno))
    return out


def _dynamic_project_imports(path: Path) -> list[tuple[str, int]]:
    """The literal dynamic imports of a project module in ``path``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        name = _literal_dynamic_import(node)
        if name is not None and name.split(".")[0] in PACKAGES:
            found.append((name, node.lineno))
    return found


def _room(mod: str) -> str:
    return max((r for r in ALLOWED if mod == r or mod.startswith(r + ".")), key=len)


def _internal(name: str) -> str | None:
    """The module of ours that ``name`` refers to (the longest known prefix), else None."""
    parts = name.split(".")
    for k in range(len(parts), 0, -1):
        cand = ".".join(parts[:k])
        if cand in MODULES:
            return cand
    return None


def test_every_package_directory_is_a_package():
    for pkg in PACKAGES:
        for d in (REPO / pkg).rglob("*"):
            if d.is_dir() and any(d.glob("*.py")) and "__pycache__" not in d.parts:
                assert (d / "__init__.py").is_file(), f"{d} has modules but no __init__.py"


@pytest.mark.parametrize("mod", sorted(MODULES))
def test_module_imports_respect_the_layout(mod):
    room = _room(mod)
    bad = []
    for name, line in _imports(mod, MODULES[mod]):
        top = name.split(".")[0]
        where = f"{MODULES[mod].relative_to(REPO)}:{line}"
        if (mod, _internal(name)) in EXCEPTIONS:
            continue
        if top in PACKAGES:
            target = _internal(name) or name
            if not any(target == a or target.startswith(a + ".") for a in ALLOWED[room]):
                bad.append(f"{where}: {room} may not import {target}")
        if top in FORBIDDEN.get(room, ()):
            bad.append(f"{where}: {room} may not import {top}")
        if mod.startswith("onboard") and top in ONBOARD_NEVER:
            bad.append(f"{where}: onboard may not import {top} (the onboard install has no simulator packages)")
    assert not bad, "\n".join(bad)


def test_there_are_no_import_cycles():
    graph = {m: sorted({t for n, _ in _imports(m, p) if (t := _internal(n)) and t != m}) for m, p in MODULES.items()}
    # a package's __init__ importing its own modules is not a cycle with them
    for m in graph:
        graph[m] = [t for t in graph[m] if not (MODULES[m].name == "__init__.py" and t.startswith(m + "."))]
    state: dict[str, int] = {}
    stack: list[str] = []
    cycles = []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for t in graph.get(m, ()):
            if state.get(t) == 1:
                cycles.append(" -> ".join(stack[stack.index(t) :] + [t]))
            elif t not in state:
                visit(t)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_the_checker_sees_function_local_and_relative_imports(tmp_path):
    p = tmp_path / "m.py"
    p.write_text("def f():\n    import zenoh\n    from onboard.core import frames\n")
    names = [n for n, _ in _imports("onboard.core.fake", p)]
    assert "zenoh" in names and "onboard.core.frames" in names


@pytest.mark.parametrize("mod", sorted(MODULES))
def test_no_dynamic_import_of_a_project_module(mod):
    bad = [
        f"{MODULES[mod].relative_to(REPO)}:{line}: dynamic import of {name}; write `import {name}`"
        for name, line in _dynamic_project_imports(MODULES[mod])
    ]
    assert not bad, "\n".join(bad)


def test_the_checker_sees_dynamic_imports_and_counts_them_as_arrows(tmp_path):
    p = tmp_path / "m.py"
    p.write_text(
        "import importlib\n"
        "from importlib import import_module\n"
        "def f(user_given):\n"
        "    __import__('groundsim.evaluation.eval', fromlist=['cmd_eval'])\n"
        "    importlib.import_module('onboard.core.frames')\n"
        "    import_module('bench.render')\n"
        "    importlib.import_module(user_given)\n"  # a plug-in the user names: not literal, allowed
        "    __import__('cv2')\n"
    )
    names = [n for n, _ in _imports("groundsim.app.fake", p)]
    assert {"groundsim.evaluation.eval", "onboard.core.frames", "bench.render", "cv2"} <= set(names)
    assert sorted(n for n, _ in _dynamic_project_imports(p)) == [
        "bench.render",
        "groundsim.evaluation.eval",
        "onboard.core.frames",
    ]


def test_the_readme_table_names_every_module_of_its_room():
    """README's "Where things are" is the newcomer's map of the rooms: each module directly in a room is named in
    that room's row (eleven had been left out, among them time_offset.py and mavlink_fast.py)."""
    rows = {}
    for line in (REPO / "README.md").read_text().splitlines():
        if line.startswith("| `") and "/` |" in line:
            room = line.split("`")[1]
            rows[room] = line
    missing = []
    for room, row in rows.items():
        folder = REPO / room
        if not folder.is_dir() or room == "bench/":  # bench's row names its benchmarks, not files
            continue
        for p in sorted(folder.glob("*.py")):
            if p.name != "__init__.py" and f"`{p.name}`" not in row:
                missing.append(f"{room}{p.name}")
    assert rows, "README has no 'Where things are' table"
    assert not missing, "README's 'Where things are' does not name: " + ", ".join(missing)
