"""coverage - device-state coverage: which states of its catalogue (:mod:`chcos.hil.catalogue`)
each device, bus and task of a cell reached in a set of tests, and which tests reached each.

:class:`CellCoverage` is the :class:`chcos.hil.observe.Sink` of one cell in one test: it turns
the records of the cell's observer into states reached (a failure and its cause class, a stale
sensor, a recovery, a safe value and why, a CANopen node's NMT state, boot-up, reboot and EMCY,
a CiA 402 axis's state and fault code, a bus's state and errors, a task's abnormal end, restart
and pre-emption). :class:`Coverage` gathers the cells of a session: the catalogue of every
subject any test's cell used, the states reached with the test ids that reached each (also
states outside the catalogue, shown but not counted), the share of the catalogue reached, the
JSON file (:meth:`Coverage.to_json`; :meth:`Coverage.merge_json` adds another's, as pytest-xdist
workers send theirs) and the terminal table (:func:`table_lines`).
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from chcos.hil.catalogue import (
    CIA402_STATES,
    STATUS_FAILED,
    STATUS_OK,
    STATUS_RECOVERED,
    STATUS_STALE,
    State,
    StateClass,
    Subject,
    SubjectKind,
    bus_subjects,
    device_subjects,
    is_axis,
    task_subject,
)
from chcos.hil.observe import Kind, Record

if TYPE_CHECKING:
    from chcos.system.embedded import System

FORMAT = "chcos-coverage 1"
"""The ``format`` of a coverage file."""
_NODE = re.compile(r"node (\d+)")
_EMCY_CODE = re.compile(r"EMCY\D*?0x([0-9A-Fa-f]{4})\b")
_ABORT_CODE = re.compile(r"0x([0-9A-Fa-f]{8})\b")
#: heartbeat NMT names (drivers.canopen_lifecycle.NmtState) as the catalogue names them
_NMT_NAMES = {"PRE_OPERATIONAL": "PRE-OPERATIONAL", "OPERATIONAL": "OPERATIONAL",
              "STOPPED": "STOPPED", "BOOT_UP": "boot-up"}
#: the driver's lifecycle of a node (drivers.canopen_lifecycle.NodeLifecycle names) as NMT
#: states: OPERATIONAL after the NMT start (confirmed by a heartbeat where there is one), held
#: in PRE-OPERATIONAL
_LIFECYCLE_NMT = {"OPERATIONAL": "OPERATIONAL", "PREOP_HELD": "PRE-OPERATIONAL"}
#: bus errors of a CANopen node that are its devices' states (NMT, EMCY), not the bus's
_NODE_ERRORS = frozenset({"emcy", "boot-up"})


@dataclass
class Hits:
    """The states one cell reached: per subject key, each state with what more is known of it
    (EMCY codes, SDO abort codes, CiA 402 fault codes)."""

    states: dict[str, dict[State, set[str]]] = field(default_factory=dict)

    def add(self, key: str, state: State, detail: str = "") -> None:
        """``key`` reached ``state`` (with ``detail``, if any)."""
        details = self.states.setdefault(key, {}).setdefault(state, set())
        if detail:
            details.add(detail)


class CellCoverage:
    """The sink of one cell's observer in one test (``test_id``): the states the cell reached.
    :meth:`subjects` is the cell's catalogue (its tasks as installed by then)."""

    def __init__(self, system: System, test_id: str) -> None:
        self.system = system
        self.test_id = test_id
        self.hits = Hits()
        devmap = system.devmap
        self._devices = device_subjects(devmap)
        self._buses = bus_subjects(devmap)
        #: device name -> its subject's key (an axis's sensors -> the axis)
        self._subject = {d: s.key for s in self._devices for d in s.devices}
        #: (bus, node id) -> the subject keys of the node's devices
        self._node: dict[tuple[str, int], list[str]] = {}
        kinds = {b.name: b.kind for b in devmap.buses}
        for spec in devmap.devices:
            if kinds.get(spec.bus) == "canopen" and "node" in spec.address:
                keys = self._node.setdefault((spec.bus, int(spec.address["node"])), [])
                if self._subject[spec.name] not in keys:
                    keys.append(self._subject[spec.name])
        self._ready: set[tuple[str, int]] = set()
        self._bus_kind = kinds
        #: the CiA 402 sensors and what each shows (``state``, ``fault``...)
        self._axis_reading = {spec.name: str(spec.address.get("reading"))
                              for spec in devmap.devices
                              if is_axis(spec) and spec.direction == "sensor"}

    def subjects(self) -> list[Subject]:
        """The catalogue of the cell: its devices, buses and tasks."""
        tasks = [task_subject(t.name, t.level, t.restart) for t in self.system.tsktab]
        return [*self._devices, *self._buses, *tasks]

    def _dev(self, device: str, cls: StateClass, name: str, detail: str = "") -> None:
        key = self._subject.get(device)
        if key is not None:
            self.hits.add(key, State(cls, name), detail)

    def record(self, rec: Record) -> None:
        """Turn one record into the states it shows reached."""
        handler = _HANDLERS.get(rec.kind)
        if handler is not None:
            handler(self, rec)

    def _value(self, rec: Record) -> None:
        self._dev(rec.subject, StateClass.STATUS, STATUS_OK)
        reading = self._axis_reading.get(rec.subject)
        if reading is None:
            return
        if reading == "state" and rec.value in CIA402_STATES:
            self._dev(rec.subject, StateClass.CIA402, str(rec.value))
        elif reading == "fault" and rec.value:
            code = f"0x{int(rec.value):04X}" if isinstance(rec.value, int) else str(rec.value)
            self._dev(rec.subject, StateClass.CIA402, "FAULT", f"0x603F {code}")

    def _status(self, rec: Record) -> None:
        if rec.value == "failed":
            self._dev(rec.subject, StateClass.STATUS, STATUS_FAILED)
            detail = ""
            if rec.cause == "sdo-abort" and (m := _ABORT_CODE.search(rec.text)) is not None:
                detail = f"0x{m.group(1).upper()}"
            self._dev(rec.subject, StateClass.FAILURE, rec.cause, detail)
        elif rec.value == "stale":
            self._dev(rec.subject, StateClass.STATUS, STATUS_STALE)
        elif rec.value == "OK" and rec.cause == "recovered":
            self._dev(rec.subject, StateClass.STATUS, STATUS_RECOVERED)
        elif rec.value == "suspended":
            self._dev(rec.subject, StateClass.STATUS, "suspended")

    def _command(self, rec: Record) -> None:
        if rec.cause.startswith("safe:"):
            self._dev(rec.subject, StateClass.SAFE, rec.cause[len("safe:"):])

    def _confirmed(self, rec: Record) -> None:
        self._dev(rec.subject, StateClass.STATUS, STATUS_OK)

    def _write_failed(self, rec: Record) -> None:
        self._dev(rec.subject, StateClass.STATUS, "write failed")

    def _bus_error(self, rec: Record) -> None:
        bus, kind = rec.subject, str(rec.value)
        key = f"{SubjectKind.BUS}:{bus}"
        canopen = self._bus_kind.get(bus) == "canopen"
        if kind in ("bus-off", "error-passive", "disconnected"):
            self.hits.add(key, State(StateClass.BUS_STATE, kind))
        elif not (canopen and kind in _NODE_ERRORS):
            self.hits.add(key, State(StateClass.BUS_ERRORS, kind))
        m = _NODE.search(rec.text) if canopen else None
        if m is None:
            return
        node = (bus, int(m.group(1)))
        if kind == "emcy":
            code = _EMCY_CODE.search(rec.text)
            reset = code is not None and int(code.group(1), 16) == 0
            for k in self._node.get(node, ()):
                self.hits.add(k, State(StateClass.EMCY, "error reset" if reset else "EMCY"),
                              "" if code is None or reset else f"0x{code.group(1).upper()}")
        elif kind == "boot-up":
            for k in self._node.get(node, ()):
                self.hits.add(k, State(StateClass.NMT, "boot-up"))
                if node in self._ready:
                    self.hits.add(k, State(StateClass.NMT, "reboot"))

    def _event(self, rec: Record) -> None:
        state = {"abnormal": "abnormal end", "restart": "restart",
                 "preempt": "pre-empted"}.get(str(rec.value))
        if state is not None:
            self.hits.add(f"{SubjectKind.TASK}:{rec.subject}", State(StateClass.TASK, state))

    def _node_state(self, rec: Record) -> None:
        bus, _, nid = rec.subject.rpartition("/")
        try:
            node = (bus, int(nid))
        except ValueError:
            return
        keys = self._node.get(node, ())
        if rec.cause == "nmt" and str(rec.value) in _NMT_NAMES:
            for k in keys:
                self.hits.add(k, State(StateClass.NMT, _NMT_NAMES[str(rec.value)]))
        elif rec.cause == "state" and str(rec.value) in _LIFECYCLE_NMT:
            for k in keys:
                self.hits.add(k, State(StateClass.NMT, _LIFECYCLE_NMT[str(rec.value)]))
        elif rec.cause == "boots" and isinstance(rec.value, int) and rec.value > 0:
            for k in keys:
                self.hits.add(k, State(StateClass.NMT, "boot-up"))
        elif rec.cause == "ready" and rec.value is True:
            self._ready.add(node)

    def _bus_state(self, rec: Record) -> None:
        key = f"{SubjectKind.BUS}:{rec.subject}"
        if rec.cause == "reconnects":
            self.hits.add(key, State(StateClass.BUS_STATE, "reconnected"))
        elif rec.cause == "controller" and rec.value not in ("error-active", "error-warning"):
            self.hits.add(key, State(StateClass.BUS_STATE, str(rec.value)))


