"""canopen_heartbeat - the controller's liveness on a ``canopen`` bus: the master heartbeat
(COB-ID 0x700 + ``master_node_id``, state OPERATIONAL, every ``master_heartbeat_ms``) and the
gate that stops it, and SYNC, when the controller makes no progress.

A heartbeat exists to reveal a controller that no longer controls: a deadlock, a kernel thread
stuck in a task step, a stalled process, not only a dead one. So what tells the nodes the master
is alive follows the progress of the controller's kernel, not the life of a thread:
:class:`Liveness` is open while the kernel completed a scheduling round within the bus's
``liveness_ms`` (:attr:`chcos.kernel.scheduler.Kernel.progress`, through the host's
``progress()``; a host without it - a test's - counts the process's life only). When it
closes, the master heartbeat stops (a node's heartbeat consumer, 0x1016, then reacts as its
0x1029 says, CiA 301 7.2.8.3.2.2: the heartbeat *stops*, it does not report another state - a
consumer watches for the heartbeat's absence, not its content) and so does SYNC (the cycles not
sent are counted given up, not caught up later).

The producers, by where the bus is:

* **SocketCAN**: a process of its own (:class:`drivers.canopen_sync.HeartbeatProducerProcess`,
  the same kind as the SYNC producer: its own raw CAN socket, absolute deadlines, ``SCHED_FIFO``
  at ``sync_priority``), so that a loaded controller does not delay it (no GIL, no Python
  thread of chcos in its way) and so that it ends with the chcos process, SIGKILL included. Its
  gate is fed by :class:`LivenessFeed`, a thread of the driver that looks at the kernel's
  progress every quarter of ``liveness_ms`` and writes ``+`` (alive) or ``-`` (stuck) to the
  producer's stdin; the producer stops at once on ``-`` and by itself when nothing came for
  ``liveness_ms`` (the whole chcos process stopped: SIGSTOP, a machine that swaps).
* **Other python-can interfaces** (virtual, udp_multicast): :class:`HeartbeatThread`, a thread
  of the driver on absolute deadlines that asks the gate before each heartbeat.
* **A virtual cell** (virtual clock, nodes simulated on it): :class:`ClockedHeartbeat`, on the
  kernel's timers: a kernel that makes no progress fires no timer, and virtual time is the
  nodes' time too.

What it implies for the consumer times: a healthy node's ``master_consumer_ms`` must exceed
``master_heartbeat_ms`` plus the producer's jitter (``chcos check`` warns below 1.5 times); a
frozen controller is noticed by the node at most ``liveness_ms`` (plus a quarter of it, the
feed's look) plus ``master_consumer_ms`` after its last scheduling round.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from drivers.base import DriverHost

#: how often, as a fraction of ``liveness_ms``, the feed looks at the kernel's progress
FEED_FRACTION = 0.25
#: the feed's shortest look interval (s)
MIN_FEED = 0.01


def host_progress(host: DriverHost) -> Callable[[], float] | None:
    """``host.progress`` (when its kernel last made progress, on its clock: what
    :class:`chcos.devices.devtab.Devtab` has), or None for a host that does not say."""
    fn = getattr(host, "progress", None)
    return fn if callable(fn) else None


def held_text(what: str, liveness: Liveness) -> str:
    """A producer's report that its gate closed (the words :func:`is_hold` knows)."""
    return (f"{what} held: no sign of the controller's progress within liveness_ms "
            f"{round(liveness.bound * 1000)} (a stuck or stopped controller; no progress for "
            f"{liveness.stalled_for():.2f} s)")


def resumed_text(what: str, seconds: float, missed: int) -> str:
    """A producer's report that its gate opened again, with what it did not send."""
    return f"{what} resumed after {seconds:.2f} s held: {missed} not sent"


def is_hold(text: str) -> bool:
    """True for a producer's report of a hold (its process's words or :func:`held_text`)."""
    return " held: no sign of the controller's progress" in text


def is_resume(text: str) -> bool:
    """True for a producer's report that its hold ended."""
    return " resumed after " in text and " s held: " in text


class Liveness:
    """Whether the controller is alive: its kernel completed a scheduling round within
    ``bound`` seconds of the host's clock (``host.progress()``; always alive with ``bound``
    0 or a host without it: then only the process's own life counts, since whoever asks runs in
    it). Thread-safe."""

    def __init__(self, host: DriverHost, bound: float) -> None:
        self.bound = bound
        self._now = host.now
        self._progress = host_progress(host) if bound > 0 else None

    @property
    def gated(self) -> bool:
        """True if the kernel's progress is watched (a bound, and a host that tells it)."""
        return self._progress is not None

    def stalled_for(self) -> float:
        """Seconds since the kernel was last seen making progress (0 when not watched)."""
        progress = self._progress
        return 0.0 if progress is None else max(0.0, self._now() - progress())

    def alive(self) -> bool:
        """True while the kernel made progress within the bound (or it is not watched)."""
        return self._progress is None or self.stalled_for() <= self.bound


