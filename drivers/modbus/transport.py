"""transport - the byte pipes of the Modbus drivers' worker thread: Modbus TCP over sockets
(one connection, or several for a poll spread over them), Modbus RTU on a serial port (pyserial:
a device, a pty, ``socket://``), and an in-process slave reached directly. Each sends one
request and returns its :data:`drivers.modbus.transactions.Outcome` as the sans-IO matching of
:mod:`drivers.modbus.transactions` judges the bytes; a transport that fails under a request
raises :class:`TransportLost` (a connection-level cause).

Timing is wall time here: these transports talk to peers that live in wall time (another
process, a serial line). On a serial line every request waits for 3.5 characters of silence
since the line was last busy, and the input is flushed before each request, so no byte of an
earlier answer is read as this one's; a broadcast is followed by the line's turnaround delay.
The kernel-thread hand-off to an in-process slave on virtual time is
:class:`drivers.modbus.engine.KernelEngine`.
"""

from __future__ import annotations

import contextlib
import fcntl
import select
import socket
import struct
import termios
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import serial

from drivers.codecs.modbus import LineTiming
from drivers.codecs.modbus_direct import DirectSlave
from drivers.modbus.transactions import (
    Answer,
    NoAnswer,
    Outcome,
    Refused,
    Request,
    RtuExchange,
    TcpStream,
    match_tcp,
)

#: transaction ids of timed-out requests kept per connection, to know their late answers
LATE_IDS = 16


class TransportLost(Exception):
    """The transport failed under a request (closed, reset, unusable stream): ``str(exc)``
    says how."""


class Transport(Protocol):
    """What the worker thread's engine needs of a transport."""

    def open(self) -> None:
        """Connect or open; raises OSError (or TransportLost) if it cannot."""

    def close(self) -> None:
        """Close; idempotent, never raises."""

    def exchange(self, req: Request, timeout: float) -> Outcome:
        """Send ``req`` and wait up to ``timeout`` s for its outcome; raises TransportLost."""

    def exchange_all(self, reqs: Sequence[Request], timeout: float) -> list[Outcome]:
        """Several requests at once where the transport has several connections, else in
        order; the outcomes in the order of ``reqs``. Raises TransportLost."""

    def broadcast(self, req: Request, turnaround: float) -> None:
        """Send ``req`` to every unit and keep the line quiet for ``turnaround`` s."""

    def hold_quiet(self, until: float) -> None:
        """Keep the line quiet until ``until`` (``time.monotonic``), throwing away what
        arrives meanwhile."""


# ---- Modbus TCP ----------------------------------------------------------------------------
class TcpLane:
    """One TCP connection: its transaction ids and the byte stream of its answers."""

    def __init__(self, host: str, port: int, connect_timeout: float,
                 on_late: Callable[[], None]) -> None:
        self._addr = (host, port)
        self._connect_timeout = connect_timeout
        self._on_late = on_late
        self.sock: socket.socket | None = None
        self.stream = TcpStream()
        self._tid = 0
        self._late: deque[int] = deque(maxlen=LATE_IDS)

    def open(self) -> None:
        """Connect (raises OSError)."""
        self.close()
        sock = socket.create_connection(self._addr, timeout=self._connect_timeout)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setblocking(False)
        self.sock = sock
        self.stream.clear()
        self._late.clear()

    def close(self) -> None:
        """Close the connection (never raises)."""
        sock, self.sock = self.sock, None
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.close()

    def send(self, req: Request) -> int:
        """Send ``req`` with the next transaction id; that id. Raises TransportLost."""
        self._tid = self._tid % 0xFFFF + 1
        data = req.tcp_adu(self._tid)
        sock = self._socket()
        try:
            sock.setblocking(True)
            sock.sendall(data)
        except OSError as exc:
            raise TransportLost(f"sending failed: {exc}") from None
        finally:
            with contextlib.suppress(OSError):
                sock.setblocking(False)
        return self._tid

    def take(self, req: Request, tid: int) -> Outcome | None:
        """Read what the connection holds and judge it for ``req`` (sent with ``tid``); None
        while its answer has not come. Raises TransportLost when the peer closed or the stream
        is no Modbus."""
        try:
            data = self._socket().recv(4096)
        except BlockingIOError:
            return None
        except OSError as exc:
            raise TransportLost(f"connection lost: {exc}") from None
        if not data:
            raise TransportLost("connection closed by the server")
        late = set(self._late)
        for frame in self.stream.feed(data):
            outcome = match_tcp(req, tid, frame, late)
            if outcome is None:
                self._late.remove(frame.tid)
                self._on_late()
                continue
            return outcome
        if self.stream.broken:
            raise TransportLost(self.stream.broken)
        return None

    def timed_out(self, tid: int) -> NoAnswer:
        """``tid``'s request got no answer in time: its late answer will be thrown away."""
        self._late.append(tid)
        return NoAnswer("no response")

    def _socket(self) -> socket.socket:
        if self.sock is None:
            raise TransportLost("not connected")
        return self.sock

    def fileno(self) -> int:
        """The socket's descriptor (for select)."""
        return self._socket().fileno()


