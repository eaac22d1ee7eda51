"""support_rtu - a libmodbus RTU slave behind a fault relay, over two socat pty pairs.

::

    chcos ── pty pair A (socat) ── FaultRelay ── pty pair B (socat) ── rtu_slave (libmodbus)

The relay passes requests through unchanged and damages the slave's answers on demand (bad CRC,
junk, truncation, silence). The slave prints what it saw after every request it answered
(:class:`RtuSlave.last_registers`). Everything lives in a temporary directory; the slave is
compiled from ``vcan_tests/peers/rtu_slave.c`` with gcc against libmodbus once per session.
"""

from __future__ import annotations

import contextlib
import os
import select
import shutil
import subprocess
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path
from typing import IO

from vcan_tests.conftest import require

SOURCE = Path(__file__).resolve().parent / "peers" / "rtu_slave.c"
GAP = 0.004      # seconds of quiet that end one answer (t3.5 at 19200 baud is 1.8 ms)


def need(what: str, ok: bool) -> None:
    """Skip the test when ``what`` is missing, or fail it under CI=true (where the set-up must
    have installed it)."""
    require(ok, f"{what} (apt-get install socat libmodbus-dev gcc)")


def build_slave(out_dir: Path) -> Path:
    """Compile the libmodbus RTU slave into ``out_dir``; skip/fail (see :func:`need`) when gcc,
    pkg-config or libmodbus-dev is missing."""
    need("gcc", shutil.which("gcc") is not None)
    need("pkg-config", shutil.which("pkg-config") is not None)
    flags = subprocess.run(["pkg-config", "--cflags", "--libs", "libmodbus"],
                           capture_output=True, text=True)
    need("libmodbus-dev (pkg-config libmodbus)", flags.returncode == 0)
    exe = out_dir / "rtu_slave"
    subprocess.run(["gcc", "-Wall", "-Wextra", "-Werror", "-O2", "-o", str(exe), str(SOURCE),
                    *flags.stdout.split()], check=True, capture_output=True, text=True)
    return exe


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


def _open_raw(path: Path) -> int:
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    return fd


class FaultRelay:
    """Copies bytes between the master's pty and the slave's pty; damages answers on demand.

    :meth:`damage` queues faults applied to the next answers, one each: ``"crc"`` (the last CRC
    byte flipped), ``"junk"`` (the answer replaced by bytes that are no frame), ``"truncate"``
    (the last three bytes dropped), ``"silence"`` (the answer dropped). ``answers`` counts the
    answers that passed, ``damaged`` the ones damaged, by fault."""

    def __init__(self, master_side: Path, slave_side: Path) -> None:
        self._m = _open_raw(master_side)
        self._s = _open_raw(slave_side)
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


class RtuSlave:
    """The libmodbus slave process on ``port`` as ``unit``; reads its report lines."""

    def __init__(self, exe: Path, port: Path, unit: int, response_timeout: str = "") -> None:
        """``response_timeout``: the slave's libmodbus response timeout in ms, or ``"default"``
        for libmodbus' own (500 ms); empty: 50 ms (see rtu_slave.c)."""
        extra = [response_timeout] if response_timeout else []
        self.proc = subprocess.Popen([str(exe), str(port), str(unit), *extra],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self._cond = threading.Condition()
        self.lines: list[str] = []
        out: IO[str] | None = self.proc.stdout
        assert out is not None
        first = out.readline().strip()
        assert first == "READY", f"rtu_slave did not start: {first!r} {self.proc.stderr!r}"
        self._thread = threading.Thread(target=self._read, args=(out,), daemon=True)
        self._thread.start()

    def _read(self, out: IO[str]) -> None:
        for line in out:
            with self._cond:
                self.lines.append(line.strip())
                self._cond.notify_all()

    def wait(self, pred: Callable[[RtuSlave], bool], timeout: float = 5.0) -> bool:
        """Block until ``pred(self)`` holds (checked on every report line); False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: pred(self), timeout)

    @property
    def answered(self) -> int:
        """How many requests the slave answered."""
        with self._cond:
            return len(self.lines)

    def last_registers(self) -> tuple[list[int], str]:
        """The holding registers and coils (as 0/1 digits) after the last answered request."""
        with self._cond:
            line = self.lines[-1] if self.lines else ""
        if not line:
            return [], ""
        words = line.split()
        hr = [int(w) for w in words[3:19]]
        return hr, words[20]

    def close(self) -> None:
        self.proc.terminate()
        self.proc.wait(5)


class LineHub:
    """A multi-drop line (RS-485) joining ``sides`` ptys: what one side sends, every other side
    receives at once (a slave hears the master and every other slave's answers, as on a real
    line). Side 0 is the master's. Each side is a pty the hub makes and keeps open on both ends,
    so a slave process may die and a new one open the same port (:meth:`port`). ``log`` holds
    every chunk read, as ``(time.monotonic(), side, bytes)``."""

    def __init__(self, sides: int) -> None:
        pairs = [os.openpty() for _ in range(sides)]
        for _, tty_fd in pairs:
            tty.setraw(tty_fd)
        self._fds = [master for master, _ in pairs]
        self._ttys = [tty_fd for _, tty_fd in pairs]
        self._lock = threading.Lock()
        self.log: list[tuple[float, int, bytes]] = []
        self._stop_r, self._stop_w = os.pipe()
        self._thread = threading.Thread(target=self._run, name="line-hub", daemon=True)
        self._thread.start()

    def port(self, side: int) -> str:
        """The device path a program opens to sit on ``side`` of the line."""
        return os.ttyname(self._ttys[side])

    def _run(self) -> None:
        while True:
            ready, _, _ = select.select([*self._fds, self._stop_r], [], [])
            if self._stop_r in ready:
                return
            for side, fd in enumerate(self._fds):
                if fd not in ready:
                    continue
                data = os.read(fd, 4096)
                with self._lock:
                    self.log.append((time.monotonic(), side, data))
                for other, out in enumerate(self._fds):
                    if other != side:
                        with contextlib.suppress(OSError):   # a full queue: lost, as on a line
                            os.write(out, data)

    def chunks(self) -> list[tuple[float, int, bytes]]:
        """A copy of :attr:`log`."""
        with self._lock:
            return list(self.log)

    def close(self) -> None:
        os.write(self._stop_w, b"x")
        self._thread.join(5)
        for fd in (*self._fds, *self._ttys, self._stop_r, self._stop_w):
            os.close(fd)
