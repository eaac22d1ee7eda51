"""devices - the device manager: Devtab, the last-value buffers, and the drivers behind them.

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

import enum
import logging
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from chcos.devspec import DeviceMap, DeviceSpec
from chcos.errors import BusError, DeviceError, SensorFailure
from chcos.kernel import Kernel, Timer
from chcos.messages import EndpointKind, InPort, Link

if TYPE_CHECKING:
    from chcos.msgmgr import MessageManager
    from chcos.tasks import TaskEntry
    from drivers.base import Driver

log = logging.getLogger("chcos.devices")


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


class Devtab:
    """The device table of one satellite, and the host of its drivers."""

    def __init__(self, kernel: Kernel, msgmgr: MessageManager) -> None:
        self.kernel = kernel
        self.msgmgr = msgmgr
        msgmgr.devtab = self
        self._entries: dict[str, DeviceEntry] = {}
        self.drivers: list[Driver] = []
        self.bus_errors: Counter[tuple[str, str]] = Counter()
        self.last_bus_error: dict[str, str] = {}
        self.on_write: list[Callable[[str, Any], None]] = []
        self._health_listeners: list[Callable[[str, bool, str], None]] = []

    def add_health_listener(self, fn: Callable[[str, bool, str], None]) -> None:
        """Call ``fn(device_name, healthy, cause)`` on the kernel thread on every health change
        of a device (healthy: OK; not healthy: failed, stale or suspended)."""
        self._health_listeners.append(fn)

    def suspend(self, device: str) -> None:
        """Host ``suspend`` of a device: SUSPENDED (readings dropped, commands refused) until
        :meth:`resume`. Raises DeviceError for an unknown device."""
        self.get(device)
        self._set_status(device, DeviceStatus.SUSPENDED, "suspended by the host")

    def resume(self, device: str) -> None:
        """Undo :meth:`suspend` (a device that is not suspended is left as it is). Raises
        DeviceError for an unknown device."""
        if self.get(device).status is DeviceStatus.SUSPENDED:
            self._set_status(device, DeviceStatus.OK, "")

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

    def stop_drivers(self) -> None:
        """Write safe values, then stop every driver (never raises)."""
        try:
            self.estop("shutdown")
        except Exception:  # shutdown must go on
            log.exception("safe values at shutdown failed")
        for drv in self.drivers:
            try:
                drv.stop()
            except Exception:
                log.exception("driver %s failed to stop", drv.bus.name)
        self.drivers.clear()

    # ---- DriverHost (thread-safe: everything goes through the interrupt queue) -------------
    def deliver(self, device: str, value: Any) -> None:
        """A new raw reading of sensor ``device`` (from a driver thread)."""
        self.kernel.interrupt(self._reading, device, value)

    inject = deliver  # the host's and the tests' way to feed a sensor

    def fail(self, device: str, reason: str) -> None:
        """Mark ``device`` failed (from a driver thread)."""
        self.kernel.interrupt(self._set_status, device, DeviceStatus.FAILED, reason)

    def recover(self, device: str) -> None:
        """Mark ``device`` working again (from a driver thread)."""
        self.kernel.interrupt(self._set_status, device, DeviceStatus.OK, "")

    def error(self, bus: str, kind: str, detail: str) -> None:
        """Count a bus-level error (from a driver thread)."""
        self.kernel.interrupt(self._bus_error, bus, kind, detail)

    def every(self, period: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the kernel thread every ``period`` seconds of kernel time."""
        self.kernel.every(period, fn)

    def now(self) -> float:
        """The kernel clock's time."""
        return self.kernel.clock.now()

    # ---- interrupt handlers (kernel thread) -------------------------------------------------
    def _reading(self, device: str, raw: Any) -> None:
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
        e.readings += 1
        if e.status is not DeviceStatus.OK:
            self._set_status(device, DeviceStatus.OK, "")
        deliver = self.msgmgr.deliver
        over = False
        for link in e.links:
            port = link.port
            if isinstance(port, InPort) and port.fresh:
                over = True
            deliver(link, value)
        if over:
            e.overwrites += 1

    def _set_status(self, device: str, status: DeviceStatus, reason: str,
                    tell: bool = True) -> None:
        e = self._entries.get(device)
        if e is None or e.status is status:
            return
        e.status = status
        e.reason = reason
        comm = self.msgmgr.comm
        if tell and comm is not None and self.msgmgr.is_local(e.spec.machine):
            comm.device_status(device, status.value, reason)
        self.msgmgr.event(f"device-{status.name.lower()}",
                          f"{device}: {reason}" if reason else device)
        for fn in self._health_listeners:
            fn(device, status is DeviceStatus.OK, reason or status.value)
        if status in (DeviceStatus.FAILED, DeviceStatus.STALE):
            failure = SensorFailure(device, reason or status.value)
            for link in e.links:
                port = link.port
                if isinstance(port, InPort) and port.waiter is not None:
                    w = port.waiter
                    self.kernel.wake(w, max(w.base_prio, link.priority), exc=failure)

    def _bus_error(self, bus: str, kind: str, detail: str) -> None:
        self.bus_errors[(bus, kind)] += 1
        self.last_bus_error[bus] = f"{kind}: {detail}"
        log.warning("bus %s: %s: %s", bus, kind, detail)

    def _arm_stale(self, e: DeviceEntry, since: float) -> None:
        limit = e.spec.stale_after
        assert limit is not None

        def check() -> None:
            e.stale_timer = None
            last = e.updated_at if e.updated_at is not None else since
            due = last + limit
            if self.kernel.clock.now() >= due:
                if e.status is DeviceStatus.OK:
                    self._set_status(e.name, DeviceStatus.STALE,
                                     f"no data for {limit} s (stale_after)")
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
        actuator, is failed or suspended, or the value is outside its limits (never clamped).
        """
        e = self.get(device)
        spec = e.spec
        if e.is_sensor:
            raise DeviceError(f"{device} is a sensor: {source} cannot write to it")
        if e.status in (DeviceStatus.FAILED, DeviceStatus.SUSPENDED):
            e.rejected += 1
            raise DeviceError(f"actuator {device} is {e.status.value} ({e.reason}): "
                              f"command {value!r} from {source} refused")
        lo, hi = spec.limits
        if _scalable(value) and ((lo is not None and value < lo) or
                                 (hi is not None and value > hi)):
            e.rejected += 1
            raise DeviceError(
                f"command {value!r} {spec.units} from {source} to {device} is outside its limits "
                f"[{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]")
        raw = (value - spec.offset) / spec.scale if _scalable(value) else value
        e.value = value
        e.updated_at = self.kernel.clock.now()
        e.commands += 1
        mm = self.msgmgr
        if not mm.is_local(spec.machine):
            assert mm.comm is not None
            mm.comm.actuator(device, spec.machine, value, source)
        elif e.driver is not None:
            e.driver.write(device, raw)
        for hook in self.on_write:
            hook(device, value)

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
        """Write the safe value of every actuator of this satellite (where configured); returns
        how many were written. Other satellites are told by the caller (see TaskContext.estop)."""
        n = 0
        for e in self._entries.values():
            if not e.is_sensor and self.msgmgr.is_local(e.spec.machine) and self._safe(e.name):
                n += 1
        log.log(logging.INFO if reason == "shutdown" else logging.WARNING,
                "estop (%s): %d actuator(s) at safe values", reason, n)
        return n

    def _safe(self, device: str) -> bool:
        e = self.get(device)
        safe = e.spec.safe_value
        if safe is None or e.is_sensor:
            return False
        try:
            if e.status is DeviceStatus.SUSPENDED:
                e.status = DeviceStatus.OK
            self.write(device, safe, source="safe-value")
        except DeviceError as exc:  # a failed actuator: report, keep going with the others
            log.error("safe value for %s not written: %s", device, exc)
            return False
        return True
