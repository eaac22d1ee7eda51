"""cycles - a task waiting for a field bus's SYNC cycle through the kernel: ``await
ctx.sync_cycle("axis")`` returns when cycle n is complete (every synchronous TPDO due in it
arrived) or known not to be (SYNC n+1 went out first: late), without blocking any thread.

The bus's driver tells each cycle's outcome once, as soon as it is known, on its own thread
(``watch_cycles``, e.g. :meth:`drivers.canopen_node.CanopenDriver.watch_cycles`); a
:class:`CycleBoard` per driver turns that into a kernel interrupt that wakes the tasks waiting
for that cycle. The board also tells the driver which cycle the task writing an actuator
answers - the one it got last, until it waits for a cycle again - so that an RPDO made in
answer to cycle n that goes out after SYNC n+1 is counted late (the bus counter
``sync-late-writes``).
"""

from __future__ import annotations

import types
import weakref
from collections import OrderedDict
from collections.abc import Callable, Generator, Iterable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

from chcos.errors import MessageError, ReadTimeout
from chcos.kernel.scheduler import BLOCK, Kernel
from chcos.tables.tasks import TaskEntry, TaskState

#: cycle outcomes a board remembers (a task asking for a cycle this far back gets an error)
HISTORY = 256
#: what a task waiting for "the next cycle" waits for before the first outcome is told
NEXT = 0


@dataclass(frozen=True)
class Cycle:
    """What :meth:`chcos.user.context.TaskContext.sync_cycle` returns: the bus, the cycle's
    number (SYNC n opens cycle n), and whether it was complete (every synchronous TPDO due in
    it arrived before SYNC n+1; False: late)."""

    bus: str
    number: int
    complete: bool


@runtime_checkable
class CycleSource(Protocol):
    """A driver with a SYNC cycle tasks may wait for."""

    def watch_cycles(self, fn: Callable[[int, bool], None],
                     responding: Callable[[], int | None]) -> Callable[[], None]:
        """Call ``fn(n, complete)`` once per cycle (on a driver thread); ``responding()``
        names the cycle the writing task answers. Returns the unwatch function; raises
        BusError if the bus has no cycle."""
        ...


class CycleBoard:
    """The kernel side of one bus's SYNC cycle: the outcomes told so far (the last
    :data:`HISTORY`), the tasks waiting for a cycle, and the cycle each task last woke for.
    Every method but :meth:`_from_driver` runs on the kernel thread."""

    def __init__(self, kernel: Kernel, bus: str, source: CycleSource) -> None:
        self.kernel = kernel
        self.bus = bus
        self.outcomes: OrderedDict[int, bool] = OrderedDict()
        self.first: int | None = None                  # the first cycle told (None: none yet)
        self.last = 0                                  # the highest cycle told
        self.waiting: dict[TaskEntry, int] = {}        # task -> the cycle it waits for
        self.answering: dict[int, int] = {}            # task id -> the cycle it last woke for
        self.unwatch = source.watch_cycles(self._from_driver, self._responding)

    def _from_driver(self, n: int, complete: bool) -> None:
        """The driver's report (its thread): handled on the kernel thread."""
        self.kernel.interrupt(self._told, n, complete)

    def _responding(self) -> int | None:
        t = self.kernel.current
        return None if t is None else self.answering.get(t.tid)

    def _told(self, n: int, complete: bool) -> None:
        """Cycle ``n``'s outcome (the driver tells them in order, each once): remembered, and
        every task waiting for it woken with it (a task waiting for "the next" one too; one
        waiting for a cycle before the first told gets MessageError)."""
        if self.first is None:
            self.first = n
        self.outcomes[n] = complete
        while len(self.outcomes) > HISTORY:
            self.outcomes.popitem(last=False)
        self.last = n
        for t, want in [(t, w) for t, w in self.waiting.items() if w <= n]:
            del self.waiting[t]
            if want is NEXT or want == n:
                self.answering[t.tid] = n
                self.kernel.wake(t, t.base_prio, Cycle(self.bus, n, complete))
            else:
                self.kernel.wake(t, t.base_prio, exc=MessageError(
                    f"sync_cycle: cycle {want} of bus {self.bus} was over before this task "
                    f"first waited (the first cycle told was {n})"))

    def forget(self, t: TaskEntry) -> None:
        """``t`` stops waiting (woken, timed out, cancelled): the task's ``unwait``."""
        self.waiting.pop(t, None)


#: one board per driver (weak: a board goes with its system)
_BOARDS: weakref.WeakKeyDictionary[Any, CycleBoard] = weakref.WeakKeyDictionary()


def board(kernel: Kernel, drivers: Iterable[Any], bus: str) -> CycleBoard:
    """The board of ``bus`` (made at the first wait). Raises MessageError if no running
    driver of this process drives ``bus`` or its driver has no SYNC cycle."""
    drv = next((d for d in drivers if getattr(getattr(d, "bus", None), "name", None) == bus),
               None)
    if drv is None:
        raise MessageError(f"sync_cycle: no bus {bus!r} driven by this process")
    found = _BOARDS.get(drv)
    if found is not None:
        return found
    if not isinstance(drv, CycleSource):
        raise MessageError(f"sync_cycle: bus {bus!r} ({getattr(drv, 'kind', '?')}) has no "
                           f"SYNC cycle")
    try:
        made = CycleBoard(kernel, bus, drv)
    except Exception as exc:   # BusError: no sync_period, not running
        raise MessageError(f"sync_cycle: {exc}") from exc
    _BOARDS[drv] = made
    return made


@types.coroutine
def wait_cycle(t: TaskEntry, kernel: Kernel, drivers: Iterable[Any], bus: str,
               n: int | None, timeout: float | None) -> Generator[Any, Any, Cycle]:
    """Task ``t`` waits (WAITING, through the kernel) for cycle ``n`` of ``bus`` - the next
    cycle whose outcome is not told yet if None - and gets its :class:`Cycle`. Raises
    MessageError (no such bus, no SYNC cycle, cycle ``n`` older than the history), ReadTimeout
    after ``timeout`` seconds of kernel time without the outcome."""
    b = board(kernel, drivers, bus)
    if n is not None and n <= NEXT:
        raise MessageError(f"sync_cycle: cycle numbers start at 1, got {n}")
    want = (NEXT if b.first is None else b.last + 1) if n is None else n
    b.answering.pop(t.tid, None)     # what it writes while it waits answers no cycle
    if want != NEXT and want <= b.last:
        if want not in b.outcomes:
            raise MessageError(f"sync_cycle: cycle {want} of bus {bus} is past (the last "
                               f"{HISTORY} are kept; the last told is {b.last})")
        b.answering[t.tid] = want
        return Cycle(bus, want, b.outcomes[want])
    b.waiting[t] = want
    t.unwait = b.forget
    kernel.block(t, TaskState.WAITING)
    if timeout is not None:
        def expire() -> None:
            t.timer = None
            kernel.wake(t, t.base_prio, exc=ReadTimeout(
                f"task {t.name}: SYNC cycle {want} of bus {bus} not over within {timeout} s"))

        t.timer = kernel.call_later(timeout, expire)
    cycle: Cycle = yield BLOCK
    return cycle
