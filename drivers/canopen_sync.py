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

Two producers: on SocketCAN the kernel's broadcast manager sends SYNC (a cyclic job, no Python
thread between two SYNCs) and the driver's reader sees each one come back with its kernel time
stamp (:meth:`SyncCycle.seen`): cycles and jitter are counted from what went on the wire, late is
an interval longer than 1.5 periods. Elsewhere (python-can's ``virtual`` bus) a thread sends SYNC
on absolute deadlines (:meth:`SyncCycle.start`) and counts from its send times.

The broadcast manager re-arms its timer one period after each expiry, not on a fixed schedule:
every late expiry (timer latency of a loaded or virtual machine) pushes all the following SYNCs
back, and over a minute the bus loses cycles (measured in the User-Mode-Linux guest at 250 Hz: 7 %
of the SYNCs never sent, while a C producer on absolute deadlines sent them all).
:class:`SyncPacer` keeps it on the absolute schedule: after a SYNC seen late, the next one is
asked for at its due time, never sooner than half a period after the late one, so the lost time
is made up over the following cycles without a burst of SYNCs (a cycle shorter than half a
period would leave the nodes no time to answer). Behind by more than :data:`MAX_BEHIND` s (the
machine stalled), the schedule starts again from the late SYNC; the cycles lost are counted
(``resynced``).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

SYNC_COB_ID = 0x080
#: cycles the jitter percentiles are computed over
WINDOW = 10_000
#: a SYNC later than this fraction of a period behind its due time makes :class:`SyncPacer` ask
#: for the next one sooner
PACE_TOLERANCE = 0.05
#: the shortest interval the pacer asks for, as a fraction of the period
MIN_INTERVAL = 0.5
#: behind the schedule by more than this (s), the pacer starts it again instead of catching up
MAX_BEHIND = 1.0


class SyncPacer:
    """Keeps a producer that re-arms relative to its last send (the kernel's broadcast manager)
    on an absolute schedule of period ``period`` (see the module doc): :meth:`seen` is told
    each SYNC's wire time and answers when the next one must go out, or None when the
    producer's own timer is right. Used by one thread (the reader)."""

    def __init__(self, period: float) -> None:
        self.period = period
        self._t0: float | None = None
        self._k = 0
        #: SYNCs asked for early, and cycles given up when the schedule started again
        self.paced = 0
        self.resynced = 0

    def seen(self, at: float) -> float | None:
        """SYNC number k went on the wire at ``at`` (s, any clock): the time (same clock) the
        next one is due, if the producer's timer would send it later than that; else None."""
        p = self.period
        if self._t0 is None:
            self._t0 = at
            return None
        self._k += 1
        due = self._t0 + self._k * p
        behind = at - due
        if behind > MAX_BEHIND:
            lost = int(behind / p)
            self.resynced += lost
            self._t0 = at - self._k * p
            return None
        if behind <= PACE_TOLERANCE * p:
            return None
        self.paced += 1
        return max(due + p, at + MIN_INTERVAL * p)


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
    #: SYNCs the pacing asked for early after a late one, and cycles given up when it started
    #: the schedule again after a stall (:class:`SyncPacer`; 0 without pacing)
    paced: int = 0
    resynced: int = 0


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
                 on_error: Callable[[str], None], name: str) -> None:
        self.period = period
        self._send = send
        self._on_error = on_error
        self._name = name
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
        #: the pacing of the kernel's producer, if any (its counters go into :meth:`stats`)
        self.pacer: SyncPacer | None = None

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
        producer does and reports each SYNC on the wire through :meth:`seen`."""
        self._running = True
        if produce:
            self._thread = threading.Thread(target=self._loop, name=self._name, daemon=True)
            self._thread.start()

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

    def _loop(self) -> None:
        start = time.monotonic()
        n = 0
        while True:
            n += 1
            deadline = start + n * self.period
            with self._cond:
                while self._running and (left := deadline - time.monotonic()) > 0:
                    self._cond.wait(left)
                if not self._running:
                    return
            now = time.monotonic()
            if now - deadline > self.period / 2:
                with self._cond:
                    self._late += 1
                if now - deadline > self.period:     # far behind: resynchronise, skip cycles
                    start = now - n * self.period
            try:
                self._send()
            except Exception as exc:  # a bus error: reported, the cycle goes on
                self._on_error(f"SYNC not sent: {exc}")
                continue
            self._sent(time.monotonic())

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

    def counters(self) -> tuple[int, int, int]:
        """(cycles, missing, late) without the jitter percentiles (cheap)."""
        with self._cond:
            return self.cycle, self._missing, self._late

    def stats(self) -> SyncStats:
        with self._cond:
            values = sorted(self._jitter)
            pacer = self.pacer
            return SyncStats(self.period, self.cycle, self._complete, self._missing, self._late,
                             percentile(values, 0.5), percentile(values, 0.99), self._jitter_max,
                             self._acyclic_count, pacer.paced if pacer else 0,
                             pacer.resynced if pacer else 0)