_HANDLERS = {Kind.VALUE: CellCoverage._value, Kind.STATUS: CellCoverage._status,
             Kind.COMMAND: CellCoverage._command, Kind.CONFIRMED: CellCoverage._confirmed,
             Kind.WRITE_FAILED: CellCoverage._write_failed, Kind.BUS_ERROR: CellCoverage._bus_error,
             Kind.EVENT: CellCoverage._event, Kind.NODE: CellCoverage._node_state,
             Kind.BUS_STATE: CellCoverage._bus_state}


# ---- the session ------------------------------------------------------------------------------
@dataclass
class StateEntry:
    """One state of a subject in the session: catalogued or not, the tests that reached it,
    what more is known (codes)."""

    state: State
    catalogued: bool
    tests: set[str] = field(default_factory=set)
    details: set[str] = field(default_factory=set)


@dataclass
class SubjectEntry:
    """One subject of the session and its states (catalogue first, in its order)."""

    subject: Subject
    states: dict[State, StateEntry] = field(default_factory=dict)

    def entry(self, state: State) -> StateEntry:
        """The entry of ``state`` (made, outside the catalogue, if it is new)."""
        e = self.states.get(state)
        if e is None:
            e = self.states[state] = StateEntry(state, False)
        return e


class Coverage:
    """Device-state coverage of a session (see the module doc)."""

    def __init__(self) -> None:
        self.subjects: dict[str, SubjectEntry] = {}
        self.tests: set[str] = set()

    def add_cell(self, cell: CellCoverage) -> None:
        """Add one cell: its catalogue, and what it reached in its test."""
        self.tests.add(cell.test_id)
        self.add(cell.subjects(), cell.hits, cell.test_id)

    def add(self, subjects: Iterable[Subject], hits: Hits, test_id: str) -> None:
        """Add a catalogue and the states ``test_id`` reached."""
        for s in subjects:
            se = self.subjects.get(s.key)
            if se is None:
                se = self.subjects[s.key] = SubjectEntry(s)
            for st in s.states:
                if st not in se.states or not se.states[st].catalogued:
                    old = se.states.get(st)
                    se.states[st] = StateEntry(st, True, old.tests if old else set(),
                                               old.details if old else set())
        for key, states in hits.states.items():
            se = self.subjects.get(key)
            if se is None:
                kind, _, name = key.partition(":")
                se = self.subjects[key] = SubjectEntry(Subject(SubjectKind(kind), name, ""))
            for st, details in states.items():
                e = se.entry(st)
                e.tests.add(test_id)
                e.details |= details

    def counts(self) -> tuple[int, int]:
        """(catalogued states reached, catalogued states)."""
        states = [e for se in self.subjects.values() for e in se.states.values()
                  if e.catalogued]
        return sum(1 for e in states if e.tests), len(states)

    def share(self) -> float:
        """Percent of the catalogue reached (100 for an empty catalogue)."""
        reached, total = self.counts()
        return 100.0 * reached / total if total else 100.0

    # ---- the file ---------------------------------------------------------------------------
    def to_json(self, root: Path | None = None) -> dict[str, Any]:
        """The coverage as plain data (the file's content); map paths relative to ``root``."""
        reached, total = self.counts()
        groups: dict[str, dict[str, Any]] = {"devices": {}, "buses": {}, "tasks": {}}
        for se in self.subjects.values():
            s = se.subject
            group = {SubjectKind.DEVICE: "devices", SubjectKind.BUS: "buses",
                     SubjectKind.TASK: "tasks"}[s.kind]
            groups[group][s.name] = {
                "role": s.role, "bus": s.bus, "bus_kind": s.bus_kind, "map": _rel(s.file, root),
                "devices": list(s.devices),
                "states": [{"class": str(e.state.cls), "state": e.state.name,
                            "catalogued": e.catalogued, "reached": bool(e.tests),
                            "tests": sorted(e.tests), "details": sorted(e.details)}
                           for e in ordered_states(se)]}
        return {"format": FORMAT, "tests": sorted(self.tests), "catalogued": total,
                "reached": reached, "share": round(self.share(), 2), **groups}

    def merge_json(self, doc: dict[str, Any]) -> None:
        """Add a coverage file's content (another process's: a pytest-xdist worker's)."""
        self.tests |= set(doc.get("tests", ()))
        for group, kind in (("devices", SubjectKind.DEVICE), ("buses", SubjectKind.BUS),
                            ("tasks", SubjectKind.TASK)):
            for name, s in doc.get(group, {}).items():
                states = [State(StateClass(x["class"]), x["state"]) for x in s["states"]
                          if x["catalogued"]]
                subject = Subject(kind, name, s.get("role", ""), s.get("bus", ""),
                                  s.get("bus_kind", ""), s.get("map", ""), tuple(states),
                                  tuple(s.get("devices", ())))
                self.add([subject], Hits(), "")
                se = self.subjects[subject.key]
                for x in s["states"]:
                    e = se.entry(State(StateClass(x["class"]), x["state"]))
                    e.tests |= set(x["tests"])
                    e.details |= set(x["details"])
        self.tests.discard("")


