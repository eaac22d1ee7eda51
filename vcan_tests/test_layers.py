"""test_layers - the house by layers (issue 14): every import in chcos/ and drivers/ points down.

The layers are the thesis' (section 6.1.2) from the bottom up, as folders of ``chcos/`` (the
system tables of section 6.1.3 at the bottom, since every manager acts on them); the
applications (``chcos/apps``) sit beside the OS and only the command line (``chcos/cli``,
``chcos/testing.py``) may reach them. Every ``import`` counts - inside functions and under
``TYPE_CHECKING`` too - because a cycle closed by a lazy import is still a cycle.

Also checked here: the tools (``tools/``) import the package as installed - no
``sys.path`` edits, no import of the tests.
"""

from __future__ import annotations

import ast
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: rank of each OS layer, bottom first; a module may import its own layer or lower ones.
LAYERS: dict[str, int] = {
    "chcos.errors": 0, "chcos.resources": 0, "chcos.tables": 1, "chcos.kernel": 2,
    "chcos.helpers": 0,
    "chcos.devices": 3, "drivers": 3, "chcos.comm": 4, "chcos.messages": 5, "chcos.user": 6,
    "chcos.system": 7, "chcos.satellites": 8, "chcos.serving": 9,
    "chcos.north": 10, "chcos.viewer": 10, "chcos.cli": 11, "chcos.testing": 11,
    # the HIL evidence watches a whole system; its pytest half is the plugin's
    "chcos.hil": 10, "chcos.hil.plugin": 11,
}
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
#: where the OS may import a driver module: nowhere but the command line and the pytest plugin
#: (``chcos.cli``, ``chcos.testing``) - the device layer owns the driver interface
#: (``chcos.devices.driver``) and finds the drivers by kind (``chcos.devices.registry``), as
#: python-can's core finds its interfaces. The applications beside the OS may (a driver of their
#: own, the codecs for a simulator).
DRIVER_USERS = ("chcos.cli", "chcos.testing", APPS, "drivers")
#: The arrows into ``drivers`` from the OS that are still to move, each with who moves it; the
#: lead deletes an entry when that branch lands (the test fails on an entry no longer needed).
DRIVER_ARROWS_TO_MOVE: dict[str, frozenset[str]] = {
    # the CiA 402 / CANopen branch: the axis vocabulary (AxisCode, the CiA 402 names of an axis
    # table) into the device layer, profile operations through Devtab
    "chcos.devices.mapparse": frozenset({"drivers.canopen_axis", "drivers.codecs.cia402"}),
    "chcos.comm.manager": frozenset({"drivers.canopen_axis", "drivers.codecs.cia402"}),
    "chcos.user.axes": frozenset({"drivers.canopen_axis", "drivers.codecs.cia402"}),
    # the importers' branch: the EDS importer's use of the CANopen object dictionary
    "chcos.devices.importers.eds": frozenset({"drivers.canopen_od"}),
    # the north branch: the lifecycle names metrics reads (NodeStatus in chcos.devices.status)
    "chcos.north.metrics": frozenset({"drivers.canopen_lifecycle"}),
}


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
#: the packages whose import graph is checked for cycles: the product and its tests
GRAPH_TOPS = ("chcos", "drivers", "vcan_tests")


def graph() -> dict[str, set[str]]:
    """Module -> the modules of :data:`GRAPH_TOPS` it imports (every import statement)."""
    if not GRAPH:
        mods = sources(ROOT, GRAPH_TOPS)
        for name, path in mods.items():
            GRAPH[name] = {i for i in imports_of(name, path) if i in mods and i != name}
    return GRAPH


def driver_arrows(g: dict[str, set[str]]) -> dict[str, set[str]]:
    """The imports of a driver module by an OS module that may not import one (see
    :data:`DRIVER_USERS`), by importer."""
    out: dict[str, set[str]] = {}
    for name, deps in g.items():
        if not under(name, ("chcos",)) or under(name, DRIVER_USERS):
            continue
        bad = {d for d in deps if under(d, ("drivers",))}
        if bad:
            out[name] = bad
    return out


def package_graph(g: dict[str, set[str]]) -> dict[str, set[str]]:
    """The layers' graph (:func:`owner`; a test module is its own node), without the arrows
    still to move (:data:`DRIVER_ARROWS_TO_MOVE`)."""
    out: dict[str, set[str]] = {}
    for name, deps in g.items():
        src = owner(name) or name
        for d in deps:
            if d in DRIVER_ARROWS_TO_MOVE.get(name, ()):
                continue
            dst = owner(d) or d
            if dst != src:
                out.setdefault(src, set()).add(dst)
        out.setdefault(src, set())
    return out