class LivenessFeed:
    """A thread that tells the producer processes whether the controller is alive (their
    ``feed(alive)``), every :data:`FEED_FRACTION` of the bound. Its looks are wall-clock
    waits: it watches a kernel that may be stuck, whose clock then says nothing. Each producer
    reports its own hold and its end (what it did not send)."""

    def __init__(self, liveness: Liveness, feeds: list[Callable[[bool], None]],
                 name: str) -> None:
        self._liveness = liveness
        self._feeds = list(feeds)
        self._name = name
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._every = max(MIN_FEED, liveness.bound * FEED_FRACTION)

    def start(self) -> None:
        self._thread = threading.Thread(target=self._loop, name=self._name, daemon=True)
        self._thread.start()

    def add(self, feed: Callable[[bool], None]) -> None:
        """Feed one more producer from now on (fed once at once: a producer process's gate is
        open for the gate's time from its start, however long the next one takes to start)."""
        self._feeds.append(feed)
        feed(self._liveness.alive())

    def stop(self) -> None:
        """End the thread and wait for it. Idempotent."""
        self._stop.set()
        t, self._thread = self._thread, None
        if t is not None and t is not threading.current_thread():
            t.join(timeout=2.0)

    def _loop(self) -> None:
        while not self._stop.is_set():
            alive = self._liveness.alive()
            for feed in list(self._feeds):
                feed(alive)
            self._stop.wait(self._every)


class HeartbeatThread:
    """The master heartbeat from a thread of the driver (python-can interfaces other than
    SocketCAN): ``send()`` every ``period`` s on absolute deadlines (wall time: the nodes'
    time; a late one is not caught up), only while ``liveness.alive()``; a failing send is
    reported through ``on_error`` once per second, a hold once when it begins and once when it
    ends."""

    def __init__(self, send: Callable[[], None], period: float, liveness: Liveness,
                 on_error: Callable[[str], None], name: str) -> None:
        self._send = send
        self.period = period
        self._liveness = liveness
        self._on_error = on_error
        self._name = name
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        #: heartbeats sent, and not sent while the gate held them
        self.sent = 0
        self.held = 0

    def start(self) -> None:
        self._thread = threading.Thread(target=self._loop, name=self._name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """No heartbeat from now on; waits for the thread. Idempotent."""
        self._stop.set()
        t, self._thread = self._thread, None
        if t is not None and t is not threading.current_thread():
            t.join(timeout=2.0)

    def _loop(self) -> None:
        t0 = time.monotonic()
        k = 0
        held_since: float | None = None
        missed = 0
        reported = -1.0
        while True:
            k = max(k + 1, int((time.monotonic() - t0) / self.period) + 1)
            if self._stop.wait(max(0.0, t0 + k * self.period - time.monotonic())):
                return
            if not self._liveness.alive():
                if held_since is None:
                    held_since, missed = time.monotonic(), 0
                    self._on_error(held_text("the master heartbeat", self._liveness))
                missed += 1
                self.held += 1
                continue
            if held_since is not None:
                self._on_error(resumed_text("the master heartbeat",
                                            time.monotonic() - held_since, missed))
                held_since = None
            try:
                self._send()
                self.sent += 1
            except Exception as exc:  # a bus error: reported, the heartbeat goes on
                now = time.monotonic()
                if now - reported >= 1.0:
                    self._on_error(f"the master heartbeat not sent: {exc}")
                    reported = now


class ClockedHeartbeat:
    """The master heartbeat on the host's timers (a virtual cell): ``send()`` at t0 + k *
    ``period`` of the host's clock, t0 its time at :meth:`start` (``host.at``). A kernel that
    makes no progress fires no timer: no gate is needed."""

    def __init__(self, send: Callable[[], None], period: float, host: DriverHost,
                 on_error: Callable[[str], None]) -> None:
        self._send = send
        self.period = period
        self._host = host
        self._on_error = on_error
        self._t0 = 0.0
        self._k = 0
        self._running = False
        self.sent = 0

    def start(self) -> None:
        self._t0 = self._host.now()
        self._k = 0
        self._running = True
        self._arm()

    def _arm(self) -> None:
        self._host.at(round(self._t0 + (self._k + 1) * self.period, 9), self._fire)

    def _fire(self) -> None:
        if not self._running:
            return
        self._k += 1
        try:
            self._send()
            self.sent += 1
        except Exception as exc:  # a bus error: reported, the heartbeat goes on
            self._on_error(f"the master heartbeat not sent: {exc}")
        self._arm()

    def stop(self) -> None:
        """No heartbeat from now on (a timer already armed does nothing). Idempotent."""
        self._running = False

