"""sendprobe - no latch on a stream bus (raw CAN, serial): after a command that could not be
sent, the driver itself tries the link again until it takes a frame, and that recovers the
actuators.

A stream bus has no answer to read back (as Modbus has): what proves the link works again is a
frame that goes out. When a command of an actuator fails on the wire (a full transmit queue, a bus
gone error-passive or off, a serial write that timed out or failed), the driver reports the write
failed and the actuator failed (so Devtab refuses commands to it, saying so), and hands the
actuator to a :class:`SendProbe`. The probe's thread, backing off from ``backoff[0]`` to
``backoff[1]`` seconds (wall time: the link is real I/O), re-sends a value the peer already holds
or may always take: the last value of that actuator that went out (the peer holds it), or else its
safe value, raw (:func:`safe_raw`). A send failure is the link's (a full transmit queue, a bus off,
a port that does not drain), not one actuator's: the first frame that goes out on the bus, a probe
or a command of any actuator (a safe value on e-stop), recovers every actuator failed by a send
(the driver's ``_link_works`` takes them from :meth:`SendProbe.recovered` and calls
``host.recover``) and ends their probing; Devtab then writes their safe values first, as on every
recovery, and the owners' next commands go out as usual. The failed command itself is never sent
again. An actuator with neither value is not probed: a frame of another actuator, or the bus coming
back (a serial port open again, CAN frames received again), recovers it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from chcos.devices.spec import DeviceSpec


def safe_raw(spec: DeviceSpec) -> Any | None:
    """``spec``'s safe value as the driver gets it (Devtab's scale and offset undone, rounded
    for a device with ``round``), or None if it has none."""
    safe = spec.safe_value
    if safe is None or isinstance(safe, bool) or not isinstance(safe, (int, float)):
        return safe
    if spec.scale == 1 and spec.offset == 0:
        return safe
    raw = (safe - spec.offset) / spec.scale
    return round(raw) if spec.round else raw


@dataclass
class _Due:
    """One actuator to probe: when next, the pause after a failed try, the value to send."""

    at: float
    delay: float
    value: Any


class SendProbe:
    """One driver's actuators failed by a send, and their probing (see the module doc): the one
    owner of which actuators wait for the link. ``send(device, value)`` puts one probe on the
    wire in the probe's thread and returns None (the driver then recovered the actuators, see
    :meth:`recovered`), or why it failed. Thread-safe."""

    def __init__(self, name: str, send: Callable[[str, Any], str | None],
                 backoff: tuple[float, float]) -> None:
        self.name = name
        self._send = send
        self._backoff = backoff
        self._cond = threading.Condition()
        self._due: dict[str, _Due] = {}
        self._failed: set[str] = set()
        self._running = True
        self._thread: threading.Thread | None = None
        #: probes that went out (each recovered its actuator), and probes that failed
        self.sent = 0
        self.failed_tries = 0

    def failed(self, device: str, value: Any | None) -> None:
        """A command of ``device`` failed on the wire: it waits for the link, probed with
        ``value`` (None: nothing to probe with, the actuator recovers with the bus)."""
        with self._cond:
            self._failed.add(device)
            if value is None or not self._running:
                return
            due = self._due.get(device)
            if due is None:
                self._due[device] = _Due(time.monotonic() + self._backoff[0], self._backoff[0],
                                         value)
            else:
                due.value = value
            if self._thread is None:
                self._thread = threading.Thread(target=self._loop, name=f"{self.name}-probe",
                                                daemon=True)
                self._thread.start()
            self._cond.notify_all()

    @property
    def any_failed(self) -> bool:
        """Whether an actuator waits for the link (a lock-free look for the send path; a
        racing :meth:`failed` is seen by the next frame)."""
        return bool(self._failed)

    def recovered(self) -> list[str]:
        """A frame went out: the link works. The actuators that waited for it, in name order,
        no longer wait and are no longer probed; the driver recovers them."""
        with self._cond:
            failed, self._failed = self._failed, set()
            for device in failed:
                self._due.pop(device, None)
        return sorted(failed)

    def clear(self) -> None:
        """The whole bus came back (the driver recovers every device itself): nothing waits
        for the link any more."""
        with self._cond:
            self._failed.clear()
            self._due.clear()

    def stop(self) -> None:
        """End the probing (its thread too). Idempotent."""
        with self._cond:
            self._running = False
            self._failed.clear()
            self._due.clear()
            self._cond.notify_all()
            t, self._thread = self._thread, None
        if t is not None and t is not threading.current_thread():
            t.join(timeout=2.0)

    def _next(self) -> tuple[str, _Due] | None:
        """Wait (under ``_cond``) until a probe is due; None when stopped."""
        while self._running:
            if not self._due:
                self._cond.wait()
                continue
            device, due = min(self._due.items(), key=lambda kv: kv[1].at)
            wait = due.at - time.monotonic()
            if wait <= 0:
                return device, due
            self._cond.wait(wait)
        return None

    def _loop(self) -> None:
        while True:
            with self._cond:
                picked = self._next()
            if picked is None:
                return
            device, due = picked
            try:
                why = self._send(device, due.value)
            except Exception as exc:    # a driver bug must not end the probing
                why = f"probe failed: {exc!r}"
            with self._cond:
                if why is not None:
                    if self._due.get(device) is not due:    # ended or re-armed meanwhile
                        continue
                    self.failed_tries += 1
                    due.delay = min(due.delay * 2, self._backoff[1])
                    due.at = time.monotonic() + due.delay
                    continue
                if self._due.get(device) is due:    # (the driver ended it already)
                    del self._due[device]
                self.sent += 1


class ClockedSendProbe(SendProbe):
    """:class:`SendProbe` on the kernel clock, for a link whose sends run on the kernel thread
    (the direct bus of virtual time): each probe is a kernel timer (``at(when, fn)``, ``now()``:
    the driver host's), backing off the same way, so no thread and no wall clock decide when a
    probe goes out."""

    def __init__(self, name: str, send: Callable[[str, Any], str | None],
                 backoff: tuple[float, float], at: Callable[[float, Callable[[], None]], None],
                 now: Callable[[], float]) -> None:
        super().__init__(name, send, backoff)
        self._at = at
        self._now = now

    def failed(self, device: str, value: Any | None) -> None:
        """As :meth:`SendProbe.failed`; the probe is armed on the kernel clock."""
        with self._cond:
            self._failed.add(device)
            if value is None or not self._running:
                return
            due = self._due.get(device)
            if due is not None:
                due.value = value
                return
            due = self._due[device] = _Due(self._now() + self._backoff[0], self._backoff[0],
                                           value)
        self._at(due.at, lambda: self._fire(device, due))

    def _fire(self, device: str, due: _Due) -> None:
        """One probe of ``device`` (a kernel timer); armed again, backing off, if it fails."""
        if not self._running or self._due.get(device) is not due:
            return
        try:
            why = self._send(device, due.value)
        except Exception as exc:    # a driver bug must not end the probing
            why = f"probe failed: {exc!r}"
        if why is None:
            if self._due.get(device) is due:
                del self._due[device]
            self.sent += 1
            return
        if self._due.get(device) is not due:
            return
        self.failed_tries += 1
        due.delay = min(due.delay * 2, self._backoff[1])
        due.at = self._now() + due.delay
        self._at(due.at, lambda: self._fire(device, due))
