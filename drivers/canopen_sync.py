"""canopen_sync - the SYNC cycle of a ``canopen`` bus as a first-class thing: a SYNC producer
(COB-ID 0x080), the cycle number, the synchronous
TPDOs (transmission type 1..240) collected per cycle, and the bus's cycle statistics: cycles,
complete cycles, missing TPDOs (a synchronous TPDO due in cycle n that had not arrived when SYNC
n+1 went out), late SYNCs (sent more than half a period after their deadline) and the SYNC
period jitter (|interval - period|) as p50/p99/max over the last :data:`WINDOW` cycles.

:meth:`SyncCycle.wait_cycle` lets a caller wait until cycle n is complete (every synchronous
TPDO of it arrived) or give up after a timeout; :meth:`SyncCycle.watch` tells each cycle's
outcome once, in order, as soon as it is known (tasks wait through it: :mod:`chcos.user.cycles`).
A TPDO of transmission type k (1..240) is due every k-th SYNC; its phase is learned from its
first arrival. A TPDO of transmission type 0 (acyclic synchronous) is sent after a SYNC only when
its data changed, so it is never due: each one received in cycle n is counted (``acyclic``), it
never counts as missing and never holds a cycle's completeness back.

Two producers. On SocketCAN, :class:`SyncProducerProcess`: a process of the driver's own (this
file run as a program, :func:`produce`; :class:`HeartbeatProducerProcess` is the same kind of
process for the master heartbeat, :func:`produce_heartbeat`) with its own raw CAN socket sends
SYNC on absolute
deadlines t0 + k * period (:class:`SyncSchedule`; ``clock_nanosleep`` with ``TIMER_ABSTIME``
through ctypes, one clock read and one send per SYNC), as a C producer would; it needs nothing
of the chcos process - not its GIL, which a thread may hold for up to
``sys.getswitchinterval()`` - and inherits its CPUs and nice value. Its scheduling is the bus's
``sync_priority`` (:data:`DEFAULT_SYNC_PRIORITY` unless set): the producer makes itself
``SCHED_FIFO`` at that priority, above the controller's threads (its reader, at up to most of a
CPU at 1 kHz, would otherwise compete with it at equal priority, each SYNC waiting for the
scheduler's wake-up preemption), as a cycle producer in a control system runs; where the
process may not (neither root nor ``CAP_SYS_NICE``, ``RLIMIT_RTPRIO`` too low) it stays
``SCHED_OTHER`` and says so once, with the reason (a bus error of the driver);
``sync_priority = 0`` leaves it ``SCHED_OTHER`` without asking. The driver's
reader sees each SYNC come back with its kernel time stamp (:meth:`SyncCycle.seen`): cycles and
jitter are counted from what went on the wire, late is an interval longer than 1.5 periods.
The producer ends when the driver stops it and when the chcos process dies, SIGKILL included:
its stdin is a pipe from the driver (end of file when the kernel closes the dying process's
end) and it checks every 50 ms that its parent is unchanged. The same pipe carries its
liveness gate (:mod:`drivers.canopen_heartbeat`): it sends only while the driver wrote
:data:`FED` within the gate's time (``liveness_ms``) and not :data:`HELD` since, so a frozen
controller (its kernel stuck, its process stopped) stops SYNC too; the cycles not sent are
given up (reported as ``given-up N: ...``, counted in :attr:`SyncStats.given_up`), not caught
up.
``PR_SET_PDEATHSIG`` is not used: it fires when the thread that started the process ends.
Elsewhere (python-can's ``virtual`` bus, inside the chcos process) a thread sends SYNC on
absolute deadlines (:meth:`SyncCycle.start`) and counts from its send times - unless the nodes
are simulated on the kernel's virtual clock (a virtual cell): then :class:`ClockedSyncProducer`
sends SYNC n on a kernel timer at exactly t0 + n * period virtual seconds and the cycle counts
from those virtual times, so synchronous PDOs follow virtual time, not wall time (the kernel
lets the simulated nodes answer each SYNC before virtual time moves on).

Why not the kernel's broadcast manager: its cyclic job re-arms one period after each expiry
(``bcm.c``: the next expiry is ``ktime_get()`` + interval), not on a grid, so every late expiry
pushes all the following SYNCs back (in the User-Mode-Linux guest at 250 Hz, 7 to 20 % of the
SYNCs never sent while a C producer on absolute deadlines sent them all). Re-arming it on the
grid from the reader thread (a Python thread: it runs when it holds the GIL) measured a p99
jitter of 3.3 ms against the C producer's 0.3 ms at 250 Hz.
"""

