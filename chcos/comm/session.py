"""session - one satellite's Zenoh session: opening and closing it, the entities declared on it,
the seals on every payload and the cached publishers (the base of
:class:`chcos.comm.transport.Transport`, which holds the operations and documents them).
"""

from __future__ import annotations

import itertools
import logging
import sys
import threading
from collections import OrderedDict
from typing import Any, Self

import zenoh

from chcos.comm.config import LinkConfig
from chcos.comm.qos import PRIORITY_BANDS, check_key
from chcos.comm.secret import SEAL_BYTES, Refusal, Sealer, SealRefused, Throttle
from chcos.comm.subscription import Subscription
from chcos.errors import LinkError

log = logging.getLogger("chcos.comm")

#: Encoding of the error replies chcos servers send (Zenoh's own errors, e.g. timeouts, differ).
SERVER_ERROR_ENCODING = "text/plain;chcos-server-error"
#: Largest payload sent or accepted on the link by default (bytes, before the seal).
MAX_MESSAGE_BYTES = 1024 * 1024
#: The receiver number of the answers to this session's requests (subscribers and servers are
#: numbered from 1, each opening the payloads it receives once).
REQUESTER = 0
#: Publishers kept declared (one per key and QoS); the least recently used beyond this is dropped.
PUBLISHER_CACHE_SIZE = 256



class Session:
    """One Zenoh session configured by a :class:`LinkConfig` (a context manager): its life
    cycle, the entities declared on it, the seals on its payloads and its publishers. The
    operations on it are :class:`chcos.comm.transport.Transport`'s.

    Raises LinkError when Zenoh cannot open the session (e.g. the listen port is taken); every
    method raises LinkError on a closed transport, a bad key or priority, or a Zenoh failure.
    """

    def __init__(self, config: LinkConfig, *, sealer: Sealer | None = None,
                 max_bytes: int = MAX_MESSAGE_BYTES) -> None:
        self.config = config
        self.sealer = sealer
        self.max_bytes = max_bytes
        self.rejected = Throttle(log)
        self._lock = threading.Lock()
        self._errors = 0
        self._malformed = 0
        self._closed = False
        self._entities: dict[int, Subscription] = {}
        self._receivers = itertools.count(REQUESTER + 1)
        # (key, priority band, express, block) -> zenoh.Publisher (zenoh.Priority is unhashable)
        self._publishers: OrderedDict[tuple[str, int, bool, bool], Any] = OrderedDict()
        try:
            self._session = zenoh.open(config.to_zenoh())
        except zenoh.ZError as exc:
            raise LinkError(
                f"link: cannot open the Zenoh session (listen {config.listen_endpoints}, "
                f"connect {config.connect_endpoints}): {exc}"
            ) from exc
        log.info(
            "link %s open: listen %s connect %s",
            self.zid,
            config.listen_endpoints,
            config.connect_endpoints,
        )

    # -- life cycle --------------------------------------------------------------------------

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Undeclare everything and close the session; its tokens vanish for the others.
        Closing twice is harmless."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            entities = list(self._entities.values())
            publishers = list(self._publishers.values())
            self._publishers.clear()
        for entity in entities:
            entity.close()
        for publisher in publishers:
            try:
                publisher.undeclare()
            except zenoh.ZError as exc:
                log.debug("undeclaring a publisher: %s", exc)
        zid = self.zid
        self._session.close()  # type: ignore[no-untyped-call]  # stub lacks "-> None"
        log.info("link %s closed", zid)

    @property
    def closed(self) -> bool:
        """True once :meth:`close` ran."""
        return self._closed

    @property
    def zid(self) -> str:
        """This session's Zenoh id (hex)."""
        return str(self._session.zid())

    def peers(self) -> list[str]:
        """Zenoh ids of the peers this session is connected to right now."""
        self._check_open("peers")
        return [str(z) for z in self._session.info.peers_zid()]

    @property
    def callback_errors(self) -> int:
        """How many exceptions escaped user callbacks and handlers so far."""
        return self._errors

    def _check_open(self, what: str) -> None:
        if self._closed:
            raise LinkError(f"{what}: the link transport is closed")

    def _register(self, what: str, entity: Any) -> Subscription:
        sub = Subscription(self._forget, what, entity)
        with self._lock:
            if self._closed:
                closed = True
            else:
                closed = False
                self._entities[id(sub)] = sub
        if closed:
            sub.close()
            raise LinkError(f"{what}: the link transport is closed")
        return sub

    def _forget(self, sub: Subscription) -> None:
        with self._lock:
            self._entities.pop(id(sub), None)

    def _failed(self, what: str) -> None:
        with self._lock:
            self._errors += 1
        exc = sys.exc_info()[1]
        self.rejected.note(f"link {what}: a callback raised (ignored)",
                           f"{type(exc).__name__}: {exc} ({self._errors} so far)")

    def _seal(self, key: str, payload: bytes, stream: int) -> bytes:
        """``payload`` sealed for ``key`` on ``stream`` (see :meth:`Sealer.seal`), or as is
        without a sealer. Raises LinkError if it is larger than the link's limit."""
        if len(payload) > self.max_bytes:
            raise LinkError(f"{key!r}: payload of {len(payload)} bytes is larger than the "
                            f"link's limit of {self.max_bytes} bytes")
        return payload if self.sealer is None else self.sealer.seal(key, payload, stream)

    def _open(self, what: str, key: str, data: bytes, roles: frozenset[str] | None,
              receiver: int) -> tuple[str, bytes] | None:
        """(role, payload) of an accepted payload, or None (counted and logged by cause)."""
        limit = self.max_bytes + (SEAL_BYTES if self.sealer is not None else 0)
        if len(data) > limit:
            self.rejected.note(f"link {what}: oversized payload dropped",
                               f"{len(data)} bytes on {key}, limit {self.max_bytes}")
            return None
        if self.sealer is None:
            return "", data
        try:
            role, payload = self.sealer.open(key, data, receiver)
        except SealRefused as exc:
            self.rejected.note(f"link {what}: {exc.refusal.value} payload dropped",
                               f"{key}: {exc}")
            return None
        if roles is not None and role not in roles:
            self.rejected.note(f"link {what}: payload from a {role} refused",
                               f"{key}: only {', '.join(sorted(roles))} may send here")
            return None
        return role, payload

    @property
    def refusals(self) -> dict[str, int]:
        """How many received payloads the seals refused so far, by kind (:class:`Refusal`
        value: unauthenticated, replayed, behind the replay window, too old, from the future,
        from a sender's earlier run); all zero without a sealer."""
        counts = self.sealer.refused if self.sealer is not None else dict.fromkeys(Refusal, 0)
        return {r.value: n for r, n in counts.items()}

    def _publisher(self, key: str, band: int, express: bool, block: bool) -> Any:
        cache_key = (key, band, express, block)
        evicted = None
        with self._lock:
            pub = self._publishers.get(cache_key)
            if pub is not None:
                self._publishers.move_to_end(cache_key)
                return pub
            check_key("publish", key, concrete=True)
            pub = self._session.declare_publisher(
                key,
                priority=PRIORITY_BANDS[band][1],
                express=express,
                congestion_control=(
                    zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
                ),
                reliability=zenoh.Reliability.RELIABLE,
            )
            self._publishers[cache_key] = pub
            if len(self._publishers) > PUBLISHER_CACHE_SIZE:
                _, evicted = self._publishers.popitem(last=False)
        if evicted is not None:
            evicted.undeclare()
        return pub
