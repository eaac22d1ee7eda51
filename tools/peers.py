"""peers - independent peers the fault tests and the fault benchmark run chcos against.

- :class:`ModbusPeer`: pyModbusTCP's server (:mod:`tools.peer_modbus`) in its own process, which
  can be killed, frozen and restarted and is read from its own side;
- :class:`CanopenPeer`: canopen's ``LocalNode`` ``NODE`` with the servo EDS on python-can's
  virtual bus (heartbeat and EMCY producer), with :data:`CANOPEN_MAP`, a device map of it.

They live in tools/ (not in vcan_tests/) because both the tests and ``tools/bench_faults.py`` use
them and a tool does not import the tests; they are not part of the installed package (they need
the dev dependencies). The Modbus peer's process runs from the checkout (``PYTHONPATH`` = it).
"""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import canopen
from pyModbusTCP.client import ModbusClient

from chcos.apps.sim.canopen_slave import SERVO_EDS

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
    """pyModbusTCP's server (:mod:`tools.peer_modbus`) in its own process."""

    port: int
    log: Path
    preset: dict[str, int] = field(default_factory=dict)
    proc: subprocess.Popen[str] | None = None
    started_at: float = 0.0

    def start(self) -> None:
        """Start the server and wait until it listens; raises RuntimeError if it does not."""
        args = [sys.executable, "-m", "tools.peer_modbus", str(self.port), str(self.log),
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
        """SIGSTOP: the kernel still accepts connections, nothing answers. Returns once the
        process is stopped (a signal is delivered when the process is next scheduled: on a
        loaded machine it could answer a request sent just after the kill(2))."""
        assert self.proc is not None
        self.proc.send_signal(signal.SIGSTOP)
        stat = Path(f"/proc/{self.proc.pid}/stat")
        deadline = time.monotonic() + WAIT
        while stat.exists() and stat.read_text().rsplit(")", 1)[1].split()[0] not in ("t", "T"):
            if time.monotonic() > deadline:
                raise RuntimeError(f"pyModbusTCP peer {self.proc.pid} did not stop")
            time.sleep(0.001)

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


NODE = 5
SPEED, TARGET, TEMP = 0x6081, 0x607A, 0x2000
CANOPEN_MAP = """
[[bus]]
name = "co"
kind = "canopen"
interface = "virtual"
channel = "{channel}"
sdo_timeout = 0.2
nodes = [{{ id = {node}, eds = "{eds}", heartbeat_timeout = 0.15, nmt_start = false }}]

[[device]]
name = "speed"
direction = "actuator"
bus = "co"
address = {{ node = {node}, index = 0x6081 }}
limits = [0, 100000]
safe_value = 0

[[device]]
name = "target"
direction = "actuator"
bus = "co"
address = {{ node = {node}, index = 0x607A }}
limits = [-100000, 100000]
safe_value = 0

[[device]]
name = "temp"
direction = "sensor"
bus = "co"
address = {{ node = {node}, index = 0x2000, poll_period = 0.1 }}
"""


class Candump(can.Listener):
    """Every frame the peer's bus received, with time.monotonic() stamps."""

    def __init__(self) -> None:
        self.frames: list[tuple[float, int, bytes]] = []

    def on_message_received(self, msg: can.Message) -> None:
        self.frames.append((time.monotonic(), msg.arbitration_id, bytes(msg.data)))


class CanopenPeer:
    """canopen.LocalNode ``NODE`` with the servo EDS, heartbeat producer, EMCY producer."""

    def __init__(self, channel: str) -> None:
        self.od: Any = canopen.import_od(str(SERVO_EDS), NODE)
        self.net: Any = canopen.Network()
        self.net.NOTIFIER_CYCLE = 0.05
        self.net.connect(interface="virtual", channel=channel)
        self.node: Any = canopen.LocalNode(NODE, self.od)
        self.net.add_node(self.node)
        self.dump = Candump()
        notifier: Any = self.net.notifier
        notifier.add_listener(self.dump)
        self.node.nmt.state = "OPERATIONAL"
        self.beat()

    def beat(self) -> None:
        self.node.nmt.start_heartbeat(20)

    def silence(self) -> None:
        self.node.nmt.stop_heartbeat()

    def value(self, index: int) -> int:
        """The node's own object ``index``:0 (SDO downloads land here)."""
        return int(self.od[index].decode_raw(self.node.get_data(index, 0)))

    def sdo_writes(self, index: int, since: float = 0.0) -> list[int]:
        """Values of expedited SDO downloads to ``index``:0 the node received since ``since``."""
        out = []
        for at, cob, data in self.dump.frames:
            if (at >= since and cob == 0x600 + NODE and data[0] & 0xE0 == 0x20
                    and int.from_bytes(data[1:3], "little") == index and data[3] == 0):
                n = 4 - ((data[0] >> 2) & 3) if data[0] & 1 else 4
                out.append(int.from_bytes(data[4:4 + n], "little", signed=True))
        return out

    def rpdo_values(self, since: float = 0.0) -> list[int]:
        """Target positions in RPDO1 frames the node received since ``since``."""
        return [int.from_bytes(d[:4], "little", signed=True) for at, cob, d in self.dump.frames
                if at >= since and cob == 0x200 + NODE]

    def close(self) -> None:
        self.silence()
        self.net.disconnect()
