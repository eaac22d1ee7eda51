"""reading - the sensory side of the task handle: reading input ports (tgetc), waiting for
whichever of several things happens first, and the exception task's tap.

Calls that can wait are awaited; a read from a failed or stale sensor raises SensorFailure,
also while waiting; every wait may have a timeout (ReadTimeout).
"""

from __future__ import annotations

import enum
import logging
import types
from collections.abc import Awaitable, Callable, Generator, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar, overload

from chcos.errors import MessageError, ReadTimeout, SensorFailure
from chcos.kernel.scheduler import BLOCK
from chcos.messages.waits import forget, forget_ports
from chcos.tables.messages import EndpointKind, InPort, Link, LinkStatus, TapPort
from chcos.tables.tasks import TaskState
from chcos.user.ports import Port, TaskHandle

log = logging.getLogger("chcos.user.context")
_WAITING = TaskState.WAITING


def _best(ports: Sequence[InPort]) -> InPort | None:
    """The port read_any takes of ``ports`` now, None if none has a message: the highest link
    priority (as the priorities are now), then the lowest port."""
    best: InPort | None = None
    top = -1  # best's link priority (priorities are 0..99)
    for p in ports:
        if p.fresh:
            prio = p.link.priority
            if prio > top or (prio == top and p.index < best.index):  # type: ignore[union-attr]
                best, top = p, prio
    return best


_Named = TypeVar("_Named", bound=Port)   # how a read_any caller names its ports


def _position(ports: Sequence[InPort], port: InPort) -> int:
    """Where ``port`` is in ``ports`` (by identity: the first place, if it is named twice)."""
    for i, p in enumerate(ports):
        if p is port:
            return i
    raise AssertionError("read_any took a port it was not given")


class EventKind(enum.StrEnum):
    """What a :class:`Event` of :meth:`TaskContext.wait_any` is about (a string enum: a task
    written as ``ev.kind == "command"`` still reads it)."""

    #: a newer command from this task's owner
    COMMAND = "command"
    #: a subordinate completed or was pre-empted
    COMPLETION = "completion"
    #: a tapped sensory message of a lower task
    EXCEPTION = "exception"
    #: a message on an input port
    MESSAGE = "message"
    #: the sensor on an input port failed or went stale while waiting
    FAILURE = "failure"


@dataclass(frozen=True)
class Event:
    """What :meth:`TaskContext.wait_any` returns: what happened first.

    ``kind`` is :attr:`EventKind.COMMAND` (``value`` is the command, ``source`` the owner),
    :attr:`~EventKind.COMPLETION` (``value`` is the :class:`Completion`, ``port`` the output
    port), :attr:`~EventKind.EXCEPTION` (``source`` is the lower task),
    :attr:`~EventKind.MESSAGE` (a message on input ``port`` from ``source``) or
    :attr:`~EventKind.FAILURE` (the sensor on input ``port``; ``value`` is the reason)."""

    kind: EventKind
    source: str
    value: Any = None
    port: int = -1


