"""tasks - the task table (Tsktab): one entry per installed feedback loop, and its states.

A task is installed once and never terminated (thesis 6 intro). Each *activation* of a task is one
run of its ``async def`` body for one command (``topen``/``invoke`` with parameters); between
activations the task is SUSPENDED. The entry keeps what Appendix 3's Tsktab lists: name, machine,
status, owner message, priority and sleep time, plus the ports of its Usrtab.
"""

from __future__ import annotations

import enum
from collections.abc import Awaitable, Callable, Coroutine, Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

from chcos.errors import TaskError
from chcos.tables.messages import InPort, Link, TapPort

TaskFunc = Callable[..., Awaitable[Any]]


class Cancellable(Protocol):
    """A pending timer as the table keeps it (a :class:`chcos.kernel.scheduler.Timer`; the
    kernel sits above the tables, so it is not named here)."""

    def cancel(self) -> None:
        """Stop the timer from firing."""


class Model(Protocol):
    """What the tables and the managers ask of a task's world model (a
    :class:`chcos.user.worldmodel.WorldModel`; the user layer sits above the tables)."""

    def answer(self, topic: str, *args: Any) -> Any:
        """The model's answer to a query about ``topic``."""

    def snapshot(self) -> dict[str, dict[str, Any]]:
        """The model's contents as plain data."""


#: What the kernel calls to end a wait: ``unwait(task)`` forgets whatever the layer that
#: blocked ``task`` registered (ports, links, queries); set by that layer when it blocks it.
Unwait = Callable[["TaskEntry"], None]


class TaskState(enum.Enum):
    """Tsktab status values (Appendix 3)."""

    CURRENT = "current"
    READY = "ready"
    SUSPENDED = "suspended"
    WAITING = "waiting"
    ASLEEP = "asleep"


class Role(enum.Enum):
    """What kind of task an entry is: an ordinary loop, the sensory exception task that hears
    every lower sensory message, an assassin that may seize or suspend any lower command task, or a
    system driver provided by chcos (file sampler, terminal/log)."""

    TASK = "task"
    EXCEPTION = "exception"
    ASSASSIN = "assassin"
    SYSTEM = "system"


class DefaultPriority:
    """A task's default priority where an owning link's priority would be (see
    :attr:`TaskEntry.prio_src`)."""

    __slots__ = ("priority",)

    def __init__(self, priority: int) -> None:
        self.priority = priority


