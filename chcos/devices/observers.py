"""observers - who watches what the device table does beyond readings and health: every bus
error a driver reports (its class and the device it concerns) and every actuator command on its
way to the wire (handed to the driver, confirmed by it, or failed), as typed reports.

The device table calls its :class:`Observers` only when one is registered (one truth test on the
paths it watches otherwise), always on the kernel thread. An observer that raises is removed and
logged, as the kernel's instruments are: the device table carries on. What reads these reports
is the HIL evidence (:mod:`chcos.hil.observe`: device-state coverage, the run's trace); readings
and health changes reach it through the device table's listener and health listeners.
"""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass
from typing import Any, Protocol

log = logging.getLogger("chcos.devices.observers")


class WriteStage(enum.Enum):
    """Where a command is: handed to its driver (``sent``; a driver that confirms writes reports
    later), on the wire (``confirmed``: confirmed by the driver, or taken by one that does not
    confirm), or not written (``failed``)."""

    SENT = "sent"
    CONFIRMED = "confirmed"
    FAILED = "failed"


@dataclass(frozen=True, slots=True)
class CommandReport:
    """One actuator command at one stage: ``value`` in engineering units, ``source`` who
    commanded it (a task, ``host``, ``safe-value``; "" where the stage does not know), ``safe``
    why a safe value was written (``shutdown``, ``abnormal completion``, ``recovery``, an
    e-stop's reason; "" for a plain command), ``reason`` why it failed."""

    device: str
    value: Any
    stage: WriteStage
    source: str = ""
    safe: str = ""
    reason: str = ""


@dataclass(frozen=True, slots=True)
class BusReport:
    """One bus error as its driver reported it (:meth:`drivers.base.DriverHost.error`): the bus,
    the error class (``timeout``, ``exception-6``, ``sdo-abort``, ``emcy``, ``bus-off``...), the
    driver's text and the device it concerns ("" for the bus as a whole)."""

    bus: str
    kind: str
    detail: str
    device: str = ""


class DeviceObserver(Protocol):
    """What an observer of the device table implements (both on the kernel thread)."""

    def bus_error(self, report: BusReport) -> None:
        """A driver reported a bus error."""

    def command(self, report: CommandReport) -> None:
        """An actuator command reached a stage."""


class Observers:
    """The observers of one device table. False while none is registered."""

    def __init__(self) -> None:
        self._observers: tuple[DeviceObserver, ...] = ()

    def __bool__(self) -> bool:
        return bool(self._observers)

    def add(self, observer: DeviceObserver) -> None:
        """Tell ``observer`` of every report from now on."""
        self._observers = (*self._observers, observer)

    def remove(self, observer: DeviceObserver) -> None:
        """Stop telling ``observer`` (no error if it was not registered)."""
        self._observers = tuple(o for o in self._observers if o is not observer)

    def bus_error(self, report: BusReport) -> None:
        """Tell every observer of a bus error."""
        for o in self._observers:
            try:
                o.bus_error(report)
            except Exception:
                self._drop(o)

    def command(self, report: CommandReport) -> None:
        """Tell every observer of a command's stage."""
        for o in self._observers:
            try:
                o.command(report)
            except Exception:
                self._drop(o)

    def _drop(self, observer: DeviceObserver) -> None:
        log.exception("device observer %r raised and has been removed", observer)
        self.remove(observer)
