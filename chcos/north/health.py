"""health - the one place the north side reads device health and bus statistics from Devtab.

Today Devtab keeps a status (OK, suspended, failed, stale) and a reason per device, and counts bus
errors per (bus, kind). A richer health model (a cause per device, health listeners, per-bus
statistics) is coming; the OPC UA server, the Modbus facade and the metrics read health only
through :func:`device_health`, :func:`bus_stats` and :func:`add_health_listener`, so switching to
it changes this module alone.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from chcos.devices import DeviceStatus

if TYPE_CHECKING:
    from chcos.devices import DeviceEntry, Devtab


@dataclass(frozen=True)
class Health:
    """A device's health as the north side shows it: ``healthy``, the Devtab ``status`` text,
    and the ``cause`` of a failure ("" when healthy)."""

    healthy: bool
    status: str
    cause: str


def device_health(entry: DeviceEntry) -> Health:
    """The health of one Devtab entry (read without locks: one attribute at a time)."""
    status = entry.status
    return Health(status is DeviceStatus.OK, status.value, entry.reason)


@dataclass(frozen=True)
class BusStats:
    """Per-bus figures: errors by kind, the last error's text, how many devices it carries."""

    name: str
    kind: str
    errors: dict[str, int]
    last_error: str
    devices: int


def bus_stats(devtab: Devtab) -> list[BusStats]:
    """Statistics of every bus of the loaded device map, also those without errors."""
    errors = dict(devtab.bus_errors)  # copy first: drivers' interrupts may add keys meanwhile
    counts: dict[str, int] = {}
    kinds: dict[str, str] = {}
    for e in list(devtab):
        counts[e.spec.bus] = counts.get(e.spec.bus, 0) + 1
    for drv in list(devtab.drivers):
        kinds[drv.bus.name] = drv.bus.kind
    names = sorted(set(counts) | {b for b, _ in errors})
    return [BusStats(b, kinds.get(b, ""), {k: n for (bb, k), n in errors.items() if bb == b},
                     devtab.last_bus_error.get(b, ""), counts.get(b, 0)) for b in names]


HealthListener = Callable[[str, bool, str], None]


def add_health_listener(devtab: Devtab, fn: HealthListener) -> None:
    """Call ``fn(device, healthy, cause)`` on the kernel thread whenever a device's status
    changes (wraps the kernel's ``device-*`` events until Devtab has listeners of its own)."""
    from chcos.instrument import Instrument

    class _Listener(Instrument):
        def event(self, kind: str, detail: str) -> None:
            if not kind.startswith("device-"):
                return
            name, _, cause = detail.partition(":")
            fn(name.strip(), kind == "device-ok", cause.strip())

    devtab.kernel.add_instrument(_Listener())


__all__ = ["BusStats", "Health", "add_health_listener", "bus_stats", "device_health"]