from __future__ import annotations

import ctypes
import errno
import os
import resource
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO

SYNC_COB_ID = 0x080
#: cycles the jitter percentiles are computed over
WINDOW = 10_000
#: the shortest interval between two SYNCs while the producer process catches up after a late
#: one, as a fraction of the period (a shorter cycle would leave the nodes no time to answer)
MIN_INTERVAL = 0.5
#: behind its schedule by more than this (s), the producer process starts the schedule again
#: from now instead of catching up
MAX_BEHIND = 1.0
#: the producer process's first line on stdout once its socket is bound
READY = "ready"
#: at most one report per this many seconds of the producer process's failing sends
ERROR_EVERY = 1.0
#: how often (ns) the producer process checks that its parent is still the driver's process
PARENT_CHECK = 50_000_000
#: clock_nanosleep's flag for an absolute deadline
TIMER_ABSTIME = 1
#: the producer process's SCHED_FIFO priority unless the bus's ``sync_priority`` says otherwise
#: (1..99; 0: SCHED_OTHER): high, above the controller's threads, below the kernel's own
#: real-time threads (priority 99)
DEFAULT_SYNC_PRIORITY = 80
#: the highest SCHED_FIFO priority on Linux
MAX_SYNC_PRIORITY = 99
#: what the driver writes to a producer process's stdin: the controller is alive (its gate
#: opens for the gate's time), or it is not (the gate closes at once)
FED = "+"
HELD = "-"
#: the first argument of the producer program in its heartbeat mode
HEARTBEAT_MODE = "heartbeat"
#: a producer's report of cycles given up starts with this, then their number and ": "
GIVEN_UP = "given-up "