class TcpTransport:
    """Modbus TCP to ``host:port``: a main connection, and for a poll of several requests up
    to ``lanes - 1`` more, opened at the first such poll (a connection is used only once it
    answered a probe read: many servers accept a connection and then close it, or never answer
    on it; a server that takes fewer is polled over those it takes, ``on_refused``)."""

    def __init__(self, host: str, port: int, timeout: float, lanes: int,
                 probe: Request | None, on_late: Callable[[], None],
                 on_refused: Callable[[int, int], None]) -> None:
        self._host, self._port, self._timeout = host, port, timeout
        self._on_late = on_late
        self._on_refused = on_refused
        self.main = TcpLane(host, port, timeout, on_late)
        self._lanes_wanted = lanes
        self._probe = probe
        self._extra: list[TcpLane] | None = None

    def open(self) -> None:
        """Connect the main connection (raises OSError)."""
        self.close()
        self.main.open()

    def close(self) -> None:
        """Close every connection."""
        self.main.close()
        for lane in self._extra or ():
            lane.close()
        self._extra = None

    def exchange(self, req: Request, timeout: float) -> Outcome:
        """One request on the main connection."""
        return _exchange_lanes([(self.main, [req])], timeout)[0][0][0]

    def exchange_all(self, reqs: Sequence[Request], timeout: float) -> list[Outcome]:
        """The requests spread over the connections, all outstanding at once (each connection
        runs its share in order); a failed extra connection's share goes to the main one."""
        lanes = [self.main, *self._lanes()]
        n = min(len(lanes), len(reqs))
        shares = [(lanes[i], list(reqs[i::n])) for i in range(n)]
        got = _exchange_lanes(shares, timeout, spare=True)
        out: list[Outcome | None] = [None] * len(reqs)
        redo: list[int] = []
        for i, (outcomes, failed) in enumerate(got):
            for k, outcome in enumerate(outcomes):
                out[i + k * n] = outcome
            if failed and i > 0:
                self._drop(shares[i][0])
                redo += [i + k * n for k in range(len(outcomes), len(shares[i][1]))]
        for j in redo:
            out[j] = self.exchange(reqs[j], timeout)
        return [o if o is not None else NoAnswer() for o in out]

    def broadcast(self, req: Request, turnaround: float) -> None:
        """Not on TCP (``chcos check`` refuses unit 0 there)."""
        raise TransportLost("broadcast on Modbus TCP")

    def hold_quiet(self, until: float) -> None:
        """Nothing to wait for: TCP answers carry their transaction id."""

    def _lanes(self) -> list[TcpLane]:
        if self._extra is None:
            self._extra = []
            for _ in range(self._lanes_wanted - 1):
                lane = TcpLane(self._host, self._port, self._timeout, self._on_late)
                if not self._lane_answers(lane):
                    lane.close()
                    self._on_refused(1 + len(self._extra), self._lanes_wanted)
                    break
                self._extra.append(lane)
        return self._extra

    def _lane_answers(self, lane: TcpLane) -> bool:
        try:
            lane.open()
            if self._probe is None:
                return True
            outcome = _exchange_lanes([(lane, [self._probe])], self._timeout)[0][0][0]
        except (OSError, TransportLost, IndexError):
            return False
        return isinstance(outcome, Answer | Refused)

    def _drop(self, lane: TcpLane) -> None:
        lane.close()
        if self._extra is not None and lane in self._extra:
            self._extra.remove(lane)


