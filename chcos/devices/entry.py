"""entry - what the device table holds: a device's status, its Devtab row, the writes in
flight, the bus counters, and the two narrow protocols by which Devtab talks upward (the
listener that fans readings out over links, the link to the devices of other satellites).
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from chcos.devices.spec import DeviceSpec
from chcos.errors import SensorFailure

if TYPE_CHECKING:
    from chcos.devices.driver import Driver


class DeviceStatus(enum.Enum):
    """Devtab status values; the value is the text maps, the viewer and the link carry."""

    OK = "OK"
    SUSPENDED = "suspended"
    FAILED = "failed"
    STALE = "stale"


@dataclass(frozen=True, slots=True)
class NumberCheck:
    """How a plain number (an int or float, not a bool) commanded to one device is checked with
    ``driver``: a value in ``lo..hi`` (integers only if ``integral``) is inside the device's
    limits, finite, and accepted by the driver without asking, or else after ``ask`` (the
    driver's ``check_value``) agrees. A device with scale, offset or ``round`` has an empty
    range (``lo > hi``): every value takes the full check."""

    driver: Driver | None
    lo: float
    hi: float
    integral: bool
    ask: Callable[[str, Any], str | None] | None


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
    driver: Driver | None = None
    failure: str = ""          # the driver-reported failure ("" none); cleared only by the driver
    stale: bool = False        # no fresh data for stale_after; cleared only by fresh data
    limit: str = ""            # why the last reading was outside the limits; cleared by one within
    since: float | None = None  # kernel time of the last status change
    rx_at: float | None = None  # driver receive time of the last reading
    pending: Any = None        # a command handed to the driver, not yet on the wire
    write_errors: int = 0
    last_write_error: str = ""
    #: how a plain numeric command is checked with the device's current driver (made and
    #: kept by :class:`chcos.devices.commands.CommandChecks`)
    number_check: NumberCheck | None = None

    @property
    def name(self) -> str:
        """The device's name."""
        return self.spec.name

    @property
    def is_sensor(self) -> bool:
        """True for an input device."""
        return self.spec.direction == "sensor"


_NUMBERS = (int, float)  # a tuple: ``int | float`` would build a union on every call


def scalable(value: Any) -> bool:
    """True for an int or float that is not a bool (what scale and offset apply to)."""
    return isinstance(value, _NUMBERS) and not isinstance(value, bool)


@dataclass(eq=False)
class Write:
    """One write handed to a driver that confirms writes, until it is confirmed or failed."""

    device: str
    value: Any           # engineering units (what the map shows once written)
    raw: Any             # what the driver got
    safe: str = ""       # why a safe value ("shutdown", "recovery"...); "" for a command
    attempts: int = 1
    done: bool | None = None    # None pending, True on the wire, False failed
    reason: str = ""


@dataclass(frozen=True)
class SafeIssue:
    """One safe value handed out (e-stop, shutdown...): on the wire at once (``write`` None and
    nothing ``refused``), tracked until its driver confirms or fails it (``write``), or refused
    before it reached a driver (``refused`` says why: the device's checks, no driver)."""

    device: str
    write: Write | None = None
    refused: str = ""

    @property
    def handed_over(self) -> bool:
        """True unless it was refused before reaching a driver."""
        return not self.refused


@dataclass(frozen=True)
class SafeOutcome:
    """What became of one actuator's safe value at shutdown: ``written`` only when the driver
    confirmed it on the wire (or, for a driver that does not confirm writes, took it);
    otherwise ``reason`` says why not. ``attempts``: how many times it was issued."""

    device: str
    value: Any
    written: bool
    reason: str = ""
    attempts: int = 1


class DeviceListener(Protocol):
    """Who hears of a device's readings and failures to pass them on (the message manager, which
    owns the links leaving devices). Called on the kernel thread."""

    def reading(self, device: str, value: Any) -> bool:
        """A new reading of sensor ``device`` (engineering units); True if it overwrote a
        message a reader had not read yet."""

    def sensor_failed(self, device: str, failure: SensorFailure) -> None:
        """Sensor ``device`` failed or went stale: wake whoever waits for it with ``failure``."""


class RemoteDevices(Protocol):
    """The devices of other satellites, as Devtab reaches them (the communications manager)."""

    def actuator(self, device: str, machine: int, value: Any, source: str) -> None:
        """Carry an actuator command to the device's satellite."""

    def device_status(self, device: str, status: DeviceStatus, reason: str) -> None:
        """Tell every satellite that a local device changed status."""