def _rel(path: str, root: Path | None) -> str:
    if not path or root is None or path.startswith("<"):
        return path
    try:
        return str(Path(path).resolve().relative_to(root.resolve()))
    except ValueError:
        return path


def ordered_states(se: SubjectEntry) -> list[StateEntry]:
    """The states of a subject: the catalogue in its order, then the others by class."""
    order = {st: i for i, st in enumerate(se.subject.states)}
    return sorted(se.states.values(),
                  key=lambda e: (not e.catalogued, order.get(e.state, 0),
                                 list(StateClass).index(e.state.cls), e.state.name))


# ---- the terminal -----------------------------------------------------------------------------
def table_lines(cov: Coverage, verbose: bool = False) -> list[str]:
    """The terminal summary: one row per subject and one column per state class, each cell
    ``reached/catalogued`` (``+n``: states reached outside the catalogue), then the share; with
    ``verbose``, each subject's states not reached and reached outside the catalogue."""
    classes = [c for c in StateClass
               if any(e.state.cls is c for se in cov.subjects.values()
                      for e in se.states.values())]
    width = max([len(_label(se)) for se in cov.subjects.values()] + [7])
    cols = [max(len(str(c)), 5) for c in classes]
    out = ["  ".join([f"{'subject':<{width}}", *(f"{c!s:>{w}}" for c, w in zip(classes, cols,
                                                                                 strict=True))])]
    for se in sorted(cov.subjects.values(), key=_row_order):
        cells = []
        for c, w in zip(classes, cols, strict=True):
            mine = [e for e in se.states.values() if e.state.cls is c]
            cat = [e for e in mine if e.catalogued]
            extra = sum(1 for e in mine if not e.catalogued and e.tests)
            text = (f"{sum(1 for e in cat if e.tests)}/{len(cat)}" if cat else
                    "-" if not extra else "")
            cells.append(f"{text + (f' +{extra}' if extra else ''):>{w}}")
        out.append("  ".join([f"{_label(se):<{width}}", *cells]))
        if verbose:
            missing = [f"{e.state}" for e in ordered_states(se) if e.catalogued and not e.tests]
            beyond = [f"{e.state}" for e in ordered_states(se) if not e.catalogued and e.tests]
            if missing:
                out.append(f"{'':<{width}}  not reached: {', '.join(missing)}")
            if beyond:
                out.append(f"{'':<{width}}  reached outside the catalogue: {', '.join(beyond)}")
    reached, total = cov.counts()
    out.append(f"device-state coverage: {reached} of {total} catalogued states reached "
               f"({cov.share():.1f} %) by {len(cov.tests)} test(s)")
    return out


def _label(se: SubjectEntry) -> str:
    s = se.subject
    return f"{s.kind} {s.name}" + (f" ({s.role})" if s.role else "")


def _row_order(se: SubjectEntry) -> tuple[int, str]:
    return list(SubjectKind).index(se.subject.kind), se.subject.name