@dataclass
class _Share:
    """One connection's share of the requests of :func:`_exchange_lanes`, as it goes."""

    lane: TcpLane
    reqs: list[Request]
    next: int = 0
    tid: int = 0
    deadline: float = 0.0
    outcomes: list[Outcome] = field(default_factory=list)
    failed: bool = False

    def send_next(self, timeout: float) -> str:
        """Send the next request; the reason if that failed."""
        if self.next >= len(self.reqs):
            return ""
        try:
            self.tid = self.lane.send(self.reqs[self.next])
        except TransportLost as exc:
            self.failed = True
            return str(exc)
        self.deadline = time.monotonic() + timeout
        return ""

    def step(self, readable: bool, now: float, timeout: float) -> str:
        """Take what came (or the timeout) for the request outstanding; the reason if the
        connection failed."""
        outcome: Outcome | None = None
        try:
            if readable:
                outcome = self.lane.take(self.reqs[self.next], self.tid)
            if outcome is None and now >= self.deadline:
                outcome = self.lane.timed_out(self.tid)
        except TransportLost as exc:
            self.failed = True
            return str(exc)
        if outcome is None:
            return ""
        self.outcomes.append(outcome)
        self.next += 1
        return self.send_next(timeout)

    @property
    def waiting(self) -> bool:
        """True while a request of the share is outstanding."""
        return not self.failed and self.next < len(self.reqs)


def _exchange_lanes(shares: Sequence[tuple[TcpLane, list[Request]]], timeout: float,
                    spare: bool = False) -> list[tuple[list[Outcome], bool]]:
    """Run each lane's share in order, all lanes at once: per lane the outcomes so far and
    whether it failed. A failure of the first lane (or of any without ``spare``) raises
    TransportLost once the other lanes are done."""
    runs = [_Share(lane, reqs) for lane, reqs in shares]
    lost = ""
    for run in runs:
        lost = run.send_next(timeout) or lost
    while True:
        live = [run for run in runs if run.waiting]
        if not live:
            break
        wait = max(0.0, min(run.deadline for run in live) - time.monotonic())
        fds = {run.lane.fileno(): run for run in live}
        ready, _, _ = select.select(list(fds), [], [], wait)
        now = time.monotonic()
        for fd, run in fds.items():
            lost = run.step(fd in ready, now, timeout) or lost
    if lost and (not spare or runs[0].failed):
        raise TransportLost(lost)
    return [(run.outcomes, run.failed) for run in runs]


# ---- Modbus RTU ----------------------------------------------------------------------------
class RtuTransport:
    """Modbus RTU on a serial port (a device, a pty, or a pyserial URL such as ``socket://``)
    with the line's timing (see the module doc)."""

    def __init__(self, url: str, line: LineTiming, on_late: Callable[[int], None]) -> None:
        self._url = url
        self.line = line
        self._on_late = on_late
        self.port: Any = None
        #: when the line last went quiet (the last byte received, the end of a request sent,
        #: a wait that timed out), on ``time.monotonic``
        self._quiet_from = 0.0

    def open(self) -> None:
        """Open the port (raises OSError or serial.SerialException as OSError)."""
        self.close()
        try:
            self.port = serial.serial_for_url(
                self._url, baudrate=self.line.baudrate, bytesize=self.line.bytesize,
                parity=self.line.parity, stopbits=self.line.stopbits, timeout=0)
        except (serial.SerialException, ValueError) as exc:
            raise OSError(str(exc)) from None
        self._quiet_from = time.monotonic()

    def close(self) -> None:
        """Close the port (never raises)."""
        port, self.port = self.port, None
        if port is not None:
            with contextlib.suppress(Exception):
                port.close()

    def exchange(self, req: Request, timeout: float) -> Outcome:
        """Send ``req`` after the silence, read its answer (see :class:`RtuExchange`)."""
        self._send(req)
        ex = RtuExchange(req)
        deadline = time.monotonic() + timeout
        try:
            while True:
                data = self._read(deadline - time.monotonic())
                if not data:
                    return ex.timed_out()
                outcome = ex.feed(data)
                if outcome is not None:
                    return outcome
        finally:
            if ex.skipped:
                self._on_late(ex.skipped)

    def exchange_all(self, reqs: Sequence[Request], timeout: float) -> list[Outcome]:
        """In order: a serial line carries one request at a time."""
        return [self.exchange(r, timeout) for r in reqs]

    def broadcast(self, req: Request, turnaround: float) -> None:
        """Send ``req`` to every unit, then keep the line quiet for the turnaround delay."""
        self._send(req)
        self.hold_quiet(self._quiet_from + turnaround)

    def hold_quiet(self, until: float) -> None:
        """Wait until ``until``, throwing away what arrives (a late answer)."""
        while True:
            left = until - time.monotonic()
            if left <= 0:
                break
            data = self._read(left)
            if data:
                self._on_late(1)
        self._flush()

    def _send(self, req: Request) -> None:
        wait = self._quiet_from + self.line.silence - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        self._flush()
        frame = req.rtu_frame()
        try:
            self._port().write(frame)
            self._port().flush()
        except (serial.SerialException, OSError) as exc:
            raise TransportLost(f"writing to {self._url} failed: {exc}") from None
        self._quiet_from = time.monotonic() + len(frame) * self.line.char_time

    def _flush(self) -> None:
        """Throw away every byte received so far (nothing read before a request is its
        answer)."""
        try:
            port = self._port()
            waiting = port.in_waiting
            if waiting:
                port.read(waiting)
                self._on_late(1)
            port.reset_input_buffer()
        except (serial.SerialException, OSError) as exc:
            raise TransportLost(f"{self._url} failed: {exc}") from None

    def _read(self, timeout: float) -> bytes:
        """The bytes the port holds once it can be read within ``timeout`` s; b"" if not."""
        port = self._port()
        try:
            fd = port.fileno()
        except (OSError, ValueError, AttributeError, serial.SerialException):
            fd = None
        try:
            if fd is None:
                port.timeout = max(0.0, timeout)
                data = bytes(port.read(1))
                if data:
                    port.timeout = 0
                    data += bytes(port.read(port.in_waiting or 0))
            else:
                if not select.select([fd], [], [], max(0.0, timeout))[0]:
                    self._quiet_from = time.monotonic()
                    return b""
                waiting = struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]
                data = bytes(port.read(max(waiting, 1)))   # readable and empty: peer closed
        except (serial.SerialException, OSError) as exc:
            raise TransportLost(f"{self._url} failed: {exc}") from None
        if fd is not None and not data:
            raise TransportLost(f"{self._url} closed")
        self._quiet_from = time.monotonic()
        return data

    def _port(self) -> Any:
        if self.port is None:
            raise TransportLost(f"{self._url} is not open")
        return self.port


