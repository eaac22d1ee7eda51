"""registry - find a driver class by bus kind, through the ``chcos.drivers`` entry points.

The device layer's one door to the drivers: Devtab starts them, the map checks and the
device-map reference ask them, all by kind name, and none imports a driver module (an entry
point is loaded when its kind is asked for). ``drivers.registry`` is the same functions under
the drivers' name.
"""

from __future__ import annotations

from importlib import import_module
from importlib.metadata import entry_points

from chcos.devices.driver import Driver
from chcos.errors import DriverNotAvailable

_GROUP = "chcos.drivers"
_cache: dict[str, type[Driver]] = {}
#: The extra of the chcos distribution that brings each built-in kind's bus library (the kinds
#: not named need none); ``vcan_tests/test_packaging.py`` checks each is declared.
EXTRAS: dict[str, str] = {"can": "can", "canopen": "canopen", "modbus-tcp": "modbus",
                          "modbus-rtu": "modbus", "serial": "serial"}


def known_kinds() -> list[str]:
    """Every bus kind registered as a ``chcos.drivers`` entry point, sorted."""
    return sorted({ep.name for ep in entry_points(group=_GROUP)})


def driver_class(kind: str) -> type[Driver]:
    """The driver class for bus kind ``kind``, imported lazily.

    Raises :class:`chcos.errors.DriverNotAvailable` if no entry point names ``kind``, its module
    fails to import (the import error is chained; the message names the extra that brings the
    kind's bus library, :data:`EXTRAS`), or
    what it names is no :class:`chcos.devices.driver.Driver`.
    """
    if kind in _cache:
        return _cache[kind]
    eps = [ep for ep in entry_points(group=_GROUP) if ep.name == kind]
    if not eps:
        raise DriverNotAvailable(
            f"no driver for bus kind {kind!r}; known kinds: {', '.join(known_kinds()) or 'none'}")
    ref = eps[0].value
    mod_name, _, attr = ref.partition(":")
    try:
        cls = getattr(import_module(mod_name), attr)
    except (ImportError, AttributeError) as exc:
        extra = EXTRAS.get(kind)
        hint = f" (pip install 'chcos[{extra}]')" if extra and isinstance(exc, ImportError) else ""
        raise DriverNotAvailable(f"driver for bus kind {kind!r} ({ref}) is not available: "
                                 f"{exc}{hint}") from exc
    if not (isinstance(cls, type) and issubclass(cls, Driver)):
        raise DriverNotAvailable(f"{ref} (bus kind {kind!r}) is not a chcos.devices.driver.Driver")
    _cache[kind] = cls
    return cls
