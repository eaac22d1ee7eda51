"""busstats - the bus counters of the device table: frames, requests, reconnects and errors by
class, per bus and per device, counted from the drivers' threads under one lock (or, for frames
sent, by each driver itself and pulled in when they are read) and read by the map, the viewer
and metrics."""

from __future__ import annotations

import logging
import threading
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from chcos.devices.observers import BusReport, Observers
from chcos.kernel.scheduler import Kernel

if TYPE_CHECKING:
    from chcos.devices.driver import Driver

log = logging.getLogger("chcos.devices.devtab")


@dataclass
class BusStats:
    """Counters of one bus, read by the map, the viewer and metrics.

    ``counts``: ``frames`` (received/sent), ``requests`` (Modbus/SDO), ``reconnects``, ``lost``
    (frames the OS dropped); ``errors``: by class (``timeout``, ``exception-6``,
    ``wrong-length``, ``crc``, ``overrun``, ``disconnected``...); ``devices``: the same keys per
    device (errors as ``error:<class>``); ``last_error``: the last error's text."""

    counts: Counter[str] = field(default_factory=Counter)
    errors: Counter[str] = field(default_factory=Counter)
    devices: dict[str, Counter[str]] = field(default_factory=dict)
    last_error: str = ""

    def copy(self) -> BusStats:
        """An independent copy (counters and per-device counters copied)."""
        return BusStats(Counter(self.counts), Counter(self.errors),
                        {d: Counter(c) for d, c in self.devices.items()}, self.last_error)

    def add_sent(self, sent: dict[str, int]) -> None:
        """Add a driver's frames sent per device (see
        :attr:`chcos.devices.driver.Driver.sent_frames`)
        as ``frames-sent``, per device and in all."""
        for device, n in sent.items():
            if n:
                self.counts["frames-sent"] += n
                self.devices.setdefault(device, Counter())["frames-sent"] += n

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON-able form."""
        return {"counts": dict(self.counts), "errors": dict(self.errors),
                "devices": {d: dict(c) for d, c in self.devices.items()},
                "last_error": self.last_error}


class BusCounters:
    """Bus statistics for :class:`chcos.devices.devtab.Devtab`, which owns one: what the drivers
    count through :meth:`stat` and :meth:`error` (any thread, under one lock), and what each
    running driver counts itself (``drivers()``: the running drivers, read when the statistics
    are), kept from a stopping driver by :meth:`keep_sent`. Every error is also told to
    ``observers`` (on the kernel thread, :meth:`bus_error`)."""

    def __init__(self, kernel: Kernel, drivers: Callable[[], Sequence[Driver]],
                 observers: Observers | None = None) -> None:
        self._kernel = kernel
        self._drivers = drivers
        self._observers = observers if observers is not None else Observers()
        #: what the drivers count through :meth:`stat`, per bus (under ``_lock``)
        self._stats: dict[str, BusStats] = {}
        self._lock = threading.Lock()

    @property
    def bus_stats(self) -> dict[str, BusStats]:
        """Per bus: frames/requests, errors by class, reconnects (see :class:`BusStats`); a
        snapshot, with the frames each running driver counted itself (``frames-sent``)."""
        with self._lock:
            out = {bus: st.copy() for bus, st in self._stats.items()}
        for drv in list(self._drivers()):
            sent = dict(drv.sent_frames)    # one C-level copy: the sender may be counting
            if sent:
                out.setdefault(drv.bus.name, BusStats()).add_sent(sent)
        return out

    def keep_sent(self, drv: Driver) -> None:
        """A driver stops and leaves the running ones: its own frame counts are copied into the
        stored statistics (the driver keeps its own; a restart makes new drivers)."""
        sent = dict(drv.sent_frames)
        if sent:
            with self._lock:
                self._stats.setdefault(drv.bus.name, BusStats()).add_sent(sent)

    def error(self, bus: str, kind: str, detail: str, device: str = "") -> None:
        """Count a bus-level error of class ``kind`` (from a driver thread)."""
        self.stat(bus, kind, device=device, error=True)
        self._kernel.interrupt(self.bus_error, bus, kind, detail, False, device)

    def stat(self, bus: str, key: str, n: int = 1, device: str = "", error: bool = False
             ) -> None:
        """Add ``n`` to bus counter ``key`` (from any thread; see :class:`BusStats`), or with
        ``error`` to error class ``key`` (a device's as ``error:<key>``)."""
        with self._lock:
            st = self._stats.get(bus)
            if st is None:
                st = self._stats[bus] = BusStats()
            (st.errors if error else st.counts)[key] += n
            if device:
                dc = st.devices.get(device)
                if dc is None:
                    dc = st.devices[device] = Counter()
                dc[f"error:{key}" if error else key] += n

    def stats_doc(self) -> dict[str, Any]:
        """The bus statistics as plain data, per bus (see :class:`BusStats`)."""
        return {bus: st.as_dict() for bus, st in sorted(self.bus_stats.items())}

    @property
    def bus_errors(self) -> Counter[tuple[str, str]]:
        """Errors by (bus, class), a copy derived from :attr:`bus_stats`."""
        with self._lock:
            return Counter({(bus, kind): n for bus, st in self._stats.items()
                            for kind, n in st.errors.items() if n})

    @property
    def last_bus_error(self) -> dict[str, str]:
        """The last error's text per bus (``"class: detail"``), derived from :attr:`bus_stats`."""
        with self._lock:
            return {bus: st.last_error for bus, st in self._stats.items() if st.last_error}

    def bus_error(self, bus: str, kind: str, detail: str, count: bool = True,
                  device: str = "") -> None:
        """On the kernel thread: an error of class ``kind`` on ``bus`` (of ``device``, if
        given) becomes its last error, a WARNING and a report to the observers (counted too
        unless ``count`` is False: :meth:`error` counted it)."""
        if count:
            self.stat(bus, kind, error=True)
        with self._lock:
            st = self._stats.get(bus)
            if st is not None:
                st.last_error = f"{kind}: {detail}"
        log.warning("bus %s: %s: %s", bus, kind, detail)
        if self._observers:
            self._observers.bus_error(BusReport(bus, kind, detail, device))
