"""devtab - the device manager: Devtab, the last-value buffers, and the drivers behind them.

Each sensor or actuator of the device maps has one Devtab entry (every satellite keeps the whole
table; only the devices of its own machines get drivers). A new sensor reading is an interrupt:
it lands in the entry's last-value buffer (a newer reading overwrites an unread older one, counted)
and on every sensory link leaving the device, readying the tasks that read it. A sensor without
fresh data for ``stale_after`` seconds turns STALE and its readers get a sensor failure. Actuator
writes are checked against limits (refused, never clamped), scaled, and handed to the driver
without blocking; safe values go out on e-stop, abnormal completion of the owning task and
shutdown. Devtab is the :class:`drivers.base.DriverHost` its drivers talk to.
"""

from __future__ import annotations

import contextlib
import enum
import logging
import math
import threading
from collections import Counter, deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from chcos.devices.spec import DeviceMap, DeviceSpec
from chcos.errors import BusError, DeviceError, SensorFailure
from chcos.kernel.scheduler import Kernel, Timer
from chcos.tables.messages import EndpointKind, InPort, Link

if TYPE_CHECKING:
    from chcos.messages.manager import MessageManager
    from chcos.tables.tasks import TaskEntry
    from drivers.base import Driver

log = logging.getLogger("chcos.devices.devtab")
#: Faults a user must see whatever the log level (failed and refused writes, undelivered safe
#: values, health changes): WARNING records of this logger pass a root logger set to ERROR.
faults = logging.getLogger("chcos.devices.devtab.faults")
faults.setLevel(logging.WARNING)

#: Attempts per safe value (e-stop, abnormal completion, shutdown, recovery) before it is
#: reported undelivered.
SAFE_ATTEMPTS = 3
#: Seconds each driver gets at shutdown to put the safe values on the wire.
SHUTDOWN_FLUSH = 5.0


class DeviceStatus(enum.Enum):
    """Devtab status values."""

    OK = "OK"
    SUSPENDED = "suspended"
    FAILED = "failed"
    STALE = "stale"


@dataclass(eq=False)
class DeviceEntry:
    """One Devtab row: the spec, the status and the last-value buffer."""

    spec: DeviceSpec
    status: DeviceStatus = DeviceStatus.OK
    reason: str = ""
    value: Any = None  # last reading (engineering units) or last command
    updated_at: float | None = None
    readings: int = 0
    overwrites: int = 0
    dropped: int = 0
    commands: int = 0
    rejected: int = 0
    links: list[Link] = field(default_factory=list)
    driver: Driver | None = None
    stale_timer: Timer | None = None
    failure: str = ""          # the driver-reported failure ("" none); cleared only by the driver
    stale: bool = False        # no fresh data for stale_after; cleared only by fresh data
    since: float | None = None  # kernel time of the last status change
    rx_at: float | None = None  # driver receive time of the last reading
    pending: Any = None        # a command handed to the driver, not yet on the wire
    pending_count: int = 0
    write_errors: int = 0
    last_write_error: str = ""

    @property
    def name(self) -> str:
        """The device's name."""
        return self.spec.name

    @property
    def is_sensor(self) -> bool:
        """True for an input device."""
        return self.spec.direction == "sensor"


