"""Setup costs that grow linearly (issue 21): counted, not timed. A device map parses its DBC and
EDS files once per load; a long install script writes sysfile.map a few times, not once per
line, and the map it leaves rebuilds the system; the assassin index wires exactly the implicit
links the table scan did, on the welding cell and figure 6.5."""

from __future__ import annotations

import shutil
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cantools
import pytest

from chcos.apps import fig65
from chcos.apps.fig65.runner import default_devmap
from chcos.apps.weld.cell import open_cell
from chcos.devices import devmap, parsecache
from chcos.errors import BusError
from chcos.kernel.clock import RealClock, VirtualClock
from chcos.system.embedded import System, sysmap
from chcos.system.installer import Installer
from chcos.tables.messages import TOP_PRIORITY, EndpointKind, LinkType, TapPort
from chcos.tables.tasks import Role, TaskEntry
from chcos.user.context import TaskContext
from drivers import canopen_od
from drivers.codecs.can import load_dbc

M = "vcan_tests.test_core_growth"
ROOT = Path(__file__).resolve().parent.parent


async def idle(ctx: TaskContext, cmd: Any) -> None:
    """A task that is installed and never needs to run."""


def _dbc_map(tmp_path: Path, n: int) -> Path:
    lines = ['VERSION ""', "", "NS_ :", "", "BS_:", "", "BU_: Node Chcos", ""]
    for m in range((n + 7) // 8):
        lines.append(f"BO_ {m + 1} M{m}: 8 Node")
        lines += [f' SG_ S{k} : {8 * k}|8@1+ (1,0) [0|255] "" Chcos' for k in range(8)]
        lines.append("")
    (tmp_path / "many.dbc").write_text("\n".join(lines) + "\n", encoding="utf-8")
    toml = ['[[bus]]', 'name = "can0"', 'kind = "can"', 'interface = "virtual"',
            'channel = "growth-test"', 'dbc = "many.dbc"', ""]
    for i in range(n):
        toml += ["[[device]]", f'name = "D{i}"', 'direction = "sensor"', 'bus = "can0"',
                 f'address = {{ message = "M{i // 8}", signal = "S{i % 8}" }}', ""]
    path = tmp_path / "many.toml"
    path.write_text("\n".join(toml), encoding="utf-8")
    return path


@pytest.fixture
def dbc_parses(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[str]]:
    calls: list[str] = []
    real = cantools.database.load_file

    def counting(path: str, *a: Any, **k: Any) -> Any:
        calls.append(str(path))
        return real(path, *a, **k)

    monkeypatch.setattr(cantools.database, "load_file", counting)
    yield calls


def test_200_devices_on_one_dbc_bus_parse_the_dbc_once(tmp_path: Path,
                                                       dbc_parses: list[str]) -> None:
    dm = devmap.load(_dbc_map(tmp_path, 200))
    assert len(dm.devices) == 200
    assert len(dbc_parses) == 1, dbc_parses
    # the driver builds its codec once more (outside the load: its own, unshared database)
    with System(dm, clock=VirtualClock(), machines=[0]) as s:
        assert s.devtab.get("D199").spec.address == {"message": "M24", "signal": "S7"}
    assert len(dbc_parses) == 2


def test_a_bad_signal_is_still_reported_with_the_cache(tmp_path: Path,
                                                       dbc_parses: list[str]) -> None:
    path = _dbc_map(tmp_path, 16)
    path.write_text(path.read_text().replace('signal = "S7" }', 'signal = "S9" }'))
    dm, errors, _ = devmap.check(path)
    assert dm is None and len(errors) == 2 and all("S9" in e for e in errors), errors
    assert len(dbc_parses) == 1


def test_eds_files_are_parsed_once_per_node_per_load(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple[str, int]] = []
    real = canopen_od.read_eds

    def counting(path: Any, node_id: int | None = None) -> Any:
        calls.append((str(path), int(node_id or 0)))
        return real(path, node_id)

    monkeypatch.setattr(canopen_od, "read_eds", counting)   # the one EDS parse of the driver
    dm = devmap.load(ROOT / "chcos" / "apps" / "weld" / "maps" / "weld_cell.toml")
    canopen_buses = [b for b in dm.buses if b.kind == "canopen"]
    nodes = sum(len(b.options["nodes"]) for b in canopen_buses)
    devices = [d for d in dm.devices if d.bus in {b.name for b in canopen_buses}]
    assert len(devices) > nodes  # several devices per node: without the cache, one parse each
    assert sorted(calls) == sorted(set(calls)) and len(calls) == nodes, calls


def test_the_parse_cache_follows_the_file_and_never_caches_errors(tmp_path: Path) -> None:
    dbc = tmp_path / "a.dbc"
    src = _dbc_map(tmp_path, 8).with_name("many.dbc").read_text()
    dbc.write_text(src)
    assert load_dbc(str(dbc)) is not load_dbc(str(dbc))  # no scope: nothing is shared
    with parsecache.scope():
        first = load_dbc(str(dbc))
        with parsecache.scope():  # nested: the outer cache
            assert load_dbc(str(dbc)) is first
        dbc.write_text(src + "\n")  # changed on disk (size and mtime): parsed again
        second = load_dbc(str(dbc))
        assert second is not first and load_dbc(str(dbc)) is second
        dbc.write_text("BO_ not a dbc")
        dbc.touch()
        for _ in range(2):
            with pytest.raises(BusError, match=r"a\.dbc"):
                load_dbc(str(dbc))


def test_a_1000_line_script_writes_the_map_a_few_times_and_it_rebuilds(tmp_path: Path) -> None:
    script = tmp_path / "install.txt"
    lines = [f"install -m0 --role=exception --level=900 --code={M}:idle EX",
             f"install -m0 --role=assassin --level=800 --code={M}:idle AS"]
    lines += [f"install -m0 --code={M}:idle T{i}" for i in range(1000)]
    lines += [f"install -m0i1 --code={M}:idle U T5", "setpri -7 T5 U", "# the end"]
    script.write_text("\n".join(lines) + "\n")
    mapfile = tmp_path / "sysfile.map"
    with System(clock=VirtualClock(), machines=[0], base_dir=tmp_path, map_path=mapfile) as s:
        s.sysmgr.map_clock = lambda: 0.0  # a burst: no time passes between the installs
        before = s.sysmgr.map_writes      # the boot's write
        s.run_script(script)
        assert s.sysmgr.map_writes - before == 1  # once, when the script ended
        doc = sysmap.read(mapfile)
        assert [t["name"] for t in doc["tasks"]] == ["EX", "AS", *(f"T{i}" for i in range(1000)),
                                                     "U"]
        assert s.msgtab.find("T5", "U").priority == 7
        links = [(lk.lid, lk.src, lk.dst, lk.type, lk.priority) for lk in s.msgtab]
    with System.from_map(mapfile, clock=VirtualClock()) as again:
        assert [(lk.lid, lk.src, lk.dst, lk.type, lk.priority) for lk in again.msgtab] == links


def test_a_burst_of_changes_is_written_when_its_time_comes(tmp_path: Path) -> None:
    now = [0.0]
    mapfile = tmp_path / "sysfile.map"
    with System(clock=VirtualClock(), base_dir=tmp_path, map_path=mapfile) as s:
        s.sysmgr.map_clock = lambda: now[0]
        s.execute("install -m0 sysfile")
        now[0] = 1.0
        s.execute(f"install -m0 --code={M}:idle A")       # due: written at once
        written = s.sysmgr.map_writes
        s.execute(f"install -m0 --code={M}:idle B")       # within the gap: waits
        assert s.sysmgr.map_writes == written
        assert [t["name"] for t in sysmap.read(mapfile)["tasks"]] == ["A"]
        now[0] = 2.0
        s.execute(f"install -m0 --code={M}:idle C")       # gap over: written, B with it
        assert [t["name"] for t in sysmap.read(mapfile)["tasks"]] == ["A", "B", "C"]
        s.execute(f"install -m0 --code={M}:idle D")
        s.run_for(0.1)                                    # a run's end writes what waits
        assert [t["name"] for t in sysmap.read(mapfile)["tasks"]][-1] == "D"


def test_a_running_system_writes_its_last_change_without_being_asked(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    written = threading.Event()
    real = sysmap.write

    def watch(path: str | Path, doc: dict[str, Any]) -> None:
        real(path, doc)
        if any(t["name"] == "B" for t in doc["tasks"]):
            written.set()

    monkeypatch.setattr(sysmap, "write", watch)
    mapfile = tmp_path / "sysfile.map"
    with System(clock=RealClock(), machines=[0], base_dir=tmp_path, map_path=mapfile) as s:
        s.start()
        s.execute(f"install -m0 --code={M}:idle A")
        s.execute(f"install -m0 --code={M}:idle B")  # within the gap: left to the timer
        assert written.wait(30), "the map never caught up with install B"
        assert [t["name"] for t in sysmap.read(mapfile)["tasks"]] == ["A", "B"]


# ---- the assassin index wires what the old table scan wired ------------------------------------
def _scan_wiring(self: Installer, t: TaskEntry) -> None:
    """The implicit links as made before issue 21: every install scanned the whole table."""
    s = self
    others = [u for u in s.tsktab if u is not t]
    if t.role is Role.EXCEPTION:
        tap = TapPort()
        t.tap = tap
        links: dict[str, Any] = {}
        s.msgmgr.taps.append((t, tap, links))
        for u in others:
            if u.level < t.level:
                links[u.name] = self.link(u.name, t.name, LinkType.SENSORY, TOP_PRIORITY,
                                           EndpointKind.TASK, EndpointKind.TASK, u.machine,
                                           t.machine, tap=True)
                u.mark_tapped()
    for e, _tap, elinks in s.msgmgr.taps:
        if e is not t and e.level > t.level:
            elinks[t.name] = self.link(t.name, e.name, LinkType.SENSORY, TOP_PRIORITY,
                                        EndpointKind.TASK, EndpointKind.TASK, t.machine,
                                        e.machine, tap=True)
            t.mark_tapped()
    if t.role is Role.ASSASSIN:
        for u in others:
            if u.level < t.level and s.msgtab.get(t.name, u.name, LinkType.COMMAND) is None:
                t.special_links[u.name] = self.link(
                    t.name, u.name, LinkType.COMMAND, TOP_PRIORITY, EndpointKind.TASK,
                    EndpointKind.TASK, t.machine, u.machine, tap=True)
    for a in others:
        if a.role is Role.ASSASSIN and a.level > t.level:
            a.special_links[t.name] = self.link(
                a.name, t.name, LinkType.COMMAND, TOP_PRIORITY, EndpointKind.TASK,
                EndpointKind.TASK, a.machine, t.machine, tap=True)


def _links(s: System) -> list[Any]:
    out = [(lk.lid, lk.src, lk.dst, lk.type, lk.priority, lk.tap, lk.src_machine,
            lk.dst_machine) for lk in s.msgtab]
    special = sorted((t.name, sorted(t.special_links)) for t in s.tsktab)
    taps = [(e.name, sorted(links)) for e, _tap, links in s.msgmgr.taps]
    tapped = [(t.name, t.tapped, len(t.up_links)) for t in s.tsktab]
    return [*out, special, taps, tapped]


def _fig65(tmp_path: Path) -> list[Any]:
    tmp_path.mkdir()
    shutil.copy(fig65.HERE / "testfile", tmp_path / "testfile")
    with System([default_devmap()], clock=VirtualClock(), task_path=[fig65.HERE],
                base_dir=tmp_path) as s:
        s.run_script(fig65.SCRIPT)
        return _links(s)


def _weld(tmp_path: Path) -> list[Any]:
    tmp_path.mkdir()
    with open_cell("direct", workdir=tmp_path) as cell:
        return _links(cell.system)


def _mixed(tmp_path: Path) -> list[Any]:
    """Assassins and exception tasks installed before, between and after ordinary tasks."""
    tmp_path.mkdir()
    lines = [f"install -m0 --role=exception --level=50 --code={M}:idle EX",
             f"install -m0 --role=assassin --level=40 --code={M}:idle AS"]
    lines += [f"install -m0 --code={M}:idle T{i}" for i in range(5)]
    lines += [f"install -m0o1 --role=assassin --level=30 --code={M}:idle AS2 T1",
              f"install -m0i1 --code={M}:idle U T0",
              f"install -m0 --role=exception --level=35 --code={M}:idle EX2",
              f"install -m0 --role=assassin --level=45 --code={M}:idle AS3"]
    lines += [f"install -m0 --code={M}:idle V{i}" for i in range(5)]
    lines += [f"install -m0 --level=60 --code={M}:idle TOP"]
    with System(clock=VirtualClock(), machines=[0], base_dir=tmp_path) as s:
        for line in lines:
            s.execute(line)
        return _links(s)


@pytest.mark.parametrize(("build", "implicit"),
                         [(_fig65, False), (_weld, True), (_mixed, True)],
                         ids=["figure-6.5", "welding-cell", "roles-interleaved"])
def test_the_assassin_index_wires_the_same_links_as_the_scan(
        build: Any, implicit: bool, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    now = build(tmp_path / "indexed")
    with monkeypatch.context() as mp:
        mp.setattr(Installer, "_exception_wiring", _scan_wiring)
        before = build(tmp_path / "scanned")
    assert any(lk[5] and lk[1] != "host" for lk in now[:-3]) == implicit, \
        "exception taps / assassin links not as the system's roles say"
    assert any(tapped for _n, tapped, _one in now[-1]) == implicit
    assert now == before
