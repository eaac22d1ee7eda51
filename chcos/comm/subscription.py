"""subscription - the handle of a declared Zenoh entity (subscriber, server, token or watcher)
of a :class:`chcos.comm.transport.Transport`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import zenoh

log = logging.getLogger("chcos.comm")


class Subscription:
    """A declared subscriber, server, token or watcher. ``close()`` (or leaving the ``with``
    block) undeclares it; closing twice is harmless. The transport closes all of them on close;
    ``forget(sub)`` tells the transport that ``sub`` is closed."""

    def __init__(self, forget: Callable[[Subscription], None], what: str, entity: Any) -> None:
        self._forget = forget
        self._entity = entity
        self._closed = False
        self.what = what

    def close(self) -> None:
        """Undeclare the Zenoh entity. Never raises."""
        if self._closed:
            return
        self._closed = True
        self._forget(self)
        try:
            self._entity.undeclare()
        except zenoh.ZError as exc:  # the session may already be closed
            log.debug("undeclaring %s: %s", self.what, exc)

    @property
    def closed(self) -> bool:
        """True once closed, by itself or by the transport."""
        return self._closed

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Subscription({self.what!r}, closed={self._closed})"
