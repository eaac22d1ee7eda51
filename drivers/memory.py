"""memory - the bus-less driver: actuator writes kept in memory, sensor values from the host.

Used by examples and tests. Bus options: ``history`` (int >= 1, default 100: how many writes per
actuator are kept; older writes are also dropped once the kept ones exceed
:data:`HISTORY_BYTES` per actuator, so huge values cannot pile up; the last write is always
kept). Device addresses must be empty. Sensor values reach the Devtab only through the host side
(:meth:`MemoryDriver.inject` or ``host.deliver`` directly).
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from chcos.devices.options import between, option
from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.errors import DeviceError
from drivers.base import Driver, DriverHost

MAX_HISTORY = 1_000_000  # writes kept per actuator


@dataclass(frozen=True)
class MemoryOptions:
    """The options of a ``memory`` bus."""

    history: int = option(100, doc="writes kept per actuator",
                          check=between(1, MAX_HISTORY))


@dataclass(frozen=True)
class NoAddress:
    """The address of a device on a bus whose devices have none (``memory``): no key."""

    NO_KEYS: ClassVar[str] = "a memory device takes no address"


#: Most bytes of kept history per actuator (approximate: text and byte strings by length, other
#: values by the length of their repr), beyond the last write.
HISTORY_BYTES = 1024 * 1024


_NUMBER = (int, float)          # bool too (a subclass of int)
_TEXT = (str, bytes, bytearray)


def _size(value: Any) -> int:
    """What ``value`` counts against HISTORY_BYTES (tuples, not ``X | Y`` unions: this runs on
    every write, and a union is built anew at each call)."""
    if isinstance(value, _NUMBER) or value is None:
        return 8
    if isinstance(value, _TEXT):
        return len(value)
    return len(repr(value))


class ActuatorStore:
    """The last value and a bounded history of every write to a set of actuators; thread-safe.

    ``wait_for`` lets a test or the host block (with a timeout) until a write satisfies a predicate.
    """

    def __init__(self, actuators: Iterable[str], history: int) -> None:
        self._cond = threading.Condition()
        self._hist: dict[str, deque[Any]] = {a: deque(maxlen=history) for a in actuators}
        self._sizes: dict[str, deque[int]] = {a: deque(maxlen=history) for a in self._hist}
        self._count: dict[str, int] = dict.fromkeys(self._hist, 0)
        self._bytes: dict[str, int] = dict.fromkeys(self._hist, 0)  # sum of each _sizes deque

    def put(self, device: str, value: Any) -> None:
        """Record a write; raises :class:`DeviceError` if ``device`` is not one of the actuators."""
        with self._cond:
            if device not in self._hist:
                raise DeviceError(f"write to {device!r}: not an actuator of this bus; expected one "
                                  f"of {', '.join(self._hist) or 'none'}")
            hist, sizes = self._hist[device], self._sizes[device]
            size = _size(value)
            total = self._bytes[device] + size
            if len(sizes) == sizes.maxlen:     # the append drops the oldest
                total -= sizes[0]
            hist.append(value)
            sizes.append(size)
            while len(hist) > 1 and total > HISTORY_BYTES:
                hist.popleft()
                total -= sizes.popleft()
            self._bytes[device] = total
            self._count[device] += 1
            self._cond.notify_all()

    def last(self, device: str) -> Any:
        """The last value written to ``device`` (None if never written); DeviceError if unknown."""
        with self._cond:
            return self._known(device)[-1] if self._known(device) else None

    def history(self, device: str) -> list[Any]:
        """The kept writes to ``device``, oldest first; DeviceError if unknown."""
        with self._cond:
            return list(self._known(device))

    def count(self, device: str) -> int:
        """How many writes ``device`` has had in total (not bounded by the history)."""
        with self._cond:
            self._known(device)
            return self._count[device]

    def wait_for(self, device: str, pred: Callable[[Any], bool], timeout: float) -> bool:
        """Block until the last write to ``device`` satisfies ``pred``; False on timeout."""
        with self._cond:
            return self._cond.wait_for(
                lambda: bool(self._known(device)) and pred(self._hist[device][-1]), timeout)

    def _known(self, device: str) -> deque[Any]:
        try:
            return self._hist[device]
        except KeyError:
            raise DeviceError(f"{device!r} is not an actuator of this bus; expected one of "
                              f"{', '.join(self._hist) or 'none'}") from None


class MemoryDriver(Driver):
    """Driver for kind ``memory``: no I/O at all; writes land in :attr:`store`."""

    kind = "memory"
    Options: ClassVar[type | None] = MemoryOptions
    Address: ClassVar[type | None] = NoAddress

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        self.config = self.bus_options(bus, MemoryOptions)
        self.store = ActuatorStore(
            (d.name for d in devices if d.direction == "actuator"), self.config.history)

    def start(self) -> None:
        """Nothing to open."""
        self._running = True

    def stop(self) -> None:
        """Nothing to close."""
        self._running = False

    def settle(self, timeout: float) -> bool:
        """Always quiet: nothing is ever in flight."""
        return True

    def _write(self, device: str, value: Any) -> None:
        """Keep ``value`` as the last write of actuator ``device``."""
        self.store.put(device, value)

    def inject(self, device: str, value: Any) -> None:
        """Hand a reading of sensor ``device`` to the host; DeviceError if it is no sensor here."""
        spec = self.devices.get(device)
        if spec is None or spec.direction != "sensor":
            sensors = [n for n, d in self.devices.items() if d.direction == "sensor"]
            raise DeviceError(f"inject into {device!r} on bus {self.bus.name!r}: expected one of "
                              f"its sensors {', '.join(sensors) or '(none)'}")
        self.host.deliver(device, value)
