"""threaded - the reader/writer-thread plumbing shared by stream drivers (raw CAN, serial).

:class:`ReaderThread` is the receive half, usable on its own (the CANopen driver): one thread
running a read loop, and the ``settle`` the kernel needs from it, in one of two ways:

- event-driven, when the link has a file descriptor (SocketCAN, a TCP serial server, a tty): the
  reader sleeps in ``select`` on that descriptor and a wake-up pipe
  (:meth:`ReaderThread.wait_readable`), and handles input by calling a non-blocking drain under
  ``lock``; the loop registers that drain with :meth:`ReaderThread.set_drain`. ``settle`` then
  runs the same drain itself, in the caller's thread, so everything already received by the
  operating system is handed over without waiting for any timer (a short receive timeout costs a
  whole timer tick on a virtual machine);
- polling otherwise (python-can's ``virtual`` interface, ``loop://``): the reader receives with a
  short timeout and calls :meth:`ReaderThread.idle` whenever a receive finds nothing, and
  ``settle`` waits for two such empty receives after it was called.

:class:`ThreadedDriver` adds the send half: a subclass writes ``_read_loop`` (run by its
ReaderThread ``_rx``) and ``_send`` (put one command on the wire); it may override ``_can_send`` to
hold commands back (a serial port not open yet). The base queues writes without blocking the
caller, runs the writer thread, starts and stops both threads, counts bus errors, and its
:meth:`ThreadedDriver.settle` settles the reader, then waits until the writer has sent every
queued command.

The fast path: a subclass whose link can take a command without waiting sets ``_inline`` and
writes ``_send_now``. A write that finds nothing queued and nothing being sent then claims the
send (``_sending``, under ``_cond``, exactly as the writer thread does, so order is kept) and is
put on the wire in the caller's thread (the kernel thread) without waiting; when the link cannot
take it at once (``_send_now`` returns False: a full transmit buffer), the write goes to the
front of the queue and the writer thread sends it with the usual timeout. Either way every write
is reported exactly once and in order through ``host.written``/``host.write_failed``.

The synchronous mode (``_synchronous``, set by a subclass before the threads would start):
a link that is a direct hand-off on the kernel thread (the in-process bus of virtual time,
whose peer answers inside the send) needs no thread at all. Neither thread is started; every
write is sent in the caller's thread by ``_send_direct`` (the fast path, and on its failure the
driver's own report of it), input arrives through the link's own callback, and
:meth:`ThreadedDriver.settle` returns at once: nothing is ever in flight.
"""

from __future__ import annotations

import contextlib
import os
import select
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

from chcos.devices.spec import BusSpec, DeviceSpec
from drivers.base import Driver, DriverHost


