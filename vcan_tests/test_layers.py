"""test_layers - the house by layers (issue 14): every import in chcos/ and drivers/ points down.

The layers are the thesis' (section 6.1.2) from the bottom up, as folders of ``chcos/`` (the
system tables of section 6.1.3 at the bottom, since every manager acts on them); the
applications (``chcos/apps``) sit beside the OS and only the command line (``chcos/cli``,
``chcos/testing.py``) may reach them. Every ``import`` counts - inside functions and under
``TYPE_CHECKING`` too - because a cycle closed by a lazy import is still a cycle.

Also checked here: the one deprecated alias (``chcos.usrmgr``, for users' task code) is imported
by nothing in the tree and warns; the tools (``tools/``) import the package as installed - no
``sys.path`` edits, no import of the tests.
"""

from __future__ import annotations

import ast
import shutil
import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: rank of each OS layer, bottom first; a module may import its own layer or lower ones.
LAYERS: dict[str, int] = {
    "chcos.errors": 0, "chcos.resources": 0, "chcos.tables": 1, "chcos.kernel": 2,
    "chcos.helpers": 0,
    "chcos.devices": 3, "drivers": 3, "chcos.comm": 4, "chcos.messages": 5, "chcos.user": 6,
    "chcos.system": 7, "chcos.satellites": 8, "chcos.north": 9, "chcos.viewer": 9,
    "chcos.cli": 10, "chcos.testing": 10,
    "chcos.usrmgr": 6,   # the deprecated alias of chcos.user.context (see DEPRECATED)
}
#: old module names kept as aliases for users' code only; nothing in the tree may import them.
DEPRECATED = ("chcos.usrmgr",)
APPS = "chcos.apps"
#: pure codecs: no I/O (no bus library, socket, thread or event loop).
CODECS = ("drivers.codecs",)
#: the in-process wires of virtual time, shared by a driver and its simulated peer as python-can's
#: own virtual bus is (they hold no driver logic: the driver is on one end, the peer on the other)
WIRES = ("drivers.can_direct", "drivers.serial_direct")
IO_MODULES = ("can", "canopen", "serial", "socket", "asyncio", "threading", "zenoh", "selectors",
              "pymodbus.client", "pymodbus.server", "subprocess")
#: the simulators, which may use the drivers' codecs but not their I/O.
SIMULATORS = ("chcos.apps.sim", "chcos.apps.weld.plant")
#: application code a bus driver exists for: the welding cell's in-process binding.
APP_DRIVERS = ("chcos.apps.weld.direct",)


def module_name(path: Path, root: Path = ROOT) -> str:
    rel = path.relative_to(root).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def sources(root: Path = ROOT, tops: tuple[str, ...] = ("chcos", "drivers")) -> dict[str, Path]:
    found = {}
    for top in tops:
        for path in (root / top).rglob("*.py"):
            found[module_name(path, root)] = path
    return found


