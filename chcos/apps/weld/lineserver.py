"""lineserver - a TCP server that writes text lines to every client: the far end of a serial line.

A serial instrument that streams lines (the welding cell's linear light sensor) is simulated as
this server; the serial driver opens it with pyserial's ``socket://HOST:PORT`` URL. Clients
are accepted, and closed peers dropped, when a line is sent, on the sender's thread, so the
server has no thread of its own.
"""

from __future__ import annotations

import contextlib
import select
import socket
import threading

from chcos.errors import BusError


class LineServer:
    """A TCP server on ``host:port`` writing text lines to every connected client (the far end of
    pyserial's ``socket://`` URL). Connections are accepted, and closed peers dropped, when a
    line is sent, on the sender's thread. Raises :class:`BusError` (naming ``what``) if the port
    cannot be bound."""

    def __init__(self, port: int, host: str = "127.0.0.1",
                 what: str = "weld simulator serial") -> None:
        self.host = host
        self.port = port
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            listener.bind((host, port))
            listener.listen(4)
            listener.setblocking(False)
        except OSError as exc:
            listener.close()
            raise BusError(f"{what}: cannot listen on {host}:{port}: {exc}") from exc
        self._listener = listener
        self._clients: list[socket.socket] = []
        self._lock = threading.Lock()
        self.lines_sent = 0
        self.connects = 0

    @property
    def url(self) -> str:
        """The pyserial URL a driver opens."""
        return f"socket://{self.host}:{self.port}"

    @property
    def clients(self) -> int:
        """Connected clients (as of the last line sent)."""
        with self._lock:
            return len(self._clients)

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self._listener.accept()
            except OSError:  # BlockingIOError: nobody waiting
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(1.0)
            self._clients.append(conn)
            self.connects += 1

    def send_line(self, text: str) -> None:
        """Write ``text`` + newline to every client; never raises (a broken client is dropped)."""
        data = (text + "\n").encode("ascii")
        with self._lock:
            self._accept()
            for conn in list(self._clients):
                try:  # discard anything the client wrote; readable with b"" is a closed peer
                    while select.select([conn], [], [], 0)[0]:
                        if not conn.recv(4096):
                            raise ConnectionResetError("peer closed")
                except (OSError, ValueError):
                    self._drop(conn)
                    continue
                try:
                    conn.sendall(data)
                except OSError:
                    self._drop(conn)
            self.lines_sent += 1

    def _drop(self, conn: socket.socket) -> None:
        self._clients.remove(conn)
        with contextlib.suppress(OSError):
            conn.close()

    def close(self) -> None:
        """Close the listener and every client. Idempotent."""
        with self._lock:
            for conn in self._clients:
                with contextlib.suppress(OSError):
                    conn.close()
            self._clients.clear()
            with contextlib.suppress(OSError):
                self._listener.close()
