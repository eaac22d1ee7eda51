"""health - the one place the north side reads device health and bus statistics from Devtab.

Devtab keeps a status (OK, suspended, failed, stale) with its cause per device, per-bus
statistics (``Devtab.bus_stats``) and health listeners; the OPC UA server, the Modbus facade and
the metrics read health only through :func:`device_health`, :func:`bus_stats` and
:func:`add_health_listener`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from chcos.devices.entry import DeviceStatus

if TYPE_CHECKING:
    from chcos.devices.devtab import Devtab
    from chcos.devices.entry import DeviceEntry


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
    """Per-bus figures: errors by class, counts (frames, requests, reconnects, lost), the last
    error's text, how many devices it carries."""

    name: str
    kind: str
    errors: dict[str, int]
    last_error: str
    devices: int
    counts: dict[str, int]


def bus_stats(devtab: Devtab) -> list[BusStats]:
    """Statistics of every bus of the loaded device map, also those without errors."""
    stats = dict(devtab.bus_stats)  # copy first: drivers' interrupts may add buses meanwhile
    counts: dict[str, int] = {}
    kinds: dict[str, str] = {}
    for e in list(devtab):
        counts[e.spec.bus] = counts.get(e.spec.bus, 0) + 1
    for drv in list(devtab.drivers):
        kinds[drv.bus.name] = drv.bus.kind
    out = []
    for b in sorted(set(counts) | set(stats)):
        st = stats.get(b)
        out.append(BusStats(b, kinds.get(b, ""), dict(st.errors) if st else {},
                            st.last_error if st else "", counts.get(b, 0),
                            dict(st.counts) if st else {}))
    return out


HealthListener = Callable[[str, bool, str], None]


def add_health_listener(devtab: Devtab, fn: HealthListener) -> None:
    """Call ``fn(device, healthy, cause)`` on the kernel thread whenever a device's health
    changes (Devtab's own listeners)."""
    devtab.add_health_listener(fn)


def remove_health_listener(devtab: Devtab, fn: HealthListener) -> None:
    """Undo :func:`add_health_listener` (no error if ``fn`` was not added)."""
    devtab.remove_health_listener(fn)


__all__ = ["BusStats", "Health", "add_health_listener", "bus_stats", "device_health",
           "remove_health_listener"]
