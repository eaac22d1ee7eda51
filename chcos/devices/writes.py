"""writes - actuator writes in flight: a driver that confirms its writes reports each one on the
wire or failed (from its own thread); a failed safe value is tried again, SAFE_ATTEMPTS in all,
unless a newer write is queued; what is finally not written is an event, a fault logged and,
for a safe value, an entry of ``safe_failures``."""

from __future__ import annotations

import threading
from collections import deque
from typing import Any

from chcos.devices.entry import DeviceEntry, Write
from chcos.devices.health import faults
from chcos.kernel.scheduler import Kernel

#: Attempts per safe value (e-stop, abnormal completion, shutdown, recovery) before it is
#: reported undelivered.
SAFE_ATTEMPTS = 3


class WriteTracking:
    """Confirmed and failed writes for :class:`chcos.devices.devtab.Devtab` (its base class)."""

    kernel: Kernel
    safe_failures: list[tuple[str, str]]
    _entries: dict[str, DeviceEntry]
    _wlock: threading.Lock
    _inflight: dict[str, deque[Write]]

    def written(self, device: str, value: Any) -> None:
        """The oldest outstanding write of ``device`` is on the wire (from a driver thread)."""
        with self._wlock:
            q = self._inflight.get(device)
            w = q.popleft() if q else None
        if w is None:
            return
        w.done = True
        self.kernel.interrupt(self._write_done, w)

    def write_failed(self, device: str, value: Any, reason: str) -> None:
        """The oldest outstanding write of ``device`` did not reach the wire (from a driver
        thread). A safe value is tried again (SAFE_ATTEMPTS in all) unless a newer write is
        queued; then it is reported undelivered."""
        with self._wlock:
            q = self._inflight.get(device)
            w = q.popleft() if q else None
            retry = (w is not None and bool(w.safe) and w.attempts < SAFE_ATTEMPTS and not q)
            if w is not None and retry:
                w.attempts += 1
                w.reason = reason
                self._inflight.setdefault(device, deque()).append(w)
        if w is None:
            return
        e = self._entries.get(device)
        if retry and e is not None and e.driver is not None:
            e.driver.write(device, w.raw)
            return
        w.done = False
        w.reason = reason
        self.kernel.interrupt(self._write_done, w)

    def _write_done(self, w: Write) -> None:
        """A confirmed or failed write, on the kernel thread: the shown value, the events."""
        e = self._entries.get(w.device)
        if e is None:
            return
        with self._wlock:
            left = len(self._inflight.get(w.device, ()))
        e.pending_count = left
        if left == 0:
            e.pending = None
        if w.done:
            e.value = w.value
            e.updated_at = self.kernel.clock.now()
            return
        e.write_errors += 1
        e.last_write_error = w.reason
        what = f"safe value ({w.safe})" if w.safe else "command"
        text = f"{w.device}: {what} {w.value!r} not written: {w.reason}"
        self.kernel.event("write-failed", text)
        if w.safe:
            self.safe_failures.append((w.device, w.reason))
            faults.error("%s", text)
        else:
            faults.warning("%s", text)
