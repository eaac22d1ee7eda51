"""No latch on a raw CAN send failure (issue 38): a frame that cannot be sent (the transmit queue
full past the send timeout, ENOBUFS; the bus error-passive or off, ENETDOWN) fails that write and
the actuator, and the driver recovers it by itself: it tries the link again, and the first frame
that goes out recovers the actuator, whose safe value then goes out, and the owner's next command
reaches the peer; an actuator failed meanwhile with nothing to probe it with recovers with that
frame too (a send failure is the bus's). The fault is injected under the driver by python-can's
virtual bus with a send that raises what SocketCAN raises; the peer is an independent python-can
reader on the same channel, and every assertion is on the frames it received."""

from __future__ import annotations

import errno
import re
import subprocess
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import pytest
from can.interfaces.virtual import VirtualBus

from chcos.devices.entry import DeviceStatus
from chcos.errors import DeviceError
from chcos.kernel.clock import RealClock
from chcos.system.embedded import System
from drivers.can_raw import CanDriver
from vcan_tests import uml
from vcan_tests.netutil import unique_channel
from vcan_tests.support_faults import wait_until

ID, LAMP = 0x230, 0x231
STEP = 20.0     # seconds a step may take in the guest (UML system calls are slow)

CAN_MAP = """
[[bus]]
name = "can0"
kind = "can"
interface = "virtual"
channel = "{channel}"

[[device]]
name = "valve"
direction = "actuator"
bus = "can0"
limits = [0, 100]
safe_value = 0
address = {{ id = 0x230, start = 0, length = 8, dlc = 1 }}

[[device]]
name = "lamp"
direction = "actuator"
bus = "can0"
limits = [0, 100]
address = {{ id = 0x231, start = 0, length = 8, dlc = 1 }}
"""


