"""registry - find a driver class by bus kind: :mod:`chcos.devices.registry` under the drivers'
name (the entry points ``chcos.drivers``)."""

from __future__ import annotations

from chcos.devices.registry import driver_class, known_kinds

__all__ = ["driver_class", "known_kinds"]
