"""transport - one satellite's end of the chcos inter-satellite link, over one Zenoh session.

:class:`Transport` offers what the communications manager needs and nothing else:

* ``publish``/``send`` and ``subscribe``: messages to tasks on other satellites, carrying their
  CHC-OS priority (0..99, higher is more urgent) mapped onto Zenoh's seven priorities, sent
  *express* (not batched) from :data:`EXPRESS_FROM` up, and with congestion control chosen by the
  message kind: sensory and status messages may be dropped under congestion (the newest value
  supersedes them anyway), every other kind blocks the sender rather than be lost. Messages
  sent from one transport in the same priority band arrive in the order sent; a message of a
  higher band may overtake lower ones (that is what priorities are for);
* ``request``/``serve``: request/reply over Zenoh queryables (e.g. a late joiner fetching the
  message table, the host's install and map requests);
* ``announce``/``watch``/``alive``: liveliness tokens, so satellites see each other appear and
  die (a killed process's tokens vanish when its TCP links reset, or at the latest when its lease
  expires).

Readiness: connections are made in the background, so "my peer is up" is learnt from its
liveliness token, never from ``Transport()`` returning. Declare a satellite's subscribers and
servers *before* announcing its token: declarations from one session reach a peer in order, so a
peer that has seen the token can publish to those subscribers and request from those servers at
once (a request sent earlier fails fast with "no server answers this key").

Threading: every callback (subscriber, server handler, liveliness watcher) runs on a thread
owned by Zenoh, never on the caller's. A callback must be short and must not block: hand the
data to your own queue (``queue.Queue.put_nowait``, ``loop.call_soon_threadsafe``) and return.
An exception escaping a callback is logged on the ``chcos.comm`` logger and counted in
:attr:`Transport.callback_errors`; it never stops the transport or later deliveries. A server
handler's exception is also sent back to the requester, whose ``request`` raises LinkError.

Authentication (:mod:`chcos.comm.secret`): a transport made with a :class:`Sealer` seals every
payload it sends (publish, request, reply) with its role's key and opens every payload it
receives; ``subscribe`` and ``serve`` take the ``roles`` they accept. A payload that is not
sealed by a member of the system, sealed by a role not accepted there, or larger than
``max_bytes`` never reaches the callback: it is counted by cause in :attr:`Transport.rejected`
and logged at most once per cause per interval (no traceback), so junk cannot flood the log.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import zenoh

from chcos.comm.codec import LinkMessage, MessageKind, decode, encode
from chcos.comm.qos import (
    EXPRESS_FROM,
    PRIORITY_BANDS,
    band_of,
    check_key,
    congestion_for,
    is_express,
    zenoh_priority,
)
from chcos.comm.secret import REPLY_STREAM
from chcos.comm.session import REQUESTER, SERVER_ERROR_ENCODING, Session
from chcos.comm.subscription import Subscription
from chcos.errors import LinkError

log = logging.getLogger("chcos.comm")

__all__ = ["EXPRESS_FROM", "PRIORITY_BANDS", "Subscription", "Transport", "congestion_for",
           "enable_zenoh_logging", "is_express", "zenoh_priority"]

Callback = Callable[[str, bytes], object]
Handler = Callable[[bytes], bytes]
KeyCallback = Callable[[str], object]


class Transport(Session):
    """One Zenoh session configured by a :class:`LinkConfig` (a context manager), with the
    operations of the module doc (the session itself is :class:`chcos.comm.session.Session`).

    Raises LinkError when Zenoh cannot open the session (e.g. the listen port is taken); every
    method raises LinkError on a closed transport, a bad key or priority, or a Zenoh failure.
    """

    def publish(
        self,
        key: str,
        payload: bytes,
        *,
        priority: int,
        kind: MessageKind,
        express: bool | None = None,
    ) -> None:
        """Send ``payload`` to every subscriber of ``key`` (a concrete key, no wildcards).

        ``priority`` 0..99 picks the Zenoh priority; ``express`` defaults to ``priority >=
        EXPRESS_FROM``; ``kind`` picks congestion control (DROP for sensory/status, else BLOCK:
        the call may then wait while the link to a slow peer is full). Raises LinkError on a
        closed transport, a bad key or priority, or a Zenoh failure.
        """
        self._check_open("publish")
        band = band_of(priority)
        if express is None:
            express = priority >= EXPRESS_FROM
        if not isinstance(payload, bytes | bytearray | memoryview):
            raise LinkError(
                f"publish {key!r}: expected bytes payload, got {type(payload).__name__}"
            )
        try:
            block = not MessageKind(kind).droppable
        except ValueError as exc:
            raise LinkError(f"publish {key!r}: expected a MessageKind, got {kind!r}") from exc
        try:
            data = self._seal(key, bytes(payload), band)
            pub = self._publisher(key, band, express, block)
            pub.put(data)
        except zenoh.ZError as exc:
            raise LinkError(f"publish {key!r}: Zenoh refused: {exc}") from exc

    def send(self, key: str, message: LinkMessage) -> None:
        """Encode ``message`` (see :mod:`chcos.comm.codec`) and publish it on ``key`` with its
        own priority and kind. Raises LinkError like :meth:`publish` and :func:`codec.encode`."""
        self.publish(key, encode(message), priority=message.priority, kind=message.kind)

    def subscribe(self, key_expr: str, callback: Callback,
                  roles: frozenset[str] | None = None) -> Subscription:
        """Call ``callback(key, payload)`` on a Zenoh thread for each message on a key matching
        ``key_expr`` (wildcards allowed) that is sealed by one of ``roles`` (None: any member).
        Hand the data off quickly; exceptions are logged and counted. Raises LinkError on a
        closed transport or a bad key expression."""
        self._check_open("subscribe")
        check_key("subscribe", key_expr, concrete=False)
        what = f"subscriber {key_expr}"
        receiver = next(self._receivers)

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                key = str(sample.key_expr)
                opened = self._open(what, key, sample.payload.to_bytes(), roles, receiver)
                if opened is not None:
                    callback(key, opened[1])
            except Exception:
                self._failed(what)

        try:
            entity = self._session.declare_subscriber(key_expr, on_sample)
        except zenoh.ZError as exc:
            raise LinkError(f"subscribe {key_expr!r}: Zenoh refused: {exc}") from exc
        return self._register(what, entity)

    def subscribe_messages(
        self, key_expr: str, callback: Callable[[str, LinkMessage], object]
    ) -> Subscription:
        """Like :meth:`subscribe`, but decode each payload with :func:`codec.decode` first and
        call ``callback(key, message)``. A payload that does not decode is logged and counted in
        :attr:`malformed` and never reaches the callback. Raises LinkError like subscribe."""
        what = f"message subscriber {key_expr}"

        def on_payload(key: str, payload: bytes) -> None:
            try:
                message = decode(payload)
            except LinkError as exc:
                with self._lock:
                    self._malformed += 1
                self.rejected.note(f"link {what}: malformed message dropped", f"{key}: {exc}")
                return
            callback(key, message)

        return self.subscribe(key_expr, on_payload)

    @property
    def malformed(self) -> int:
        """How many received payloads failed to decode in :meth:`subscribe_messages`."""
        return self._malformed

    # -- request/reply -----------------------------------------------------------------------

    def serve(self, key_expr: str, handler: Handler,
              roles: frozenset[str] | None = None) -> Subscription:
        """Answer requests on keys matching ``key_expr`` with ``handler(payload) -> bytes``, run
        on a Zenoh thread; requests not sealed by one of ``roles`` (None: any member) are
        answered with a refusal and never reach the handler. If the handler raises, the error
        is logged, counted and sent back (the requester's :meth:`request` raises LinkError).
        Raises LinkError on a closed transport or a bad key expression."""
        self._check_open("serve")
        check_key("serve", key_expr, concrete=False)
        what = f"server {key_expr}"
        receiver = next(self._receivers)

        def on_query(query: zenoh.Query) -> None:
            try:
                payload = query.payload
                key = str(query.key_expr)
                opened = self._open(what, key, b"" if payload is None else payload.to_bytes(),
                                    roles, receiver)
                if opened is None:
                    query.reply_err(b"refused: not authenticated or not authorised here",
                                    encoding=SERVER_ERROR_ENCODING)
                    return
                try:
                    result = handler(opened[1])
                    if not isinstance(result, bytes | bytearray | memoryview):
                        raise TypeError(f"handler returned {type(result).__name__}, expected bytes")
                    answer = self._seal(key, bytes(result), REPLY_STREAM)
                except Exception as exc:
                    self._failed(what)
                    query.reply_err(
                        f"{what} failed: {type(exc).__name__}: {exc}".encode(),
                        encoding=SERVER_ERROR_ENCODING,
                    )
                else:
                    query.reply(query.key_expr, answer)
            except zenoh.ZError:
                log.warning("link %s: could not reply (requester gone?)", what, exc_info=True)
            finally:
                query.drop()  # type: ignore[no-untyped-call]  # stub lacks "-> None"

        try:
            entity = self._session.declare_queryable(key_expr, on_query)
        except zenoh.ZError as exc:
            raise LinkError(f"serve {key_expr!r}: Zenoh refused: {exc}") from exc
        return self._register(what, entity)

    def request(
        self,
        key: str,
        payload: bytes = b"",
        *,
        timeout: float,
        priority: int = 50,
        roles: frozenset[str] | None = None,
    ) -> bytes:
        """Send ``payload`` to the server of ``key`` (concrete) and return its answer, which
        must be sealed by one of ``roles`` (None: any member) when the transport seals.

        Every server of ``key`` is asked and each answer is seen as it arrives: an answer whose
        seal is refused (a session holding only the link's password answering first, a
        replayed answer) is dropped and counted in :attr:`refusals` / :attr:`rejected` by kind,
        and the request goes on waiting for a good one until ``timeout``. Blocks the caller at
        most about ``timeout`` seconds. Raises LinkError when nobody serves ``key``, when no
        accepted answer came in time (naming the refused ones), or when the server's handler
        failed (its message is included)."""
        self._check_open("request")
        check_key("request", key, concrete=True)
        if not timeout > 0:
            raise LinkError(f"request {key!r}: expected a timeout > 0 seconds, got {timeout!r}")
        start = time.monotonic()
        refused = 0
        server_error = ""
        zenoh_error = ""
        try:
            replies = self._session.get(
                key,
                payload=self._seal(key, bytes(payload), band_of(priority)),
                timeout=timeout,
                # every server, every answer as it comes: Zenoh's consolidation would keep
                # the first answer for the key and drop the others, a forged one included
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
                priority=zenoh_priority(priority),
                express=is_express(priority),
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            for reply in replies:
                ok = reply.ok
                if ok is not None:
                    opened = self._open(f"request {key}", key, ok.payload.to_bytes(), roles,
                                        REQUESTER)
                    if opened is None:  # counted by kind; a good answer may still come
                        refused += 1
                        continue
                    return opened[1]
                err = reply.err
                if err is None:  # pragma: no cover - a reply is either ok or err
                    continue
                # an error answer is not sealed: kept, and raised only if no good answer comes
                text = err.payload.to_bytes().decode("utf-8", "replace")
                if str(err.encoding) == SERVER_ERROR_ENCODING:
                    server_error = server_error or text
                else:
                    zenoh_error = zenoh_error or text
        except zenoh.ZError as exc:
            raise LinkError(f"request {key!r}: Zenoh refused: {exc}") from exc
        if server_error:
            raise LinkError(f"request {key!r}: the server failed: {server_error}")
        if refused:
            raise LinkError(f"request {key!r}: no authenticated answer within {timeout} s "
                            f"({refused} unauthenticated or stale answer(s) refused)")
        elapsed = time.monotonic() - start
        if elapsed >= timeout * 0.9:
            raise LinkError(f"request {key!r}: no answer within {timeout} s ({zenoh_error})")
        if zenoh_error:
            raise LinkError(f"request {key!r}: Zenoh reported: {zenoh_error}")
        raise LinkError(f"request {key!r}: no server answers this key (after {elapsed:.3f} s)")

    # -- liveliness --------------------------------------------------------------------------

    def announce(self, token_key: str) -> Subscription:
        """Declare a liveliness token on ``token_key`` (concrete): it lives as long as this
        transport (or until the returned handle is closed). Raises LinkError on a closed
        transport or a bad key."""
        self._check_open("announce")
        check_key("announce", token_key, concrete=True)
        try:
            token = self._session.liveliness().declare_token(token_key)
        except zenoh.ZError as exc:
            raise LinkError(f"announce {token_key!r}: Zenoh refused: {exc}") from exc
        return self._register(f"token {token_key}", token)

    def watch(self, key_expr: str, on_join: KeyCallback, on_leave: KeyCallback) -> Subscription:
        """Call ``on_join(key)`` for every token matching ``key_expr`` that exists now or
        appears later, and ``on_leave(key)`` when one vanishes (its owner closed, died, or lost
        its links). Callbacks run on a Zenoh thread; exceptions are logged and counted. Raises
        LinkError on a closed transport or a bad key expression."""
        self._check_open("watch")
        check_key("watch", key_expr, concrete=False)
        what = f"watcher {key_expr}"

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                key = str(sample.key_expr)
                if sample.kind == zenoh.SampleKind.PUT:
                    on_join(key)
                else:
                    on_leave(key)
            except Exception:
                self._failed(what)

        try:
            entity = self._session.liveliness().declare_subscriber(
                key_expr, on_sample, history=True
            )
        except zenoh.ZError as exc:
            raise LinkError(f"watch {key_expr!r}: Zenoh refused: {exc}") from exc
        return self._register(what, entity)

    def alive(self, key_expr: str, *, timeout: float = 1.0) -> list[str]:
        """The keys of the liveliness tokens matching ``key_expr`` right now (sorted), asking the
        connected peers for at most ``timeout`` seconds. Raises LinkError like :meth:`watch`."""
        self._check_open("alive")
        check_key("alive", key_expr, concrete=False)
        try:
            replies = self._session.liveliness().get(key_expr, timeout=timeout)
            keys = {str(r.ok.key_expr) for r in replies if r.ok is not None}
        except zenoh.ZError as exc:
            raise LinkError(f"alive {key_expr!r}: Zenoh refused: {exc}") from exc
        return sorted(keys)


def enable_zenoh_logging(level: str = "warn") -> None:
    """Turn on Zenoh's own log (connection refusals, authentication failures...) at ``level``
    (a tracing filter: ``"warn"``, ``"warn,zenoh::net::runtime::orchestrator=debug"``...)
    unless ``RUST_LOG`` says otherwise. Zenoh writes it to the process's standard output (file
    descriptor 1, bypassing ``sys.stdout``). Process-wide; call once, early."""
    zenoh.init_log_from_env_or(level)
