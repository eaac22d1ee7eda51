"""health - per-device failure causes shared by drivers: a device fails on its first cause and
recovers when its last cause clears (heartbeat lost and SDO abort at once, link down...)."""

from __future__ import annotations

import threading

from drivers.base import DriverHost


class Health:
    """Per-device failure causes; reports fail on the first cause and recover when none is left.
    Thread-safe."""

    def __init__(self, host: DriverHost) -> None:
        self._host = host
        self._lock = threading.Lock()
        self._causes: dict[str, dict[str, str]] = {}
        #: the reason last given to ``host.fail`` per failed device
        self._shown: dict[str, str] = {}

    def fail(self, device: str, cause: str, reason: str) -> None:
        """Add ``cause`` (a key such as ``"heartbeat"``, ``"link"``) to ``device``;
        ``host.fail`` if it is the first."""
        with self._lock:
            causes = self._causes.setdefault(device, {})
            report = cause not in causes
            causes[cause] = reason
            if report:
                self._shown[device] = reason
        if report:
            self._host.fail(device, reason)

    def restate(self, device: str, cause: str, reason: str) -> None:
        """``device`` stays failed for ``cause``, now for ``reason`` (a recovery that moved
        on): ``host.fail`` again with it, so that the reason shown is the true one; nothing if
        the device has no such cause or the reason is the same."""
        with self._lock:
            causes = self._causes.get(device)
            if not causes or cause not in causes or self._shown.get(device) == reason:
                return
            causes[cause] = reason
            self._shown[device] = reason
        self._host.fail(device, reason)

    def clear(self, device: str, cause: str, why: str = "") -> None:
        """Remove ``cause`` from ``device``; ``host.recover`` (with ``why``, the event that ended
        it) when it was the last one."""
        if not self._causes.get(device):       # the common case, a healthy device: no lock
            return
        with self._lock:
            causes = self._causes.get(device)
            if not causes or cause not in causes:
                return
            del causes[cause]
            recovered = not causes
            if recovered:
                self._shown.pop(device, None)
        if recovered:
            self._host.recover(device, why or f"{cause} failure ended")

    def has_causes(self, device: str) -> bool:
        """True while ``device`` has any failure cause, without the lock (a glance for the hot
        path: a healthy device skips building the recovery reason; :meth:`clear` decides)."""
        return bool(self._causes.get(device))

    def failed(self, device: str) -> bool:
        """True while ``device`` has any failure cause."""
        with self._lock:
            return bool(self._causes.get(device))
