"""support_cosim - a master scripted on the wire against a simulated CANopen node's pure core
(:meth:`chcos.apps.sim.canopen_slave.CanopenSlave.handle`), on virtual time.

No bus, no thread: each frame the test writes (bytes laid out as CiA 301 says, written in the
test, never encoded by canopen or chcos) is handed to the node with the node's time, and what
the node answers is kept with that time. What the node sends on its own (heartbeats, event
timers, timeouts) comes from :meth:`Script.run`, which advances the node's clock in steps.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

from chcos.apps.sim.canopen_slave import CanopenSlave, Clock
from chcos.apps.sim.cia402_drive import Cia402Drive
from drivers.codecs.can import CanFrame

STRICT_EDS = Path(__file__).resolve().parent / "vendor" / "strict_node.eds"


@dataclass(frozen=True)
class Seen:
    """A frame the node sent, at the node time it sent it."""

    at: float
    cob_id: int
    data: bytes


class Script:
    """The wire of one node ``node_id`` (``eds``; a :class:`Cia402Drive` with ``drive``), its
    time starting at 0."""

    def __init__(self, node_id: int, eds: Path = STRICT_EDS, drive: bool = False,
                 **kw: object) -> None:
        kw.setdefault("heartbeat_period", 0)
        self.node_id = node_id
        kind = Cia402Drive if drive else CanopenSlave
        self.slave = kind(node_id, eds, channel="unused", clock=Clock.TICK,
                          **kw)  # type: ignore[arg-type]
        self.seen: list[Seen] = []
        self.slave.attach()
        self._keep(self.slave.take())

    @property
    def now(self) -> float:
        return self.slave.now()

    def _keep(self, frames: list[CanFrame]) -> list[Seen]:
        seen = [Seen(self.now, f.arbitration_id, bytes(f.data)) for f in frames]
        self.seen.extend(seen)
        return seen

    def send(self, cob_id: int, data: bytes) -> list[Seen]:
        """One frame to the node now; what it answered."""
        return self._keep(self.slave.handle(CanFrame(cob_id, bytes(data))))

    def run(self, seconds: float, step: float = 0.01) -> list[Seen]:
        """Advance the node's clock by ``seconds`` in steps of ``step``; what it sent."""
        out: list[Seen] = []
        for _ in range(round(seconds / step)):
            self.slave.tick(step)
            out += self._keep(self.slave.take())
        return out

    def set(self, index: int, subindex: int, value: object) -> list[Seen]:
        """Set an object as the device would (its own measurement); what that sent."""
        self.slave.set(index, subindex, value)
        return self._keep(self.slave.take())

    def nmt(self, command: int) -> list[Seen]:
        return self.send(0x000, bytes([command, self.node_id]))

    def sdo(self, request: bytes) -> list[bytes]:
        """One SDO request (8 bytes as given); the data of every SDO response."""
        return [s.data for s in self.send(0x600 + self.node_id, request)
                if s.cob_id == 0x580 + self.node_id]

    def sdo1(self, request: bytes) -> bytes:
        """One SDO request that must get exactly one response; that response."""
        answers = self.sdo(request)
        assert len(answers) == 1, f"{request.hex()} got {[a.hex() for a in answers]}"
        return answers[0]

    def emcys(self, since: int = 0) -> list[bytes]:
        """The data of every EMCY seen (from ``seen[since]`` on)."""
        return [s.data for s in self.seen[since:] if s.cob_id == 0x80 + self.node_id]


def abort(index: int, sub: int, code: int) -> bytes:
    """An abort transfer frame as CiA 301 lays it out: 80, index LE, sub-index, code LE."""
    return bytes([0x80, index & 0xFF, index >> 8, sub]) + struct.pack("<I", code)


def upload(index: int, sub: int) -> bytes:
    """Initiate upload request: 40, index LE, sub-index, 4 reserved bytes."""
    return bytes([0x40, index & 0xFF, index >> 8, sub, 0, 0, 0, 0])


def download(index: int, sub: int, data: bytes) -> bytes:
    """Expedited download request with the size indicated: 0x23 | (4 - n) << 2."""
    cs = 0x23 | ((4 - len(data)) << 2)
    return bytes([cs, index & 0xFF, index >> 8, sub]) + data.ljust(4, b"\x00")


def crc_ccitt(data: bytes) -> int:
    """CRC-16-CCITT as CiA 301 specifies the block transfer CRC (x^16 + x^12 + x^5 + 1,
    initial value 0), bit by bit."""
    crc = 0
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc
