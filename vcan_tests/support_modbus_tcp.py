"""support_modbus_tcp - a Modbus TCP server of the tests' own, written from the MBAP layout (not
from chcos' codec), that answers each holding register the way the test sets: well, with the
wrong function code, a short byte count, another transaction or unit id, late, or not at all.
It records every request it received and every connection it accepted, so a test asserts what
the server saw."""

from __future__ import annotations

import contextlib
import socket
import struct
import threading
from dataclasses import dataclass, field
from enum import Enum


class Fault(Enum):
    """How the server answers a read of a register."""

    GOOD = "good"
    FUNCTION = "function"      # function code 4 in the answer to a function 3 request
    SHORT = "short"            # byte count 2 whatever the count asked
    TID = "tid"                # transaction id + 1000
    UNIT = "unit"              # unit id + 1
    LATE = "late"              # the good answer, ``late`` seconds later
    SILENT = "silent"          # nothing


@dataclass(frozen=True)
class Seen:
    """One request the server received."""

    tid: int
    unit: int
    function: int
    address: int
    count: int


@dataclass
class ScriptedTcpServer:
    """Holding registers 0..99 hold 100 + address; :attr:`faults` maps an address to how a read
    starting there is answered; ``late`` is the delay of :attr:`Fault.LATE` answers."""

    late: float = 0.3
    faults: dict[int, Fault] = field(default_factory=dict)
    seen: list[Seen] = field(default_factory=list)
    connections: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __post_init__(self) -> None:
        self._sock = socket.create_server(("127.0.0.1", 0))
        self.port = self._sock.getsockname()[1]
        self._thread = threading.Thread(target=self._accept, daemon=True)
        self._thread.start()

    def set(self, address: int, fault: Fault) -> None:
        """Answer reads of ``address`` with ``fault`` from now on."""
        with self.lock:
            self.faults[address] = fault

    def requests(self, address: int) -> list[Seen]:
        """The requests received for ``address``."""
        with self.lock:
            return [s for s in self.seen if s.address == address]

    def close(self) -> None:
        self._sock.close()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self._sock.accept()
            except OSError:
                return
            with self.lock:
                self.connections += 1
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        send_lock = threading.Lock()
        with conn:
            buf = b""
            while True:
                try:
                    data = conn.recv(4096)
                except OSError:
                    return
                if not data:
                    return
                buf += data
                while len(buf) >= 7:
                    length = struct.unpack(">H", buf[4:6])[0]
                    if len(buf) < 6 + length:
                        break
                    frame, buf = buf[:6 + length], buf[6 + length:]
                    self._answer(conn, send_lock, frame)

    def _answer(self, conn: socket.socket, send_lock: threading.Lock, frame: bytes) -> None:
        tid, _, _, unit = struct.unpack(">HHHB", frame[:7])
        fc, address, count = struct.unpack(">BHH", frame[7:12])
        with self.lock:
            self.seen.append(Seen(tid, unit, fc, address, count))
            fault = self.faults.get(address, Fault.GOOD)
        if fc not in (3, 6, 16):
            pdu = bytes([fc | 0x80, 1])
        elif fc in (6, 16):
            pdu = frame[7:12]
        else:
            regs = b"".join(struct.pack(">H", 100 + address + i) for i in range(count))
            pdu = bytes([fc, len(regs)]) + regs
            if fault is Fault.FUNCTION:
                pdu = bytes([4]) + pdu[1:]
            elif fault is Fault.SHORT:
                pdu = bytes([fc, 2]) + regs[:2]
        if fault is Fault.TID:
            tid = (tid + 1000) & 0xFFFF
        if fault is Fault.UNIT:
            unit = (unit + 1) & 0xFF
        out = struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu
        if fault is Fault.SILENT:
            return
        if fault is Fault.LATE:
            timer = threading.Timer(self.late, self._send, args=(conn, send_lock, out))
            timer.daemon = True
            timer.start()
            return
        self._send(conn, send_lock, out)

    @staticmethod
    def _send(conn: socket.socket, send_lock: threading.Lock, data: bytes) -> None:
        with send_lock, contextlib.suppress(OSError):
            conn.sendall(data)