class SyncSchedule:
    """When the producer process sends each SYNC (nanoseconds, a monotonic clock): at the
    deadlines t0 + k * ``step``; after a late SYNC the next due one goes out no sooner than
    :data:`MIN_INTERVAL` steps after it, so the lost time is made up over the following cycles
    without a burst; behind by more than :data:`MAX_BEHIND` s (the machine stalled), the
    schedule starts again from now and the cycles given up are counted (``resynced``)."""

    def __init__(self, t0: int, step: int) -> None:
        if step <= 0:
            raise ValueError(f"SYNC period {step} ns: must be positive")
        self.step = step
        self._t0 = t0
        self._k = 0
        self._gap = round(MIN_INTERVAL * step)
        self._behind_max = round(MAX_BEHIND * 1e9)
        self.resynced = 0

    def restart(self, now: int) -> int:
        """Start the schedule again from ``now`` (the producer was held by the liveness gate:
        a controller that made no progress); the cycles that fell due meanwhile are given up
        (counted in :attr:`resynced`, and returned), not caught up."""
        due = self._t0 + (self._k + 1) * self.step
        skipped = max(0, (now - due) // self.step + 1) if now >= due else 0
        self.resynced += skipped
        self._t0, self._k = now, 0
        return skipped

    def next(self, now: int, last: int) -> int:
        """The time the next SYNC goes out, ``now`` being the time and ``last`` the time the
        previous one went out (t0 for the first)."""
        self._k += 1
        due = self._t0 + self._k * self.step
        if now - due > self._behind_max:
            self.resynced += (now - due) // self.step
            self._t0, self._k = now, 0
            return now
        return max(due, last + self._gap)


@dataclass(frozen=True)
class SyncStats:
    """The SYNC cycle's counters and jitter (seconds) so far."""

    period: float
    cycles: int
    complete: int
    missing: int
    late: int
    jitter_p50: float
    jitter_p99: float
    jitter_max: float
    #: acyclic synchronous TPDOs (transmission type 0) received, each in the cycle it came in
    acyclic: int = 0
    #: cycles the producer gave up: not sent after a stall of the machine (more than
    #: :data:`MAX_BEHIND` s behind) or while the controller made no progress (the liveness
    #: gate held it), and not caught up
    given_up: int = 0


@dataclass
class _Due:
    """A synchronous TPDO of the cycle: every ``every``-th SYNC, phase from its first arrival."""

    every: int
    phase: int | None = None
    arrived_in: int = -1


def percentile(sorted_values: list[float], q: float) -> float:
    """The ``q`` quantile (0..1, nearest rank) of ascending ``sorted_values``; 0 if empty."""
    if not sorted_values:
        return 0.0
    rank = min(len(sorted_values) - 1, max(0, round(q * (len(sorted_values) - 1))))
    return sorted_values[rank]


class SyncCycle:
    """SYNC producer and cycle bookkeeping (see the module doc). ``send(cob_id)`` puts a SYNC
    on the wire (raises on a bus error: reported through ``on_error`` and the cycle goes on)."""

    def __init__(self, period: float, send: Callable[[], None],
                 on_error: Callable[[str], None], name: str,
                 alive: Callable[[], bool] | None = None) -> None:
        self.period = period
        self._send = send
        self._on_error = on_error
        self._name = name
        #: the liveness gate of the producer thread (:meth:`start`): no SYNC while it says
        #: the controller makes no progress (None: always open); its bound (s), for reports
        self._alive = alive
        self.liveness = 0.0
        self._given_up = 0
        self._cond = threading.Condition()
        self._running = False
        self._thread: threading.Thread | None = None
        self._due: dict[int, _Due] = {}          # COB-ID -> its schedule
        #: acyclic synchronous TPDOs (type 0): COB-ID -> the last cycle one arrived in
        self._acyclic: dict[int, int] = {}
        self._acyclic_count = 0
        self.cycle = 0                           # the number of the last SYNC sent
        self._complete = 0
        self._missing = 0
        self._late = 0
        self._last_sent: float | None = None
        self._jitter: deque[float] = deque(maxlen=WINDOW)
        self._jitter_max = 0.0
        self._completed_upto = 0                 # the highest cycle known complete
        #: who is told each cycle's outcome (:meth:`watch`), and the highest cycle told
        self._watchers: list[Callable[[int, bool], None]] = []
        self._told_upto = 0

    def expect(self, cob_id: int, transmission_type: int) -> None:
        """A synchronous TPDO the cycle collects: type 1..240 is due every k-th cycle, type 0
        (acyclic synchronous) is counted when it comes and never due; other types are not the
        cycle's. Call before :meth:`start`."""
        if 1 <= transmission_type <= 240:
            self._due[cob_id] = _Due(transmission_type)
        elif transmission_type == 0:
            self._acyclic[cob_id] = -1

    def watch(self, fn: Callable[[int, bool], None]) -> Callable[[], None]:
        """Call ``fn(n, complete)`` once per cycle from now on, as soon as its outcome is
        known: complete when its last synchronous TPDO arrives, not complete when SYNC n+1
        goes out first; in cycle order, with this object's lock held (on the reader's or the
        producer's thread): ``fn`` must not block nor call back. Returns the function that
        ends the watch."""
        with self._cond:
            self._watchers.append(fn)
            self._told_upto = max(self._told_upto, self._completed_upto,
                                  self.cycle - 1 if self.cycle else 0)

        def unwatch() -> None:
            with self._cond:
                if fn in self._watchers:
                    self._watchers.remove(fn)
        return unwatch

    def _tell(self, n: int, complete: bool) -> None:
        """Tell the watchers cycle ``n``'s outcome; called with the lock held, so that they
        hear the cycles in order, each once."""
        self._told_upto = n
        for fn in self._watchers:
            fn(n, complete)

    def start(self, produce: bool = True) -> None:
        """Begin: with ``produce`` the producer thread sends SYNC; without it the caller's
        producer does: a process whose SYNCs the reader reports through :meth:`seen`, or a
        clock's timers sending through :meth:`send_at` (:class:`ClockedSyncProducer`)."""
        self._running = True
        if produce:
            self._thread = threading.Thread(target=self._loop, name=self._name, daemon=True)
            self._thread.start()

    def send_at(self, at: float) -> None:
        """Send one SYNC now, ``at`` being the time it goes out (clocked mode: the caller's
        timer, :class:`ClockedSyncProducer`): the cycle turns, counted at ``at``. Nothing once
        stopped; a failing send is reported through ``on_error`` and the cycle does not turn."""
        with self._cond:
            if not self._running:
                return
        self._send_counted(at)

    def seen(self, at: float) -> None:
        """A SYNC went on the wire at ``at`` (its receive time stamp, seconds): the cycle turns
        (observed mode: reader thread)."""
        with self._cond:
            if self._last_sent is not None and at - self._last_sent > 1.5 * self.period:
                self._late += 1
        self._sent(at)

    def stop(self) -> None:
        with self._cond:
            self._running = False
            self._cond.notify_all()
        t, self._thread = self._thread, None
        if t is not None and t is not threading.current_thread():
            t.join(timeout=2.0)

    def gave_up(self, n: int) -> None:
        """``n`` cycles were given up by the producer (not sent, not caught up): counted in
        :meth:`stats` (``given_up``) and :meth:`counters`."""
        with self._cond:
            self._given_up += n

    def _loop(self) -> None:
        start = time.monotonic()
        n = 0
        held_since: float | None = None
        missed = 0
        while True:
            n += 1
            deadline = start + n * self.period
            with self._cond:
                while self._running and (left := deadline - time.monotonic()) > 0:
                    self._cond.wait(left)
                if not self._running:
                    return
            alive = self._alive
            if alive is not None and not alive():
                if held_since is None:
                    held_since, missed = time.monotonic(), 0
                    self._on_error(f"SYNC held: no sign of the controller's progress within "
                                   f"liveness_ms {round(self.liveness * 1000)} (a stuck or "
                                   f"stopped controller)")
                missed += 1
                self.gave_up(1)
                continue
            if held_since is not None:
                self._on_error(f"SYNC resumed after {time.monotonic() - held_since:.2f} s "
                               f"held: {missed} not sent")
                held_since = None
            now = time.monotonic()
            if now - deadline > self.period / 2:
                with self._cond:
                    self._late += 1
                if now - deadline > self.period:     # far behind: resynchronise, skip cycles
                    skipped = int((now - deadline) // self.period)
                    start = now - n * self.period
                    if skipped:
                        self.gave_up(skipped)
            self._send_counted(None)

    def _send_counted(self, at: float | None) -> None:
        """Send one SYNC and turn the cycle, counted at ``at`` (None: the time it was sent);
        a failing send is reported through ``on_error`` and the cycle does not turn."""
        try:
            self._send()
        except Exception as exc:  # a bus error: reported, the cycle goes on
            self._on_error(f"SYNC not sent: {exc}")
            return
        self._sent(time.monotonic() if at is None else at)

    def _sent(self, at: float) -> None:
        """SYNC number ``cycle + 1`` is on the wire: close the previous cycle's books."""
        with self._cond:
            if self._last_sent is not None:
                j = abs(at - self._last_sent - self.period)
                self._jitter.append(j)
                self._jitter_max = max(self._jitter_max, j)
            self._last_sent = at
            closing = self.cycle
            if closing > 0:
                due = [d for d in self._due.values() if self._is_due(d, closing)]
                absent = sum(1 for d in due if d.arrived_in != closing)
                self._missing += absent
                if due and not absent:
                    self._complete += 1
                if self._watchers and closing > self._told_upto:
                    self._tell(closing, self._completed_upto >= closing)
            self.cycle += 1
            self._cond.notify_all()

    @staticmethod
    def _is_due(d: _Due, cycle: int) -> bool:
        return d.phase is not None and (cycle - d.phase) % d.every == 0

    def tpdo(self, cob_id: int) -> None:
        """A TPDO arrived (reader thread): counted for the current cycle if it is synchronous."""
        d = self._due.get(cob_id)
        if d is None:
            if cob_id in self._acyclic:
                with self._cond:
                    self._acyclic[cob_id] = self.cycle
                    self._acyclic_count += 1
            return
        with self._cond:
            cycle = self.cycle
            if d.phase is None:
                d.phase = cycle % d.every
            d.arrived_in = cycle
            if all(dd.arrived_in == cycle for dd in self._due.values()
                   if self._is_due(dd, cycle)):
                self._completed_upto = max(self._completed_upto, cycle)
                if self._watchers and cycle > self._told_upto:
                    self._tell(cycle, True)
            self._cond.notify_all()

    def acyclic_in(self, cob_id: int) -> int | None:
        """The cycle the last acyclic synchronous TPDO ``cob_id`` arrived in (None: none yet,
        or not a type-0 TPDO of this cycle)."""
        with self._cond:
            n = self._acyclic.get(cob_id, -1)
            return None if n < 0 else n

    def wait_cycle(self, n: int, timeout: float) -> bool:
        """Wait until cycle ``n`` is complete (every synchronous TPDO due in it arrived): True,
        or False once SYNC n+1 went out without them or ``timeout`` passed."""
        with self._cond:
            self._cond.wait_for(lambda: self._completed_upto >= n or self.cycle > n
                                or not self._running, timeout)
            return self._completed_upto >= n

    def counters(self) -> tuple[int, int, int, int]:
        """(cycles, missing, late, given up) without the jitter percentiles (cheap)."""
        with self._cond:
            return self.cycle, self._missing, self._late, self._given_up

    def stats(self) -> SyncStats:
        with self._cond:
            values = sorted(self._jitter)
            return SyncStats(self.period, self.cycle, self._complete, self._missing, self._late,
                             percentile(values, 0.5), percentile(values, 0.99), self._jitter_max,
                             self._acyclic_count, self._given_up)


class ClockedSyncProducer:
    """SYNC on a clock's timers (see the module doc): SYNC n goes out at exactly
    ``t0 + n * period`` of that clock, t0 being its time at :meth:`start`, through
    :meth:`SyncCycle.send_at`. ``now()`` reads the clock; ``at(when, fn)`` runs ``fn`` once at
    clock time ``when`` (a driver host's kernel timer, :meth:`drivers.base.DriverHost.at`)."""

    def __init__(self, cycle: SyncCycle, now: Callable[[], float],
                 at: Callable[[float, Callable[[], None]], None]) -> None:
        self._cycle = cycle
        self._now = now
        self._at = at
        self._t0 = 0.0
        self._n = 0
        self._running = False

    def start(self) -> None:
        """Start the cycle's books and arm the timer of SYNC 1."""
        self._cycle.start(produce=False)
        self._t0 = self._now()
        self._n = 0
        self._running = True
        self._arm()

    def _arm(self) -> None:
        # from t0 each time (not from the previous deadline), so no rounding accumulates
        self._at(round(self._t0 + (self._n + 1) * self._cycle.period, 9), self._fire)

    def _fire(self) -> None:
        if not self._running:
            return
        self._n += 1
        self._cycle.send_at(round(self._t0 + self._n * self._cycle.period, 9))
        self._arm()

    def stop(self) -> None:
        """No SYNC from now on (a timer already armed does nothing). Idempotent."""
        self._running = False


class ProducerProcess:
    """A frame producer on SocketCAN in a dedicated child process (see the module doc): this
    file run as a program with ``args`` (after the channel, period, parent pid and priority),
    its own raw CAN socket, absolute deadlines. It stops when :meth:`stop` closes its stdin, or
    when this process dies (its stdin reaches end of file; it also checks its parent's pid every
    :data:`PARENT_CHECK` ns). It runs ``SCHED_FIFO`` at ``priority`` (1..99; 0:
    ``SCHED_OTHER``) when the process may set that. With ``gate`` (s, > 0) it sends only while
    it is fed (:meth:`feed`) within ``gate`` seconds and the last feed said alive: the
    controller's liveness (:mod:`drivers.canopen_heartbeat`). Its reports (a failing send, a
    refused priority, a hold and its end, an unexpected exit) go to ``on_error``; a report of
    cycles given up (``given-up N: ...``) also to ``on_given_up(N)``."""

    #: what it produces, in its error messages
    what = "frame"

    def __init__(self, channel: str, period: float, on_error: Callable[[str], None],
                 name: str, priority: int = DEFAULT_SYNC_PRIORITY, gate: float = 0.0,
                 args: tuple[str, ...] = (),
                 on_given_up: Callable[[int], None] | None = None) -> None:
        if not 0 <= priority <= MAX_SYNC_PRIORITY:
            raise ValueError(f"sync_priority: expected 0..{MAX_SYNC_PRIORITY}, got {priority}")
        self.channel = channel
        self.period = period
        self.priority = priority
        self.gate = gate
        self._args = args
        self._on_error = on_error
        self._on_given_up = on_given_up
        self._name = name
        self._proc: subprocess.Popen[str] | None = None
        self._thread: threading.Thread | None = None
        self._stopping = False
        self._feed_lock = threading.Lock()

    @property
    def pid(self) -> int | None:
        """The producer process's id while it runs (None before :meth:`start`)."""
        return self._proc.pid if self._proc is not None else None

    def start(self) -> None:
        """Start the producer process and wait until its socket is bound. Raises OSError when
        it cannot start (no such interface, no AF_CAN), with its own words."""
        proc = subprocess.Popen(
            [sys.executable, "-I", os.path.abspath(__file__), *self._args, self.channel,
             repr(self.period), str(os.getpid()), str(self.priority), repr(self.gate)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        assert proc.stdout is not None
        first = proc.stdout.readline().strip()
        if first != READY:
            rest = proc.stdout.read()
            if proc.stdin is not None:
                proc.stdin.close()
            rc = proc.wait()
            words = " ".join(f"{first} {rest}".split()) or "no output"
            raise OSError(f"the {self.what} producer process for {self.channel} did not start "
                          f"(exit status {rc}): {words}")
        self._proc = proc
        self._thread = threading.Thread(target=self._listen, args=(proc, proc.stdout),
                                        name=self._name, daemon=True)
        self._thread.start()

    def feed(self, alive: bool) -> None:
        """Tell the producer whether the controller is alive (its gate opens for ``gate``
        seconds, or closes at once). Never blocks for long, never raises (a producer that
        ended is reported by its listener)."""
        proc = self._proc
        if proc is None or proc.stdin is None:
            return
        with self._feed_lock:
            try:
                proc.stdin.write(FED if alive else HELD)
                proc.stdin.flush()
            except (OSError, ValueError):
                pass

    def _listen(self, proc: subprocess.Popen[str], out: IO[str]) -> None:
        """The producer's reports (one line each) to ``on_error``, until it exits; an exit
        that :meth:`stop` did not ask for is reported too."""
        for line in out:
            text = line.strip()
            if not text:
                continue
            head, sep, rest = text.partition(": ")
            if sep and head.startswith(GIVEN_UP) and head[len(GIVEN_UP):].strip().isdigit():
                if self._on_given_up is not None:
                    self._on_given_up(int(head[len(GIVEN_UP):]))
                text = rest
            self._on_error(text)
        rc = proc.wait()
        if not self._stopping:
            self._on_error(f"the {self.what} producer process exited (status {rc}): no "
                           f"{self.what} on {self.channel} any more")

    def stop(self) -> None:
        """End the producer: close its stdin, wait for it (killed if it does not end within
        2 s). Idempotent; never raises."""
        self._stopping = True
        proc, self._proc = self._proc, None
        if proc is None:
            return
        try:
            with self._feed_lock:
                if proc.stdin is not None:
                    proc.stdin.close()
            proc.wait(timeout=2.0)
        except (OSError, subprocess.TimeoutExpired):
            proc.kill()
            proc.wait()
        t, self._thread = self._thread, None
        if t is not None and t is not threading.current_thread():
            t.join(timeout=2.0)


class SyncProducerProcess(ProducerProcess):
    """SYNC on SocketCAN from a dedicated child process (see :class:`ProducerProcess` and the
    module doc): SYNC every ``period`` s on absolute deadlines; cycles given up (a stall, the
    liveness gate) are reported to ``on_given_up``."""

    what = "SYNC"

    def __init__(self, channel: str, period: float, on_error: Callable[[str], None],
                 name: str, priority: int = DEFAULT_SYNC_PRIORITY, gate: float = 0.0,
                 on_given_up: Callable[[int], None] | None = None) -> None:
        super().__init__(channel, period, on_error, name, priority, gate, (),
                         on_given_up)


class HeartbeatProducerProcess(ProducerProcess):
    """The master's heartbeat (COB-ID 0x700 + ``node_id``, state OPERATIONAL) on SocketCAN
    from a dedicated child process (see :class:`ProducerProcess`): one every ``period`` s on
    absolute deadlines (a late one is not caught up: the next goes on the grid)."""

    what = "master heartbeat"

    def __init__(self, channel: str, period: float, node_id: int,
                 on_error: Callable[[str], None], name: str,
                 priority: int = DEFAULT_SYNC_PRIORITY, gate: float = 0.0) -> None:
        super().__init__(channel, period, on_error, name, priority, gate,
                         (HEARTBEAT_MODE, str(node_id)))


def producer_processes(parent: int, kind: str = "sync") -> list[int]:
    """The pids of the producer processes of ``kind`` (``"sync"``, ``"heartbeat"``) among
    process ``parent``'s children (what ``ps`` shows as ``... drivers/canopen_sync.py``): for
    tests and benchmarks that look at a producer from outside. Linux only (``/proc``)."""
    found = []
    for task in Path(f"/proc/{parent}/task").iterdir():
        try:                                     # a thread or child may end meanwhile
            children = (task / "children").read_text().split()
        except FileNotFoundError:
            continue
        for child in children:
            try:
                cmd = Path(f"/proc/{child}/cmdline").read_bytes().split(b"\0")
            except FileNotFoundError:
                continue
            at = next((i for i, arg in enumerate(cmd) if arg.endswith(b"canopen_sync.py")), -1)
            if at < 0:
                continue
            beat = at + 1 < len(cmd) and cmd[at + 1] == HEARTBEAT_MODE.encode()
            if beat == (kind == "heartbeat"):
                found.append(int(child))
    return found


def _absolute_sleep() -> Callable[[int], None]:
    """``sleep_until(t)``: sleep until ``t`` (ns, ``time.monotonic_ns``'s clock) with one
    ``clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME)`` call, as the C producer does (the GIL
    is released meanwhile); ``time.sleep`` where libc has no such call."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        call = libc.clock_nanosleep
    except (OSError, AttributeError):
        return lambda t: time.sleep(max(0, t - time.monotonic_ns()) * 1e-9)

    class Timespec(ctypes.Structure):
        _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]

    when = Timespec()
    ref = ctypes.byref(when)
    call.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p]
    call.restype = ctypes.c_int

    def sleep_until(t: int) -> None:
        when.tv_sec, when.tv_nsec = divmod(t, 1_000_000_000)
        while call(time.CLOCK_MONOTONIC, TIMER_ABSTIME, ref, None) == errno.EINTR:
            pass
    return sleep_until


class _Gate:
    """The producer program's liveness gate: open while the driver fed it (:data:`FED`)
    within ``bound`` ns and did not say :data:`HELD` since; always open without a bound. Fed by
    the stdin thread, asked by the main loop (plain attributes: one writer)."""

    def __init__(self, bound: int) -> None:
        self.bound = bound
        self.fed_at = time.monotonic_ns()
        self.held = False

    def feed(self, data: bytes) -> None:
        """What the driver wrote: its last word counts."""
        last = data.rstrip()[-1:]
        if last == FED.encode():
            self.fed_at, self.held = time.monotonic_ns(), False
        elif last == HELD.encode():
            self.held = True

    def open(self, now: int) -> bool:
        return self.bound <= 0 or (not self.held and now - self.fed_at <= self.bound)


def _watch_stdin(fd: int, gate: _Gate) -> None:
    """The producer's stdin is a pipe from the driver: what it writes feeds the gate; at its
    end (the driver stopped it, or the driver's process died and the kernel closed its end)
    the producer ends at once."""
    while data := os.read(fd, 4096):
        gate.feed(data)
    os._exit(0)


def real_time(priority: int, what: str = "SYNC") -> str | None:
    """Make the calling process ``SCHED_FIFO`` at ``priority`` (0: leave it as it is). None when
    done (or not asked for), else why it stays ``SCHED_OTHER`` (the kernel's refusal, and what
    would allow it); ``what`` names what it produces."""
    if priority <= 0:
        return None
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as exc:
        limit = str(resource.getrlimit(resource.RLIMIT_RTPRIO)[0])
        return (f"{what} runs without real-time priority (SCHED_OTHER, competing with the "
                f"controller's threads): SCHED_FIFO priority {priority} refused ({exc}); it "
                f"needs root, CAP_SYS_NICE or RLIMIT_RTPRIO >= {priority} (it is {limit}); "
                f"sync_priority = 0 does not ask")
    return None


def _open(channel: str) -> socket.socket | None:
    """A raw CAN socket on ``channel`` that receives nothing; None after saying why not."""
    try:
        sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
        sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER, b"")
        sock.bind((channel,))
    except OSError as exc:
        print(f"cannot open a raw CAN socket on {channel}: {exc}", flush=True)
        return None
    return sock


def _begin(priority: int, what: str, gate: float) -> tuple[_Gate, Callable[[int], None]]:
    """The common start of a producer program once its socket is bound: its priority, the
    stdin watcher feeding its gate (``gate`` s), :data:`READY`, the refusal if any."""
    sleep_until = _absolute_sleep()
    refused = real_time(priority, what)         # before the watcher thread: it inherits it
    g = _Gate(round(gate * 1e9))
    threading.Thread(target=_watch_stdin, args=(sys.stdin.fileno(), g), daemon=True).start()
    print(READY, flush=True)
    if refused is not None:
        print(refused, flush=True)
    return g, sleep_until


class _Hold:
    """The producer's reports of the gate: once when it closes, once (with what was not sent)
    when it opens again."""

    def __init__(self, what: str, channel: str, gate: float) -> None:
        self.what, self.channel, self.gate = what, channel, gate
        self.since: int | None = None
        self.missed = 0

    def closed(self, now: int) -> None:
        if self.since is None:
            self.since = now
            print(f"{self.what} on {self.channel} held: no sign of the controller's progress "
                  f"within liveness_ms {round(self.gate * 1000)} (a stuck or stopped "
                  f"controller)", flush=True)
        self.missed += 1

    def opened(self, now: int, given_up: bool) -> None:
        if self.since is None:
            return
        held = (now - self.since) / 1e9
        head = f"{GIVEN_UP}{self.missed}: " if given_up else ""
        print(f"{head}{self.what} on {self.channel} resumed after {held:.2f} s held: "
              f"{self.missed} not sent", flush=True)
        self.since, self.missed = None, 0


def produce(channel: str, period: float, parent: int,
            priority: int = DEFAULT_SYNC_PRIORITY, gate: float = 0.0) -> int:
    """The SYNC producer process's body (``python drivers/canopen_sync.py CHANNEL PERIOD
    PARENT PRIORITY GATE``): SYNC on ``channel`` on :class:`SyncSchedule`, until stdin ends or
    ``parent`` is no longer its parent, ``SCHED_FIFO`` at ``priority`` if it may
    (:func:`real_time`), only while its liveness gate is open (``gate`` s; 0: always). Prints
    :data:`READY` once bound, then one line per report (a refused priority, failing sends, a
    hold of the gate and its end, a stall that restarted the schedule; cycles given up as
    ``given-up N: ...``); when the socket cannot be opened or bound, says why instead and
    returns 1."""
    # Ctrl-C at a terminal reaches the whole process group: SYNC goes on until the driver,
    # shutting down, stops it
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    sock = _open(channel)
    if sock is None:
        return 1
    frame = struct.pack("=IB3x8s", SYNC_COB_ID, 0, b"")
    g, sleep_until = _begin(priority, "SYNC", gate)
    last = time.monotonic_ns()
    schedule = SyncSchedule(last, round(period * 1e9))
    hold = _Hold("SYNC", channel, gate)
    failed = 0
    reported = 0
    resynced = 0
    checked = last
    while True:
        now = last                               # one clock read per SYNC, after its send
        if now - checked >= PARENT_CHECK:
            if os.getppid() != parent:
                return 0
            checked = now
        at = schedule.next(now, last)
        if at > now:
            sleep_until(at)
        if schedule.resynced > resynced:
            n = schedule.resynced - resynced
            print(f"{GIVEN_UP}{n}: SYNC producer on {channel} stalled: schedule started "
                  f"again, {n} cycles given up", flush=True)
            resynced = schedule.resynced
        if not g.open(at):
            hold.closed(at)                      # this cycle is given up, not caught up
            last = max(at, time.monotonic_ns())
            continue
        hold.opened(at, given_up=True)
        try:
            sock.send(frame)
        except OSError as exc:
            failed += 1
            now = time.monotonic_ns()
            if now - reported >= ERROR_EVERY * 1e9:
                print(f"SYNC not sent on {channel} ({failed} since the last report): {exc}",
                      flush=True)
                failed, reported = 0, now
        last = time.monotonic_ns()


def produce_heartbeat(channel: str, period: float, parent: int, priority: int, gate: float,
                      node_id: int) -> int:
    """The master heartbeat producer process's body (``python drivers/canopen_sync.py
    heartbeat NODE CHANNEL PERIOD PARENT PRIORITY GATE``): the heartbeat of node ``node_id``
    (state OPERATIONAL) on ``channel`` at t0 + k * ``period`` (a deadline missed is not caught
    up: the next goes on the grid), only while its liveness gate is open; ends as
    :func:`produce` does, reports as it does."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    sock = _open(channel)
    if sock is None:
        return 1
    frame = struct.pack("=IB3x8s", 0x700 + node_id, 1, b"\x05")
    g, sleep_until = _begin(priority, "the master heartbeat", gate)
    step = round(period * 1e9)
    t0 = checked = time.monotonic_ns()
    hold = _Hold("the master heartbeat", channel, gate)
    k = 0
    failed = reported = 0
    while True:
        now = time.monotonic_ns()
        if now - checked >= PARENT_CHECK:
            if os.getppid() != parent:
                return 0
            checked = now
        k = max(k + 1, (now - t0) // step + 1)   # the next grid point, none caught up
        at = t0 + k * step
        sleep_until(at)
        if not g.open(at):
            hold.closed(at)
            continue
        hold.opened(at, given_up=False)
        try:
            sock.send(frame)
        except OSError as exc:
            failed += 1
            if at - reported >= ERROR_EVERY * 1e9:
                print(f"the master heartbeat not sent on {channel} ({failed} since the last "
                      f"report): {exc}", flush=True)
                failed, reported = 0, at


def main(argv: list[str]) -> int:
    """The producer program: ``[heartbeat NODE] CHANNEL PERIOD PARENT [PRIORITY [GATE]]``."""
    if argv[:1] == [HEARTBEAT_MODE]:
        node, rest = int(argv[1]), argv[2:]
        return produce_heartbeat(rest[0], float(rest[1]), int(rest[2]), int(rest[3]),
                                 float(rest[4]), node)
    return produce(argv[0], float(argv[1]), int(argv[2]),
                   int(argv[3]) if len(argv) > 3 else DEFAULT_SYNC_PRIORITY,
                   float(argv[4]) if len(argv) > 4 else 0.0)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