class FaultyBus(VirtualBus):
    """python-can's virtual bus whose ``send`` raises :attr:`failing` while it is set (the
    error SocketCAN's send raises), counting the refused frames, and whose ``recv`` raises
    :attr:`recv_failing` once (SocketCAN reports an interface gone down once)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.failing: can.CanError | None = None
        self.recv_failing: can.CanError | None = None
        self.refused = 0

    def recv(self, timeout: float | None = None) -> can.Message | None:
        failing, self.recv_failing = self.recv_failing, None
        if failing is not None:
            raise failing
        return super().recv(timeout)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        failing = self.failing
        if failing is not None:
            self.refused += 1
            raise failing
        super().send(msg, timeout)


class Reader(can.Listener):
    """The independent peer: the data byte of every frame of each id, in order."""

    def __init__(self) -> None:
        self.values: dict[int, list[int]] = {ID: [], LAMP: []}
        self._lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        with self._lock:
            self.values.setdefault(msg.arbitration_id, []).append(msg.data[0])

    def got(self, can_id: int = ID) -> list[int]:
        with self._lock:
            return list(self.values.get(can_id, []))


@pytest.fixture
def rig(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
        ) -> Iterator[tuple[System, FaultyBus, Reader, can.BusABC]]:
    channel = unique_channel("cansend")
    peer = can.Bus(interface="virtual", channel=channel)     # before the driver's bus is faulty
    reader = Reader()
    notifier = can.Notifier(peer, [reader], timeout=0.05)
    made: list[FaultyBus] = []

    def faulty(**cfg: Any) -> FaultyBus:
        cfg.pop("interface", None)
        made.append(FaultyBus(**cfg))
        return made[-1]

    monkeypatch.setattr(can, "Bus", faulty)
    path = tmp_path / "can.toml"
    path.write_text(CAN_MAP.format(channel=channel), encoding="utf-8")
    s = System([path], clock=RealClock(), machines=[0], map_path=tmp_path / "sysfile.map")
    monkeypatch.undo()
    s.start()
    try:
        (bus,) = made
        yield s, bus, reader, peer
    finally:
        s.shutdown()
        notifier.stop()
        peer.shutdown()


@pytest.mark.parametrize("fault", [
    can.CanOperationError("No buffer space available", errno.ENOBUFS),
    can.CanOperationError("Network is down (bus-off)", errno.ENETDOWN),
], ids=["enobufs", "bus-off"])
def test_a_send_failure_does_not_latch_the_actuator(
        rig: tuple[System, FaultyBus, Reader, can.BusABC], fault: can.CanError) -> None:
    s, bus, reader, _peer = rig
    dt = s.devtab

    def status(device: str = "valve") -> DeviceStatus:
        return s.call(lambda: dt.get(device).status)

    s.call(dt.write, "valve", 30)
    assert wait_until(lambda: reader.got() == [30]), reader.got()
    bus.failing = fault
    s.call(dt.write, "valve", 80)
    assert wait_until(lambda: status() is DeviceStatus.FAILED), "the actuator failed"
    assert "CAN send on bus 'can0' failed" in s.call(lambda: dt.get("valve").reason)
    s.call(dt.write, "lamp", 7)     # never sent before, no safe value: nothing to probe it with
    assert wait_until(lambda: status("lamp") is DeviceStatus.FAILED), "the lamp failed"
    with pytest.raises(DeviceError, match="actuator valve is failed"):   # said, not held
        s.call(dt.write, "valve", 50)
    assert wait_until(lambda: bus.refused >= 3), "the driver tries the link again by itself"
    bus.failing = None       # the bus takes frames again: no command is needed to find out
    assert wait_until(lambda: status() is DeviceStatus.OK), "recovered by the driver's own send"
    assert wait_until(lambda: status("lamp") is DeviceStatus.OK), "the bus took a frame: both"
    assert wait_until(lambda: reader.got() == [30, 30, 0]), reader.got()
    s.call(dt.write, "valve", 60)                # the owner's next command reaches the peer
    assert wait_until(lambda: reader.got() == [30, 30, 0, 60]), reader.got()
    assert 80 not in reader.got() and 50 not in reader.got()
    s.call(dt.write, "lamp", 5)
    assert wait_until(lambda: reader.got(LAMP) == [5]), reader.got(LAMP)   # never the 7


def test_a_receive_failure_does_not_latch_the_actuators_of_a_bus_that_only_sends(
        rig: tuple[System, FaultyBus, Reader, can.BusABC]) -> None:
    """The interface reports a receive error (gone down and back): every device fails, and
    on a bus with actuators only no frame will ever come to end it; the driver's own send
    does."""
    s, bus, reader, peer = rig
    dt = s.devtab

    def status() -> DeviceStatus:
        return s.call(lambda: dt.get("valve").status)

    changes: list[tuple[bool, str]] = []
    s.call(dt.add_health_listener, lambda d, ok, cause: changes.append((ok, cause))
           if d == "valve" else None)
    s.call(dt.write, "valve", 30)
    assert wait_until(lambda: reader.got() == [30]), reader.got()
    bus.recv_failing = can.CanOperationError("Network is down", errno.ENETDOWN)
    peer.send(can.Message(arbitration_id=0x7FF, data=b"", is_extended_id=False))  # wakes it
    assert wait_until(lambda: len(changes) >= 2), "failed, then recovered"
    (down, why), (up, how) = changes[:2]
    assert not down and "receive failed: Network is down" in why, why
    assert up and "the bus took a frame again" in how, how
    assert status() is DeviceStatus.OK
    assert wait_until(lambda: reader.got() == [30, 30, 0]), reader.got()
    s.call(dt.write, "valve", 60)
    assert wait_until(lambda: reader.got() == [30, 30, 0, 60]), reader.got()


@pytest.mark.socketcan
def test_on_socketcan_the_interface_down_and_up_does_not_latch_the_actuator(
        tmp_path: Path) -> None:
    """Real SocketCAN in the guest: ``ip link set vcan0 down``: the driver's receive reports
    it (ENETDOWN), the actuator fails and commands are refused, the driver's probes fail
    (ENETDOWN on send); once the interface is up again a probe goes out and recovers the
    actuator, and candump (can-utils, running through the outage with -D) shows what went on
    the wire: the command before, the probe, the safe value, the next command."""
    channel = uml.can_channel("socketcan")
    dump = tmp_path / "candump.log"
    with dump.open("w", encoding="ascii") as out:
        candump = subprocess.Popen(["candump", "-D", "-L", f"{channel},{ID:03X}:7FF"],
                                   stdout=out, stderr=subprocess.STDOUT)
    path = tmp_path / "can.toml"
    path.write_text(CAN_MAP.format(channel=channel).replace('"virtual"', '"socketcan"'),
                    encoding="utf-8")
    s = System([path], clock=RealClock(), machines=[0], map_path=tmp_path / "sysfile.map")
    s.start()
    dt = s.devtab

    def seen() -> list[int]:
        return [int(m, 16) for m in re.findall(rf"{ID:03X}#([0-9A-F]+)",
                                                dump.read_text(encoding="ascii"))]

    def status() -> DeviceStatus:
        return s.call(lambda: dt.get("valve").status)

    try:
        first = 30
        while True:     # until candump shows it listens: a command it received
            s.call(dt.write, "valve", first)
            if wait_until(lambda v=first: v in seen(), 2.0):
                break
            first += 1
            assert first < 40, dump.read_text(encoding="ascii")
        subprocess.run(["ip", "link", "set", channel, "down"], check=True, timeout=STEP)
        try:
            assert wait_until(lambda: status() is DeviceStatus.FAILED, STEP), "failed"
            with pytest.raises(DeviceError, match="actuator valve is failed"):
                s.call(dt.write, "valve", 80)
            drv = dt.drivers[0]
            assert isinstance(drv, CanDriver)
            assert wait_until(lambda: drv.probe.failed_tries >= 2, STEP), "probes while down"
        finally:
            subprocess.run(["ip", "link", "set", channel, "up"], check=True, timeout=STEP)
        assert wait_until(lambda: status() is DeviceStatus.OK, STEP), "recovered by itself"
        assert wait_until(lambda: seen()[-3:] == [first, first, 0], STEP), seen()
        s.call(dt.write, "valve", 60)
        assert wait_until(lambda: seen()[-4:] == [first, first, 0, 60], STEP), seen()
        assert 80 not in seen()
    finally:
        s.shutdown()
        candump.terminate()
        candump.wait(timeout=STEP)
