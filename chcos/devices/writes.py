"""writes - actuator writes in flight: a driver that confirms its writes reports each one on the
wire or failed (from its own thread); a failed safe value is tried again, SAFE_ATTEMPTS in all,
unless a newer write is queued; what is finally not written is an event, a fault logged and,
for a safe value, an entry of ``safe_failures``.

An outcome reported from a driver thread reaches the kernel thread through ``kernel.interrupt``;
one reported on the kernel thread itself (a driver's fast path sends during the writing task's
step) is applied at once, unless an earlier outcome of the same device is still queued there
(then it queues behind it, so outcomes are applied in order).

Devtab's fast path (kernel thread) asks without the lock whether anything of a device is in
flight or has an outcome queued (:meth:`WriteTracking.outstanding`). Only the kernel thread
adds to the in-flight queues and takes queued outcomes off; another thread that ends a write
counts its queued outcome *before* it takes the write off the in-flight queue, and a safe value
tried again never leaves it. So whenever a thread switch falls between the two, the check still
sees one of them."""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from typing import Any

from chcos.devices.entry import Write
from chcos.devices.health import faults
from chcos.devices.observers import CommandReport, Observers, WriteStage
from chcos.devices.table import DeviceTable
from chcos.kernel.scheduler import Kernel

#: Attempts per safe value (e-stop, abnormal completion, shutdown, recovery) before it is
#: reported undelivered.
SAFE_ATTEMPTS = 3


class WriteTracking:
    """Confirmed and failed writes for :class:`chcos.devices.devtab.Devtab`, which owns one:
    the writes in flight per device (:meth:`track`), their outcomes from the drivers
    (:meth:`written`, :meth:`write_failed`) applied to the entries of ``table`` on the kernel
    thread, and a safe value finally not written handed to ``safe_failed(device, reason)``;
    each outcome is told to ``observers``."""

    def __init__(self, kernel: Kernel, table: DeviceTable,
                 safe_failed: Callable[[str, str], None],
                 observers: Observers | None = None) -> None:
        self._kernel = kernel
        self._table = table
        self._safe_failed = safe_failed
        self._observers = observers if observers is not None else Observers()
        self._lock = threading.Lock()
        self._inflight: dict[str, deque[Write]] = {}
        #: per device, outcomes queued to the kernel thread and not yet applied (under
        #: ``_lock``; None until the first)
        self._queued: dict[str, int] | None = None

    def track(self, w: Write) -> None:
        """``w`` is handed to its driver, which will report its outcome (any thread)."""
        with self._lock:
            q = self._inflight.get(w.device)
            if q is None:
                q = self._inflight[w.device] = deque()
            q.append(w)

    def outstanding(self, device: str) -> bool:
        """Whether a write of ``device`` is in flight or has an outcome on its way to the
        kernel thread. Asked on the kernel thread without the lock (see the module doc)."""
        queued = self._queued
        return bool(self._inflight.get(device)) or bool(queued and queued.get(device))

    def written(self, device: str, value: Any) -> None:
        """The oldest outstanding write of ``device`` is on the wire (from any thread; on the
        kernel thread applied at once, see the module doc)."""
        with self._lock:
            q = self._inflight.get(device)
            if not q:
                return
            now = self._kernel.on_kernel_thread() and not (self._queued and
                                                          self._queued.get(device))
            if not now:
                self._queue_outcome(device)     # first (see the module doc)
            w = q.popleft()
            w.done = True
        if now:
            self._write_done(w)
        else:
            self._kernel.interrupt(self._queued_done, w)

    def _queue_outcome(self, device: str) -> None:
        """Count one outcome of ``device`` queued to the kernel thread (under ``_wlock``)."""
        if self._queued is None:
            self._queued = {}
        self._queued[device] = self._queued.get(device, 0) + 1

    def _queued_done(self, w: Write) -> None:
        """A queued outcome reaches the kernel thread: uncount it, apply it."""
        with self._lock:
            if self._queued is not None:
                n = self._queued.get(w.device, 0) - 1
                if n > 0:
                    self._queued[w.device] = n
                else:
                    self._queued.pop(w.device, None)
        self._write_done(w)

    def write_failed(self, device: str, value: Any, reason: str) -> None:
        """The oldest outstanding write of ``device`` did not reach the wire (from a driver
        thread). A safe value is tried again (SAFE_ATTEMPTS in all) unless a newer write is
        queued; then it is reported undelivered."""
        with self._lock:
            q = self._inflight.get(device)
            if not q:
                return
            w = q[0]
            e = self._table.find(device)
            driver = e.driver if e is not None else None
            retry = (bool(w.safe) and w.attempts < SAFE_ATTEMPTS and len(q) == 1
                     and driver is not None)
            if retry:       # stays in flight, first: tried again below
                w.attempts += 1
                w.reason = reason
            else:
                self._queue_outcome(device)     # first (see the module doc)
                q.popleft()
        if driver is not None and retry:
            driver.write(device, w.raw)
            return
        w.done = False
        w.reason = reason
        self._kernel.interrupt(self._queued_done, w)

    def _write_done(self, w: Write) -> None:
        """A confirmed or failed write, on the kernel thread: the shown value, the events."""
        e = self._table.find(w.device)
        if e is None:
            return
        with self._lock:
            left = len(self._inflight.get(w.device, ()))
        if left == 0:
            e.pending = None
        if self._observers:
            self._observers.command(CommandReport(
                w.device, w.value, WriteStage.CONFIRMED if w.done else WriteStage.FAILED,
                safe=w.safe, reason=w.reason))
        if w.done:
            e.value = w.value
            e.updated_at = self._kernel.clock.now()
            return
        e.write_errors += 1
        e.last_write_error = w.reason
        what = f"safe value ({w.safe})" if w.safe else "command"
        text = f"{w.device}: {what} {w.value!r} not written: {w.reason}"
        self._kernel.event("write-failed", text)
        if w.safe:
            self._safe_failed(w.device, w.reason)
            faults.error("%s", text)
        else:
            faults.warning("%s", text)
