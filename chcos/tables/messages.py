"""messages - the message table (Msgtab), its links, and the input ports that hold their messages.

A link joins a source to a destination and is either *sensory* (upward: sensor, file or lower task
to a higher task) or *command* (downward: task to lower task, actuator or file). Each has a priority
0..99 and a status (Appendix 3). A sensory message waits in the destination's input port, where a
newer message overwrites an unread older one ("yesterday's newspaper"); a link declared *queued*
keeps a bounded FIFO instead and refuses a message when full.
"""

from __future__ import annotations

import enum
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from chcos.errors import MessageError, QueueOverflow

#: Every priority a link, a task or a device's interrupt may have (thesis: 0..99); checked as
#: ``p in PRIORITIES`` wherever a priority comes in.
PRIORITIES = range(0, 100)
#: The range as messages write it.
PRIORITY_TEXT = f"{PRIORITIES[0]}..{PRIORITIES[-1]}"
#: Default link priorities: sensory links run their receivers above command links (thesis 5.2).
DEFAULT_SENSORY_PRIORITY = 8
DEFAULT_COMMAND_PRIORITY = 4
#: The priority of exception taps and assassin links: above everything else.
TOP_PRIORITY = PRIORITIES[-1]
PORTS = 8


class LinkType(enum.Enum):
    """Sensory messages only go up, command messages only go down."""

    SENSORY = "sensory"
    COMMAND = "command"


class LinkStatus(enum.Enum):
    """Msgtab status values (Appendix 3), as ``msgstat`` reports them."""

    OK = "OK"
    SUSPENDED = "suspended"
    PREEMPTED = "pre-empted"
    NORMAL = "normal completion"
    ABNORMAL = "abnormal completion"


class EndpointKind(enum.Enum):
    """What a link end is."""

    TASK = "task"
    DEVICE = "device"
    FILE = "file"
    HOST = "host"


@dataclass(frozen=True)
class Completion:
    """What ``done``/``call`` return: how a command message ended, and with what."""

    status: LinkStatus
    result: Any = None
    error: str = ""

    @property
    def ok(self) -> bool:
        """True for a normal completion."""
        return self.status is LinkStatus.NORMAL


@dataclass(eq=False, slots=True)
class Link:
    """One Msgtab entry."""

    lid: int
    src: str
    dst: str
    type: LinkType
    priority: int
    src_kind: EndpointKind
    dst_kind: EndpointKind
    src_machine: int = 0
    dst_machine: int = 0
    queued: int = 0  # 0: newest wins; n > 0: FIFO of at most n messages
    tap: bool = False  # an implicit link: exception tap, assassin or host link
    remote: bool = False  # the destination lives on another satellite (set at install)
    _status: LinkStatus = LinkStatus.OK  # see :attr:`status`
    port: InPort | None = None  # where sensory messages to a task land (install)
    src_port: int = -1  # index in the source task's out_links (command links)
    dst_port: int = -1  # index in the destination task's in_ports (sensory links)
    # command-link state
    pending: bool = False  # the caller waits for a reply (in the target's wait queue)
    reported: bool = False  # a completion/pre-emption is there for ``done`` to pick up
    result: Any = None
    error: str = ""
    # statistics (sent = delivered + overwritten + unread + discarded on the destination's
    # satellite; refused messages were never taken)
    sent: int = 0
    overwritten: int = 0
    refused: int = 0
    discarded: int = 0  # unread messages dropped when the receiving task was reset
    suspended: bool = False  # status is SUSPENDED (kept by the status setter)

    def set_priority(self, priority: int) -> None:
        """Change the link's priority (setpri, resetpri, an invoke at a priority)."""
        self.priority = priority

    @property
    def status(self) -> LinkStatus:
        """OK, SUSPENDED, or how the last command message on the link ended."""
        return self._status

    @status.setter
    def status(self, status: LinkStatus) -> None:
        self._status = status
        self.suspended = status is LinkStatus.SUSPENDED

    @property
    def delivered(self) -> int:
        """Messages the receiver has taken: on a sensory link into a local input port, what
        was sent and neither overwritten, discarded nor is still unread; on a command link to
        an actuator or a file, what was sent (written at once); 0 on any other link here (the
        task's own satellite counts a remote link's)."""
        port = self.port
        if port is not None and not self.remote:
            # max: a reader on another thread may see sent before the unread message it made
            return max(0, self.sent - self.overwritten - self.discarded - port.unread())
        if self.dst_kind is EndpointKind.DEVICE or self.dst_kind is EndpointKind.FILE:
            return self.sent
        return 0

    @property
    def name(self) -> str:
        """``SRC/DST``, as the thesis writes links (``S1/A1``)."""
        return f"{self.src}/{self.dst}"

    def completion(self) -> Completion:
        """The link's status as a :class:`Completion`."""
        return Completion(self.status, self.result, self.error)

    def __repr__(self) -> str:
        return f"<link {self.name} {self.type.value} p{self.priority} {self.status.value}>"