def violations(root: Path = ROOT) -> list[str]:
    mods = sources(root)
    bad = []
    for name, path in sorted(mods.items()):
        mine = owner(name)
        for imp in sorted(imports_of(name, path)):
            their = owner(imp)
            where = f"{path.relative_to(root)} imports {imp}"
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


def cycles(g: dict[str, set[str]] | None = None) -> list[list[str]]:
    """The strongly connected components of more than one node of ``g`` (the module graph by
    default; Tarjan)."""
    g = graph() if g is None else g
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
    """No circle of modules in chcos/, drivers/ and the tests (helpers included)."""
    found = cycles()
    assert not found, "\n".join(" <-> ".join(c) for c in found)


def test_no_circle_between_layers() -> None:
    """No circle of layers either (the services starting the viewer, which used the services'
    auth: both now use chcos.serving; the device layer and the drivers)."""
    found = cycles(package_graph(graph()))
    assert not found, "\n".join(" <-> ".join(c) for c in found)


def test_the_os_imports_no_driver_but_through_the_registry() -> None:
    """chcos.devices and every OS layer reach the drivers by kind (chcos.devices.registry),
    never by importing one; only the arrows still to move are allowed, and each of them must
    still be there (an entry no longer needed is deleted)."""
    found = driver_arrows(graph())
    new = {n: sorted(d - DRIVER_ARROWS_TO_MOVE.get(n, frozenset())) for n, d in found.items()}
    assert not {n: d for n, d in new.items() if d}, new
    stale = {n: sorted(d - found.get(n, set())) for n, d in DRIVER_ARROWS_TO_MOVE.items()}
    assert not {n: d for n, d in stale.items() if d}, f"moved already: delete {stale}"


def test_the_graph_checks_catch_what_they_forbid() -> None:
    """A circle of test helpers, a circle of layers and a driver import by the device layer
    are each found in a graph that has one."""
    assert cycles({"vcan_tests.a": {"vcan_tests.b"}, "vcan_tests.b": {"vcan_tests.a"}}) == [
        ["vcan_tests.a", "vcan_tests.b"]]
    g = {"chcos.north.services": {"chcos.viewer.server"}, "chcos.viewer.server": {
        "chcos.north.auth"}, "chcos.north.auth": set()}
    assert cycles(package_graph(g)) == [["chcos.north", "chcos.viewer"]]
    assert driver_arrows({"chcos.devices.devtab": {"drivers.memory", "chcos.kernel.clock"},
                          "chcos.cli.monitor": {"drivers.memory"}}) == {
        "chcos.devices.devtab": {"drivers.memory"}}


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
    a higher layer, and a codec importing I/O, are reported."""
    for top in ("chcos", "drivers"):
        shutil.copytree(ROOT / top, tmp_path / top,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    assert violations(tmp_path) == violations()
    (tmp_path / "chcos" / "kernel" / "_layer_probe.py").write_text(
        "from chcos.apps import weld\nfrom chcos.system import manager\n")
    (tmp_path / "drivers" / "codecs").mkdir(exist_ok=True)
    (tmp_path / "drivers" / "codecs" / "_probe.py").write_text("import socket\n")
    bad = violations(tmp_path)
    assert any("_probe.py imports socket: a codec imports I/O" in b for b in bad)
    assert any("_layer_probe.py imports chcos.apps: the OS imports an application" in b
               for b in bad)
    assert any("_layer_probe.py imports chcos.system.manager: layer chcos.kernel imports the "
               "higher layer chcos.system" in b for b in bad)


def test_tools_neither_edit_sys_path_nor_import_the_tests() -> None:
    """Tools run with chcos installed (``python -m tools.X`` or as scripts)."""
    bad = []
    for name, path in sorted(sources(ROOT, ("tools",)).items()):
        text = path.read_text()
        if "sys.path.insert" in text or "sys.path.append" in text:
            bad.append(f"{path.relative_to(ROOT)} edits sys.path")
        bad += [f"{path.relative_to(ROOT)} imports {imp} (tests are not a library)"
                for imp in sorted(imports_of(name, path)) if under(imp, ("vcan_tests",))]
    assert not bad, "\n".join(bad)


def test_layout_tree_counts_every_module_of_the_worktree() -> None:
    """tools/layout_tree (the before/after tree of the issue note) misses no module or line."""
    from tools import layout_tree

    mods = layout_tree.modules(layout_tree.WORKTREE)
    assert set(mods) == {p.relative_to(ROOT).as_posix() for p in sources().values()}
    text = layout_tree.render(layout_tree.WORKTREE, 400)
    assert f"{len(mods)} modules, {sum(mods.values()):,} lines" in text
    assert "  kernel/" in text and "drivers/" in text
