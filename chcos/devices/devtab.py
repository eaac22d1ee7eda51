"""devtab - the device manager: Devtab, the last-value buffers, and the drivers behind them.

Each sensor or actuator of the device maps has one Devtab entry (every satellite keeps the whole
table; only the devices of its own machines get drivers). A new sensor reading is an interrupt:
it lands in the entry's last-value buffer (a newer reading overwrites an unread older one, counted)
and goes to the listener that fans it out over the links leaving the device (the message
manager: Devtab knows devices and drivers, not links). Health (FAILED, STALE, SUSPENDED) is
:mod:`chcos.devices.health`, the bus counters :mod:`chcos.devices.busstats`. Actuator
writes are checked against limits (refused, never clamped), scaled, and handed to the driver
without blocking; safe values go out on e-stop, abnormal completion of the owning task and
shutdown. Devtab is the :class:`chcos.devices.driver.DriverHost` its drivers talk to.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import TYPE_CHECKING, Any

from chcos.devices.busstats import BusCounters, BusStats
from chcos.devices.commands import CommandChecks
from chcos.devices.entry import (
    DeviceEntry,
    DeviceListener,
    DeviceStatus,
    RemoteDevices,
    SafeIssue,
    SafeOutcome,
    Write,
    scalable,
)
from chcos.devices.health import DeviceHealth, HealthListener, faults, log
from chcos.devices.observers import CommandReport, DeviceObserver, Observers, WriteStage
from chcos.devices.spec import DeviceMap
from chcos.devices.status import DriverStatus
from chcos.devices.table import DeviceTable
from chcos.devices.writes import WriteTracking
from chcos.errors import BusError, DeviceError
from chcos.kernel.scheduler import Kernel, SettleBound

if TYPE_CHECKING:
    from chcos.devices.driver import Driver

#: Seconds the drivers get at shutdown, in all, to put the safe values on the wire (a safe value
#: reported failed is re-issued until it is confirmed or this window ends).
SHUTDOWN_FLUSH = 5.0
#: Seconds between two issues of a safe value reported failed at shutdown.
SHUTDOWN_RETRY_PAUSE = 0.1
# module constants: read on every reading and every command
_FAILED = DeviceStatus.FAILED
_SUSPENDED = DeviceStatus.SUSPENDED
_INF = float("inf")
#: the start of the failure of a sensor whose reading is no number (NaN, an infinity)
NOT_A_VALUE = "reading is not a finite number"
_OPEN = (None, None)   # limits that say nothing


class Devtab:
    """The device table of one satellite, and the host of its drivers.

    ``local`` are the machines whose devices this process drives (None: all of them);
    ``remote`` reaches the actuators of the others and hears of local status changes (None in
    a one-process system: a command to another machine's actuator is then refused). Readings
    and sensor failures go to the one :meth:`listen`-er (the message manager).

    Devtab composes its parts, each with its own state, and delegates to them: the entries
    (:class:`~chcos.devices.table.DeviceTable`), their health
    (:class:`~chcos.devices.health.DeviceHealth`), the command checks
    (:class:`~chcos.devices.commands.CommandChecks`), the writes in flight
    (:class:`~chcos.devices.writes.WriteTracking`) and the bus counters
    (:class:`~chcos.devices.busstats.BusCounters`)."""

    def __init__(self, kernel: Kernel, *, local: Iterable[int] | None = None,
                 remote: RemoteDevices | None = None) -> None:
        self.kernel = kernel
        self._table = DeviceTable(local)
        self._listener: DeviceListener | None = None
        self.drivers: list[Driver] = []
        self.on_write: list[Callable[[str, Any], None]] = []
        #: the driver's receive time of each sensor's last reading (set on the driver threads)
        self._rx_stamp: dict[str, float] = {}
        self._health = DeviceHealth(kernel, self._table, self._rx_stamp)
        self.remote = remote
        self._checks = CommandChecks(self._table)
        #: told of every bus error and every command's stage (:mod:`chcos.devices.observers`)
        self._observers = Observers()
        self._counters = BusCounters(kernel, lambda: self.drivers, self._observers)
        self._writes = WriteTracking(kernel, self._table, self._safe_failed, self._observers)
        #: (device, reason) of every safe value that could not be put on the wire, oldest first.
        self.safe_failures: list[tuple[str, str]] = []
        #: what became of each local actuator's safe value at the last shutdown
        #: (:meth:`stop_drivers`): confirmed by its driver, or not and why
        self.safe_outcomes: dict[str, SafeOutcome] = {}
        #: seconds :meth:`stop_drivers` keeps trying to put the safe values on the wire
        self.shutdown_window = SHUTDOWN_FLUSH
        #: each stopped driver's last :meth:`chcos.devices.driver.Driver.status`, by bus
        self._kept_status: dict[str, DriverStatus] = {}
        #: True when the drivers' peers are simulated on this kernel's virtual clock (a virtual
        #: cell, :func:`chcos.cli.cellsystem.open_cell`): a driver then supervises their
        #: heartbeats on that clock, not on wall time
        #: (:func:`chcos.devices.driver.host_peers_on_clock`)
        self.peers_on_clock = False
        #: True when the drivers' peers are real, in other processes, while the clock is
        #: virtual (a test of a real PLC or a peer process on virtual time): a driver that
        #: settles then waits for them at most the virtual time to the next timer
        #: (:class:`chcos.kernel.scheduler.SettleBound`), instead of until they are done
        self.real_peers = False

    def listen(self, listener: DeviceListener) -> None:
        """Send every reading and sensor failure to ``listener`` from now on (one listener: the
        layer that owns the links leaving the devices)."""
        self._listener = listener
        self._health.listener = listener

    @property
    def remote(self) -> RemoteDevices | None:
        """The devices of other satellites: reaches their actuators and hears of local status
        changes; a composition root that builds the link after this table puts it here before
        the kernel runs (None: commands to other machines' actuators are refused)."""
        return self._health.remote

    @remote.setter
    def remote(self, remote: RemoteDevices | None) -> None:
        self._health.remote = remote

    # ---- table ------------------------------------------------------------------------------
    def load(self, devmap: DeviceMap) -> None:
        """Enter every device of ``devmap``; raises DeviceError (nothing entered) if a name is
        already in the table."""
        self._table.load(devmap)

    def get(self, name: str) -> DeviceEntry:
        """The entry called ``name``; raises DeviceError naming it if there is none."""
        return self._table.get(name)

    def is_local(self, machine: int) -> bool:
        """True if ``machine``'s devices are driven by this process."""
        return self._table.is_local(machine)

    def __contains__(self, name: object) -> bool:
        return name in self._table

    def __iter__(self) -> Iterator[DeviceEntry]:
        return iter(self._table)

    def __len__(self) -> int:
        return len(self._table)

    # ---- health (DeviceHealth) --------------------------------------------------------------
    def suspend(self, device: str) -> None:
        """Host ``suspend`` of a device: SUSPENDED (readings dropped, commands refused) until
        :meth:`resume`. Raises DeviceError for an unknown device."""
        self._health.suspend(device)

    def resume(self, device: str) -> None:
        """Undo :meth:`suspend` (see :meth:`chcos.devices.health.DeviceHealth.resume`). Raises
        DeviceError for an unknown device."""
        self._health.resume(device)

    def healthy(self, device: str) -> bool:
        """Whether ``device`` delivers (neither failed nor stale). Raises DeviceError for an
        unknown device."""
        return self._health.healthy(device)

    def check_readable(self, device: str) -> None:
        """Raise SensorFailure if sensor ``device`` is failed or stale (DeviceError if there is
        no such device)."""
        self._health.check_readable(device)

    def set_status(self, device: str, status: DeviceStatus, reason: str) -> None:
        """Another satellite reports the status of one of its devices (or that it died)."""
        self._health.set_status(device, status, reason)

    def add_health_listener(self, fn: HealthListener) -> None:
        """Call ``fn(device, healthy, cause)`` on the kernel thread whenever a device's health
        changes: ``healthy`` False with the failure's cause, True with the event that ended it."""
        self._health.add_health_listener(fn)

    def remove_health_listener(self, fn: HealthListener) -> None:
        """Stop calling ``fn`` (added by :meth:`add_health_listener`; no error if it is not)."""
        self._health.remove_health_listener(fn)

    def add_observer(self, observer: DeviceObserver) -> None:
        """Tell ``observer`` of every bus error and every command's stage (handed to the
        driver, confirmed, failed), on the kernel thread (see :mod:`chcos.devices.observers`)."""
        self._observers.add(observer)

    def remove_observer(self, observer: DeviceObserver) -> None:
        """Stop telling ``observer`` (no error if it was not added)."""
        self._observers.remove(observer)


    # ---- bus counters (BusCounters) ---------------------------------------------------------
    @property
    def bus_stats(self) -> dict[str, BusStats]:
        """Per bus: frames/requests, errors by class, reconnects (see :class:`BusStats`); a
        snapshot, with the frames each running driver counted itself (``frames-sent``)."""
        return self._counters.bus_stats

    def stats_doc(self) -> dict[str, Any]:
        """The bus statistics as plain data, per bus (see :class:`BusStats`)."""
        return self._counters.stats_doc()

    @property
    def bus_errors(self) -> Counter[tuple[str, str]]:
        """Errors by (bus, class), a copy derived from :attr:`bus_stats`."""
        return self._counters.bus_errors

    @property
    def last_bus_error(self) -> dict[str, str]:
        """The last error's text per bus (``"class: detail"``), derived from :attr:`bus_stats`."""
        return self._counters.last_bus_error

    # ---- drivers ----------------------------------------------------------------------------
    def start_drivers(self, devmap: DeviceMap, machines: Iterable[int] | None = None) -> None:
        """Start a driver for every bus that has devices on ``machines`` (all if None).

        Raises BusError (every driver started so far is stopped again) if one fails to start, and
        DriverNotAvailable for an unknown bus kind.
        """
        from chcos.devices.registry import driver_class

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
                    self._table.get(d.name).driver = drv
                if drv.settles:     # work in flight on threads of its own (kernel module doc)
                    self.kernel.add_settler(drv.settle, SettleBound.CLOCK if self.real_peers
                                            else SettleBound.PEER)
        except Exception as exc:
            for drv in started:
                drv.stop()
            if isinstance(exc, BusError):
                raise
            raise BusError(f"cannot start bus drivers: {exc}") from exc
        self.drivers.extend(started)
        for e in self._table:
            if e.is_sensor and e.spec.stale_after is not None and e.driver is not None:
                self._health.arm_stale(e, self.kernel.clock.now())

    def stop_drivers(self) -> list[tuple[str, str]]:
        """Write safe values (whatever state the actuators are in), keep putting the ones not
        confirmed on the wire for up to :attr:`shutdown_window` seconds in all (a peer that
        comes back within it gets its safe value), then stop every driver. Never raises;
        returns (device, reason) of every safe value that was not confirmed (also logged, and
        in :attr:`safe_outcomes`). On a virtual clock whose kernel is not running the window is
        virtual time in which the drivers' timers keep running (see
        :meth:`_shutdown_on_virtual_time`). Without running drivers (none started, or already
        stopped) there is nothing to do."""
        undelivered: list[tuple[str, str]] = []
        if not self.drivers:
            return undelivered
        try:
            kernel = self.kernel
            outcomes = (self._shutdown_on_virtual_time()
                        if kernel.clock.virtual and not kernel.running
                        else self._shutdown_safe_values(time.monotonic() + self.shutdown_window))
            self.safe_outcomes = {o.device: o for o in outcomes}
            undelivered = [(o.device, o.reason) for o in outcomes if not o.written]
            for name, why in undelivered:
                if (name, why) not in self.safe_failures:
                    self.safe_failures.append((name, why))
                faults.error("safe value for %s not delivered at shutdown: %s", name, why)
            lvl = logging.INFO if not undelivered else logging.ERROR
            faults.log(lvl, "estop (shutdown): %d of %d actuator(s) at safe values%s",
                       len(outcomes) - len(undelivered), len(outcomes),
                       "" if not undelivered else "; not delivered: " + ", ".join(
                           f"{d} ({why})" for d, why in undelivered))
        except Exception:  # shutdown must go on
            log.exception("safe values at shutdown failed")
        for drv in self.drivers:
            self._keep_status(drv)
            try:
                drv.stop()
            except Exception:
                log.exception("driver %s failed to stop", drv.bus.name)
            self._counters.keep_sent(drv)
        self.drivers.clear()
        return undelivered

    def statuses(self) -> dict[str, DriverStatus]:
        """What each bus's driver shows beyond the counters (:meth:`Driver.status`: e.g.
        CANopen nodes' lifecycles and the SYNC cycle), by bus name, only buses with something
        to show; a stopped driver's as it was when it stopped. Thread-safe."""
        out = dict(self._kept_status)
        for drv in list(self.drivers):
            st = drv.status()
            if st:
                out[drv.bus.name] = st
        return dict(sorted(out.items()))

    def bus_status(self) -> dict[str, dict[str, Any]]:
        """:meth:`statuses` as JSON (:meth:`DriverStatus.to_json`), for the system map and the
        consumers that still read documents."""
        return {bus: st.to_json() for bus, st in self.statuses().items()}

    def _keep_status(self, drv: Driver) -> None:
        try:
            st = drv.status()
        except Exception:   # shutdown must go on
            log.exception("driver %s: status not kept", drv.bus.name)
            return
        if st:
            self._kept_status[drv.bus.name] = st

    def _shutdown_safe_values(self, deadline: float) -> list[SafeOutcome]:
        """Every local actuator's safe value, issued and then re-issued while it is reported
        failed, a pause of :data:`SHUTDOWN_RETRY_PAUSE` apart, until it is confirmed or the
        ``deadline`` (``time.monotonic()``) passes; what became of each. Only what a driver
        confirmed counts as written (a driver that does not confirm writes counts as written
        once it took the value); a value the device's checks refuse is not tried again."""
        issued = {i.device: i for i in self._safe_all("shutdown")}
        attempts = dict.fromkeys(issued, 1)
        while True:
            self._flush_drivers(deadline)
            again = [name for name, i in issued.items()
                     if i.write is not None and i.write.done is False]
            if not again or time.monotonic() + SHUTDOWN_RETRY_PAUSE >= deadline:
                break
            time.sleep(SHUTDOWN_RETRY_PAUSE)  # let the peer come back (a reconnect, a reboot)
            for name in again:
                issued[name] = self._safe_write(self._table.get(name), "shutdown")
                attempts[name] += 1
        return [self._safe_outcome(i, attempts[name]) for name, i in issued.items()]

    def _shutdown_on_virtual_time(self) -> list[SafeOutcome]:
        """:meth:`_shutdown_safe_values` on a virtual clock, where time moves only while the
        kernel runs: the window is :attr:`shutdown_window` seconds of virtual time, during which
        the kernel runs the drivers' timers and interrupts without stepping tasks
        (:meth:`Kernel.run_drivers`: a drive ramps down to standstill, a driver's timeout and
        retries run, a simulated peer steps). No wall-clock decision is made here: what the
        drivers have in flight is waited for by the kernel's settlers, each bounded by its
        :class:`~chcos.kernel.scheduler.SettleBound` (a real peer that does not answer costs
        at most the window's virtual seconds in wall time)."""
        clock = self.kernel.clock
        end = clock.now() + self.shutdown_window
        issued = {i.device: i for i in self._safe_all("shutdown")}
        attempts = dict.fromkeys(issued, 1)
        # a flush that does not wait tells each driver the shutdown began (a Modbus link
        # lost now reconnects every reconnect_delay); the kernel's settle does the waiting
        for drv in self.drivers:
            try:
                drv.flush(0.0)
            except Exception:
                log.exception("driver %s failed to flush", drv.bus.name)

        def settled() -> bool:
            return all(i.write is None or i.write.done is not None for i in issued.values())

        def never() -> bool:
            return False

        while True:
            self.kernel.run_drivers(end, settled)
            again = [name for name, i in issued.items()
                     if i.write is not None and i.write.done is False]
            if not again or clock.now() + SHUTDOWN_RETRY_PAUSE >= end:
                break
            # let the peer come back (a reconnect, a reboot), on virtual time
            self.kernel.run_drivers(clock.now() + SHUTDOWN_RETRY_PAUSE, never)
            for name in again:
                issued[name] = self._safe_write(self._table.get(name), "shutdown")
                attempts[name] += 1
        return [self._safe_outcome(i, attempts[name]) for name, i in issued.items()]

    def _flush_drivers(self, deadline: float) -> None:
        """Let every driver put what it was handed on the wire, until ``deadline`` at most."""
        for drv in self.drivers:
            try:
                drv.flush(max(0.0, deadline - time.monotonic()))
            except Exception:
                log.exception("driver %s failed to flush", drv.bus.name)

    def _safe_outcome(self, issue: SafeIssue, attempts: int) -> SafeOutcome:
        """What became of a safe value, from its last issue (see :meth:`_safe_all`)."""
        name = issue.device
        value = self._table.get(name).spec.safe_value
        match issue:
            case SafeIssue(refused=str(why)) if why:
                return SafeOutcome(name, value, False, why, attempts)
            case SafeIssue(write=None) | SafeIssue(write=Write(done=True)):
                return SafeOutcome(name, value, True, attempts=attempts)
            case SafeIssue(write=Write(done=False, reason=why)):
                return SafeOutcome(name, value, False, why or "refused", attempts)
            case _:
                return SafeOutcome(name, value, False,
                                   f"not confirmed on the wire within {self.shutdown_window} s",
                                   attempts)

    # ---- DriverHost (thread-safe: everything goes through the interrupt queue) -------------
    def written(self, device: str, value: Any) -> None:
        """The oldest outstanding write of ``device`` is on the wire (from any thread; see
        :mod:`chcos.devices.writes`)."""
        self._writes.written(device, value)

    def write_failed(self, device: str, value: Any, reason: str) -> None:
        """The oldest outstanding write of ``device`` did not reach the wire (from a driver
        thread); a safe value is tried again (see :mod:`chcos.devices.writes`)."""
        self._writes.write_failed(device, value, reason)

    def stat(self, bus: str, key: str, n: int = 1, device: str = "", error: bool = False
             ) -> None:
        """Add ``n`` to bus counter ``key`` (from any thread; see :class:`BusStats`), or with
        ``error`` to error class ``key`` (a device's as ``error:<key>``)."""
        self._counters.stat(bus, key, n, device, error)

    def error(self, bus: str, kind: str, detail: str, device: str = "") -> None:
        """Count a bus-level error of class ``kind`` (from a driver thread)."""
        self._counters.error(bus, kind, detail, device)

    @property
    def virtual_clock(self) -> bool:
        """True if the kernel runs on a virtual clock (a driver then stamps readings ``now``,
        see :func:`chcos.devices.driver.host_clock_virtual`)."""
        return self.kernel.clock.virtual

    def deliver(self, device: str, value: Any, at: float | None = None) -> None:
        """A new raw reading of sensor ``device`` (from a driver thread), stamped with the time
        the driver got it, or ``at`` (kernel-clock time the frame was received, never later
        than now): staleness is judged from that, not from when the kernel handles it."""
        now = self.kernel.clock.now()
        at = now if at is None or at > now else at
        self._rx_stamp[device] = at
        self.kernel.interrupt(self._readings, ((device, value),), at)

    inject = deliver  # the host's and the tests' way to feed a sensor

    def deliver_now(self, device: str, value: Any) -> None:
        """A new raw reading of sensor ``device`` taken on the kernel thread between task
        steps (a driver's timer callback, see :meth:`every`): handled at once, as its
        interrupt would be when the kernel next looked, without the round trip through the
        interrupt queue. Anywhere else (another thread, a task's step) it is :meth:`deliver`.
        It is handled before whatever still waits in the interrupt queue: a driver that also
        reports failures (:meth:`fail`, an interrupt) uses :meth:`deliver`, which keeps the
        order."""
        kernel = self.kernel
        if kernel.current is not None or not kernel.on_kernel_thread():
            self.deliver(device, value)
            return
        at = kernel.clock.now()
        self._rx_stamp[device] = at
        self._reading(device, value, at, at)

    def deliver_many(self, readings: Sequence[tuple[str, Any]], at: float | None = None) -> None:
        """New raw readings taken together (one poll of a driver: ``(device, value)`` pairs, in
        order) as one interrupt, so the kernel wakes once per poll; each is handled as
        :meth:`deliver` would, all stamped with this call's time, or ``at`` as in
        :meth:`deliver` (see :func:`chcos.devices.driver.deliver_all`)."""
        now = self.kernel.clock.now()
        at = now if at is None or at > now else at
        stamp = self._rx_stamp
        for device, _ in readings:
            stamp[device] = at
        self.kernel.interrupt(self._readings, tuple(readings), at)

    def fail(self, device: str, reason: str) -> None:
        """The driver reports ``device`` failed (from a driver thread); it stays failed until
        the driver reports the end of it (:meth:`recover`), whatever readings arrive."""
        self.kernel.interrupt(self._driver_health, device, reason)

    def recover(self, device: str, reason: str = "") -> None:
        """The driver reports that the event ending ``device``'s failure happened (from a
        driver thread)."""
        self.kernel.interrupt(self._driver_health, device, "", reason or "recovered")

    def every(self, period: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the kernel thread every ``period`` seconds of kernel time."""
        self.kernel.every(period, fn)

    def at(self, when: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` once on the kernel thread at kernel time ``when`` (at once if past); from
        any other thread through the interrupt queue, so the timer heap is only touched by the
        kernel thread."""
        if self.kernel.on_kernel_thread():
            self.kernel.call_at(when, fn)
        else:
            self.kernel.interrupt(self._arm, when, fn)

    def _arm(self, when: float, fn: Callable[[], None]) -> None:
        self.kernel.call_at(when, fn)

    def now(self) -> float:
        """The kernel clock's time."""
        return self.kernel.clock.now()

    def progress(self) -> float:
        """When the kernel was last seen making progress, in kernel-clock time
        (:attr:`chcos.kernel.scheduler.Kernel.progress`): a driver's liveness gate stops what
        tells the devices the controller is alive once it is too old. Thread-safe."""
        return self.kernel.progress

    # ---- interrupt handlers (kernel thread) -------------------------------------------------
    def _reading(self, device: str, raw: Any, at: float, now: float) -> None:
        """One reading on the kernel thread (see :meth:`_readings`): got by the driver at
        ``at``, handled at kernel time ``now``."""
        e = self._table.find(device)
        if e is None:
            self._counters.bus_error("?", "unknown-device",
                                     f"reading for unknown device {device!r}")
            return
        if e.status is _SUSPENDED or e.failure:   # a failed sensor delivers nothing until
            e.dropped += 1                         # the end of its failure is reported
            return
        spec = e.spec
        kind = raw.__class__  # int and float first: scalable() for the rest (bool is not scaled)
        value = (raw * spec.scale + spec.offset if kind is int or kind is float or scalable(raw)
                 else raw)
        if value.__class__ is float and not -_INF < value < _INF:     # NaN, an infinity
            self._not_a_value(e, raw)
            return
        if spec.limits != _OPEN:
            if self._limit(e, value, at, now):
                return
        elif e.limit:           # a number again: the failure a NaN made ends
            e.limit = ""
            self._health.refresh(e, "a finite reading")
        e.value = value
        e.updated_at = now
        e.rx_at = at
        e.readings += 1
        if e.stale:  # fresh data ends staleness, and nothing else (a driver failure stays)
            e.stale = False
            self._health.refresh(e, "fresh data")
        if self._listener is not None and self._listener.reading(device, value):
            e.overwrites += 1

    def _not_a_value(self, e: DeviceEntry, raw: Any) -> None:
        """Sensor ``e`` received NaN or an infinity (after scale and offset): no value for a
        task. The reading is dropped (counted in ``dropped``) and the sensor fails with the
        reason (as a reading outside its limits does, :meth:`_limit`) until a finite reading
        comes; its value stays the last number it had."""
        e.dropped += 1
        why = (f"{NOT_A_VALUE}: the device sent {raw!r}"
               + ("" if e.value is None else f" (last value {e.value!r})"))
        if e.limit != why:
            e.limit = why
            self._health.refresh(e, "")

    def _limit(self, e: DeviceEntry, value: Any, at: float, now: float) -> bool:
        """The limit rule of every bus: a reading outside its sensor's limits is not delivered
        (no reader gets it; the entry shows it, as what the device sent) and fails the sensor,
        reason ``limit: ...`` (readers get SensorFailure), until a reading within them ends
        it. True if ``value`` was outside."""
        lo, hi = e.spec.limits
        if scalable(value) and ((lo is not None and value < lo) or (hi is not None and value > hi)):
            e.dropped += 1
            e.value, e.updated_at, e.rx_at = value, now, at
            e.stale = False
            why = (f"limit: reading {value:g} {e.spec.units}".rstrip() +
                   f" outside [{'-inf' if lo is None else f'{lo:g}'}, "
                   f"{'inf' if hi is None else f'{hi:g}'}]")
            if e.limit != why:
                e.limit = why
                self._health.refresh(e, "")
            return True
        if e.limit:
            e.limit = ""
            self._health.refresh(e, "a reading within the limits")
        return False

    def _readings(self, readings: Sequence[tuple[str, Any]], at: float) -> None:
        """The interrupt of :meth:`deliver_many` and :meth:`deliver`: each reading in turn, all
        handled at the same kernel time; one that raises does not keep the others from their
        buffers (the first error is raised after the last, for the kernel to record)."""
        first: Exception | None = None
        now = self.kernel.clock.now()
        reading = self._reading
        for device, raw in readings:
            try:
                reading(device, raw, at, now)
            except Exception as exc:
                first = first or exc
        if first is not None:
            raise first

    def _driver_health(self, device: str, failure: str, ended: str = "") -> None:
        e = self._table.find(device)
        if e is None:
            return
        was = e.status
        e.failure = failure
        self._health.refresh(e, ended)
        if (not failure and was is DeviceStatus.FAILED and e.status is not DeviceStatus.FAILED
                and not e.is_sensor and e.spec.safe_value is not None
                and self.is_local(e.spec.machine)):
            # back: the safe value before any command; it stays until the owner commands again
            self._safe(device, "recovery")

    # ---- task side --------------------------------------------------------------------------
    def write(self, device: str, value: Any, source: str = "host") -> None:
        """Command actuator ``device`` with ``value`` (engineering units), without blocking.

        Raises DeviceError naming the device, the value and the rule if ``device`` is not an
        actuator, is failed or suspended, the value is not a finite number (for a numeric
        actuator), is outside its limits (never clamped), or its address cannot carry it (an
        integer address and a fraction without the device's ``round = true``, a value outside the
        address type's range). The device shows the value once the driver has put it on the wire
        (``pending`` until then); a write that fails later is a WARNING event (``write-failed``).
        """
        e = self._table.find(device) or self._table.get(device)   # get() names a missing one
        if e.spec.direction == "sensor":
            raise DeviceError(f"{device} is a sensor: {source} cannot write to it")
        status = e.status
        if status is _FAILED or status is _SUSPENDED:
            e.rejected += 1
            raise DeviceError(f"actuator {device} is {e.status.value} ({e.reason}): "
                              f"command {value!r} from {source} refused")
        raw = self._checks.check(e, value, source)
        self._send(e, value, raw, source)

    def _send(self, e: DeviceEntry, value: Any, raw: Any, source: str,
              safe: str = "") -> Write | None:
        """Hand a checked write to the driver (or the device's satellite); the Write to watch
        if the driver confirms writes."""
        spec = e.spec
        device = spec.name
        w: Write | None = None
        if not self._table.is_local(spec.machine):
            remote = self._health.remote
            if remote is None:
                raise DeviceError(f"actuator {device} is on machine {spec.machine}, which this "
                                  f"process does not drive, and no link leads there")
            remote.actuator(device, spec.machine, value, source)
        elif e.driver is not None and e.driver.confirms_writes:
            if safe or not self._write_now(e, device, raw):   # else on the wire, confirmed
                w = Write(device, value, raw, safe)
                self._writes.track(w)
                e.pending = value       # before the hand-over: the outcome may come at once
                e.driver.write(device, raw)
        elif e.driver is not None:
            e.driver.write(device, raw)
        # a remote actuator's satellite confirms it there: here it is only sent
        self._commanded(e, value, self.kernel.clock.now(), shown=w is None, source=source,
                        safe=safe, confirmed=w is None and self._table.is_local(spec.machine))
        return w

    def _commanded(self, e: DeviceEntry, value: Any, now: float, shown: bool,
                   source: str = "", safe: str = "", confirmed: bool | None = None) -> None:
        """The bookkeeping of a write handed over (to the driver, to the device's satellite, or
        on the wire already): when and how often the actuator was commanded, the value it shows
        (``shown``; else it stays ``pending`` until the driver's outcome), the
        :attr:`on_write` hooks and the observers (a command from ``source``, a safe value
        for ``safe``; ``confirmed``, default ``shown``: on the wire already). The one place a
        write is recorded, for every path to a bus."""
        e.updated_at = now
        e.commands += 1
        if shown:
            e.value = value
        for hook in self.on_write:
            hook(e.name, value)
        if self._observers:
            done = shown if confirmed is None else confirmed
            self._observers.command(CommandReport(
                e.name, value, WriteStage.CONFIRMED if done else WriteStage.SENT,
                source or "host", safe))

    def _write_now(self, e: DeviceEntry, device: str, raw: Any) -> bool:
        """The driver's synchronous fast path (:meth:`chcos.devices.driver.Driver.write_now`, the
        template that checks it as :meth:`chcos.devices.driver.Driver.write` does), tried only on
        the kernel thread and when no earlier write of ``device`` is outstanding or has an
        outcome on its way here (so the shown value and the order stay those of the wire). True if
        ``raw`` is on the wire; then nothing is tracked."""
        assert e.driver is not None
        if not self.kernel.on_kernel_thread() or self._writes.outstanding(device):
            return False
        return e.driver.write_now(device, raw)

    def safe_values(self, devices: Iterable[str], why: str = "abnormal completion") -> int:
        """Write the safe value of each actuator of ``devices`` that has one (whatever state
        it is in); returns how many were handed over. Raises DeviceError for an unknown
        device."""
        return sum(1 for d in devices if self._safe(d, why))

    def estop(self, reason: str) -> int:
        """Write the safe value of every actuator of this satellite (where configured), whatever
        state it is in; returns how many were handed to the drivers. One that cannot be
        delivered (after SAFE_ATTEMPTS) is reported as a ``write-failed`` event, logged at ERROR
        and added to :attr:`safe_failures`. Other satellites are told by the caller (see
        TaskContext.estop)."""
        issued = self._safe_all(reason)
        n = sum(1 for i in issued if i.handed_over)
        log.log(logging.INFO if reason == "shutdown" else logging.WARNING,
                "estop (%s): %d safe value(s) sent", reason, n)
        return n

    def _safe_all(self, reason: str) -> list[SafeIssue]:
        """Every local actuator's safe value: first all those the drivers can put on the wire
        at once (:meth:`_safe_burst`), then the others one by one, tracked and tried again as
        any safe value; one :class:`SafeIssue` each."""
        todo = self._table.local_safe_actuators()
        done = self._safe_burst(todo, reason)
        return [SafeIssue(e.name) if e.name in done else self._safe_write(e, reason)
                for e in todo]

    def _safe_burst(self, entries: list[DeviceEntry], why: str) -> set[str]:
        """On the kernel thread, put the safe values of ``entries`` that nothing of theirs is
        outstanding for on the wire back to back, one call per driver
        (:meth:`chcos.devices.driver.Driver.write_now_many`), before any bookkeeping: an emergency
        stop's last safe frame leaves as early as it can. Returns the names written; the rest
        (a value the check refuses, a driver that cannot send now) are left to the tracked
        path, which reports them."""
        if not self.kernel.on_kernel_thread():
            return set()
        groups: dict[Driver, list[tuple[DeviceEntry, Any]]] = {}
        for e in entries:
            drv = e.driver
            name = e.name
            if drv is None or not drv.confirms_writes or self._writes.outstanding(name):
                continue
            try:
                raw = self._checks.check(e, e.spec.safe_value, "safe-value")
            except Exception:   # the tracked path checks it again and reports it
                continue
            groups.setdefault(drv, []).append((e, raw))
        written: list[DeviceEntry] = []
        for drv, items in groups.items():
            sent = drv.write_now_many([(e.name, raw) for e, raw in items])
            written += [e for (e, _raw), ok in zip(items, sent, strict=True) if ok]
        now = self.kernel.clock.now()
        for e in written:   # as Devtab.write's fast path: on the wire, confirmed, not tracked
            self._commanded(e, e.spec.safe_value, now, shown=True, source="safe-value",
                            safe=why)
        return {e.name for e in written}

    def _safe(self, device: str, why: str = "abnormal completion") -> bool:
        e = self._table.get(device)
        if e.spec.safe_value is None or e.is_sensor:
            return False
        return self._safe_write(e, why).handed_over

    def _safe_write(self, e: DeviceEntry, why: str) -> SafeIssue:
        """Put ``e``'s safe value out whatever its status: with the Write to watch (none if the
        driver does not confirm writes), or the reason it could not even be handed over."""
        safe = e.spec.safe_value
        assert safe is not None
        try:
            raw = self._checks.check(e, safe, "safe-value")
            w = self._send(e, safe, raw, "safe-value", safe=why)
        except Exception as exc:  # report, keep going with the others
            text = f"{e.name}: safe value ({why}) {safe!r} not written: {exc}"
            self.safe_failures.append((e.name, str(exc)))
            faults.error("%s", text)
            self.kernel.event("write-failed", text)
            return SafeIssue(e.name, refused=str(exc))
        return SafeIssue(e.name, w)

    def _safe_failed(self, device: str, reason: str) -> None:
        """A tracked safe value was finally not written (:class:`WriteTracking` reports it)."""
        self.safe_failures.append((device, reason))
