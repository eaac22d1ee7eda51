"""The simulated node's CiA 301 strictness on real SocketCAN (runs inside the User-Mode-Linux
guest): can-utils is the client - ``cansend`` writes each request as CiA 301 lays it out,
``candump`` shows what the node put on vcan0 - so neither python-can's encoding nor canopen's is
on the client side. The node runs on real time (its python-can socketcan transport, its timers on
the wall clock)."""

from __future__ import annotations

import os
import selectors
import shutil
import subprocess
import time
from collections.abc import Iterator

import pytest

from chcos.apps.sim.canopen_slave import CanopenSlave, Clock
from vcan_tests.conftest import require
from vcan_tests.support_cosim import STRICT_EDS

NODE = 9
STEP_TIMEOUT = 10.0   # bound on every wait in the guest
PROBE = "7FE#00"


class Candump:
    """``candump -L`` of the node's answers on one channel, line by line (bounded waits)."""

    def __init__(self, channel: str) -> None:
        filters = ",".join(f"{cob:03X}:7FF" for cob in (0x580 + NODE, 0x80 + NODE,
                                                        0x700 + NODE, 0x7FE))
        self.channel = channel
        self.proc = subprocess.Popen(["candump", "-L", f"{channel},{filters}"],
                                     stdout=subprocess.PIPE)
        assert self.proc.stdout is not None
        self._fd = self.proc.stdout.fileno()
        os.set_blocking(self._fd, False)
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._fd, selectors.EVENT_READ)
        self._buf = b""
        self.lines: list[str] = []
        deadline = time.monotonic() + STEP_TIMEOUT
        while time.monotonic() < deadline:      # candump is ready once it shows a probe
            cansend(channel, PROBE)
            if self.expect(PROBE, 0.2, quiet=True) is not None:
                return
        raise AssertionError(f"candump showed no probe within {STEP_TIMEOUT} s")

    def _line(self, timeout: float) -> str | None:
        deadline = time.monotonic() + timeout
        while b"\n" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0 or not self._sel.select(left):
                return None
            chunk = os.read(self._fd, 4096)
            if not chunk:
                return None
            self._buf += chunk
        line, self._buf = self._buf.split(b"\n", 1)
        frame = line.decode().rsplit(" ", 1)[-1]      # "(stamp) vcan0 589#80..."
        self.lines.append(frame)
        return frame

    def expect(self, frame: str, timeout: float = STEP_TIMEOUT,
               quiet: bool = False) -> str | None:
        """Wait for ``frame`` (``ID#DATA``, upper-case hex); None (quiet) or fail if not seen."""
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            line = self._line(left)
            if line == frame:
                return line
        if quiet:
            return None
        raise AssertionError(f"candump did not show {frame}: {self.lines[-20:]}")

    def next_from(self, cob: int) -> str:
        """The next frame on COB-ID ``cob``."""
        prefix = f"{cob:03X}#"
        deadline = time.monotonic() + STEP_TIMEOUT
        while (left := deadline - time.monotonic()) > 0:
            line = self._line(left)
            if line is not None and line.startswith(prefix):
                return line
        raise AssertionError(f"candump showed nothing on {prefix}: {self.lines[-20:]}")

    def close(self) -> None:
        self._sel.close()
        self.proc.terminate()
        self.proc.wait(timeout=STEP_TIMEOUT)
        assert self.proc.stdout is not None
        self.proc.stdout.close()


def cansend(channel: str, frame: str) -> None:
    subprocess.run(["cansend", channel, frame], check=True, timeout=STEP_TIMEOUT)


@pytest.fixture
def node() -> Iterator[tuple[str, Candump]]:
    from vcan_tests import uml

    for tool in ("cansend", "candump"):
        require(shutil.which(tool), f"{tool} on PATH (apt-get install can-utils)")
    channel = uml.can_channel("socketcan")
    dump = Candump(channel)
    slave = CanopenSlave(NODE, STRICT_EDS, interface="socketcan", channel=channel,
                         heartbeat_period=0, clock=Clock.REAL)
    try:
        slave.start()
        dump.expect(f"{0x700 + NODE:03X}#00")          # boot-up
        yield channel, dump
    finally:
        slave.stop()
        dump.close()


@pytest.mark.socketcan
def test_sdo_aborts_on_socketcan(node: tuple[str, Candump]) -> None:
    channel, dump = node
    for request, answer in (
            ("609#4008200100000000", "589#8008200111000906"),   # 0x2008:01 of a variable
            ("609#6000000000000000", "589#8000000001000405"),   # a stray segment, no transfer
            ("609#2317100064000000", "589#8017100012000706"),   # 4 bytes into UNSIGNED16
            ("609#2B03200065000000", "589#8003200031000906"),   # 101 > HighLimit 100
            ("609#4001200000000000", "589#8001200001000106"),   # read of a write-only object
            ("609#4099600000000000", "589#8099600000000206")):  # no such object
        cansend(channel, request)
        assert dump.next_from(0x580 + NODE) == answer, request


@pytest.mark.socketcan
def test_block_upload_starts_and_a_client_abort_ends_it(node: tuple[str, Candump]) -> None:
    channel, dump = node
    cansend(channel, "609#A408100004000000")                    # block upload, CRC, 4 per block
    assert dump.next_from(0x580 + NODE) == "589#C608100016000000"   # 22 bytes, CRC
    cansend(channel, "609#A300000000000000")                    # start
    assert [dump.next_from(0x580 + NODE)[:6] for _ in range(4)] == [
        "589#01", "589#02", "589#03", "589#84"]                 # 4 segments, the last with c
    cansend(channel, "609#A204040000000000")                    # all 4 acknowledged
    end = dump.next_from(0x580 + NODE)
    assert end[:6] == "589#D9"                                  # end: 6 bytes unused
    cansend(channel, "609#A100000000000000")
    cansend(channel, "609#6000000000000000")                    # the transfer is over
    assert dump.next_from(0x580 + NODE) == "589#8000000001000405"


@pytest.mark.socketcan
def test_a_short_rpdo_raises_emcy_8210_on_socketcan(node: tuple[str, Candump]) -> None:
    channel, dump = node
    cansend(channel, f"000#01{NODE:02X}")                       # NMT start
    cansend(channel, "609#4017100000000000")                    # answered after the start
    dump.next_from(0x580 + NODE)
    cansend(channel, "209#0102")                                # 2 of 6 bytes
    assert dump.next_from(0x80 + NODE) == "089#1082110100020600"
    cansend(channel, "209#000000000000")                        # the right length
    assert dump.next_from(0x80 + NODE) == "089#0000000000000000"