def _scalable(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


@dataclass(eq=False)
class _Write:
    """One write handed to a driver that confirms writes, until it is confirmed or failed."""

    device: str
    value: Any           # engineering units (what the map shows once written)
    raw: Any             # what the driver got
    safe: str = ""       # why a safe value ("shutdown", "recovery"...); "" for a command
    attempts: int = 1
    done: bool | None = None    # None pending, True on the wire, False failed
    reason: str = ""


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

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON-able form."""
        return {"counts": dict(self.counts), "errors": dict(self.errors),
                "devices": {d: dict(c) for d, c in self.devices.items()},
                "last_error": self.last_error}


class Devtab:
    """The device table of one satellite, and the host of its drivers."""

    def __init__(self, kernel: Kernel, msgmgr: MessageManager) -> None:
        self.kernel = kernel
        self.msgmgr = msgmgr
        msgmgr.devtab = self
        self._entries: dict[str, DeviceEntry] = {}
        self.drivers: list[Driver] = []
        self.on_write: list[Callable[[str, Any], None]] = []
        #: Per bus: frames/requests, errors by class, reconnects (see :class:`BusStats`).
        self.bus_stats: dict[str, BusStats] = {}
        self._stats_lock = threading.Lock()
        #: (device, reason) of every safe value that could not be put on the wire, oldest first.
        self.safe_failures: list[tuple[str, str]] = []
        self._health_listeners: list[Callable[[str, bool, str], None]] = []
        self._wlock = threading.Lock()
        self._inflight: dict[str, deque[_Write]] = {}
        self._rx_stamp: dict[str, float] = {}

    def suspend(self, device: str) -> None:
        """Host ``suspend`` of a device: SUSPENDED (readings dropped, commands refused) until
        :meth:`resume`. Raises DeviceError for an unknown device."""
        self.get(device)
        self._set_status(device, DeviceStatus.SUSPENDED, "suspended by the host")

    def resume(self, device: str) -> None:
        """Undo :meth:`suspend`: the device takes the status its health gives (a failure its
        driver reported meanwhile, staleness, else OK); one that is not suspended is left as
        it is. Raises DeviceError for an unknown device."""
        e = self.get(device)
        if e.status is DeviceStatus.SUSPENDED:
            status, reason = self._health_status(e)
            self._set_status(device, status, reason, ended="resumed by the host")

    # ---- table ------------------------------------------------------------------------------
    def load(self, devmap: DeviceMap) -> None:
        """Enter every device of ``devmap``; raises DeviceError (nothing entered) if a name is
        already in the table."""
        clash = [d.name for d in devmap.devices if d.name in self._entries]
        if clash:
            raise DeviceError(f"device(s) already in Devtab: {', '.join(clash)}")
        for spec in devmap.devices:
            self._entries[spec.name] = DeviceEntry(spec)

    def get(self, name: str) -> DeviceEntry:
        """The entry called ``name``; raises DeviceError naming it if there is none."""
        try:
            return self._entries[name]
        except KeyError:
            raise DeviceError(f"no device named {name!r} in Devtab") from None

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def __iter__(self) -> Iterator[DeviceEntry]:
        return iter(self._entries.values())

    def __len__(self) -> int:
        return len(self._entries)

    # ---- drivers ----------------------------------------------------------------------------
    def start_drivers(self, devmap: DeviceMap, machines: Iterable[int] | None = None) -> None:
        """Start a driver for every bus that has devices on ``machines`` (all if None).

        Raises BusError (every driver started so far is stopped again) if one fails to start, and
        DriverNotAvailable for an unknown bus kind.
        """
        from drivers.registry import driver_class

        wanted = None if machines is None else set(machines)
        started: list[Driver] = []
        try:
            for bus in devmap.buses:
                devs = [d for d in devmap.devices_on(bus.name)
                        if wanted is None or d.machine in wanted]
                if not devs:
                    continue
                drv = driver_class(bus.kind)(bus, devs, self)
                drv.start()
                started.append(drv)
                for d in devs:
                    self.get(d.name).driver = drv
                self.kernel.add_settler(drv.settle)
        except Exception as exc:
            for drv in started:
                drv.stop()
            if isinstance(exc, BusError):
                raise
            raise BusError(f"cannot start bus drivers: {exc}") from exc
        self.drivers.extend(started)
        for e in self._entries.values():
            if e.is_sensor and e.spec.stale_after is not None and e.driver is not None:
                self._arm_stale(e, self.kernel.clock.now())

    def stop_drivers(self) -> list[tuple[str, str]]:
        """Write safe values (whatever state the actuators are in), let every driver put them on
        the wire (up to SHUTDOWN_FLUSH s each), then stop every driver. Never raises; returns
        (device, reason) of every safe value that was not delivered (also logged). Without
        running drivers (none started, or already stopped) there is nothing to do."""
        undelivered: list[tuple[str, str]] = []
        if not self.drivers:
            return undelivered
        try:
            issued = self._safe_all("shutdown")
            for drv in self.drivers:
                try:
                    drv.flush(SHUTDOWN_FLUSH)
                except Exception:
                    log.exception("driver %s failed to flush", drv.bus.name)
            for name, w in issued:
                if isinstance(w, str):
                    undelivered.append((name, w))
                elif w is not None and not w.done:
                    undelivered.append((name, w.reason or f"not confirmed on the wire within "
                                                          f"{SHUTDOWN_FLUSH} s"))
            for name, why in undelivered:
                if (name, why) not in self.safe_failures:
                    self.safe_failures.append((name, why))
                faults.error("safe value for %s not delivered at shutdown: %s", name, why)
            lvl = logging.INFO if not undelivered else logging.ERROR
            faults.log(lvl, "estop (shutdown): %d of %d actuator(s) at safe values%s",
                       len(issued) - len(undelivered), len(issued),
                       "" if not undelivered else "; not delivered: " + ", ".join(
                           f"{d} ({why})" for d, why in undelivered))
        except Exception:  # shutdown must go on
            log.exception("safe values at shutdown failed")
        for drv in self.drivers:
            try:
                drv.stop()
            except Exception:
                log.exception("driver %s failed to stop", drv.bus.name)
        self.drivers.clear()
        return undelivered

    # ---- DriverHost (thread-safe: everything goes through the interrupt queue) -------------
    def deliver(self, device: str, value: Any) -> None:
        """A new raw reading of sensor ``device`` (from a driver thread), stamped with the time
        the driver got it: staleness is judged from that, not from when the kernel handles it."""
        at = self.kernel.clock.now()
        self._rx_stamp[device] = at
        self.kernel.interrupt(self._reading, device, value, at)

    inject = deliver  # the host's and the tests' way to feed a sensor

    def fail(self, device: str, reason: str) -> None:
        """The driver reports ``device`` failed (from a driver thread); it stays failed until
        the driver reports the end of it (:meth:`recover`), whatever readings arrive."""
        self.kernel.interrupt(self._driver_health, device, reason)

    def recover(self, device: str, reason: str = "") -> None:
        """The driver reports that the event ending ``device``'s failure happened (from a
        driver thread)."""
        self.kernel.interrupt(self._driver_health, device, "", reason or "recovered")

    def error(self, bus: str, kind: str, detail: str, device: str = "") -> None:
        """Count a bus-level error of class ``kind`` (from a driver thread)."""
        self._count(bus, kind, device, error=True)
        self.kernel.interrupt(self._bus_error, bus, kind, detail, False)

    def stat(self, bus: str, key: str, n: int = 1, device: str = "") -> None:
        """Add ``n`` to bus counter ``key`` (from any thread; see :class:`BusStats`)."""
        self._count(bus, key, device, n=n)

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

    def stats_doc(self) -> dict[str, Any]:
        """The bus statistics as plain data, per bus (see :class:`BusStats`)."""
        with self._stats_lock:
            return {bus: st.as_dict() for bus, st in sorted(self.bus_stats.items())}

    @property
    def bus_errors(self) -> Counter[tuple[str, str]]:
        """Errors by (bus, class), a copy derived from :attr:`bus_stats`."""
        with self._stats_lock:
            return Counter({(bus, kind): n for bus, st in self.bus_stats.items()
                            for kind, n in st.errors.items() if n})

    @property
    def last_bus_error(self) -> dict[str, str]:
        """The last error's text per bus (``"class: detail"``), derived from :attr:`bus_stats`."""
        with self._stats_lock:
            return {bus: st.last_error for bus, st in self.bus_stats.items() if st.last_error}

    def add_health_listener(self, fn: Callable[[str, bool, str], None]) -> None:
        """Call ``fn(device, healthy, cause)`` on the kernel thread whenever a device's health
        changes: ``healthy`` False with the failure's cause, True with the event that ended it."""
        self._health_listeners.append(fn)

    def remove_health_listener(self, fn: Callable[[str, bool, str], None]) -> None:
        """Stop calling ``fn`` (added by :meth:`add_health_listener`; no error if it is not)."""
        with contextlib.suppress(ValueError):
            self._health_listeners.remove(fn)

    def every(self, period: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the kernel thread every ``period`` seconds of kernel time."""
        self.kernel.every(period, fn)

    def now(self) -> float:
        """The kernel clock's time."""
        return self.kernel.clock.now()

    # ---- interrupt handlers (kernel thread) -------------------------------------------------
    def _reading(self, device: str, raw: Any, at: float | None = None) -> None:
        e = self._entries.get(device)
        if e is None:
            self._bus_error("?", "unknown-device", f"reading for unknown device {device!r}")
            return
        if e.status is DeviceStatus.SUSPENDED:
            e.dropped += 1
            return
        spec = e.spec
        value = raw * spec.scale + spec.offset if _scalable(raw) else raw
        now = self.kernel.clock.now()
        e.value = value
        e.updated_at = now
        e.rx_at = now if at is None else at
        e.readings += 1
        if e.stale:  # fresh data ends staleness, and nothing else (a driver failure stays)
            e.stale = False
            self._refresh(e, "fresh data")
        deliver = self.msgmgr.deliver
        over = False
        for link in e.links:
            port = link.port
            if isinstance(port, InPort) and port.fresh:
                over = True
            deliver(link, value)
        if over:
            e.overwrites += 1

    def _driver_health(self, device: str, failure: str, ended: str = "") -> None:
        e = self._entries.get(device)
        if e is None:
            return
        was = e.status
        e.failure = failure
        self._refresh(e, ended)
        if (not failure and was is DeviceStatus.FAILED and e.status is not DeviceStatus.FAILED
                and not e.is_sensor and e.spec.safe_value is not None
                and self.msgmgr.is_local(e.spec.machine)):
            # back: the safe value before any command; it stays until the owner commands again
            self._safe(device, "recovery")

    @staticmethod
    def _health_status(e: DeviceEntry) -> tuple[DeviceStatus, str]:
        """The status ``e``'s health gives, with its reason: a driver failure first, then
        staleness, else OK."""
        if e.failure:
            return DeviceStatus.FAILED, e.failure
        if e.stale:
            return DeviceStatus.STALE, f"no data for {e.spec.stale_after} s (stale_after)"
        return DeviceStatus.OK, ""

    def _refresh(self, e: DeviceEntry, ended: str) -> None:
        """Set ``e``'s status from its health (unless the host suspended it)."""
        if e.status is DeviceStatus.SUSPENDED:
            return
        status, reason = self._health_status(e)
        if status is e.status:
            e.reason = reason
            return
        self._set_status(e.name, status, reason, ended=ended)

    def _set_status(self, device: str, status: DeviceStatus, reason: str,
                    tell: bool = True, ended: str = "") -> None:
        e = self._entries.get(device)
        if e is None or e.status is status:
            return
        old = e.status
        e.status = status
        e.reason = reason
        e.since = self.kernel.clock.now()
        comm = self.msgmgr.comm
        if tell and comm is not None and self.msgmgr.is_local(e.spec.machine):
            comm.device_status(device, status.value, reason)
        cause = reason if status is not DeviceStatus.OK else (ended or f"was {old.value}")
        self.msgmgr.event(f"device-{status.name.lower()}",
                          f"{device}: {cause}" if cause else device)
        if status is not DeviceStatus.SUSPENDED and old is not DeviceStatus.SUSPENDED:
            faults.warning("device %s %s at t=%.6f: %s", device, status.value, e.since, cause)
        for fn in list(self._health_listeners):
            try:
                fn(device, status is DeviceStatus.OK, cause)
            except Exception:  # a listener must not break the device manager
                log.exception("health listener failed for %s", device)
        if status in (DeviceStatus.FAILED, DeviceStatus.STALE):
            failure = SensorFailure(device, reason or status.value)
            for link in e.links:
                port = link.port
                if isinstance(port, InPort) and port.waiter is not None:
                    w = port.waiter
                    self.kernel.wake(w, max(w.base_prio, link.priority), exc=failure)

    def _count(self, bus: str, key: str, device: str, n: int = 1, error: bool = False) -> None:
        with self._stats_lock:
            st = self.bus_stats.get(bus)
            if st is None:
                st = self.bus_stats[bus] = BusStats()
            (st.errors if error else st.counts)[key] += n
            if device:
                dc = st.devices.get(device)
                if dc is None:
                    dc = st.devices[device] = Counter()
                dc[f"error:{key}" if error else key] += n

    def _bus_error(self, bus: str, kind: str, detail: str, count: bool = True) -> None:
        if count:
            self._count(bus, kind, "", error=True)
        with self._stats_lock:
            st = self.bus_stats.get(bus)
            if st is not None:
                st.last_error = f"{kind}: {detail}"
        log.warning("bus %s: %s: %s", bus, kind, detail)

    def _write_done(self, w: _Write) -> None:
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
        self.msgmgr.event("write-failed", text)
        if w.safe:
            self.safe_failures.append((w.device, w.reason))
            faults.error("%s", text)
        else:
            faults.warning("%s", text)

    def _arm_stale(self, e: DeviceEntry, since: float) -> None:
        limit = e.spec.stale_after
        assert limit is not None

        def check() -> None:
            e.stale_timer = None
            # the driver's receive time: a reading received but not yet handled is late, not
            # missing (the stamp is set in the driver's thread before the interrupt is queued)
            last = max(since, e.rx_at if e.rx_at is not None else since,
                       self._rx_stamp.get(e.name, since))
            due = last + limit
            if self.kernel.clock.now() >= due:
                if not e.stale:
                    e.stale = True
                    self._refresh(e, "")
                due = self.kernel.clock.now() + limit
            e.stale_timer = self.kernel.call_at(due, check)

        e.stale_timer = self.kernel.call_at(since + limit, check)

    # ---- task side --------------------------------------------------------------------------
    def check_readable(self, device: str) -> None:
        """Raise SensorFailure if sensor ``device`` is failed or stale."""
        e = self.get(device)
        if e.status in (DeviceStatus.FAILED, DeviceStatus.STALE):
            raise SensorFailure(device, e.reason or e.status.value)

    def write(self, device: str, value: Any, source: str = "host") -> None:
        """Command actuator ``device`` with ``value`` (engineering units), without blocking.

        Raises DeviceError naming the device, the value and the rule if ``device`` is not an
        actuator, is failed or suspended, the value is not a finite number (for a numeric
        actuator), is outside its limits (never clamped), or its address cannot carry it (an
        integer address and a fraction without the device's ``round = true``, a value outside the
        address type's range). The device shows the value once the driver has put it on the wire
        (``pending`` until then); a write that fails later is a WARNING event (``write-failed``).
        """
        e = self.get(device)
        if e.is_sensor:
            raise DeviceError(f"{device} is a sensor: {source} cannot write to it")
        if e.status in (DeviceStatus.FAILED, DeviceStatus.SUSPENDED):
            e.rejected += 1
            raise DeviceError(f"actuator {device} is {e.status.value} ({e.reason}): "
                              f"command {value!r} from {source} refused")
        raw = self._check_command(e, value, source)
        self._send(e, value, raw, source)

    def _check_command(self, e: DeviceEntry, value: Any, source: str) -> Any:
        """The raw value for ``value``; raises DeviceError (counted as rejected) if refused."""
        spec = e.spec
        device = e.name
        # a bus that carries numbers only (every field bus); memory actuators may hold any value
        numeric = spec.round or (e.driver is not None and e.driver.numeric_only)
        if isinstance(value, bool):
            value = int(value)
        if numeric and not _scalable(value):
            e.rejected += 1
            raise DeviceError(f"command {value!r} from {source} to {device}: expected a number "
                              f"({spec.units or 'engineering units'})")
        if _scalable(value) and not math.isfinite(value):
            e.rejected += 1
            raise DeviceError(f"command {value!r} from {source} to {device}: expected a finite "
                              f"number")
        lo, hi = spec.limits
        if _scalable(value) and ((lo is not None and value < lo) or
                                 (hi is not None and value > hi)):
            e.rejected += 1
            raise DeviceError(
                f"command {value!r} {spec.units} from {source} to {device} is outside its limits "
                f"[{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]")
        raw = (value - spec.offset) / spec.scale if _scalable(value) else value
        if _scalable(raw):
            if not math.isfinite(raw):
                e.rejected += 1
                raise DeviceError(f"command {value!r} from {source} to {device}: raw value "
                                  f"{raw!r} (scale/offset) is not a finite number")
            if spec.round:
                raw = round(raw)
            elif isinstance(raw, float) and raw.is_integer() is False:
                near = round(raw)
                if abs(raw - near) <= 1e-9 * max(1.0, abs(raw)):
                    raw = float(near)   # only scale/offset arithmetic noise
        if e.driver is not None and self.msgmgr.is_local(spec.machine):
            why = e.driver.check_value(device, raw)
            if why is not None:
                e.rejected += 1
                raise DeviceError(f"command {value!r} from {source} to {device} refused: raw "
                                  f"value {raw!r}: {why}"
                                  + ("" if spec.round else " (a device with round = true rounds "
                                                           "to an integer)"))
        return raw

    def _send(self, e: DeviceEntry, value: Any, raw: Any, source: str,
              safe: str = "") -> _Write | None:
        """Hand a checked write to the driver (or the device's satellite); the _Write to watch
        if the driver confirms writes."""
        device = e.name
        spec = e.spec
        e.updated_at = self.kernel.clock.now()
        e.commands += 1
        mm = self.msgmgr
        w: _Write | None = None
        if not mm.is_local(spec.machine):
            assert mm.comm is not None
            mm.comm.actuator(device, spec.machine, value, source)
            e.value = value
        elif e.driver is not None and e.driver.confirms_writes:
            w = _Write(device, value, raw, safe)
            with self._wlock:
                q = self._inflight.setdefault(device, deque())
                q.append(w)
                e.pending_count = len(q)
            e.pending = value
            e.driver.write(device, raw)
        else:
            e.value = value
            if e.driver is not None:
                e.driver.write(device, raw)
        for hook in self.on_write:
            hook(device, value)
        return w

    def safe_outputs(self, task: TaskEntry) -> int:
        """Write the safe value of every actuator ``task`` commands; returns how many."""
        n = 0
        for link in task.out_links:
            if link.dst_kind is EndpointKind.DEVICE and self._safe(link.dst):
                n += 1
        return n

    def set_status(self, device: str, status: str, reason: str) -> None:
        """Another satellite reports the status of one of its devices."""
        self._set_status(device, DeviceStatus(status), reason, tell=False)

    def estop(self, reason: str) -> int:
        """Write the safe value of every actuator of this satellite (where configured), whatever
        state it is in; returns how many were handed to the drivers. One that cannot be
        delivered (after SAFE_ATTEMPTS) is reported as a ``write-failed`` event, logged at ERROR
        and added to :attr:`safe_failures`. Other satellites are told by the caller (see
        TaskContext.estop)."""
        issued = self._safe_all(reason)
        n = sum(1 for _, w in issued if not isinstance(w, str))
        log.log(logging.INFO if reason == "shutdown" else logging.WARNING,
                "estop (%s): %d safe value(s) sent", reason, n)
        return n

    def _safe_all(self, reason: str) -> list[tuple[str, _Write | str | None]]:
        out: list[tuple[str, _Write | str | None]] = []
        for e in self._entries.values():
            if (not e.is_sensor and e.spec.safe_value is not None
                    and self.msgmgr.is_local(e.spec.machine)):
                out.append((e.name, self._safe_write(e, reason)))
        return out

    def _safe(self, device: str, why: str = "abnormal completion") -> bool:
        e = self.get(device)
        if e.spec.safe_value is None or e.is_sensor:
            return False
        return not isinstance(self._safe_write(e, why), str)

    def _safe_write(self, e: DeviceEntry, why: str) -> _Write | str | None:
        """Put ``e``'s safe value out whatever its status: the _Write to watch (None if the
        driver does not confirm writes), or the reason it could not even be handed over."""
        safe = e.spec.safe_value
        assert safe is not None
        try:
            raw = self._check_command(e, safe, "safe-value")
            w = self._send(e, safe, raw, "safe-value", safe=why)
        except Exception as exc:  # report, keep going with the others
            text = f"{e.name}: safe value ({why}) {safe!r} not written: {exc}"
            self.safe_failures.append((e.name, str(exc)))
            faults.error("%s", text)
            self.msgmgr.event("write-failed", text)
            return str(exc)
        return w
