"""support_fb - a fake DriverHost for the field-bus driver tests: a thread-safe recorder.

Every host call is recorded under one condition variable, so a test waits for what it expects
(``wait_for``) with a timeout instead of sleeping. ``every()`` registrations are kept and run only
when the test calls :meth:`FakeHost.tick`, on a virtual clock the test advances.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

WAIT = 5.0  # seconds a test waits for an expected event before it fails


@dataclass
class Periodic:
    """One ``every()`` registration (or, with period None, one ``at()``) and when it is next
    due on the virtual clock."""

    period: float | None
    fn: Callable[[], None]
    due: float = 0.0


@dataclass
class FakeHost:
    """Records deliver/fail/recover/error calls; a virtual clock drives ``every()`` callbacks."""

    delivered: list[tuple[str, Any]] = field(default_factory=list)
    failures: list[tuple[str, str]] = field(default_factory=list)
    recoveries: list[str] = field(default_factory=list)
    errors: list[tuple[str, str, str]] = field(default_factory=list)
    writes: list[tuple[str, Any, str]] = field(default_factory=list)  # (device, raw, failure)
    stats: dict[str, int] = field(default_factory=dict)
    #: errors counted without a report (the repeats of a streak, see drivers.reports)
    error_counts: dict[str, int] = field(default_factory=dict)
    periodics: list[Periodic] = field(default_factory=list)
    clock: float = 0.0
    cond: threading.Condition = field(default_factory=threading.Condition)

    # -- DriverHost ---------------------------------------------------------------------------

    def deliver(self, device: str, value: Any) -> None:
        with self.cond:
            self.delivered.append((device, value))
            self.cond.notify_all()

    deliver_now = deliver  # (no kernel thread here: the same)

    def deliver_many(self, readings: Sequence[tuple[str, Any]], at: float | None = None) -> None:
        """A batch of readings: each recorded as by :meth:`deliver`, in order."""
        with self.cond:
            self.delivered.extend(readings)
            self.cond.notify_all()

    def fail(self, device: str, reason: str) -> None:
        with self.cond:
            self.failures.append((device, reason))
            self.cond.notify_all()

    def recover(self, device: str, reason: str = "") -> None:
        with self.cond:
            self.recoveries.append(device)
            self.cond.notify_all()

    def error(self, bus: str, kind: str, detail: str, device: str = "") -> None:
        with self.cond:
            self.errors.append((bus, kind, detail))
            self.cond.notify_all()

    def written(self, device: str, value: Any) -> None:
        with self.cond:
            self.writes.append((device, value, ""))
            self.cond.notify_all()

    def write_failed(self, device: str, value: Any, reason: str) -> None:
        with self.cond:
            self.writes.append((device, value, reason or "failed"))
            self.cond.notify_all()

    def stat(self, bus: str, key: str, n: int = 1, device: str = "", error: bool = False
             ) -> None:
        with self.cond:
            counts = self.error_counts if error else self.stats
            counts[key] = counts.get(key, 0) + n
            self.cond.notify_all()

    def every(self, period: float, fn: Callable[[], None]) -> None:
        with self.cond:
            self.periodics.append(Periodic(period, fn, self.clock + period))

    def at(self, when: float, fn: Callable[[], None]) -> None:
        with self.cond:
            self.periodics.append(Periodic(None, fn, when))

    def now(self) -> float:
        with self.cond:
            return self.clock

    # -- test side ----------------------------------------------------------------------------

    def tick(self, dt: float | None = None) -> int:
        """Advance the virtual clock by ``dt`` (default: the shortest period) and run every
        callback that fell due, on the calling thread; returns how many ran."""
        with self.cond:
            if dt is None:
                dt = min((p.period if p.period is not None else max(0.0, p.due - self.clock)
                          for p in self.periodics), default=0.0)
            self.clock += dt
            due = [p for p in self.periodics if p.due <= self.clock + 1e-9]
            for p in due:
                if p.period is None:
                    self.periodics.remove(p)
                else:
                    p.due = self.clock + p.period
        for p in due:
            p.fn()
        return len(due)

    def wait_for(self, pred: Callable[[FakeHost], bool], timeout: float = WAIT) -> bool:
        """Block until ``pred(self)`` holds (checked on every recorded call); False on timeout."""
        with self.cond:
            return self.cond.wait_for(lambda: pred(self), timeout)

    def values(self, device: str) -> list[Any]:
        """Every value delivered to ``device``, in order."""
        with self.cond:
            return [v for d, v in self.delivered if d == device]

    def failed(self, device: str) -> list[str]:
        """The reasons of every failure reported for ``device``."""
        with self.cond:
            return [r for d, r in self.failures if d == device]

    def error_kinds(self) -> list[str]:
        """The ``kind`` of every error reported."""
        with self.cond:
            return [k for _, k, _ in self.errors]


def make_device(name: str, direction: str, bus: str, key: str = "device[0]",
                **address: Any) -> Any:
    """A :class:`chcos.devices.spec.DeviceSpec` on ``bus`` with ``address``."""
    from chcos.devices.spec import DeviceSpec

    return DeviceSpec(name=name, direction=direction, machine=0, bus=bus,  # type: ignore[arg-type]
                      address=address, key=key)
