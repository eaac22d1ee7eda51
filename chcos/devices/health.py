"""health - the health half of the device table: status (OK, FAILED, STALE, SUSPENDED) from
what the drivers report and from staleness, the host's suspend/resume, and who is told.

A device is FAILED while its driver reports a failure (cleared only by the driver) or while a
sensor's last reading was outside its limits (cleared by a reading within them), STALE while
a sensor has had no fresh data for ``stale_after`` seconds (cleared only by fresh data), and
SUSPENDED while the host holds it; every change is an event, a WARNING on the faults logger,
a call to each health listener, and for a local device a status message to the other
satellites. A sensor that fails or goes stale wakes its readers with a SensorFailure.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Mapping

from chcos.devices.entry import DeviceEntry, DeviceListener, DeviceStatus, RemoteDevices
from chcos.devices.table import DeviceTable
from chcos.errors import SensorFailure
from chcos.kernel.scheduler import Kernel

#: the states a sensor cannot be read in (a module constant: no enum lookups per read)
_UNREADABLE = (DeviceStatus.FAILED, DeviceStatus.STALE)

log = logging.getLogger("chcos.devices.devtab")
#: Faults a user must see whatever the log level (failed and refused writes, undelivered safe
#: values, health changes): WARNING records of this logger pass a root logger set to ERROR.
faults = logging.getLogger("chcos.devices.devtab.faults")
faults.setLevel(logging.WARNING)

HealthListener = Callable[[str, bool, str], None]


class DeviceHealth:
    """Device status for :class:`chcos.devices.devtab.Devtab`, which owns one: the status of the
    entries of ``table`` from what the drivers report (:meth:`refresh` after a change of an
    entry's ``failure`` or ``stale``), the host's suspend/resume, staleness timers, and who is
    told. ``rx_stamps`` are the drivers' receive times by device (kept by Devtab, read here by
    the staleness check). :attr:`remote` hears of local status changes, :attr:`listener` of
    failed sensors; both are set by the owner."""

    def __init__(self, kernel: Kernel, table: DeviceTable, rx_stamps: Mapping[str, float]
                 ) -> None:
        self._kernel = kernel
        self._table = table
        self._rx_stamps = rx_stamps
        #: the devices of other satellites, told of local status changes (None: no link)
        self.remote: RemoteDevices | None = None
        #: told of every sensor that fails or goes stale (the message manager)
        self.listener: DeviceListener | None = None
        self._listeners: list[HealthListener] = []

    def suspend(self, device: str) -> None:
        """Host ``suspend`` of a device: SUSPENDED (readings dropped, commands refused) until
        :meth:`resume`. Raises DeviceError for an unknown device."""
        self._table.get(device)
        self._set_status(device, DeviceStatus.SUSPENDED, "suspended by the host")

    def resume(self, device: str) -> None:
        """Undo :meth:`suspend`: the device takes the status its health gives (a failure its
        driver reported meanwhile, staleness, else OK); one that is not suspended is left as
        it is. Raises DeviceError for an unknown device."""
        e = self._table.get(device)
        if e.status is DeviceStatus.SUSPENDED:
            status, reason = self._health_status(e)
            self._set_status(device, status, reason, ended="resumed by the host")

    def healthy(self, device: str) -> bool:
        """Whether ``device`` delivers (neither failed nor stale). Raises DeviceError for an
        unknown device."""
        return self._table.get(device).status not in (DeviceStatus.FAILED, DeviceStatus.STALE)

    def check_readable(self, device: str) -> None:
        """Raise SensorFailure if sensor ``device`` is failed or stale."""
        e = self._table.get(device)
        if e.status in _UNREADABLE:
            raise SensorFailure(device, e.reason or e.status.value)

    def set_status(self, device: str, status: DeviceStatus, reason: str) -> None:
        """Another satellite reports the status of one of its devices (or that it died)."""
        self._set_status(device, status, reason, tell=False)

    def add_health_listener(self, fn: HealthListener) -> None:
        """Call ``fn(device, healthy, cause)`` on the kernel thread whenever a device's health
        changes: ``healthy`` False with the failure's cause, True with the event that ended it."""
        self._listeners.append(fn)

    def remove_health_listener(self, fn: HealthListener) -> None:
        """Stop calling ``fn`` (added by :meth:`add_health_listener`; no error if it is not)."""
        with contextlib.suppress(ValueError):
            self._listeners.remove(fn)

    @staticmethod
    def _health_status(e: DeviceEntry) -> tuple[DeviceStatus, str]:
        """The status ``e``'s health gives, with its reason: a driver failure first, then
        staleness, else OK."""
        if e.failure:
            return DeviceStatus.FAILED, e.failure
        if e.limit:
            return DeviceStatus.FAILED, e.limit
        if e.stale:
            return DeviceStatus.STALE, f"no data for {e.spec.stale_after} s (stale_after)"
        return DeviceStatus.OK, ""

    def refresh(self, e: DeviceEntry, ended: str) -> None:
        """Set ``e``'s status from its health (unless the host suspended it); ``ended`` names
        the event that ended a failure or staleness."""
        if e.status is DeviceStatus.SUSPENDED:
            return
        status, reason = self._health_status(e)
        if status is e.status:
            e.reason = reason
            return
        self._set_status(e.name, status, reason, ended=ended)

    def _set_status(self, device: str, status: DeviceStatus, reason: str,
                    tell: bool = True, ended: str = "") -> None:
        e = self._table.find(device)
        if e is None or e.status is status:
            return
        old = e.status
        e.status = status
        e.reason = reason
        e.since = self._kernel.clock.now()
        if tell and self.remote is not None and self._table.is_local(e.spec.machine):
            self.remote.device_status(device, status, reason)
        cause = reason if status is not DeviceStatus.OK else (ended or f"was {old.value}")
        self._kernel.event(f"device-{status.name.lower()}",
                          f"{device}: {cause}" if cause else device)
        if status is not DeviceStatus.SUSPENDED and old is not DeviceStatus.SUSPENDED:
            faults.warning("device %s %s at t=%.6f: %s", device, status.value, e.since, cause)
        for fn in list(self._listeners):
            try:
                fn(device, status is DeviceStatus.OK, cause)
            except Exception:  # a listener must not break the device manager
                log.exception("health listener failed for %s", device)
        listener = self.listener
        if status in (DeviceStatus.FAILED, DeviceStatus.STALE) and listener is not None:
            listener.sensor_failed(device, SensorFailure(device, reason or status.value))

    def arm_stale(self, e: DeviceEntry, since: float) -> None:
        """Check sensor ``e`` for staleness from kernel time ``since`` on, every
        ``stale_after`` seconds of no fresh data (a kernel timer, for as long as the kernel
        runs)."""
        limit = e.spec.stale_after
        assert limit is not None

        def check() -> None:
            # the driver's receive time: a reading received but not yet handled is late, not
            # missing (the stamp is set in the driver's thread before the interrupt is queued)
            last = max(since, e.rx_at if e.rx_at is not None else since,
                       self._rx_stamps.get(e.name, since))
            due = last + limit
            if self._kernel.clock.now() >= due:
                if not e.stale:
                    e.stale = True
                    self.refresh(e, "")
                due = self._kernel.clock.now() + limit
            self._kernel.call_at(due, check)

        self._kernel.call_at(since + limit, check)
