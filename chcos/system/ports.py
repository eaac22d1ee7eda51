"""ports - what the system manager (TSK0) needs of its collaborators, as narrow protocols.

The composition root (:class:`chcos.system.embedded.System`) builds the kernel, the tables, the
message manager and the device table and hands them to :class:`chcos.system.manager.
SystemManager` at construction, with a :class:`Setup` saying where files are and how to start a
machine's drivers. The protocols below list the few operations the system manager uses of each,
so it depends on no ``System`` (no service locator, no import cycle).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from chcos.kernel.clock import Clock
from chcos.tables.messages import Link, TapPort
from chcos.tables.tasks import TaskEntry

if TYPE_CHECKING:
    from chcos.devices.entry import DeviceEntry
    from chcos.user.context import TaskContext


class Scheduler(Protocol):
    """The kernel: its clock, interrupts and idle hooks."""

    clock: Clock

    def add_idle_hook(self, hook: Callable[[], None]) -> None:
        """Call ``hook()`` each time the kernel goes idle."""

    def interrupt(self, handler: Callable[..., None], *args: Any) -> None:
        """Run ``handler(*args)`` on the kernel thread (callable from any thread)."""

    def stats(self) -> dict[str, int]:
        """Steps, ready tasks, timers, skipped timer periods, handler errors (for the map)."""
        ...


class Messages(Protocol):
    """The message manager, as the system manager drives it."""

    taps: list[tuple[TaskEntry, TapPort, dict[str, Link]]]

    def is_local(self, machine: int) -> bool:
        """True if ``machine`` runs in this process."""
        ...

    def resolve_path(self, name: str) -> Path:
        """The file an install argument names."""
        ...

    def event(self, kind: str, detail: str) -> None:
        """Report a system event."""

    def setpri(self, link: Link, prio: int) -> None:
        """Set ``link``'s priority now."""

    def open(self, link: Link, command: Any, *, wait: bool) -> bool:
        """topen on ``link``."""
        ...

    def close(self, link: Link) -> None:
        """tclose on ``link``."""

    def add_device_link(self, link: Link) -> None:
        """Fan the readings of ``link``'s source device out over ``link`` from now on."""
        ...

    def deliver(self, link: Link, value: Any) -> int:
        """Put ``value`` into ``link``'s destination port; 1 if taken, 0 if suspended."""
        ...

    def wipe(self, t: TaskEntry, why: str) -> None:
        """End ``t``'s activation and clear its state (reload)."""

    def start_standing(self, t: TaskEntry, why: str = "started") -> None:
        """Start standing task ``t``."""

    def suspend_task(self, t: TaskEntry, by: str) -> None:
        """Suspend ``t``."""

    def resume_task(self, t: TaskEntry) -> None:
        """Resume ``t``."""

    def resetpri(self, t: TaskEntry) -> int:
        """``t`` back to its owner's or default priority; returns it."""
        ...

    def reset_task(self, t: TaskEntry) -> bool:
        """The operator's reset of suspended task ``t``."""
        ...


@runtime_checkable
class NodeMaster(Protocol):
    """A driver that is the NMT master of its bus's nodes (the CANopen driver): the host's
    ``nmt`` command reaches it through this."""

    #: the bus it drives (its ``name``)
    bus: Any

    def node_states(self) -> Mapping[int, Any]:
        """Each node's status by node id."""
        ...

    def nmt(self, command: str, node: int) -> str:
        """Send NMT ``command`` (a host word) to ``node``; the answer. Raises BusError."""
        ...


class Devices(Protocol):
    """The device table, as the system manager sees it."""

    #: the running drivers (their ``bus.name`` says which bus)
    drivers: list[Any]

    def __contains__(self, name: object) -> bool:
        """Whether a device ``name`` exists."""
        ...

    def __iter__(self) -> Iterator[DeviceEntry]:
        """Every device entry."""
        ...

    def get(self, name: str) -> DeviceEntry:
        """The entry of device ``name``."""
        ...

    def add_health_listener(self, fn: Callable[[str, bool, str], None]) -> None:
        """Call ``fn(device, ok, cause)`` on every change of a device's health."""

    def write(self, device: str, value: Any, source: str = "host") -> None:
        """Command actuator ``device``."""

    def suspend(self, device: str) -> None:
        """Suspend a device."""

    def resume(self, device: str) -> None:
        """Resume a device."""

    def inject(self, device: str, value: Any) -> None:
        """Feed a reading to a sensor."""

    def stats_doc(self) -> dict[str, Any]:
        """The bus statistics, for the map."""
        ...

    def bus_status(self) -> dict[str, dict[str, Any]]:
        """What each bus's driver shows beyond the counters (CANopen nodes, the SYNC cycle),
        for the map."""
        ...


@dataclass
class Setup:
    """Where a system's files are and what the system manager calls outside the tables.

    ``task_path`` are the directories where bare task names are found; ``base_dir`` resolves
    relative names; ``map_path`` is where sysfile.map is written (None: nowhere); ``devmaps``
    the device-map files the system was loaded from; ``start_drivers(machines)`` starts the bus
    drivers of newly loaded machines; ``context(task)`` makes a task's user context;
    ``errors()`` lists the errors the system collected (for the map)."""

    task_path: list[Path]
    base_dir: Path
    map_path: Path | None
    devmaps: list[str]
    start_drivers: Callable[[Iterable[int]], None]
    context: Callable[[TaskEntry], TaskContext]
    errors: Callable[[], list[str]]