# ---- an in-process slave, from the worker thread -------------------------------------------
class DirectTransport:
    """An in-process slave reached by a call (see :mod:`drivers.codecs.modbus_direct`), on the
    worker thread and wall time (a driver on a real clock: its silence costs the timeout). On a
    virtual clock the kernel thread reaches it instead (:class:`drivers.modbus.engine.
    KernelEngine`)."""

    def __init__(self, slave: DirectSlave, name: str) -> None:
        self._slave = slave
        self._name = name
        self._tid = 0
        self._lock = threading.Lock()
        self._open = False

    def open(self) -> None:
        """Connect: refused while the slave takes no connections."""
        if not self._slave.accepts():
            raise ConnectionRefusedError(f"simulated slave {self._name} refuses connections")
        self._open = True

    def close(self) -> None:
        """Nothing to close."""
        self._open = False

    def exchange(self, req: Request, timeout: float) -> Outcome:
        """Hand ``req``'s bytes over; no answer costs ``timeout`` s."""
        outcome, later = direct_exchange(self._slave, req, self._next_tid(), time.monotonic())
        if outcome is None:
            time.sleep(timeout)
            return later
        return outcome

    def exchange_all(self, reqs: Sequence[Request], timeout: float) -> list[Outcome]:
        """In order (an in-process slave answers at once)."""
        return [self.exchange(r, timeout) for r in reqs]

    def broadcast(self, req: Request, turnaround: float) -> None:
        """Hand the broadcast over; the turnaround passes."""
        direct_exchange(self._slave, req, 0, time.monotonic())
        time.sleep(turnaround)

    def hold_quiet(self, until: float) -> None:
        """Nothing can come late from an in-process slave."""

    def _next_tid(self) -> int:
        with self._lock:
            self._tid = self._tid % 0xFFFF + 1
            return self._tid


def direct_exchange(slave: DirectSlave, req: Request, tid: int,
                    now: float) -> tuple[Outcome | None, Outcome]:
    """``req`` handed to ``slave`` in its framing (transaction id ``tid`` on TCP) at ``now``:
    ``(outcome, None)`` when the bytes that came back decide it, else ``(None, outcome at the
    timeout)`` - silence, or an RTU answer too short to be one. Raises TransportLost when a TCP
    slave stopped taking connections or answered with bytes that are no Modbus TCP."""
    if slave.framing == "tcp":
        if not slave.accepts():
            raise TransportLost("connection closed by the server")
        answer = slave.exchange(req.tcp_adu(tid), now)
        stream = TcpStream()
        for frame in stream.feed(answer or b""):
            outcome = match_tcp(req, tid, frame, set())
            if outcome is not None:
                return outcome, NO_ANSWER
        if stream.broken:
            raise TransportLost(stream.broken)
        return None, NO_ANSWER
    ex = RtuExchange(req)
    answer = slave.exchange(req.rtu_frame(), now)
    outcome = ex.feed(answer) if answer else None
    return (outcome, NO_ANSWER) if outcome is not None else (None, ex.timed_out())


NO_ANSWER = NoAnswer("no response")
