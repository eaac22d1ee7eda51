"""ports - what the communications manager needs of its collaborators, as narrow protocols.

The composition root (:class:`chcos.system.embedded.System`) hands a
:class:`chcos.comm.manager.CommManager` its kernel, tables, message manager and device table
at construction; these protocols say which few operations of each it uses, so the
communications manager (layer 4) depends on no concrete higher layer and on no ``System``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Any, Protocol

from chcos.devices.entry import DeviceStatus
from chcos.kernel.clock import Clock
from chcos.kernel.scheduler import Timer
from chcos.tables.messages import Link, LinkStatus, TapPort
from chcos.tables.tasks import TaskEntry

if TYPE_CHECKING:
    from chcos.comm.payloads import OpenAnswer
    from chcos.devices.entry import DeviceEntry


class Scheduler(Protocol):
    """The kernel: its clock, timers, interrupts and idle hooks (all on the kernel thread)."""

    clock: Clock
    #: seconds spent idle on real time so far (see chcos.kernel.scheduler.Kernel.idle_time)
    idle_time: float

    def add_idle_hook(self, hook: Callable[[], None]) -> None:
        """Call ``hook()`` each time the kernel goes idle."""

    def call_later(self, delay: float, callback: Callable[[], None]) -> Timer:
        """Run ``callback`` once, ``delay`` seconds from now."""
        ...

    def interrupt(self, handler: Callable[..., None], *args: Any) -> None:
        """Run ``handler(*args)`` on the kernel thread (callable from any thread)."""


class Tasks(Protocol):
    """The task table, by name."""

    def get(self, name: str) -> TaskEntry:
        """The entry of task ``name``; raises TaskError if there is none."""
        ...


class Links(Protocol):
    """The message table: its links, indexed by link id."""

    links: list[Link]


class Messages(Protocol):
    """The message manager, as far as messages from other satellites reach it."""

    def deliver(self, link: Link, value: Any) -> int:
        """Put a sensory value into ``link``'s destination port; 1 if taken, 0 if suspended."""
        ...

    def deliver_tap(self, link: Link, tap: TapPort, source: str, value: Any) -> None:
        """Put ``source``'s tapped message into an exception task's tap."""

    def remote_open(self, link: Link, command: Any, wait: bool) -> OpenAnswer:
        """Run an ``open`` another satellite asked for."""
        ...

    def open_answer(self, link: Link, answer: OpenAnswer) -> None:
        """The target's satellite answered this satellite's ``open`` on ``link``."""

    def close(self, link: Link) -> None:
        """tclose on ``link`` for a caller on another satellite."""

    def remote_report(self, link: Link, status: LinkStatus, result: Any, error: str) -> None:
        """A completion or pre-emption on ``link`` from the target's satellite."""

    def world_answer(self, target: TaskEntry, topic: str, args: Sequence[Any]) -> Any:
        """What ``target``'s world model answers about ``topic``."""

    def ask_answered(self, qid: int, answer: Any, error: str | None) -> None:
        """The answer (or refusal) of remote query ``qid`` arrived."""

    def event(self, kind: str, detail: str) -> None:
        """Report a system event."""

    def satellite_lost(self, machine: int) -> int:
        """Machine ``machine`` died; returns how many owners were told."""
        ...

    def superseded(self, link: Link, n: int) -> None:
        """``n`` messages of ``link`` were replaced on the sender's satellite before they left:
        count them as sent and overwritten on this satellite's copy of the link."""


class Devices(Protocol):
    """The device table: statuses from other satellites, actuator commands, the e-stop."""

    def get(self, name: str) -> DeviceEntry:
        """The entry of device ``name``; raises DeviceError if there is none."""
        ...

    def __iter__(self) -> Iterator[DeviceEntry]:
        """Every device entry."""
        ...

    def set_status(self, device: str, status: DeviceStatus, reason: str) -> None:
        """Another satellite reports the status of one of its devices."""

    def estop(self, reason: str) -> int:
        """Write the safe value of every local actuator."""
        ...

    def write(self, device: str, value: Any, source: str = "host") -> None:
        """Command actuator ``device``."""


class LinkTransport(Protocol):
    """The part of :class:`chcos.comm.transport.Transport` the communications manager uses."""

    def subscribe(self, key_expr: str, callback: Callable[[str, bytes], object],
                  roles: frozenset[str] | None = None) -> Closable:
        """Call ``callback(key, payload)`` for each message on ``key_expr``."""
        ...

    def watch(self, key_expr: str, on_join: Callable[[str], object],
              on_leave: Callable[[str], object]) -> Closable:
        """Watch liveliness tokens matching ``key_expr`` come and go."""
        ...

    def announce(self, token_key: str) -> Closable:
        """Declare a liveliness token."""
        ...

    def publish(self, key: str, payload: bytes, *, priority: int, kind: Any,
                express: bool | None = None) -> None:
        """Send ``payload`` to the subscribers of ``key``."""


class Closable(Protocol):
    """A declared subscriber, token or watcher."""

    def close(self) -> None:
        """Undeclare it."""