class ReaderThread:
    """One reader thread running ``loop()`` while :attr:`running`, and the settle of its input
    (see the module doc). ``lock`` is held by whoever drains."""

    def __init__(self, loop: Callable[[], None], name: str) -> None:
        self._loop = loop
        self.name = name
        self.lock = threading.Lock()
        self._cond = threading.Condition()
        self._drain: Callable[[], object] | None = None
        self._wake: tuple[int, int] | None = None
        self._idle_gen = 0
        self._offline = False
        self._thread: threading.Thread | None = None
        self.running = False

    def start(self) -> None:
        """Start the thread (once)."""
        r, w = os.pipe()
        os.set_blocking(r, False)
        os.set_blocking(w, False)
        self._wake = (r, w)
        self.running = True
        self._thread = threading.Thread(target=self._loop, name=self.name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Tell the loop to end, wake it and wait for it (not when called from the loop)."""
        with self._cond:
            self.running = False
            self._cond.notify_all()
        wake, self._wake = self._wake, None
        if wake is not None:
            with contextlib.suppress(OSError):
                os.write(wake[1], b"x")
        t, self._thread = self._thread, None
        if t is not None and t is not threading.current_thread():
            t.join(timeout=2.0)
        self.set_drain(None)
        if wake is not None:
            for fd in wake:
                with contextlib.suppress(OSError):
                    os.close(fd)

    def pause(self, seconds: float) -> None:
        """Loop: wait ``seconds`` (after an error), or less if stopped."""
        with self._cond:
            self._cond.wait_for(lambda: not self.running, seconds)

    def wait_readable(self, fd: int, timeout: float) -> bool:
        """Loop: sleep until ``fd`` has input (True), or until :meth:`stop` wakes it, the
        timeout passes or ``fd`` is closed under it (False)."""
        wake = self._wake
        if wake is None:
            return False
        try:
            ready, _, _ = select.select([fd, wake[0]], [], [], timeout)
        except (OSError, ValueError):
            return False
        if wake[0] in ready:
            with contextlib.suppress(OSError):
                os.read(wake[0], 64)
        return fd in ready

    def set_drain(self, drain: Callable[[], object] | None) -> None:
        """Make :meth:`settle` event-driven with ``drain`` (a call that hands over all input
        receivable now, without blocking; run under ``lock``), or polling again (None)."""
        with self.lock:
            self._drain = drain
        with self._cond:
            self._cond.notify_all()

    def set_offline(self, offline: bool) -> None:
        """Loop: the link is down (True: nothing can arrive, so :meth:`settle` returns at once
        instead of waiting for receives that never come) or open again (False)."""
        with self._cond:
            self._offline = offline
            self._cond.notify_all()

    def idle(self) -> None:
        """Loop (polling): a receive found nothing (wakes :meth:`settle`)."""
        with self._cond:
            self._idle_gen += 1
            self._cond.notify_all()

    def settle(self, timeout: float) -> bool:
        """Hand over everything that arrived before this call: drain it here (event-driven), or
        wait for two empty receives of the loop (polling). True at once when stopped; False on
        timeout."""
        if self._drain is not None:
            with self.lock:
                drain = self._drain
                if drain is not None:
                    drain()
                    return True
        with self._cond:
            if not self.running or self._offline:
                return True
            gen = self._idle_gen
            quiet = self._cond.wait_for(
                lambda: (not self.running or self._offline or self._idle_gen > gen + 1
                         or self._drain is not None), timeout)
        if quiet and self._drain is not None:  # the link opened meanwhile: drain it here
            with self.lock:
                if self._drain is not None:
                    self._drain()
        return quiet


class ThreadedDriver(Driver):
    """A driver with one reader and one writer thread (see the module doc). ``_send`` reports
    every write through ``host.written`` or ``host.write_failed``; writes still queued when the
    threads stop are reported failed."""

    confirms_writes = True
    numeric_only = True
    #: True for a class that overrides :meth:`_can_send` (set for each subclass): the fast
    #: path asks it only then (otherwise a command may always go: a call less per frame)
    _gated: ClassVar[bool] = False

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls._gated = cls._can_send is not ThreadedDriver._can_send

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        #: one lock under two conditions: ``_cond`` for whoever waits on the driver's state
        #: (settle, a port opening, stop), ``_work`` for the writer thread alone, notified only
        #: when it has a command to take or must stop, so a write on the fast path does not wake
        #: it (a thread switch per frame on one core)
        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self._work = threading.Condition(self._lock)
        self._outbox: deque[tuple[str, Any]] = deque()
        self._sending = False
        self._settling = 0      # callers waiting in settle() (under _lock)
        #: whether writes may take the fast path (see the module doc); set by a subclass
        self._inline = False
        #: the synchronous mode (see the module doc): no threads; set by a subclass
        self._synchronous = False
        self._writer: threading.Thread | None = None
        self._rx = ReaderThread(self._read_loop, f"{self.kind}-{bus.name}-rx")
        self.error_counts: Counter[str] = Counter()

    def _read_loop(self) -> None:
        raise NotImplementedError

    def _send(self, device: str, value: Any) -> None:
        """Put one command on the wire (writer thread); report failures to the host."""
        raise NotImplementedError

    def _send_now(self, device: str, value: Any, report: bool = True) -> bool:
        """Fast path (caller's thread, the send claimed): put one command on the wire without
        waiting and report it as ``_send`` does (True), or leave it untouched and unreported for
        the writer thread (False: the link cannot take it right now). With ``report`` False
        (:meth:`write_now`) True means on the wire, reported to nobody, and a value that cannot
        be encoded is left untouched too (False). Only called when ``_inline`` is set; the
        default hands every command to the writer."""
        return False

    def _can_send(self) -> bool:
        """Whether a taken command may go now (checked under ``_cond``); default always."""
        return True

    def _send_direct(self, device: str, value: Any) -> None:
        """Synchronous mode: put one command on the wire in the caller's thread and report it
        (``host.written``, or ``host.write_failed`` and what a failure means for the device).
        The default: the fast path, else ``_send``."""
        if not self._send_now(device, value):
            self._send(device, value)

    def _write_loop(self) -> None:
        while True:
            with self._lock:
                self._work.wait_for(lambda: (bool(self._outbox) and not self._sending)
                                    or not self._running)
                if not self._running:
                    return
                device, value = self._outbox.popleft()
                self._sending = True
                self._cond.wait_for(lambda: self._can_send() or not self._running)
                if not self._running:
                    self._sending = False
                    return
            try:
                self._send(device, value)
            except Exception as exc:    # a driver bug must not end the writer thread (later
                # writes would wait in the outbox forever): this write is reported failed
                reason = f"{self.kind} bus {self.bus.name}: sending failed: {exc!r}"
                self._error("internal", reason)
                self.host.write_failed(device, value, reason)
            finally:
                with self._lock:
                    self._sending = False
                    self._cond.notify_all()

    def _error(self, kind: str, detail: str) -> None:
        """Count and report a bus-level error (malformed frame, garbage line...)."""
        self.error_counts[kind] += 1
        self.host.error(self.bus.name, kind, detail)

    def _start_threads(self) -> None:
        """Start the reader and the writer, named ``<kind>-<bus>-rx``/``-tx`` (none in the
        synchronous mode)."""
        self._running = True
        if self._synchronous:
            self.settles = False      # nothing in flight: Devtab registers no settler
            return
        self._rx.start()
        self._writer = threading.Thread(target=self._write_loop,
                                        name=f"{self.kind}-{self.bus.name}-tx", daemon=True)
        self._writer.start()

    def _stop_threads(self) -> None:
        """Tell both threads to end and wait for them (a thread never waits for itself)."""
        with self._lock:
            self._running = False
            self._cond.notify_all()
            self._work.notify_all()
        self._rx.stop()
        t, self._writer = self._writer, None
        if t is not None and t is not threading.current_thread():
            t.join(timeout=2.0)
        with self._cond:
            left = list(self._outbox)
            self._outbox.clear()
        for device, value in left:
            self.host.write_failed(device, value, f"{self.kind} bus {self.bus.name} stopped "
                                                  f"before the write was sent")

    def _write(self, device: str, value: Any) -> None:
        """Send ``value`` to actuator ``device`` on the fast path when nothing is queued or being
        sent and the link takes it at once (see the module doc), else queue it for the writer
        thread; the outcome arrives as ``host.written``/``host.write_failed`` (on the fast path
        before this returns). Never blocks. In the synchronous mode it is sent here and now."""
        if self._synchronous:
            if self._running:
                self._send_direct(device, value)
            else:
                self._refuse(device, value, "stopped", f"{self.kind} bus {self.bus.name} is "
                                                       f"not running")
            return
        with self._lock:
            running = self._running     # stop() may have come between write's check and here
            inline = (running and self._inline and not self._outbox and not self._sending
                      and (not self._gated or self._can_send()))
            if inline:
                self._sending = True    # claimed: the writer thread waits, order is kept
            elif running:
                self._outbox.append((device, value))
                self._work.notify()
        if not running:
            self._refuse(device, value, "stopped", f"{self.kind} bus {self.bus.name} is not "
                                                   f"running")
            return
        if not inline:
            return
        sent = True     # an unexpected exception propagates; the command is not sent twice
        try:
            sent = self._send_now(device, value)
        finally:
            with self._lock:
                lost = not sent and not self._running
                if not sent and not lost:
                    self._outbox.appendleft((device, value))    # before any queued meanwhile
                self._claim_ends()
        if lost:
            self.host.write_failed(device, value, f"{self.kind} bus {self.bus.name} stopped "
                                                  f"before the write was sent")

    def _write_now(self, device: str, value: Any) -> bool:
        """The fast path without a confirmation to the host (see :meth:`Driver.write_now`):
        taken only when nothing is queued or being sent and the link takes the frame at once.
        The send holds ``_lock`` instead of claiming it: ``_send_now`` never waits, and with
        ``report`` False the host calls it makes (statistics, a recovery interrupt) take no lock
        of a driver's, so nobody waits long and the writer thread and settle() find the driver
        as they left it."""
        if not self._inline:
            return False
        with self._lock:
            return not (not self._running or self._outbox or self._sending
                        or (self._gated and not self._can_send())
                        or not self._send_now(device, value, False))

    def _write_now_many(self, writes: Sequence[tuple[str, Any]]) -> list[bool]:
        """:meth:`_write_now` for several actuators under one hold of ``_lock`` (an emergency
        stop's safe values, back to back): each as :meth:`_write_now` would, in order."""
        if not self._inline:
            return [False] * len(writes)
        with self._lock:
            free = (self._running and not self._outbox and not self._sending
                    and (not self._gated or self._can_send()))
            return [free and self._send_now(device, value, False) for device, value in writes]

    def _claimed(self, send: Callable[[], str | None], timeout: float = 0.5) -> str | None:
        """Run ``send`` (a frame that is no queued command: a probe, see
        :mod:`drivers.sendprobe`) holding the send as the writer thread does, once nothing is
        queued or being sent, so commands keep their order; its result, or why it did not run
        (stopped, or the link busy for ``timeout`` seconds). In the synchronous mode nothing
        else can be sending: it runs at once."""
        if self._synchronous:
            return send() if self._running else f"{self.kind} bus {self.bus.name} stopped"
        with self._lock:
            free = self._cond.wait_for(
                lambda: not self._running or (not self._outbox and not self._sending), timeout)
            if not self._running:
                return f"{self.kind} bus {self.bus.name} stopped"
            if not free:
                return "the link is busy with commands"
            self._sending = True
        try:
            return send()
        finally:
            with self._lock:
                self._claim_ends()
                self._cond.notify_all()

    def _claim_ends(self) -> None:
        """A fast-path send is over (under ``_lock``): the writer is woken only if commands
        were queued meanwhile, settle() if anyone waits in it."""
        self._sending = False
        if self._outbox:
            self._work.notify()
        if self._settling:
            self._cond.notify_all()

    def settle(self, timeout: float) -> bool:
        """Hand the host every frame or line that arrived before this call and wait until no
        command is queued or on its way (see the module doc). True at once when stopped; False
        on timeout; at once in the synchronous mode (nothing is in flight)."""
        if self._synchronous:
            return True
        deadline = time.monotonic() + timeout
        if not self._rx.settle(timeout):
            return False
        with self._cond:
            self._settling += 1
            try:
                return self._cond.wait_for(
                    lambda: not self._running or (not self._outbox and not self._sending),
                    max(0.0, deadline - time.monotonic()))
            finally:
                self._settling -= 1
