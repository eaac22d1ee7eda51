"""registry - find a driver class by bus kind, through the ``chcos.drivers`` entry points."""

from __future__ import annotations

from importlib import import_module
from importlib.metadata import entry_points

from chcos.errors import DriverNotAvailable
from drivers.base import Driver

_cache: dict[str, type[Driver]] = {}


def known_kinds() -> list[str]:
    """Every bus kind registered as a ``chcos.drivers`` entry point, sorted."""
    return sorted({ep.name for ep in entry_points(group="chcos.drivers")})


def driver_class(kind: str) -> type[Driver]:
    """The driver class for bus kind ``kind``, imported lazily.

    Raises :class:`chcos.errors.DriverNotAvailable` if no entry point names ``kind`` or its module
    fails to import (the import error is chained).
    """
    if kind in _cache:
        return _cache[kind]
    eps = [ep for ep in entry_points(group="chcos.drivers") if ep.name == kind]
    if not eps:
        raise DriverNotAvailable(
            f"no driver for bus kind {kind!r}; known kinds: {', '.join(known_kinds()) or 'none'}")
    ref = eps[0].value
    mod_name, _, attr = ref.partition(":")
    try:
        cls = getattr(import_module(mod_name), attr)
    except (ImportError, AttributeError) as exc:
        raise DriverNotAvailable(f"driver for bus kind {kind!r} ({ref}) is not available: {exc}") \
            from exc
    if not (isinstance(cls, type) and issubclass(cls, Driver)):
        raise DriverNotAvailable(f"{ref} (bus kind {kind!r}) is not a drivers.base.Driver")
    _cache[kind] = cls
    return cls
