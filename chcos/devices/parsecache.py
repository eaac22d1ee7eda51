"""parsecache - parse each DBC / EDS file once per device-map load, not once per device.

Drivers' ``check_bus`` / ``check_device`` need the parsed DBC database or EDS object dictionary
of their bus; a map with D devices on one bus would parse the same file D times. Inside
:func:`scope` (entered by :func:`chcos.devices.devmap.check` and by drivers that re-check at start),
:func:`cached` keeps each parsed file keyed by its resolved path, modification time and size
(and any extra key such as a CANopen node id), so a file changed on disk is parsed again. Outside
a scope nothing is cached: a long-lived cache would hand a driver a stale or shared object.
The cache is per thread; scopes nest (the outermost one owns the cache).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Hashable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")

_local = threading.local()


@contextmanager
def scope() -> Iterator[None]:
    """Cache parsed files on this thread until the outermost ``with scope()`` ends."""
    outer = getattr(_local, "cache", None)
    if outer is None:
        _local.cache = {}
    try:
        yield
    finally:
        if outer is None:
            _local.cache = None


def cached(kind: str, path: str | Path, extra: Hashable, load: Callable[[], T]) -> T:
    """``load()`` for ``path``, or the object it returned earlier in this scope for the same
    file (same resolved path, mtime and size) and ``extra``. Errors are not cached: ``load``'s
    exception propagates and the next call tries again. A path that cannot be stat'ed is
    loaded every time (``load`` reports the error)."""
    cache: dict[tuple[Any, ...], Any] | None = getattr(_local, "cache", None)
    if cache is None:
        return load()
    try:
        p = Path(path).expanduser().resolve()
        st = p.stat()
    except OSError:
        return load()
    key = (kind, str(p), st.st_mtime_ns, st.st_size, extra)
    if key in cache:
        return cache[key]  # type: ignore[no-any-return]
    value = load()
    cache[key] = value
    return value
