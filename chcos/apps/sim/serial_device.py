"""serial_device - a simulated serial instrument on a pty pair or a TCP socket on 127.0.0.1.

:class:`PtySerialSim` opens a pty pair (``os.openpty``); the driver opens :attr:`PtySerialSim.path`
(the slave). :class:`TcpSerialSim` listens on 127.0.0.1 for pyserial's ``socket://`` URL
(:attr:`TcpSerialSim.url`) and can drop the connection to test reconnects. Both write lines or
frames (:meth:`SerialSim.send_line`, :meth:`SerialSim.send_frame`), inject garbage
(:meth:`SerialSim.send_bytes`), and collect what the driver writes so a test can wait for a
command (:meth:`SerialSim.wait_received`).
"""

from __future__ import annotations

import contextlib
import os
import select
import socket
import struct
import threading
import tty
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from typing import Self

from chcos.errors import BusError
from drivers.codecs.serial import checksum


class SerialSim(ABC):
    """The common part: a reader thread collecting input, and the ways to write."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._rx = bytearray()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=type(self).__name__, daemon=True)

    @abstractmethod
    def _run(self) -> None:
        """Reader thread body: feed :meth:`_received` until :attr:`_stop` is set."""

    @abstractmethod
    def send_bytes(self, data: bytes) -> None:
        """Write raw bytes to the driver side (garbage injection too); BusError if not possible."""

    def _received(self, data: bytes) -> None:
        with self._cond:
            self._rx += data
            self._cond.notify_all()

    def send_line(self, text: str, eol: str = "\n") -> None:
        """Write ``text`` + ``eol`` (ASCII)."""
        self.send_bytes((text + eol).encode("ascii"))

    def send_frame(self, sync: bytes, fmt: str, values: Sequence[float | int],
                   check: str = "none") -> None:
        """Write sync + ``struct.pack(fmt, *values)`` + checksum byte (none/sum8/xor8)."""
        payload = struct.pack(fmt, *values)
        self.send_bytes(sync + payload + checksum(check, payload))

    def received(self) -> bytes:
        """Everything the driver wrote so far."""
        with self._cond:
            return bytes(self._rx)

    def wait_received(self, pred: Callable[[bytes], bool], timeout: float) -> bool:
        """Wait until everything received so far satisfies ``pred``; False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: pred(bytes(self._rx)), timeout)

    def close(self) -> None:
        """Stop the reader and close the endpoints. Idempotent."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self._close()

    @abstractmethod
    def _close(self) -> None:
        """Release the OS resources."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class PtySerialSim(SerialSim):
    """A device at the master side of a pty; the driver opens :attr:`path`."""

    def __init__(self) -> None:
        super().__init__()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.path = os.ttyname(self._slave)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], 0.05)
            if ready:
                try:
                    data = os.read(self._master, 4096)
                except OSError:
                    return
                self._received(data)

    def send_bytes(self, data: bytes) -> None:
        """Write to the pty master."""
        try:
            os.write(self._master, data)
        except OSError as exc:
            raise BusError(f"simulated serial device {self.path}: write failed: {exc}") from exc

    def _close(self) -> None:
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)


class TcpSerialSim(SerialSim):
    """A device behind a TCP server on 127.0.0.1 (``port`` 0 picks a free one); one client at a
    time. :meth:`drop` closes the current client connection (the driver must reconnect)."""

    def __init__(self, port: int = 0) -> None:
        super().__init__()
        self._server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._server.bind(("127.0.0.1", port))
        except OSError as exc:
            self._server.close()
            raise BusError(f"simulated serial device: cannot listen on 127.0.0.1:{port}: "
                           f"{exc}") from exc
        self._server.listen(1)
        self.port = int(self._server.getsockname()[1])
        self.url = f"socket://127.0.0.1:{self.port}"
        self._client: socket.socket | None = None
        self.connections = 0
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._cond:
                client = self._client
            rlist = [client] if client is not None else [self._server]
            try:
                ready, _, _ = select.select(rlist, [], [], 0.05)
            except (OSError, ValueError):
                self._drop_client(client)
                continue
            if not ready:
                continue
            if client is None:
                conn, _ = self._server.accept()
                with self._cond:
                    self._client = conn
                    self.connections += 1
                    self._cond.notify_all()
                continue
            try:
                data = client.recv(4096)
            except OSError:
                data = b""
            if data:
                self._received(data)
            else:
                self._drop_client(client)

    def _drop_client(self, client: socket.socket | None) -> None:
        with self._cond:
            if client is not None and self._client is client:
                self._client = None
                with contextlib.suppress(OSError):
                    client.close()
            self._cond.notify_all()

    def wait_connected(self, count: int, timeout: float) -> bool:
        """Wait until ``count`` connections have been accepted in total and one is open."""
        with self._cond:
            return self._cond.wait_for(
                lambda: self.connections >= count and self._client is not None, timeout)

    def drop(self) -> None:
        """Close the current client connection (simulates the port going away)."""
        with self._cond:
            client = self._client
        if client is not None:
            with contextlib.suppress(OSError):
                client.shutdown(socket.SHUT_RDWR)
            self._drop_client(client)

    def send_bytes(self, data: bytes) -> None:
        """Send to the connected client; BusError if none is connected."""
        with self._cond:
            client = self._client
        if client is None:
            raise BusError(f"simulated serial device {self.url}: no client connected")
        try:
            client.sendall(data)
        except OSError as exc:
            raise BusError(f"simulated serial device {self.url}: send failed: {exc}") from exc

    def _close(self) -> None:
        self.drop()
        with contextlib.suppress(OSError):
            self._server.close()
