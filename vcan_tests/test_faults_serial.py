"""No latch on a serial line (issue 38): a command that cannot be written (the write timing out,
as on a peer that stopped reading or a line held by flow control; the write failing) fails that
write and the actuator, and the driver recovers it by itself: it tries the port again, the first
command that goes out recovers the actuator, its safe value then goes out, and the owner's next
command reaches the peer; an actuator failed meanwhile with nothing to probe it with recovers
with that write too (the failure is the port's). The peer is the test itself on the master side
of a pty (no chcos simulator) reading what arrives; the fault is injected in the port under the
driver (pyserial's own port class with a write that raises what pyserial raises)."""

from __future__ import annotations

import os
import select
import threading
import tty
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import serial

from chcos.devices.entry import DeviceStatus
from chcos.errors import DeviceError
from chcos.kernel.clock import RealClock
from chcos.system.embedded import System
from vcan_tests.support_faults import wait_until

SERIAL_MAP = """
[[bus]]
name = "line"
kind = "serial"
url = "{url}"
protocol = "line"
pattern = 'T=(?P<t>\\S+)'
reconnect_min = 0.05
reconnect_max = 0.5

[[device]]
name = "valve"
direction = "actuator"
bus = "line"
limits = [0, 100]
safe_value = 0
address = {{ format = "SET V {{value:.0f}}" }}

[[device]]
name = "lamp"
direction = "actuator"
bus = "line"
limits = [0, 100]
address = {{ format = "L {{value:.0f}}" }}
"""


class FaultyPort(serial.Serial):
    """pyserial's port whose ``write`` raises :attr:`failing` while it is set, counting the
    refused writes."""

    failing: Exception | None = None
    refused = 0

    def write(self, data: Any) -> int | None:
        failing = type(self).failing
        if failing is not None:
            type(self).refused += 1
            raise failing
        return super().write(data)


class Peer:
    """The pty's master side: every line that arrives, in order (a reader thread)."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self._lines: list[str] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        buf = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self.fd], [], [], 0.05)
            if not ready:
                continue
            try:
                buf += os.read(self.fd, 1024)
            except OSError:
                return
            *done, buf = buf.split(b"\n")
            with self._lock:
                self._lines += [d.decode("ascii").strip() for d in done]

    def lines(self) -> list[str]:
        with self._lock:
            return list(self._lines)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


@pytest.fixture
def rig(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[System, Peer]]:
    master, slave = os.openpty()
    tty.setraw(master)
    url = os.ttyname(slave)
    peer = Peer(master)

    def port(url: str, **kw: Any) -> FaultyPort:
        return FaultyPort(url, **kw)

    monkeypatch.setattr(FaultyPort, "failing", None)
    monkeypatch.setattr(FaultyPort, "refused", 0)
    monkeypatch.setattr(serial, "serial_for_url", port)
    path = tmp_path / "serial.toml"
    path.write_text(SERIAL_MAP.format(url=url), encoding="utf-8")
    s = System([path], clock=RealClock(), machines=[0], map_path=tmp_path / "sysfile.map")
    s.start()
    try:
        yield s, peer
    finally:
        s.shutdown()
        peer.stop()
        os.close(master)
        os.close(slave)


@pytest.mark.parametrize("fault", [serial.SerialTimeoutException("Write timeout"),
                                   serial.SerialException("write failed: [Errno 5] EIO")],
                         ids=["write-timeout", "write-error"])
def test_a_failed_write_does_not_latch_the_actuator(rig: tuple[System, Peer],
                                                    fault: Exception) -> None:
    s, peer = rig
    dt = s.devtab

    def status(device: str = "valve") -> DeviceStatus:
        return s.call(lambda: dt.get(device).status)

    def write(value: float, device: str = "valve") -> None:
        s.call(dt.write, device, value)

    assert wait_until(lambda: status() is DeviceStatus.OK and dt.drivers[0].connects == 1)
    write(30)
    assert wait_until(lambda: peer.lines() == ["SET V 30"]), peer.lines()
    FaultyPort.failing = fault
    write(80)
    assert wait_until(lambda: status() is DeviceStatus.FAILED), "the actuator failed"
    assert "write to" in s.call(lambda: dt.get("valve").reason)
    write(7, "lamp")    # never written before, no safe value: nothing to probe it with
    assert wait_until(lambda: status("lamp") is DeviceStatus.FAILED), "the lamp failed"
    with pytest.raises(DeviceError, match="actuator valve is failed"):   # said, not held
        write(50)
    assert wait_until(lambda: FaultyPort.refused >= 3), "the driver tries the port by itself"
    FaultyPort.failing = None       # the port takes writes again: no command needed to find out
    assert wait_until(lambda: status() is DeviceStatus.OK), "recovered by the driver's own write"
    assert wait_until(lambda: status("lamp") is DeviceStatus.OK), "the port took a write: both"
    assert wait_until(lambda: peer.lines() == ["SET V 30", "SET V 30", "SET V 0"]), peer.lines()
    write(60)                       # the owner's next command reaches the peer
    assert wait_until(lambda: peer.lines() == ["SET V 30", "SET V 30", "SET V 0", "SET V 60"]
                      ), peer.lines()
    write(5, "lamp")
    assert wait_until(lambda: peer.lines()[4:] == ["L 5"]), peer.lines()     # never the 7
