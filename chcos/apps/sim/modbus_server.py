"""modbus_server - the simulated Modbus slave on a network or a serial line, and ``chcos sim
modbus``.

The slave itself - the store and the strict request handler - is
:mod:`chcos.apps.sim.modbus_slave`; this module moves its bytes:

* :class:`ModbusSimServer` - on ``127.0.0.1:port`` (loopback unless told otherwise) on a
  thread of its own: Modbus TCP (MBAP frames), or RTU frames over the TCP stream (what a client
  reaches as the serial port ``socket://host:port``); at most :data:`MAX_CONNECTIONS`
  connections at once (one more is closed at once). It can be stopped (every client sees its
  connection close) and restarted on the same port with the data kept.
* :class:`SerialSlaveServer` - Modbus RTU on a serial device or pty (one end of a socat pty
  pair: the master opens the other).

RTU frames are delimited as a slave does: by the length the function code fixes, else by the
silence after the last byte (:data:`FRAME_GAP`). ``chcos sim modbus`` runs one from the command
line.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import selectors
import socket
import sys
import threading
import time
import tty
from collections.abc import Sequence
from typing import Literal

from chcos.apps.sim.modbus_slave import (
    Framing,
    ModbusSlave,
    RegisterStore,
    TcpRole,
    merge,
    request_size,
)
from chcos.errors import BusError

__all__ = ["FRAME_GAP", "MAX_CONNECTIONS", "ModbusSimServer", "RegisterStore",
           "SerialSlaveServer", "main", "merge"]

#: the most client connections a simulated server keeps at once
MAX_CONNECTIONS = 32
#: seconds of silence that end an RTU frame whose length its function code does not fix
FRAME_GAP = 0.004
_MBAP_BYTES = 7


class _Deframer:
    """The request frames of one byte stream, as a slave takes them (see the module doc)."""

    def __init__(self, framing: Framing) -> None:
        self.framing = framing
        self.buf = bytearray()
        self.last = 0.0
        #: set when the stream holds bytes that are no Modbus TCP frame
        self.broken = False

    def feed(self, data: bytes, now: float) -> list[bytes]:
        """The whole frames the stream holds after ``data``."""
        self.buf += data
        self.last = now
        return self._whole()

    def due(self, now: float) -> bytes | None:
        """An RTU frame ended by silence (its bytes), if the gap has passed."""
        if self.framing == "rtu" and self.buf and now - self.last >= FRAME_GAP:
            frame = bytes(self.buf)
            self.buf.clear()
            return frame
        return None

    def _whole(self) -> list[bytes]:
        out: list[bytes] = []
        buf = self.buf
        while buf:
            if self.framing == "tcp":
                if len(buf) < _MBAP_BYTES:
                    break
                length = int.from_bytes(buf[4:6], "big")
                if not 2 <= length <= 254:
                    self.broken = True
                    break
                end = 6 + length
            else:
                size = request_size(bytes(buf[:7]))
                if size is None:
                    break
                end = size
            if len(buf) < end:
                break
            out.append(bytes(buf[:end]))
            del buf[:end]
        return out


class ModbusSimServer:
    """Serves a :class:`RegisterStore` on ``host:port`` (``framer`` ``"tcp"`` or ``"rtu"``: RTU
    frames over a TCP socket). ``role``: ``device`` or ``gateway`` (default: gateway when the
    store has several units). :attr:`slave` is the request handler (``slave``, or one made
    here).

    :meth:`start` raises :class:`chcos.errors.BusError` when the port cannot be bound.
    """

    def __init__(self, store: RegisterStore, port: int, *, host: str = "127.0.0.1",
                 framer: Literal["tcp", "rtu"] = "tcp", role: TcpRole | None = None,
                 slave: ModbusSlave | None = None) -> None:
        self.store = store
        self.host = host
        self.port = port
        self.framer: Framing = framer
        chosen: TcpRole = role or ("gateway" if len(store.units) > 1 else "device")
        self.slave = slave if slave is not None else ModbusSlave(store, framer, chosen)
        self._thread: threading.Thread | None = None
        self._stop_r, self._stop_w = -1, -1
        self._lock = threading.Lock()

    @property
    def running(self) -> bool:
        """True between a successful :meth:`start` and :meth:`stop`."""
        return self._thread is not None

    def start(self) -> None:
        """Listen and serve on a new thread; returns once the port is bound."""
        with self._lock:
            if self._thread is not None:
                return
            try:
                listener = socket.create_server((self.host, self.port), reuse_port=False)
            except OSError as exc:
                raise BusError(f"modbus sim server: cannot listen on {self.host}:{self.port}: "
                               f"{exc}") from exc
            listener.setblocking(False)
            self._stop_r, self._stop_w = os.pipe()
            self._thread = threading.Thread(target=self._serve, args=(listener, self._stop_r),
                                            name=f"modbus-sim-{self.port}", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        """Close the listener and every client connection; the store is kept. Idempotent."""
        with self._lock:
            thread, self._thread = self._thread, None
            if thread is None:
                return
            os.write(self._stop_w, b"x")
            thread.join(timeout=5.0)
            for fd in (self._stop_r, self._stop_w):
                with contextlib.suppress(OSError):
                    os.close(fd)

    def restart(self) -> None:
        """:meth:`stop` then :meth:`start` on the same port."""
        self.stop()
        self.start()

    def __enter__(self) -> ModbusSimServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _serve(self, listener: socket.socket, stop_fd: int) -> None:
        sel = selectors.DefaultSelector()
        sel.register(listener, selectors.EVENT_READ, None)
        sel.register(stop_fd, selectors.EVENT_READ, "stop")
        conns: dict[socket.socket, _Deframer] = {}
        try:
            while True:
                pending = [d for d in conns.values() if d.framing == "rtu" and d.buf]
                wait = FRAME_GAP if pending else None
                for key, _ in sel.select(wait):
                    if key.data == "stop":
                        return
                    if key.fileobj is listener:
                        self._accept(listener, sel, conns)
                    else:
                        self._receive(key.fileobj, sel, conns)  # type: ignore[arg-type]
                now = time.monotonic()
                for sock, d in list(conns.items()):
                    frame = d.due(now)
                    if frame is not None:
                        self._answer(sock, frame, sel, conns)
        finally:
            for sock in list(conns):
                sock.close()
            sel.close()
            listener.close()

    def _accept(self, listener: socket.socket, sel: selectors.BaseSelector,
                conns: dict[socket.socket, _Deframer]) -> None:
        try:
            sock, _ = listener.accept()
        except OSError:
            return
        if len(conns) >= MAX_CONNECTIONS:
            sock.close()                         # as a device out of connections does
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conns[sock] = _Deframer(self.framer)
        sel.register(sock, selectors.EVENT_READ, "conn")

    def _receive(self, sock: socket.socket, sel: selectors.BaseSelector,
                 conns: dict[socket.socket, _Deframer]) -> None:
        try:
            data = sock.recv(4096)
        except OSError:
            data = b""
        d = conns.get(sock)
        if not data or d is None:
            self._drop(sock, sel, conns)
            return
        for frame in d.feed(data, time.monotonic()):
            self._answer(sock, frame, sel, conns)
        if d.broken:
            self._drop(sock, sel, conns)

    def _answer(self, sock: socket.socket, frame: bytes, sel: selectors.BaseSelector,
                conns: dict[socket.socket, _Deframer]) -> None:
        answer = self.slave.exchange(frame, time.monotonic())
        if answer is None:
            return
        try:
            sock.setblocking(True)
            sock.sendall(answer)
            sock.setblocking(False)
        except OSError:
            self._drop(sock, sel, conns)

    @staticmethod
    def _drop(sock: socket.socket, sel: selectors.BaseSelector,
              conns: dict[socket.socket, _Deframer]) -> None:
        conns.pop(sock, None)
        with contextlib.suppress(KeyError, ValueError):
            sel.unregister(sock)
        sock.close()


class SerialSlaveServer:
    """The slave answering Modbus RTU on the serial device or pty ``path`` (raw mode), on a
    thread of its own, until :meth:`stop`."""

    def __init__(self, store: RegisterStore, path: str) -> None:
        self.store = store
        self.path = path
        self.slave = ModbusSlave(store, "rtu")
        self._fd = -1
        self._stop_r, self._stop_w = os.pipe()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Open the port and serve; raises BusError if it cannot be opened."""
        try:
            self._fd = os.open(self.path, os.O_RDWR | os.O_NOCTTY)
            tty.setraw(self._fd)
        except OSError as exc:
            raise BusError(f"modbus sim: cannot open {self.path}: {exc}") from exc
        self._thread = threading.Thread(target=self._serve, name=f"modbus-sim-{self.path}",
                                        daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop serving and close the port. Idempotent."""
        thread, self._thread = self._thread, None
        if thread is not None:
            os.write(self._stop_w, b"x")
            thread.join(timeout=5.0)
        for fd in (self._fd, self._stop_r, self._stop_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._fd = self._stop_r = self._stop_w = -1

    def _serve(self) -> None:
        d = _Deframer("rtu")
        sel = selectors.DefaultSelector()
        sel.register(self._fd, selectors.EVENT_READ, "port")
        sel.register(self._stop_r, selectors.EVENT_READ, "stop")
        try:
            while True:
                ready = sel.select(FRAME_GAP if d.buf else None)
                if any(key.data == "stop" for key, _ in ready):
                    return
                now = time.monotonic()
                frames = []
                if ready:
                    try:
                        data = os.read(self._fd, 4096)
                    except OSError:
                        return
                    frames = d.feed(data, now)
                frame = d.due(now)
                if frame is not None:
                    frames.append(frame)
                for f in frames:
                    answer = self.slave.exchange(f, now)
                    if answer is not None:
                        os.write(self._fd, answer)
        finally:
            sel.close()


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="chcos sim modbus",
        description="A simulated Modbus slave: functions 1-6, 15, 16 on the mapped entries "
                    "(0..SIZE-1 of each table), exception 01/02/03 as a device answers.")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=5020)
    parser.add_argument("--framer", choices=("tcp", "rtu"), default="tcp",
                        help="tcp, or rtu frames over TCP (client port socket://host:port)")
    parser.add_argument("--serial", metavar="PATH",
                        help="Modbus RTU on this serial device or pty instead of a TCP port")
    parser.add_argument("--units", type=int, nargs="+", default=[1], help="unit ids served")
    parser.add_argument("--role", choices=("device", "gateway"),
                        help="Modbus TCP: one device (any unit id) or a gateway (0x0B for a "
                             "unit not served); default: gateway with several units")
    parser.add_argument("--size", type=int, default=1000, help="entries per table")
    parser.add_argument("--duration", type=float, default=None, help="run this long, s")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """``chcos sim modbus``: serve a fresh store until interrupted or ``--duration`` elapses.
    Returns the exit status (0 ok, 2 when the port cannot be bound or opened)."""
    args = _parser().parse_args(list(argv) if argv is not None else None)
    store = RegisterStore(args.units, args.size)
    server: ModbusSimServer | SerialSlaveServer
    if args.serial:
        server, where = SerialSlaveServer(store, args.serial), f"rtu on {args.serial}"
    else:
        server = ModbusSimServer(store, args.port, host=args.host, framer=args.framer,
                                 role=args.role)
        where = f"{args.framer} server on {args.host}:{args.port}"
    try:
        server.start()
    except BusError as exc:
        print(f"chcos sim modbus: {exc}", file=sys.stderr)
        return 2
    print(f"modbus {where} units {args.units}", flush=True)
    try:
        threading.Event().wait(args.duration)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
    return 0
