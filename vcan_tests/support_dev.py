"""support_dev - a fake DriverHost for driver tests: records everything, lets tests wait on it.

:class:`FakeHost` implements :class:`drivers.base.DriverHost`. Deliveries, failures, recoveries and
bus errors are recorded under one condition variable, so a test waits (with a timeout) for what a
driver thread does instead of sleeping. ``every()`` registrations are kept and run by
:meth:`FakeHost.advance`, which moves a virtual clock by hand.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from chcos.devices.spec import BusSpec, DeviceSpec

EXAMPLES = Path(__file__).resolve().parent.parent / "busconfig" / "examples"
CELL_DBC = EXAMPLES / "cell.dbc"
WAIT = 5.0


class FakeHost:
    """A DriverHost that records calls; thread-safe; virtual clock for ``every``."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self.delivered: list[tuple[str, Any]] = []
        self.failures: list[tuple[str, str]] = []
        self.recoveries: list[str] = []
        self.errors: list[tuple[str, str, str]] = []
        self.writes: list[tuple[str, Any, str]] = []   # (device, raw, failure or "")
        self.stats: dict[str, int] = {}
        self.timers: list[list[Any]] = []      # [period, next_due, fn]
        self.clock = 0.0

    def deliver(self, device: str, value: Any) -> None:
        with self._cond:
            self.delivered.append((device, value))
            self._cond.notify_all()

    deliver_now = deliver  # (no kernel thread here: the same)

    def deliver_many(self, readings: Sequence[tuple[str, Any]], at: float | None = None) -> None:
        """A batch of readings: each recorded as by :meth:`deliver`, in order."""
        with self._cond:
            self.delivered.extend(readings)
            self._cond.notify_all()

    def fail(self, device: str, reason: str) -> None:
        with self._cond:
            self.failures.append((device, reason))
            self._cond.notify_all()

    def recover(self, device: str, reason: str = "") -> None:
        with self._cond:
            self.recoveries.append(device)
            self._cond.notify_all()

    def error(self, bus: str, kind: str, detail: str, device: str = "") -> None:
        with self._cond:
            self.errors.append((bus, kind, detail))
            self._cond.notify_all()

    def written(self, device: str, value: Any) -> None:
        with self._cond:
            self.writes.append((device, value, ""))
            self._cond.notify_all()

    def write_failed(self, device: str, value: Any, reason: str) -> None:
        with self._cond:
            self.writes.append((device, value, reason or "failed"))
            self._cond.notify_all()

    def stat(self, bus: str, key: str, n: int = 1, device: str = "", error: bool = False
             ) -> None:
        with self._cond:
            self.stats[key] = self.stats.get(key, 0) + n

    def every(self, period: float, fn: Callable[[], None]) -> None:
        self.timers.append([period, self.clock + period, fn])

    def at(self, when: float, fn: Callable[[], None]) -> None:
        self.timers.append([None, when, fn])

    def now(self) -> float:
        return self.clock

    def advance(self, seconds: float) -> None:
        """Move the virtual clock, running every due ``every`` callback in time order."""
        end = self.clock + seconds
        while self.timers:
            t = min(self.timers, key=lambda x: float(x[1]))
            if t[1] > end + 1e-12:
                break
            self.clock = t[1]
            if t[0] is None:                 # at(): once
                self.timers.remove(t)
            else:
                t[1] += t[0]
            t[2]()
        self.clock = end

    def values(self, device: str) -> list[Any]:
        """Every value delivered for ``device`` so far."""
        with self._cond:
            return [v for d, v in self.delivered if d == device]

    def error_kinds(self) -> list[str]:
        with self._cond:
            return [k for _, k, _ in self.errors]

    def wait(self, pred: Callable[[FakeHost], object], timeout: float = WAIT) -> bool:
        """Wait until ``pred(self)`` holds (evaluated under the lock); False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: bool(pred(self)), timeout)


def bus(kind: str, name: str = "b", **options: Any) -> BusSpec:
    """A BusSpec for tests."""
    return BusSpec(name=name, kind=kind, options=options, file="test.toml", key="bus[0]")


def device(name: str, direction: str, bus_name: str = "b", i: int = 0,
           **address: Any) -> DeviceSpec:
    """A DeviceSpec for tests."""
    return DeviceSpec(name=name, direction="sensor" if direction == "sensor" else "actuator",
                      machine=0, bus=bus_name, address=address, file="test.toml",
                      key=f"device[{i}]")