class Reading(TaskHandle):
    """Input ports, ``wait_any`` and the exception tap (part of
    :class:`chcos.user.context.TaskContext`)."""

    def input_file(self, port: Port = 0) -> str:
        """The path of the file on input ``port`` (relative names resolved against the system's
        base directory); raises MessageError if it is not a file."""
        link = self._in(port).link
        if link.src_kind is not EndpointKind.FILE:
            raise MessageError(f"input {link.src} of task {self._t.name} is not a file")
        return str(self._mm.resolve_path(link.src))

    def _check_source(self, p: InPort) -> None:
        link = p.link
        if link.src_kind is EndpointKind.DEVICE:
            self._mm.devices.check_readable(link.src)

    def _take(self, p: InPort) -> Any:
        """Take the message on ``p`` (an instrument hears of its delivery)."""
        value = p.take()
        if p.sent_at is not None:  # sent while an instrument measured latency
            self._mm.taken(p.link, p.sent_at)
        return value

    def _arm_timeout(self, timeout: float | None, what: str) -> None:
        if timeout is None:
            return
        t, k = self._t, self._k

        def expire() -> None:
            t.timer = None
            k.wake(t, t.base_prio, exc=ReadTimeout(
                f"task {t.name}: no message on {what} within {timeout} s"))

        t.timer = k.call_later(timeout, expire)

    @types.coroutine
    def read(self, port: Port = 0, *,
             timeout: float | None = None) -> Generator[Any, Any, Any]:
        """The newest message on input ``port`` (an index or the source's name), waiting for
        one if there is none (the oldest unread one on a queued link).

        Raises MessageError for a bad port, SensorFailure if the source is a failed or stale
        sensor (also while waiting), ReadTimeout after ``timeout`` seconds without a message.
        """
        try:  # an index is looked up at once; a name, a bad index or a bad type through _in
            p = self._t.in_ports[port] if port.__class__ is int and port >= 0 else self._in(port)
        except IndexError:
            p = self._in(port)
        if not p.fresh:
            if p.device:
                self._check_source(p)
            self._wait_for((p,), timeout)
            yield BLOCK
        value = p.take()
        if p.sent_at is not None:  # sent while an instrument measured latency
            self._mm.taken(p.link, p.sent_at)
        return value

    @overload
    def read_any(self, ports: None = None, *,
                 timeout: float | None = None) -> Awaitable[tuple[int, Any]]: ...

    @overload
    def read_any(self, ports: Sequence[_Named], *,
                 timeout: float | None = None) -> Awaitable[tuple[_Named, Any]]: ...

    @types.coroutine  # type: ignore[misc]
    def read_any(self, ports: Sequence[Port] | None = None, *,
                 timeout: float | None = None) -> Generator[Any, Any, tuple[Port, Any]]:
        """(port, message) from whichever of ``ports`` (default: all inputs) has one; if
        several do, the highest-priority link first, then the lowest port. Waits if none has.
        The port comes back as the caller named it: the element of ``ports`` it was given as
        (a source name stays a name, an index an index); without ``ports``, the port index.
        Raises as :meth:`read`."""
        t = self._t
        chosen = tuple(t.in_ports if ports is None else [self._in(p) for p in ports])
        best = _best(chosen)
        if best is None:
            if not chosen:
                raise MessageError(f"task {t.name} has no input ports to read")
            for p in chosen:
                if p.device:  # its link comes from a sensor
                    self._mm.devices.check_readable(p.link.src)
            self._wait_for(chosen, timeout)
            yield BLOCK
            # woken by the first message; others may have come before this step: the best of
            # what is there now, by the priorities now
            best = _best(chosen)
            assert best is not None
        # what the caller named: the element of ``ports`` that is this port, else its index
        named: Port = best.index if ports is None else ports[_position(chosen, best)]
        return named, self._take(best)

    def _wait_for(self, ports: tuple[InPort, ...], timeout: float | None) -> None:
        """Record that the calling task waits for a message on one of ``ports`` (a delivery
        wakes it through the kernel), for at most ``timeout`` seconds (then ReadTimeout)."""
        t = self._t
        t.wait_ports = ports
        t.unwait = forget_ports
        self._k.block(t, _WAITING)
        if timeout is not None:
            self._arm_timeout(timeout, ", ".join(p.link.name for p in ports))

    def poll(self, port: Port = 0, default: Any = None) -> Any:
        """The newest message on ``port`` if there is one, else ``default`` (never waits).
        Raises SensorFailure if there is none because the source sensor failed or is stale."""
        p = self._in(port)
        if p.fresh:
            return self._take(p)
        self._check_source(p)
        return default

    @types.coroutine
    def wait_any(self, ports: Sequence[Port] = (), *, exceptions: bool = False,
                 completions: Sequence[Port] = (), commands: bool = False,
                 when: Callable[[str, Any], bool] | None = None,
                 timeout: float | None = None) -> Generator[Any, Any, Event]:
        """Wait for whichever happens first and return it as an :class:`Event`: a message on one
        of the input ``ports``, a tapped message (``exceptions``, exception task only), the
        completion or pre-emption of a command sent on one of the output ports in
        ``completions``, a newer command from this task's owner (``commands``). What is already
        there is returned at once, in that order of importance: command, completion, tapped
        message, port message (highest link priority first). The returned message, completion or
        command is consumed.

        ``when(source, message)``, if given, decides which port and tap messages are worth
        waking for; it runs at delivery time in the sender's step, so it must be cheap and must
        not block. Messages it turns down stay unread (a newer one overwrites them).
        A sensor that fails while waited on gives a ``"failure"`` event (an already failed sensor
        is not reported again: wait for its next reading). Raises MessageError for a bad port or
        ``exceptions`` in a task that is not the exception task, ReadTimeout after ``timeout``
        seconds with nothing."""
        t = self._t
        ins = tuple(self._in(p) for p in ports)
        links = tuple(self._task_link(p) for p in completions)
        tap = t.tap if exceptions else None
        if exceptions and not isinstance(tap, TapPort):
            raise MessageError(f"task {t.name} is not an exception task: it has no tap to wait on")
        if not (ins or links or exceptions or commands):
            raise MessageError(f"task {t.name}: wait_any with nothing to wait for")
        deadline = None if timeout is None else self._k.clock.now() + timeout
        while True:
            ev = self._happened(ins, links, tap, commands, when)
            if ev is not None:
                if t.timer is not None:
                    t.timer.cancel()
                    t.timer = None
                return ev
            t.wait_ports = ins
            if tap is not None:
                tap.waiter = t
            t.wait_links = links
            t.wait_commands = commands
            t.wake_filter = when
            t.multi_wait = True
            t.unwait = forget
            self._k.block(t, TaskState.WAITING)
            if deadline is not None:
                self._arm_timeout(max(0.0, deadline - self._k.clock.now()), "wait_any")
            try:
                yield BLOCK
            except SensorFailure as exc:
                self._k.unhook(t)
                index = next((p.index for p in ins if p.link.src == exc.device), -1)
                return Event(EventKind.FAILURE, exc.device, exc.reason, index)
            finally:
                if t.multi_wait:  # woken by a message, the timer (the deadline) stays
                    t.unwait = None
                    forget(t)

    def _happened(self, ins: tuple[InPort, ...], links: tuple[Link, ...], tap: Any,
                  commands: bool, when: Callable[[str, Any], bool] | None) -> Event | None:
        t = self._t
        if commands and t.new_command is not None:
            src = t.owner.src if t.owner is not None else ""
            return Event(EventKind.COMMAND, src, self.take_command())
        for link in links:
            report = self._mm.done_now(link)
            if report is not None:
                return Event(EventKind.COMPLETION, link.dst, report, link.src_port)
        if tap is not None and tap.order:
            for src in tap.order:
                value = tap.newest[src][0]
                if when is None or _accepts(when, src, value):
                    _s, value, _at = tap.take_from(src)
                    return Event(EventKind.EXCEPTION, src, value)
        best: InPort | None = None
        for p in ins:
            if (p.fresh and (best is None or p.link.priority > best.link.priority)
                    and (when is None or _accepts(when, p.link.src, p.head()))):
                best = p
        if best is not None:
            return Event(EventKind.MESSAGE, best.link.src, self._take(best), best.index)
        return None

    def feed(self, port: Port, value: Any) -> None:
        """Deliver ``value`` on input ``port`` as if its source had sent it. Thread-safe: for
        system drivers whose own thread reads a terminal or a file (the delivery happens on
        the kernel thread, between task steps). Raises MessageError for a bad port."""
        link = self._in(port).link
        mm = self._mm

        def deliver() -> None:
            mm.deliver(link, value)

        self._k.interrupt(deliver)

    def pending(self, port: Port = 0) -> bool:
        """True if a message waits on ``port``."""
        return self._in(port).fresh

    def input_status(self, port: Port) -> LinkStatus:
        """The status of the link on input ``port``."""
        return self._in(port).link.status

    @types.coroutine
    def read_exception(self, *, timeout: float | None = None) -> Generator[Any, Any,
                                                                         tuple[str, Any]]:
        """(source task, message): the next sensory message any lower task sent, newest per
        source. Only for a task installed as the exception task; raises MessageError otherwise."""
        tap = self._t.tap
        if not isinstance(tap, TapPort):
            raise MessageError(f"task {self._t.name} is not an exception task")
        if not tap.fresh:
            t = self._t
            tap.waiter = t
            t.unwait = forget
            self._k.block(t, TaskState.WAITING)
            self._arm_timeout(timeout, "the exception tap")
            try:
                yield BLOCK
            finally:
                tap.waiter = None
        src, value, _at = tap.take()
        return src, value

def _accepts(when: Callable[[str, Any], bool], source: str, value: Any) -> bool:
    """``when(source, value)``; a filter that raises accepts (a failure is never masked)."""
    try:
        return bool(when(source, value))
    except Exception:
        log.exception("wait_any filter failed on a message from %s", source)
        return True