class InPort:
    """One of a task's eight input ports, on a newest-wins link: the newest unread message (a
    newer one overwrites it). A queued link's port is a :class:`QueuedInPort` (make either with
    :func:`in_port`). ``reader`` is the task it belongs to (its only reader); whether that task
    waits for it is the task's own record (``TaskEntry.wait_ports``)."""

    __slots__ = ("device", "fresh", "index", "link", "reader", "sent_at", "value")

    def __init__(self, link: Link, index: int, reader: Any) -> None:
        self.link = link
        self.index = index
        # the TaskEntry this port belongs to (chcos.tables.tasks imports this module, so the
        # type is not named: the task table sits on the message table, not beside it)
        self.reader: Any = reader
        self.device = link.src_kind is EndpointKind.DEVICE
        self.value: Any = None
        #: True while a message is unread
        self.fresh = False
        #: when the unread message was sent (after :meth:`take`: the one taken), None when no
        #: instrument measured it
        self.sent_at: float | None = None

    def store(self, value: Any, sent_at: float | None) -> bool:
        """Put a message in, sent at clock time ``sent_at`` (None: not measured, no instrument
        listens to deliveries); True if it overwrote an unread one."""
        over = self.fresh
        self.value = value
        self.fresh = True
        self.sent_at = sent_at
        return over

    def take(self) -> Any:
        """Remove and return the message, leaving the time it was sent in :attr:`sent_at`;
        raises MessageError if there is none."""
        if not self.fresh:
            raise MessageError(f"no message on {self.link.name}")
        self.fresh = False
        value = self.value
        self.value = None
        return value

    def head(self) -> Any:
        """The message :meth:`take` would return, left in place (None if there is none)."""
        return self.value

    def unread(self) -> int:
        """How many messages wait here."""
        return 1 if self.fresh else 0

    def discard(self) -> int:
        """Drop every unread message; returns how many."""
        n = self.unread()
        self.fresh = False
        self.value = None
        return n


class QueuedInPort(InPort):
    """An input port on a queued link: a FIFO of at most ``link.queued`` unread messages,
    refusing a message when full."""

    __slots__ = ("fifo",)

    def __init__(self, link: Link, index: int, reader: Any) -> None:
        super().__init__(link, index, reader)
        self.fifo: deque[tuple[Any, float | None]] = deque()

    def store(self, value: Any, sent_at: float | None) -> bool:
        """Queue a message sent at clock time ``sent_at`` (None: not measured); never
        overwrites (False). Raises QueueOverflow when the link's FIFO is full (the message is
        refused, nothing is lost silently)."""
        fifo = self.fifo
        if len(fifo) >= self.link.queued:
            self.link.refused += 1
            raise QueueOverflow(
                f"queued link {self.link.name} is full ({self.link.queued} messages unread)")
        fifo.append((value, sent_at))
        self.fresh = True
        return False

    def take(self) -> Any:
        """Remove and return the oldest unread message, leaving the time it was sent in
        :attr:`sent_at`; raises MessageError if there is none."""
        if not self.fresh:
            raise MessageError(f"no message on {self.link.name}")
        fifo = self.fifo
        value, self.sent_at = fifo.popleft()
        self.fresh = bool(fifo)
        return value

    def head(self) -> Any:
        """The oldest unread message, left in place (None if there is none)."""
        return self.fifo[0][0] if self.fifo else None

    def unread(self) -> int:
        """How many messages wait here."""
        return len(self.fifo)

    def discard(self) -> int:
        """Drop every unread message; returns how many."""
        n = len(self.fifo)
        self.fifo.clear()
        self.fresh = False
        return n