@dataclass(eq=False, slots=True)
class TaskEntry:
    """One Tsktab row. Mutated only on the kernel thread."""

    tid: int
    name: str
    machine: int
    level: int
    func: TaskFunc
    code: str = ""
    role: Role = Role.TASK
    params: dict[str, Any] = field(default_factory=dict)  # install-time parameters
    state: TaskState = TaskState.SUSPENDED
    prio: int = 0
    _owner: Link | None = None  # see :attr:`owner`
    coro: Coroutine[Any, Any, Any] | None = None
    command: Any = None  # parameters of the current activation
    in_ports: list[InPort] = field(default_factory=list)
    out_links: list[Link] = field(default_factory=list)
    up_links: list[Link] = field(default_factory=list)  # add with add_up_link
    tapped: bool = False  # an exception task's tap link leaves this task (see mark_tapped)
    special_links: dict[str, Link] = field(default_factory=dict)  # assassin links by target
    tap: TapPort | None = None  # the exception task's tap
    waitq: list[tuple[int, Link, Any]] = field(default_factory=list)
    #: the handle the task function gets (a chcos.user.context.TaskContext, from the layer above)
    ctx: object = None
    world: Model | None = None
    # standing task and restart policy (install --standing --restart=... --backoff=...)
    standing: bool = False
    restart: str = "never"
    backoff: float = 1.0
    last_command: Any = None  # the command of the last activation (restarts reuse it)
    waiting_devices: frozenset[str] = frozenset()  # on-recovery: devices that must be healthy
    restart_timer: Cancellable | None = None
    new_command: tuple[Any] | None = None  # a newer command from the owner, not yet taken
    wait_commands: bool = False  # waiting (wait_any) for a command message
    wait_links: tuple[Link, ...] = ()  # waiting (wait_any) for a completion on these links
    wake_filter: Callable[[str, Any], bool] | None = None  # wait_any(when=...)
    multi_wait: bool = False  # waiting in wait_any (for any of the above)
    # scheduler bookkeeping
    send_value: Any = None
    throw_exc: BaseException | None = None
    frozen: bool = False
    frozen_ready: int | None = None
    cancelling: bool = False
    next_command: tuple[Any, int, Link | None] | None = None
    wait_ports: tuple[InPort, ...] = ()
    wait_link: Link | None = None
    wait_query: int | None = None  # the remote world-model query awaiting its answer
    timer: Cancellable | None = None
    sleep_until: float | None = None
    unwait: Unwait | None = None  # how to end the current wait (see Unwait)
    frozen_state: TaskState | None = None  # the state a suspended task goes back to
    # statistics
    steps: int = 0
    activations: int = 0
    completions: int = 0
    abnormal: int = 0
    restarts: int = 0
    last_error: str = ""

    #: where :attr:`base_prio` comes from: the owning link, or the holder of the default
    #: priority when nobody owns the task (kept by the two setters below)
    prio_src: Link | DefaultPriority = field(init=False, repr=False)
    _default: DefaultPriority = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._default = DefaultPriority(4)  # until the installer sets default_prio
        self.prio_src = self._owner if self._owner is not None else self._default

    @property
    def owner(self) -> Link | None:
        """The command link whose message the task is carrying out (None: nobody owns it)."""
        return self._owner

    @owner.setter
    def owner(self, link: Link | None) -> None:
        self._owner = link
        self.prio_src = link if link is not None else self._default

    @property
    def default_prio(self) -> int:
        """The priority a released task goes back to (resetpri)."""
        return self._default.priority

    @default_prio.setter
    def default_prio(self, prio: int) -> None:
        self._default.priority = prio

    @property
    def base_prio(self) -> int:
        """The priority of the owning command message, or the task's default priority when
        nobody owns it (a message wakes it at the higher of this and the link's priority)."""
        return self.prio_src.priority

    def add_up_link(self, link: Link) -> None:
        """A sensory link leaving this task (at install)."""
        self.up_links.append(link)

    def mark_tapped(self) -> None:
        """An exception task's tap link now leaves this task (at install): its messages also
        go into the taps."""
        self.tapped = True

    def __repr__(self) -> str:
        return f"<task {self.name} m{self.machine} L{self.level} {self.state.value} p{self.prio}>"


class Tsktab:
    """The task table: entries by name and by id, in install order."""

    def __init__(self) -> None:
        self._by_name: dict[str, TaskEntry] = {}
        self._by_tid: list[TaskEntry] = []

    def add(self, entry: TaskEntry) -> None:
        """Enter a new task; raises TaskError if the name is taken (tasks are never removed)."""
        if entry.name in self._by_name:
            raise TaskError(f"task {entry.name} is already installed (tasks are never removed)")
        self._by_name[entry.name] = entry
        self._by_tid.append(entry)

    def next_tid(self) -> int:
        """The id the next entry will get."""
        return len(self._by_tid)

    def get(self, name: str) -> TaskEntry:
        """The task called ``name``; raises TaskError naming it if there is none."""
        try:
            return self._by_name[name]
        except KeyError:
            raise TaskError(f"no task named {name!r}") from None

    def by_tid(self, tid: int) -> TaskEntry:
        """The task with id ``tid``; raises TaskError if there is none."""
        if 0 <= tid < len(self._by_tid):
            return self._by_tid[tid]
        raise TaskError(f"no task with id {tid}")

    def __contains__(self, name: object) -> bool:
        return name in self._by_name

    def __iter__(self) -> Iterator[TaskEntry]:
        return iter(self._by_tid)

    def __len__(self) -> int:
        return len(self._by_tid)
