"""Helpers of the bus-fault tests: a pyModbusTCP server process that can be killed, frozen and
restarted, read from its own side, and a wall-clock-bounded run of a virtual-time System."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from pyModbusTCP.client import ModbusClient

from chcos.system.embedded import System

ROOT = Path(__file__).resolve().parent.parent
WAIT = 20.0   # generous wall-clock bound for anything that involves a peer process


@dataclass
class PeerWrite:
    """One write request the peer received."""

    at: float         # time.monotonic() in the peer (the same clock as the test's)
    table: str        # "h" holding, "c" coil
    address: int
    values: list[int]
    outcome: str      # "ok" or "busy"


@dataclass
class ModbusPeer:
    """pyModbusTCP's server (vcan_tests.peer_modbus) in its own process."""

    port: int
    log: Path
    preset: dict[str, int] = field(default_factory=dict)
    proc: subprocess.Popen[str] | None = None
    started_at: float = 0.0

    def start(self) -> None:
        """Start the server and wait until it listens; raises RuntimeError if it does not."""
        args = [sys.executable, "-m", "vcan_tests.peer_modbus", str(self.port), str(self.log),
                *(f"{k}={v}" for k, v in self.preset.items())]
        self.proc = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.PIPE, text=True,
                                     env={**os.environ, "PYTHONPATH": str(ROOT)})
        assert self.proc.stdout is not None
        ready, _, _ = select.select([self.proc.stdout], [], [], WAIT)
        line = self.proc.stdout.readline() if ready else ""
        if line.strip() != "ready":
            self.kill()
            raise RuntimeError(f"pyModbusTCP peer on port {self.port} did not start: {line!r}")
        self.started_at = time.monotonic()

    def kill(self) -> None:
        """SIGKILL the server (a crash: no goodbye on the connection)."""
        if self.proc is not None:
            self.proc.send_signal(signal.SIGCONT)
            self.proc.kill()
            self.proc.wait(WAIT)
            self.proc = None

    def freeze(self) -> None:
        """SIGSTOP: the kernel still accepts connections, nothing answers."""
        assert self.proc is not None
        self.proc.send_signal(signal.SIGSTOP)

    def thaw(self) -> None:
        """SIGCONT."""
        assert self.proc is not None
        self.proc.send_signal(signal.SIGCONT)

    def client(self) -> ModbusClient:
        """An independent client (pyModbusTCP's) to look at the server's own tables."""
        return ModbusClient(host="127.0.0.1", port=self.port, auto_open=True, auto_close=True,
                            timeout=5.0)

    def holding(self, address: int) -> int:
        """The server's holding register ``address``; raises AssertionError if unreadable."""
        regs = self.client().read_holding_registers(address, 1)
        assert regs is not None, f"peer on port {self.port} did not answer a read"
        return int(regs[0])

    def coil(self, address: int) -> bool:
        """The server's coil ``address``."""
        bits = self.client().read_coils(address, 1)
        assert bits is not None, f"peer on port {self.port} did not answer a read"
        return bool(bits[0])

    def set_busy(self, busy: bool) -> None:
        """Make the server answer every write with exception 6 (or stop doing so)."""
        assert self.client().write_single_register(900, 1 if busy else 0)

    def writes(self, since: float = 0.0) -> list[PeerWrite]:
        """The write requests the server received at or after ``since`` (monotonic time)."""
        if not self.log.exists():
            return []
        out = []
        for line in self.log.read_text(encoding="ascii").splitlines():
            at, table, addr, values, outcome = line.split()
            if float(at) >= since and int(addr) != 900:
                out.append(PeerWrite(float(at), table, int(addr),
                                     [int(v) for v in values.split(",")], outcome))
        return out


def run_until(system: System, pred: Callable[[], bool], step: float = 0.05,
              wall: float = WAIT) -> bool:
    """Run ``system`` on its virtual clock in ``step`` slices until ``pred()`` holds; False if
    it does not within ``wall`` seconds of wall-clock time (real peers reconnect in real
    time)."""
    deadline = time.monotonic() + wall
    while not pred():
        if time.monotonic() > deadline:
            return False
        system.run_for(step)
    return True
