"""support_rtu - a libmodbus RTU slave behind a fault relay, over two socat pty pairs (the slave
process and the multi-drop line hub are :mod:`tools.peer_rtu`).

::

    chcos ── pty pair A (socat) ── FaultRelay ── pty pair B (socat) ── rtu_slave (libmodbus)

The relay passes requests through unchanged and damages the slave's answers on demand (bad CRC,
junk, truncation, silence). The slave prints what it saw after every request it answered
(:class:`RtuSlave.last_registers`). Everything lives in a temporary directory; the slave is
compiled from ``vcan_tests/peers/rtu_slave.c`` with gcc against libmodbus once per session.
"""

from __future__ import annotations

import os
import select
import shutil
import subprocess
import threading
from pathlib import Path

from tools.peer_rtu import LineHub, RtuSlave, compile_client, compile_slave, open_raw
from vcan_tests.conftest import require

__all__ = ["FaultRelay", "LineHub", "PtyPair", "RtuSlave", "build_client", "build_slave",
           "need"]

GAP = 0.004      # seconds of quiet that end one answer (t3.5 at 19200 baud is 1.8 ms)


def need(what: str, ok: bool) -> None:
    """Skip the test when ``what`` is missing, or fail it under CI=true (where the set-up must
    have installed it)."""
    require(ok, f"{what} (apt-get install socat libmodbus-dev gcc)")


def _need_toolchain() -> None:
    need("gcc", shutil.which("gcc") is not None)
    need("pkg-config", shutil.which("pkg-config") is not None)
    flags = subprocess.run(["pkg-config", "--cflags", "--libs", "libmodbus"],
                           capture_output=True, text=True)
    need("libmodbus-dev (pkg-config libmodbus)", flags.returncode == 0)


def build_slave(out_dir: Path) -> Path:
    """Compile the libmodbus RTU slave into ``out_dir``; skip/fail (see :func:`need`) when gcc,
    pkg-config or libmodbus-dev is missing."""
    _need_toolchain()
    return compile_slave(out_dir)


def build_client(out_dir: Path) -> Path:
    """Compile the libmodbus one-request client into ``out_dir`` (as :func:`build_slave`)."""
    _need_toolchain()
    return compile_client(out_dir)


class PtyPair:
    """Two linked ptys made by socat: ``a`` and ``b`` are their paths."""

    def __init__(self, directory: Path, name: str) -> None:
        need("socat", shutil.which("socat") is not None)
        self.a = directory / f"{name}-a"
        self.b = directory / f"{name}-b"
        self.proc = subprocess.Popen(
            ["socat", "-d", "-d", f"pty,raw,echo=0,link={self.a}",
             f"pty,raw,echo=0,link={self.b}"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        assert self.proc.stderr is not None
        started = 0
        for line in self.proc.stderr:        # socat reports each pty it made, then the loop
            if "PTY is" in line:
                started += 1
            if "starting data transfer loop" in line:
                break
        assert started == 2 and self.a.exists() and self.b.exists(), "socat made no ptys"

    def close(self) -> None:
        self.proc.terminate()
        self.proc.wait(5)


class FaultRelay:
    """Copies bytes between the master's pty and the slave's pty; damages answers on demand.

    :meth:`damage` queues faults applied to the next answers, one each: ``"crc"`` (the last CRC
    byte flipped), ``"junk"`` (the answer replaced by bytes that are no frame), ``"truncate"``
    (the last three bytes dropped), ``"silence"`` (the answer dropped). ``answers`` counts the
    answers that passed, ``damaged`` the ones damaged, by fault."""

    def __init__(self, master_side: Path, slave_side: Path) -> None:
        self._m = open_raw(master_side)
        self._s = open_raw(slave_side)
        self._faults: list[str] = []
        self._lock = threading.Lock()
        self.answers = 0
        self.damaged: dict[str, int] = {}
        self.requests: list[bytes] = []
        self._stop_r, self._stop_w = os.pipe()
        self._thread = threading.Thread(target=self._run, name="fault-relay", daemon=True)
        self._thread.start()

    def damage(self, *faults: str) -> None:
        """Damage the next ``len(faults)`` answers, in order."""
        with self._lock:
            self._faults.extend(faults)

    def _apply(self, answer: bytes) -> bytes:
        with self._lock:
            fault = self._faults.pop(0) if self._faults else ""
            if not fault:
                self.answers += 1
                return answer
            self.damaged[fault] = self.damaged.get(fault, 0) + 1
        if fault == "crc":
            return answer[:-1] + bytes([answer[-1] ^ 0x5A])
        if fault == "junk":
            return bytes([0xF7, 0x00, 0xEE, 0x13, 0x37, 0x00, 0x42])[:max(len(answer), 3)]
        if fault == "truncate":
            return answer[:-3]
        return b""                              # silence

    def _run(self) -> None:
        pending = b""
        while True:
            timeout = GAP if pending else None
            ready, _, _ = select.select([self._m, self._s, self._stop_r], [], [], timeout)
            if self._stop_r in ready:
                return
            if not ready and pending:            # the answer is complete: pass it on
                out = self._apply(pending)
                pending = b""
                if out:
                    os.write(self._m, out)
                continue
            if self._m in ready:
                data = os.read(self._m, 4096)
                self.requests.append(data)
                os.write(self._s, data)
            if self._s in ready:
                pending += os.read(self._s, 4096)

    def close(self) -> None:
        os.write(self._stop_w, b"x")
        self._thread.join(5)
        for fd in (self._m, self._s, self._stop_r, self._stop_w):
            os.close(fd)
