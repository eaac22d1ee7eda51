"""scheduler - the priority scheduler that steps task coroutines, its timers, its interrupt queue.

Tasks are ``async def`` coroutines stepped with ``send``/``throw`` (as trio and curio step theirs).
A task gives the processor back only at an ``await`` of a chcos call; whenever several tasks are
ready the one with the highest priority runs next, ties first come first served (the thesis'
``resched``). Interrupts from device threads and the host arrive through a thread-safe queue that
wakes the kernel; timers (the thesis' delta list, kept here as a heap of deadlines) drive sleeps,
read timeouts and periodic device polls. Nothing busy-waits: an idle kernel blocks in its clock.
A failing interrupt handler or timer callback does not stop the kernel: it is logged and
collected, and :meth:`Kernel.check` raises it.

Virtual time: the contract for drivers and simulated peers. On a :class:`VirtualClock` the kernel
jumps to the next timer as soon as nothing is ready and no interrupt is queued: it never waits
for the wall clock, and it makes no wall-clock decision of its own (no ``time.*`` call on this
path). Whatever must happen at a virtual instant must therefore be *on the kernel thread* by the
time the kernel looks, and there are two ways for a driver to be so:

1. **On the kernel thread** (the aim for every simulated bus): the driver's I/O and its
   simulated peer run in kernel timers and interrupt handlers (``host.every``/``host.at``, a
   direct hand-off of the encoded bytes to the peer, the peer's answer handled in the same
   call). Nothing is in flight between two interrupts, so the driver needs no settle: it sets
   :attr:`chcos.devices.driver.Driver.settles` False and Devtab registers nothing with the kernel.
   Every timeout it has is a kernel timer, so a request to a silent peer times out at its
   virtual deadline, whatever the machine's load.
2. **Threads and a transport of its own** (python-can notifiers, sockets, ptys): work handed to
   those threads is in flight, and virtual time must not move on before it is back. Such a
   driver registers ``settle(timeout)`` (:meth:`Kernel.add_settler`; Devtab does it for every
   driver whose ``settles`` is true) and, with a simulated peer on threads of its own, that
   peer's activity count (:meth:`Kernel.add_settle_activity`). The kernel calls the settlers
   before every jump, in rounds until no activity count moves. How long a settler may wait
   depends on its peer (:class:`SettleBound`): a simulated peer in this process (``PEER``) is
   waited for until it is done, :data:`SETTLE_TIMEOUT` wall seconds at most (a guard against a
   hung thread, never reached by a working one); a real peer in another process (``CLOCK``)
   gets at most the virtual time left to the next timer, so that virtual time never runs ahead
   of the real time the peer lives in while something is in flight (a silent real peer costs
   as many wall seconds as the virtual time it is silent for, and its answer is taken at the
   virtual instant it arrives in).

A driver may not use ``time.monotonic``/``time.time``/``time.sleep`` or an ``Event.wait``
timeout for a decision on virtual time (a timeout, a period, a retry): those come from
``host.now()``/``host.at()``/``host.every()``. ``tools/wallclock_audit.py`` lists the calls that
are still made (``vcan_tests/test_vtime_wallclock.py`` asserts there are none in the kernel,
Devtab and the protocol-free binding).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Coroutine
from enum import Enum
from heapq import heapify, heappop, heappush
from itertools import count
from typing import Any

from chcos.errors import KernelError
from chcos.kernel.clock import Clock, RealClock
from chcos.kernel.instrument import Hooks, Instrument
from chcos.kernel.lifecycle import BLOCK, YIELD, End, EndHandler, Lifecycle
from chcos.kernel.timers import HandlerErrors, Timer, Timers
from chcos.tables.tasks import TaskEntry, TaskState

# Timer: what call_at returns
__all__ = ["BLOCK", "YIELD", "End", "EndHandler", "Kernel", "SettleBound", "Timer"]

log = logging.getLogger("chcos.kernel.scheduler")
#: the most rounds of settles before virtual time moves on (see Kernel._settle_rounds)
SETTLE_ROUNDS = 50
#: wall seconds a settler may wait for a simulated peer on threads of this process to finish
#: what is in flight (:attr:`SettleBound.PEER`): a guard against a hung thread, which a
#: working peer never reaches (it decides nothing a run's results depend on)
SETTLE_TIMEOUT = 5.0


class SettleBound(Enum):
    """How long a settler may wait (see the module doc, "Virtual time")."""

    #: the peer is simulated in this process, on threads of its own: wait until it is done
    #: (at most :data:`SETTLE_TIMEOUT` wall seconds)
    PEER = "peer"
    #: the peer is real, in another process, living in real time: wait at most the virtual
    #: time left to the next timer (virtual time does not run ahead of it)
    CLOCK = "clock"


_READY, _CURRENT, _SUSPENDED = TaskState.READY, TaskState.CURRENT, TaskState.SUSPENDED


def _nothing() -> None:
    """The interrupt :meth:`Kernel.stop` queues: the run loop looks at its stop flag only
    after draining interrupts, so a stop must leave one there."""


class Kernel:
    """One satellite's scheduler. Everything except :meth:`interrupt` and :meth:`stop` must be
    called on the kernel thread (from tasks, timer callbacks or interrupt handlers).

    The kernel knows tasks, priorities, timers and sleeps; what else a task waits for (ports,
    links, queries) belongs to the layer that blocked it, which leaves ``task.unwait`` to undo
    it when the task is woken or cancelled. Every path that readies a task goes through
    :meth:`ready` (a wake-up through :meth:`wake`, which calls it), and every task step through
    :meth:`_step`. Instruments: see :class:`Hooks`; suspend, resume, cancel and how
    activations end: :attr:`lifecycle` (a :class:`Lifecycle`); instruments: :attr:`hooks` (a
    :class:`Hooks`); timers: :attr:`timers` (a :class:`Timers`); the
    errors collected on the kernel thread: :attr:`errors` (a :class:`HandlerErrors`)."""

    def __init__(self, clock: Clock | None = None) -> None:
        #: the installed instruments, one tuple per hook (see :class:`Hooks`)
        self.hooks = Hooks()
        self.clock: Clock = clock if clock is not None else RealClock()
        self.current: TaskEntry | None = None
        # the ready queue, a heap of (-priority, sequence, task): one entry for each READY
        # task and nothing else (a re-queue, a suspension or a wipe takes the entry out, see
        # unready), so a step needs no test for a stale entry. Only ready() pushes onto it.
        self._ready: list[tuple[int, int, TaskEntry]] = []
        # numbers the ready-queue entries in the order they were made (ties: first come first)
        self._seq = count(1)
        #: the errors of interrupt handlers and timer callbacks, raised by :meth:`check`
        self.errors = HandlerErrors()
        #: the kernel's timers (the thesis' delta list)
        self.timers = Timers(self.clock, self.errors)
        self._irq: deque[tuple[Callable[..., None], tuple[Any, ...]]] = deque()
        self._wake = threading.Event()
        self._idle = False
        #: seconds this kernel spent in its idle waits on real time (the wake-up included),
        #: so far: a reader compares two readings to see how saturated it was in between
        self.idle_time = 0.0
        self._stop = False
        self._running = False
        #: the ident of the thread running :meth:`run`, None when it is not running
        self.thread_ident: int | None = None
        self._settlers: list[tuple[Callable[[float], bool], SettleBound]] = []
        self._activity: list[Callable[[], int]] = []
        self._idle_hooks: list[Callable[[], None]] = []
        # every task this kernel has started (a dict as an ordered set): steps sums their
        # step counts, so a step counts once, on its task, and nowhere else
        self._tasks: dict[TaskEntry, None] = {}
        #: suspend, resume, cancel and the end of activations
        self.lifecycle = Lifecycle(self)
        # scheduling rounds completed (one per turn of run's loop), and when a reader of
        # progress last saw the count move (see progress)
        self._rounds = 0
        self._seen_rounds = -1
        self._progress_at = 0.0

    # ---- instruments, the lifecycle of activations, timers, collected errors (owned objects) --
    def add_instrument(self, instrument: Instrument) -> None:
        """See :meth:`Hooks.add_instrument`."""
        self.hooks.add_instrument(instrument)

    def remove_instrument(self, instrument: Instrument) -> None:
        """See :meth:`Hooks.remove_instrument`."""
        self.hooks.remove_instrument(instrument)

    @property
    def instruments(self) -> tuple[Instrument, ...]:
        """The installed instruments, in the order they were added."""
        return self.hooks.instruments

    @property
    def dropped_instruments(self) -> list[tuple[Instrument, str, str]]:
        """(instrument, hook, error text) of every instrument removed because a hook raised."""
        return self.hooks.dropped_instruments

    def event(self, kind: str, detail: str) -> None:
        """See :meth:`Hooks.event`: report a system event to the instruments and the log."""
        self.hooks.event(kind, detail)

    def set_end_handler(self, handler: EndHandler) -> None:
        """Who is told when an activation ends: ``handler(task, how, value)`` with ``how`` an
        :class:`End`. The system connects the message manager here."""
        self.lifecycle.on_end = handler

    def suspend(self, t: TaskEntry) -> None:
        """See :meth:`Lifecycle.suspend`."""
        self.lifecycle.suspend(t)

    def resume(self, t: TaskEntry) -> None:
        """See :meth:`Lifecycle.resume`."""
        self.lifecycle.resume(t)

    def cancel(self, t: TaskEntry, reason: str) -> None:
        """See :meth:`Lifecycle.cancel`."""
        self.lifecycle.cancel(t, reason)

    def unhook(self, t: TaskEntry) -> None:
        """See :meth:`Lifecycle.unhook`."""
        self.lifecycle.unhook(t)

    def call_at(self, deadline: float, callback: Callable[[], None],
                period: float | None = None) -> Timer:
        """See :meth:`Timers.call_at`."""
        return self.timers.call_at(deadline, callback, period)

    def call_later(self, delay: float, callback: Callable[[], None]) -> Timer:
        """See :meth:`Timers.call_later`."""
        return self.timers.call_later(delay, callback)

    def every(self, period: float, callback: Callable[[], None]) -> Timer:
        """See :meth:`Timers.every`."""
        return self.timers.every(period, callback)

    @property
    def skipped_periods(self) -> int:
        """Periods that periodic timers skipped because the kernel came back too late."""
        return self.timers.skipped_periods

    @property
    def irq_errors(self) -> list[str]:
        """Text of every failed interrupt handler and timer callback (the newest ones)."""
        return self.errors.texts

    def check(self) -> None:
        """See :meth:`HandlerErrors.check`: raise the oldest error collected on the kernel
        thread and not raised yet (a HandlerError). Thread-safe."""
        self.errors.check()

    @property
    def steps(self) -> int:
        """Task executions (steps) so far, all tasks together."""
        return sum(t.steps for t in self._tasks)

    def stats(self) -> dict[str, int]:
        """What the kernel has done and holds now, for monitors: task steps, ready tasks,
        pending timers, periods that periodic timers skipped because the kernel came back too
        late for them (see :mod:`chcos.kernel.timers`), failed handlers and timer callbacks."""
        return {"steps": self.steps,
                "ready": len(self._ready),
                "timers": self.timers.pending(),
                "skipped_periods": self.skipped_periods,
                "handler_errors": len(self.irq_errors)}

    # ---- task manager primitives ------------------------------------------------------------
    def start(self, t: TaskEntry, coro: Coroutine[Any, Any, Any], prio: int) -> None:
        """Begin an activation of ``t``: its next step runs ``coro`` from the start (Xinu's
        create and resume); ``t`` is made ready at ``prio``, and its steps count in
        :attr:`steps` from now on."""
        self._tasks[t] = None
        t.coro = coro
        self.ready(t, prio)

    def ready(self, t: TaskEntry, prio: int) -> None:
        """Make ``t`` ready at priority ``prio`` (the thesis' and Xinu's ready): the one place
        that puts a task on the ready queue. A task already ready is re-queued at ``prio``,
        behind the others there; a suspended task keeps the wake-up (the highest priority)
        for :meth:`resume`. Instruments hear of it (``task_scheduled``)."""
        if t.frozen:
            t.frozen_ready = prio if t.frozen_ready is None else max(prio, t.frozen_ready)
            t.state = _SUSPENDED
            return
        if t.state is _READY:
            self.unready(t)
        t.prio = prio
        t.state = _READY
        heappush(self._ready, (-prio, next(self._seq), t))
        if self.hooks.h_scheduled:
            self.hooks.notify(self.hooks.h_scheduled, "task_scheduled", t)

    def wake(self, t: TaskEntry, prio: int, value: Any = None,
             exc: BaseException | None = None) -> None:
        """End ``t``'s wait (its timer, and whatever its ``unwait`` undoes) and ready it at
        ``prio`` with ``value`` as the result of its pending ``await`` (or ``exc`` thrown into
        it): every layer that wakes a waiting task calls this (Xinu's signal calls ready)."""
        unwait = t.unwait
        if unwait is not None:
            t.unwait = None
            unwait(t)
        if t.timer is not None:
            t.timer.cancel()
            t.timer = None
            t.sleep_until = None
        t.send_value = value
        t.throw_exc = exc
        self.ready(t, prio)

    def unready(self, t: TaskEntry) -> None:
        """Take ``t``'s entry out of the ready queue, if it has one (a linear search: for the
        rare re-queue, suspension or wipe of a ready task, so that a step needs no test)."""
        heap = self._ready
        for i, entry in enumerate(heap):
            if entry[2] is t:
                last = heap.pop()
                if i < len(heap):
                    heap[i] = last
                    heapify(heap)
                return

    def block(self, t: TaskEntry, state: TaskState) -> None:
        """Record that the current task ``t`` is about to wait in ``state`` (instruments hear
        of it when its step ends in the block: see :meth:`_watched_step`): the one place a
        task's wait is written, as :meth:`ready` is the one place it is readied."""
        t.state = state

    def set_priority(self, t: TaskEntry, prio: int) -> None:
        """``t`` runs at priority ``prio`` from now on (Xinu's chprio): a ready task is
        re-queued at it through :meth:`ready` (behind the others there); any other task keeps
        it for the step it runs next or the :meth:`ready` that wakes it with its own priority;
        a suspended (frozen) task's kept wake-up is moved to ``prio`` too, so that
        :meth:`resume` readies it there. The one place a task's priority changes outside
        :meth:`ready`."""
        if t.frozen:
            t.prio = prio
            if t.frozen_ready is not None:
                t.frozen_ready = prio
        elif t.state is _READY:
            self.ready(t, prio)
        else:
            t.prio = prio

    def ready_priorities(self) -> list[int]:
        """Priorities of the tasks now ready, highest first (for tests and monitors)."""
        return sorted((-p for p, _s, _t in self._ready), reverse=True)

    def ready_tasks(self) -> list[TaskEntry]:
        """The tasks now ready, in the order they will run (for tests and monitors)."""
        return [t for _p, _s, t in sorted(self._ready)]

    # ---- interrupts -------------------------------------------------------------------------
    def interrupt(self, handler: Callable[..., None], *args: Any) -> None:
        """Queue ``handler(*args)`` to run on the kernel thread between task steps.

        Thread-safe: device threads and the host call it. Wakes an idle kernel.
        """
        self._irq.append((handler, args))
        if self._idle:
            self._wake.set()

    def _drain_irq(self) -> None:
        irq = self._irq
        while irq:
            handler, args = irq.popleft()
            try:
                handler(*args)
            except Exception as exc:
                self.errors.record(getattr(handler, "__qualname__", repr(handler)), exc)

    def add_settler(self, settle: Callable[[float], bool],
                    bound: SettleBound = SettleBound.PEER) -> None:
        """Register a driver's ``settle(timeout)``: called before virtual time jumps ahead so
        that everything already on a bus is delivered first, with a ``timeout`` in wall seconds
        set by ``bound`` (see :class:`SettleBound` and the module doc). A driver whose work all
        runs on the kernel thread registers none."""
        self._settlers.append((settle, bound))

    @property
    def settling(self) -> bool:
        """Whether any settler is registered: some driver or peer still works on threads of its
        own, and virtual time waits for it before each jump (see the module doc)."""
        return bool(self._settlers)

    def add_settle_activity(self, count: Callable[[], int]) -> None:
        """Register ``count()``, a number that grows whenever a driver sent something to a peer
        on threads of its own (a simulated slave) and whenever the peer is done with it: while
        it moves during a round of settles, the round is repeated, so that virtual time moves
        on only after a whole round in which nothing reached the peer and the peer handled
        nothing (everything it sent back was then delivered in that round)."""
        self._activity.append(count)

    def settle(self) -> bool:
        """On a virtual clock, let every driver and simulated peer finish what is in flight
        now (see :meth:`add_settle_activity`); a simulated peer calls it on the kernel thread
        before and after it steps, so that its step sees, at that virtual instant, exactly what
        was sent before it, whatever the threads' timing. True if that queued interrupts or
        readied tasks. Nothing on a real clock, nor when no settler is registered."""
        if not self.clock.virtual or not self._settlers:
            return False
        return self._settle(self.timers.next_deadline())

    def add_idle_hook(self, hook: Callable[[], None]) -> None:
        """Call ``hook()`` on the kernel thread each time nothing is left to run, before the
        kernel waits (the communications manager flushes its batches there)."""
        self._idle_hooks.append(hook)

    # ---- running ----------------------------------------------------------------------------
    def stop(self) -> None:
        """Ask :meth:`run` to return after the current step. Thread-safe."""
        self._stop = True
        self._irq.append((_nothing, ()))
        self._wake.set()

    @property
    def running(self) -> bool:
        """True while :meth:`run` is executing."""
        return self._running

    @property
    def progress(self) -> float:
        """The clock time at which the kernel was last seen making progress: completing a
        scheduling round (interrupts drained, due timers fired, a task stepped), waiting idle
        for work, or not running. A reader on another thread (a driver's liveness gate) looks
        now and then: the time is that of the look that saw the round count move, so a kernel
        stuck in a step or an interrupt handler (a deadlock, a task that never awaits) shows
        ``clock.now() - progress`` growing. Thread-safe (a read of plain attributes)."""
        rounds = self._rounds
        if rounds != self._seen_rounds or self._idle or not self._running:
            self._seen_rounds = rounds
            self._progress_at = self.clock.now()
        return self._progress_at

    def on_kernel_thread(self) -> bool:
        """True when called from the thread that is running :meth:`run`."""
        return self.thread_ident == threading.get_ident()

    def run(self, until: float | None = None) -> None:
        """Schedule tasks until :meth:`stop`, or until clock time ``until``.

        On a virtual clock, returns as soon as nothing can happen any more (no ready task, no
        timer, nothing from the drivers). Raises KernelError if already running.
        """
        if self._running:
            raise KernelError("kernel is already running")
        self._running = True
        self._stop = False
        self.thread_ident = threading.get_ident()
        irq, timers, ready, step = self._irq, self.timers.heap, self._ready, self._step
        hooks = self.hooks
        try:
            while True:
                self._rounds += 1   # progress: read by the liveness gates of drivers
                if irq:  # interrupts first, and stop(), which queues one
                    self._drain_irq()
                    if self._stop:
                        break
                if timers:
                    now = self.clock.now()
                    due = timers[0][0]
                    if due <= now and (until is None or due <= until):
                        self.timers.fire(now if until is None else min(now, until))
                if ready:  # the highest priority first, ties first come first served
                    if hooks.h_step:  # an instrument watches steps
                        self._watched_step(heappop(ready)[2])
                    else:
                        step(heappop(ready)[2])
                elif not self._idle_wait(until):
                    break
        finally:
            self.current = None
            self._running = False
            self.thread_ident = None

    def _idle_wait(self, until: float | None) -> bool:
        """Nothing is ready: wait for the next event. False when :meth:`run` should return."""
        if self._idle_hooks:
            for hook in self._idle_hooks:
                hook()
            if self._ready or self._irq:
                return True
        clock = self.clock
        deadline = self.timers.next_deadline()
        if until is not None and (deadline is None or deadline > until):
            deadline = until
        if clock.virtual:
            if self._settlers and self._settle(deadline):
                return True
            if deadline is None:
                return False
            if until is not None and clock.now() >= until:
                return False
            clock.idle(self._wake, deadline)
            return True
        if until is not None and clock.now() >= until:
            return False
        self._idle = True
        began = clock.now()
        try:
            if not self._irq and not self._stop:
                clock.idle(self._wake, deadline)
        finally:
            self._idle = False
            self._wake.clear()
            self.idle_time += clock.now() - began
        return True

    def run_drivers(self, until: float, done: Callable[[], bool],
                    wall_deadline: float | None = None) -> None:
        """The shutdown window on a virtual clock: interrupts and timers run and virtual time
        jumps from timer to timer as in :meth:`run` (drivers poll, simulated peers step, a
        drive ramps down), but no task is stepped (user tasks have ended; a task woken now
        stays ready and never runs). Returns as soon as ``done()`` is true or clock time
        ``until`` is reached (at once when nothing more can happen: no timer, nothing in
        flight); what the drivers have in flight is waited for as in :meth:`run` (the
        settlers, each bounded by its :class:`SettleBound`: a real peer that does not answer
        costs at most the window's virtual seconds in wall time). ``wall_deadline``, if given,
        also ends it once ``time.monotonic()`` passes it (for a caller that must bound its own
        wall time; the kernel makes no such decision itself). Runs on the calling thread, which
        is the kernel thread meanwhile. Raises KernelError if the kernel is running or its
        clock is not virtual."""
        if self._running:
            raise KernelError("kernel is already running")
        if not self.clock.virtual:
            raise KernelError("run_drivers needs a virtual clock")
        self._running = True
        self.thread_ident = threading.get_ident()
        clock, irq, timers = self.clock, self._irq, self.timers
        try:
            while True:
                self._rounds += 1
                if irq:
                    self._drain_irq()
                if done() or (wall_deadline is not None and time.monotonic() >= wall_deadline):
                    return
                now = clock.now()
                due = timers.next_deadline()
                if due is not None and due <= now:
                    timers.fire(now)
                    continue
                if self._settlers:
                    self._settle_rounds(min(until, due) if due is not None else until)
                    if irq:
                        continue
                if now >= until:
                    return
                if due is None:     # nothing can happen any more: the time passes
                    clock.idle(self._wake, until)
                    return
                clock.idle(self._wake, min(due, until))
        finally:
            self._running = False
            self.thread_ident = None

    def _settle(self, deadline: float | None = None) -> bool:
        """Let every driver finish what is in flight (the next timer or the run's end at clock
        time ``deadline``, None: none); True if that produced work."""
        self._settle_rounds(deadline)
        return bool(self._irq or self._ready)

    def _settle_timeout(self, bound: SettleBound, deadline: float | None) -> float:
        """The wall seconds a settler of ``bound`` may wait when the next timer is at clock
        time ``deadline`` (see :class:`SettleBound`)."""
        if bound is SettleBound.PEER or deadline is None:
            return SETTLE_TIMEOUT
        return min(SETTLE_TIMEOUT, max(0.0, deadline - self.clock.now()))

    def _settle_rounds(self, deadline: float | None) -> None:
        """Call every settler, again while an activity count (:meth:`add_settle_activity`)
        moved during the round: a driver sent a simulated peer something, or the peer handled
        it on its own thread, and its answer must be delivered in this instant too. At most
        :data:`SETTLE_ROUNDS` rounds (a peer that keeps talking on its own wall-clock thread
        would never let it end). ``deadline``: the clock time of the next timer (see
        :meth:`_settle_timeout`)."""
        activity = self._activity
        peer = SETTLE_TIMEOUT
        for _ in range(SETTLE_ROUNDS):
            before = [count() for count in activity]
            for settle, bound in self._settlers:
                settle(peer if bound is SettleBound.PEER
                       else self._settle_timeout(bound, deadline))
            if [count() for count in activity] == before:
                return

    def _step(self, t: TaskEntry) -> bool:
        """Context switch: run ``t`` until its next trap (the thesis' ctxsw), then requeue it
        (a yield), leave it waiting (a block), or end its activation. True if it now waits."""
        coro = t.coro
        if coro is None:  # woken after its activation ended: nothing to run
            t.state = _SUSPENDED
            return False
        t.state = _CURRENT
        self.current = t
        t.steps += 1
        try:
            if t.throw_exc is None:
                # the value of the last wake-up stays until the next one replaces it: a step
                # after a yield sends it again, and a yield's await ignores what it is sent
                trap = coro.send(t.send_value)
            else:
                exc = t.throw_exc
                t.throw_exc = None
                trap = coro.throw(exc)
        except Exception as err:
            self.current = None
            self.lifecycle.raised(t, err)
            return False
        self.current = None
        if t.cancelling:  # cancelled during its own step, or it carried on after one
            self.lifecycle.odd_trap(t, coro, trap)
        elif trap is BLOCK:
            return True
        elif trap is YIELD:
            self.ready(t, t.prio)
        else:
            self.lifecycle.odd_trap(t, coro, trap)
        return False

    def _watched_step(self, t: TaskEntry) -> None:
        """:meth:`_step` told to the instruments watching steps (:attr:`Hooks.h_step`):
        ``before_step``, then ``task_blocked`` if the step ended in a wait, then
        ``after_step``. An instrument hears whole steps, those begun after it was added: one
        that a step adds hears of the next step on."""
        if t.coro is None:  # nothing to run: no step to tell of
            self._step(t)
            return
        hooks = self.hooks
        watching = hooks.h_step
        if hooks.h_before:
            hooks.notify(hooks.h_before, "before_step", t)
        if self._step(t):
            hooks.notify(hooks.still(watching, hooks.h_blocked), "task_blocked", t)
        hooks.notify(hooks.still(watching, hooks.h_after), "after_step", t)