def imports_of(name: str, path: Path) -> set[str]:
    """Every module ``name`` imports (absolute names), wherever the statement is."""
    tree = ast.parse(path.read_text(), str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.add(mod)
            out.update(f"{mod}.{a.name}" for a in node.names)   # from pkg import module
    return out


def owner(name: str) -> str | None:
    """The layer key (or APPS) a chcos/drivers module belongs to."""
    if name == APPS or name.startswith(APPS + "."):
        return APPS
    best = None
    for key in LAYERS:
        if (name == key or name.startswith(key + ".")) and (best is None or len(key) > len(best)):
            best = key
    return best


def under(name: str, prefixes: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


GRAPH: dict[str, set[str]] = {}


def graph() -> dict[str, set[str]]:
    if not GRAPH:
        mods = sources()
        for name, path in mods.items():
            GRAPH[name] = {i for i in imports_of(name, path) if i in mods and i != name}
    return GRAPH


def violations(root: Path = ROOT) -> list[str]:
    mods = sources(root)
    bad = []
    for name, path in sorted(mods.items()):
        mine = owner(name)
        for imp in sorted(imports_of(name, path)):
            their = owner(imp)
            where = f"{path.relative_to(root)} imports {imp}"
            if under(imp, DEPRECATED) and not under(name, DEPRECATED):
                bad.append(f"{where}: a deprecated alias (import its new name)")
            if under(name, CODECS) and under(imp, IO_MODULES):
                bad.append(f"{where}: a codec imports I/O")
            if under(name, SIMULATORS) and under(imp, ("drivers",)) and not under(imp, CODECS
                                                                             + WIRES):
                bad.append(f"{where}: a simulator imports a driver's I/O (use drivers.codecs)")
            if their is None or mine is None:
                continue
            if their == APPS:
                if mine != APPS and LAYERS[mine] < LAYERS["chcos.cli"]:
                    bad.append(f"{where}: the OS imports an application")
                continue
            if mine == APPS:
                if LAYERS[their] >= LAYERS["chcos.cli"]:
                    bad.append(f"{where}: an application imports the command line")
                continue
            if LAYERS[their] > LAYERS[mine]:
                bad.append(f"{where}: layer {mine} imports the higher layer {their}")
    return bad


def cycles() -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    g = graph()
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in g[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    import sys
    sys.setrecursionlimit(10000)
    for v in sorted(g):
        if v not in index:
            visit(v)
    return out


def test_every_import_points_down() -> None:
    bad = violations()
    assert not bad, "\n".join(bad)


def test_no_import_cycle() -> None:
    found = cycles()
    assert not found, "\n".join(" <-> ".join(c) for c in found)


def test_every_module_has_a_layer() -> None:
    stray = [n for n in sources() if owner(n) is None and n not in ("chcos", )]
    assert not stray, f"modules outside every layer: {stray}"


@pytest.mark.parametrize("case, expected", [
    ("chcos.kernel.scheduler", "chcos.kernel"), ("chcos.apps.weld.plant", APPS),
    ("drivers.codecs.can", "drivers"), ("chcos.cli.main", "chcos.cli")])
def test_owner_finds_the_layer(case: str, expected: str) -> None:
    assert owner(case) == expected


def test_the_rules_catch_what_they_forbid(tmp_path: Path) -> None:
    """The checker is not vacuous: in a copy of the tree, an OS module importing an application,
    a higher layer or the deprecated alias, and a codec importing I/O, are reported."""
    for top in ("chcos", "drivers"):
        shutil.copytree(ROOT / top, tmp_path / top,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    assert violations(tmp_path) == violations()
    (tmp_path / "chcos" / "kernel" / "_layer_probe.py").write_text(
        "from chcos.apps import weld\nfrom chcos.system import manager\n"
        "from chcos.usrmgr import TaskContext\n")
    (tmp_path / "drivers" / "codecs").mkdir(exist_ok=True)
    (tmp_path / "drivers" / "codecs" / "_probe.py").write_text("import socket\n")
    bad = violations(tmp_path)
    assert any("_probe.py imports socket: a codec imports I/O" in b for b in bad)
    assert any("_layer_probe.py imports chcos.usrmgr: a deprecated alias" in b for b in bad)
    assert any("_layer_probe.py imports chcos.apps: the OS imports an application" in b
               for b in bad)
    assert any("_layer_probe.py imports chcos.system.manager: layer chcos.kernel imports the "
               "higher layer chcos.system" in b for b in bad)


def test_the_deprecated_alias_warns_and_is_the_new_class() -> None:
    import importlib
    import sys

    from chcos.user.context import TaskContext

    sys.modules.pop("chcos.usrmgr", None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        old = importlib.import_module("chcos.usrmgr")
    assert old.TaskContext is TaskContext
    assert any(issubclass(w.category, DeprecationWarning)
               and "chcos.user.context" in str(w.message) for w in caught)


def test_tools_neither_edit_sys_path_nor_import_the_tests() -> None:
    """Tools run with chcos installed (``python -m tools.X`` or as scripts)."""
    bad = []
    for name, path in sorted(sources(ROOT, ("tools",)).items()):
        text = path.read_text()
        if "sys.path.insert" in text or "sys.path.append" in text:
            bad.append(f"{path.relative_to(ROOT)} edits sys.path")
        bad += [f"{path.relative_to(ROOT)} imports {imp} (tests are not a library)"
                for imp in sorted(imports_of(name, path)) if under(imp, ("vcan_tests",))]
        bad += [f"{path.relative_to(ROOT)} imports {imp}: a deprecated alias"
                for imp in sorted(imports_of(name, path)) if under(imp, DEPRECATED)]
    assert not bad, "\n".join(bad)


def test_layout_tree_counts_every_module_of_the_worktree() -> None:
    """tools/layout_tree (the before/after tree of the issue note) misses no module or line."""
    from tools import layout_tree

    mods = layout_tree.modules(layout_tree.WORKTREE)
    assert set(mods) == {p.relative_to(ROOT).as_posix() for p in sources().values()}
    text = layout_tree.render(layout_tree.WORKTREE, 400)
    assert f"{len(mods)} modules, {sum(mods.values()):,} lines" in text
    assert "  kernel/" in text and "drivers/" in text
