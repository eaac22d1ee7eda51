"""base - the driver interface, as the drivers import it: :class:`Driver`, :class:`DriverHost` and
their helpers live in the device layer (:mod:`chcos.devices.driver`, which Devtab uses without
importing a driver); this module is their name under ``drivers``."""

from __future__ import annotations

from chcos.devices.driver import (
    Driver,
    DriverHost,
    deliver_all,
    host_clock_virtual,
    host_peers_on_clock,
    not_finite,
)

__all__ = ["Driver", "DriverHost", "deliver_all", "host_clock_virtual", "host_peers_on_clock",
           "not_finite"]
