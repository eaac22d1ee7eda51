"""status - what a driver knows of its bus beyond the bus statistics, typed: its remote nodes, its
SYNC cycle, its controller's error state and the messages it sends every cycle.

:class:`DriverStatus` is what :meth:`chcos.devices.driver.Driver.status` returns and what the
consumers (the run summary, the system map's text view, metrics, OPC UA) read; it becomes JSON
only at the edge (:meth:`DriverStatus.to_json`: the system map, a snapshot for another process)
and is read back there with :meth:`DriverStatus.from_json`, which refuses a document it does not
know (naming the key) rather than guessing.
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class NodeStatus:
    """One remote node with a life of its own (a CANopen node's lifecycle): its state name,
    whether it is ready for its devices, and what happened to it so far."""

    node: int
    state: str
    ready: bool
    #: OPERATIONAL (or what it must reach) confirmed by its heartbeat
    confirmed: bool = False
    #: the NMT state of its last heartbeat (None: none heard)
    nmt: str | None = None
    boots: int = 0
    nmt_starts: int = 0
    heartbeat_losses: int = 0
    emcys: int = 0
    #: configurations stored in its flash (``store_config``)
    config_stores: int = 0
    #: object 0x1001 as last read or carried by an EMCY (None: unknown)
    error_register: int | None = None
    last_emcy: str | None = None
    #: why it is not ready ("" when it is)
    reason: str = ""
    heartbeat_lost: bool = False
    #: restarts of its recovery policy since its last boot (a CANopen node that left
    #: OPERATIONAL by itself)
    restarts: int = 0


@dataclass(frozen=True)
class SyncStatus:
    """A SYNC cycle's counters and jitter (seconds) so far."""

    period: float
    cycles: int
    complete: int
    missing: int
    late: int
    jitter_p50: float
    jitter_p99: float
    jitter_max: float
    #: RPDO answers to cycle n that went out after SYNC n+1
    late_writes: int = 0
    #: acyclic synchronous TPDOs (transmission type 0) received
    acyclic: int = 0
    #: cycles the producer gave up (a stall, a controller making no progress), not caught up
    given_up: int = 0


class ErrorState(enum.StrEnum):
    """A CAN controller's fault confinement state (ISO 11898-1)."""

    ERROR_ACTIVE = "error-active"
    ERROR_WARNING = "error-warning"     # a counter reached 96: still error-active
    ERROR_PASSIVE = "error-passive"     # a counter reached 128: sends, passive error flags
    BUS_OFF = "bus-off"                 # the transmit counter passed 255: off the bus


@dataclass(frozen=True)
class BusState:
    """A bus controller's error state and its error counters (None: the interface does not
    tell them), with how often it went bus-off, error-passive and was restarted, and the error
    frames that told it."""

    state: ErrorState
    tx_errors: int | None = None
    rx_errors: int | None = None
    bus_offs: int = 0
    error_passive: int = 0
    restarts: int = 0
    error_frames: int = 0
    #: what the last error frame said ("" before the first)
    last: str = ""


@dataclass(frozen=True)
class CyclicStatus:
    """One message the driver sends every cycle (chcos' own cyclic CAN message): its name,
    period (seconds), whether its first command started it, and the frames sent so far where
    the driver sends them itself (None: the interface's periodic sender does)."""

    message: str
    period: float
    started: bool = False
    frames: int | None = None


@dataclass(frozen=True)
class DriverStatus:
    """What a driver shows beyond the counters; empty (false) when it has nothing to show."""

    nodes: tuple[NodeStatus, ...] = ()
    sync: SyncStatus | None = None
    bus_state: BusState | None = None
    cyclic: tuple[CyclicStatus, ...] = ()

    def __bool__(self) -> bool:
        return (bool(self.nodes) or self.sync is not None or self.bus_state is not None
                or bool(self.cyclic))

    def to_json(self) -> dict[str, Any]:
        """The JSON document (only the parts there are): ``nodes`` a list of objects, ``sync``
        and ``bus_state`` objects, the error state by its value."""
        doc: dict[str, Any] = {}
        if self.nodes:
            doc["nodes"] = [dataclasses.asdict(n) for n in self.nodes]
        if self.sync is not None:
            doc["sync"] = dataclasses.asdict(self.sync)
        if self.bus_state is not None:
            doc["bus_state"] = {**dataclasses.asdict(self.bus_state),
                                "state": self.bus_state.state.value}
        if self.cyclic:
            doc["cyclic"] = [dataclasses.asdict(c) for c in self.cyclic]
        return doc

    @classmethod
    def from_json(cls, doc: Mapping[str, Any]) -> DriverStatus:
        """The status a :meth:`to_json` document (or a driver's ``status_doc``) describes.
        Raises ValueError naming the key that is unknown, missing or of the wrong kind."""
        _known(doc, ("nodes", "sync", "bus_state", "cyclic"), "status")
        nodes = tuple(_build(NodeStatus, n, f"nodes[{i}]")
                      for i, n in enumerate(doc.get("nodes") or ()))
        cyclic = tuple(_build(CyclicStatus, c, f"cyclic[{i}]")
                       for i, c in enumerate(doc.get("cyclic") or ()))
        sync = doc.get("sync")
        state = doc.get("bus_state")
        if state is not None:
            state = _build(BusState, {**_table(state, "bus_state"),
                                      "state": _error_state(state.get("state"))}, "bus_state")
        return cls(nodes, None if sync is None else _build(SyncStatus, sync, "sync"), state,
                   cyclic)


def _table(v: Any, key: str) -> Mapping[str, Any]:
    if not isinstance(v, Mapping):
        raise ValueError(f"driver status {key}: expected an object, got {v!r}")
    return v


def _known(doc: Any, keys: tuple[str, ...], key: str) -> None:
    extra = sorted(set(_table(doc, key)) - set(keys))
    if extra:
        raise ValueError(f"driver status {key}: unknown key {extra[0]!r}; expected one of "
                         f"{', '.join(keys)}")


def _error_state(v: Any) -> ErrorState:
    try:
        return ErrorState(v)
    except ValueError:
        raise ValueError(f"driver status bus_state.state: expected one of "
                         f"{', '.join(s.value for s in ErrorState)}, got {v!r}") from None


def _build(kind: type[Any], doc: Any, key: str) -> Any:
    names = tuple(f.name for f in dataclasses.fields(kind))
    _known(doc, names, key)
    try:
        return kind(**doc)
    except TypeError as exc:    # a required field missing
        raise ValueError(f"driver status {key}: {exc}") from None
