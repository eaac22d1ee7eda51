"""peer_rtu - libmodbus peers as independent Modbus peers for the tests and benchmarks: the RTU
slave program (``vcan_tests/peers/rtu_slave.c``) and a one-request client (``mb_client.c``),
compiled with gcc against libmodbus, the process running a slave (:class:`RtuSlave`), and a
multi-drop line joining the master and several slaves over ptys (:class:`LineHub`). The fault
relay and socat pty pairs of the single-slave tests are in ``vcan_tests/support_rtu.py``, which
uses these.
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

PEERS = Path(__file__).resolve().parent.parent / "vcan_tests" / "peers"
SOURCE = PEERS / "rtu_slave.c"
CLIENT_SOURCE = PEERS / "mb_client.c"


def compile_slave(out_dir: Path) -> Path:
    """Compile the libmodbus RTU slave into ``out_dir`` and return its path. Raises
    RuntimeError naming what is missing (gcc, pkg-config, libmodbus-dev) or the compiler's
    message."""
    return compile_peer(SOURCE, out_dir)


def compile_client(out_dir: Path) -> Path:
    """Compile the libmodbus client (``vcan_tests/peers/mb_client.c``: one raw request, TCP or
    RTU, the answer printed) into ``out_dir``, as :func:`compile_slave`."""
    return compile_peer(CLIENT_SOURCE, out_dir)


def compile_peer(source: Path, out_dir: Path) -> Path:
    """Compile the C program ``source`` against libmodbus into ``out_dir``; its path. Raises
    RuntimeError naming what is missing or the compiler's message."""
    for tool in ("gcc", "pkg-config"):
        if shutil.which(tool) is None:
            raise RuntimeError(f"missing: {tool} (apt-get install gcc pkg-config libmodbus-dev)")
    flags = subprocess.run(["pkg-config", "--cflags", "--libs", "libmodbus"],
                           capture_output=True, text=True)
    if flags.returncode != 0:
        raise RuntimeError("missing: libmodbus-dev (pkg-config libmodbus)")
    exe = out_dir / source.stem
    done = subprocess.run(["gcc", "-Wall", "-Wextra", "-Werror", "-O2", "-o", str(exe),
                           str(source), *flags.stdout.split()], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"cannot compile {source.name}: {done.stderr}")
    return exe


def open_raw(path: Path | str) -> int:
    """Open the tty ``path`` read-write in raw mode (no controlling terminal)."""
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    return fd


class RtuSlave:
    """The libmodbus slave process on ``port`` as ``unit``; reads its report lines."""

    def __init__(self, exe: Path, port: Path, unit: int, response_timeout: str = "",
                 reply_delay_ms: int = 0) -> None:
        """``response_timeout``: the slave's libmodbus response timeout in ms, or ``"default"``
        for libmodbus' own (500 ms); empty: 50 ms (see rtu_slave.c). ``reply_delay_ms``: how
        late it answers."""
        extra = [response_timeout or "50"] if response_timeout or reply_delay_ms else []
        if reply_delay_ms:
            extra.append(str(reply_delay_ms))
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