def in_port(link: Link, index: int, reader: Any) -> InPort:
    """Input port ``index`` of task ``reader`` for sensory ``link``: a :class:`QueuedInPort`
    if the link is queued, else a newest-wins :class:`InPort`."""
    return QueuedInPort(link, index, reader) if link.queued else InPort(link, index, reader)


class TapPort:
    """The exception task's tap: the newest unread message of each lower task, in arrival order."""

    __slots__ = ("newest", "order", "waiter")

    def __init__(self) -> None:
        self.newest: dict[str, tuple[Any, float]] = {}
        self.order: deque[str] = deque()
        self.waiter: Any = None  # the exception task's TaskEntry while it waits (see InPort)

    @property
    def fresh(self) -> bool:
        """True when a message is unread."""
        return bool(self.order)

    def store_from(self, source: str, value: Any, now: float) -> bool:
        """Keep ``value`` as ``source``'s newest message; True if it overwrote an unread one."""
        over = source in self.newest
        if not over:
            self.order.append(source)
        self.newest[source] = (value, now)
        return over

    def take(self) -> tuple[str, Any, float]:
        """Remove and return the oldest unread (source, message, time sent)."""
        src = self.order.popleft()
        value, at = self.newest.pop(src)
        return src, value, at

    def take_from(self, source: str) -> tuple[str, Any, float]:
        """Remove and return ``source``'s unread (source, message, time sent); raises KeyError
        if there is none."""
        value, at = self.newest.pop(source)
        self.order.remove(source)
        return source, value, at


@dataclass
class Msgtab:
    """The message table: every link in the system, by id and by (source, destination, type)."""

    links: list[Link] = field(default_factory=list)
    _index: dict[tuple[str, str, LinkType], Link] = field(default_factory=dict)

    def add(self, link: Link) -> None:
        """Enter ``link``; raises MessageError if the same link exists."""
        key = (link.src, link.dst, link.type)
        if key in self._index:
            raise MessageError(f"link {link.name} ({link.type.value}) already exists")
        self.links.append(link)
        self._index[key] = link

    def next_lid(self) -> int:
        """The id the next link will get."""
        return len(self.links)

    def find(self, src: str, dst: str, type: LinkType | None = None) -> Link:
        """The link from ``src`` to ``dst`` (of ``type`` if given, else the only one).

        Raises MessageError naming the pair if there is no such link, or if ``type`` is None and
        both a sensory and a command link join them in that direction.
        """
        if type is not None:
            link = self._index.get((src, dst, type))
            if link is None:
                raise MessageError(f"no {type.value} link {src}/{dst}")
            return link
        found = [lk for t in LinkType if (lk := self._index.get((src, dst, t))) is not None]
        if not found:
            raise MessageError(f"no link {src}/{dst}")
        if len(found) > 1:
            raise MessageError(f"{src}/{dst} names a sensory and a command link; give the type")
        return found[0]

    def get(self, src: str, dst: str, type: LinkType) -> Link | None:
        """The link or None."""
        return self._index.get((src, dst, type))

    def __iter__(self) -> Iterator[Link]:
        return iter(self.links)

    def __len__(self) -> int:
        return len(self.links)
