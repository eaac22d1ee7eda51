"""A CiA 402 drive that maps its statusword into no TPDO (issue 46): the independent durand drive
(vcan_tests/peers/durand_cia402.py) with no PDOs at all, so everything goes by SDO. Its fault is
seen at once (the fatal EMCY makes the axis read 0x6041 and 0x603F), a command is judged on a
statusword read when it starts (``enable`` of a faulted drive fails naming the fault instead of
answering "done"), the host's fault reset reaches the drive's controlword and its result shows
the new 0x603F; a plain map (the controlword as an ordinary actuator) can write the fault reset
after the fault's EMCY; ``chcos check`` warns about the missing statusword TPDO. Every assertion
is about what the DRIVE received and the state it is in, or what chcos reports."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from chcos.devices import devmap
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System
from drivers.codecs.cia402 import AxisCommandFailed
from vcan_tests.netutil import unique_channel
from vcan_tests.peers.durand_cia402 import ENABLED, FAULT, SOD, DurandCia402Drive
from vcan_tests.support_cia402 import drive_eds
from vcan_tests.test_cia402_axis_stack import M as STACK
from vcan_tests.test_cia402_axis_stack import axis_map

NODE = 5
STEP = 0.02
WALL = 20.0


def running(s: System, drive: DurandCia402Drive, pred: Callable[[], bool]) -> bool:
    """Step the drive and the system's virtual clock together until ``pred()`` (or
    :data:`WALL` wall seconds)."""
    deadline = time.monotonic() + WALL
    while not pred():
        if time.monotonic() > deadline:
            return False
        drive.step(STEP)
        s.run_for(STEP)
    return True


def no_pdo_drive(tmp_path: Path) -> tuple[DurandCia402Drive, Path, str]:
    channel = unique_channel("nopdo")
    drive = DurandCia402Drive(channel, NODE, quick_stop_option=2, pdos=False)
    eds = tmp_path / "drive.eds"
    eds.write_text(drive_eds(rpdos=(), tpdos=()), encoding="utf-8")
    return drive, eds, channel


def test_an_axis_without_a_statusword_tpdo_sees_the_fault_and_resets_it(
        tmp_path: Path) -> None:
    drive, eds, channel = no_pdo_drive(tmp_path)
    path = tmp_path / "axis.toml"
    path.write_text(axis_map(channel, eds), encoding="utf-8")
    _dm, errors, warnings = devmap.check(path)
    assert errors == []
    assert any("axis x's statusword 0x6041 is in no enabled TPDO" in w for w in warnings), \
        warnings
    s = System([path], clock=VirtualClock(), machines=[0])
    s.execute(f"install -m0o1 --code={STACK}:axis_task T x")
    log: list[tuple[str, Any]] = []

    def do(*steps: tuple[Any, ...]) -> list[tuple[str, Any]]:
        start = len(log)
        s.invoke("T", {"steps": list(steps), "log": log})
        assert running(s, drive, lambda: len(log) >= start + len(steps)), log
        return log[start:]

    def value(name: str) -> Any:
        return s.devtab.get(name).value

    try:
        assert running(s, drive, lambda: value("x.state") == "SWITCH_ON_DISABLED")
        assert do(("set_mode",), ("enable",)) == [("set_mode", "ok"), ("enable", "ok")]
        assert drive.state == ENABLED and drive.received[-3:] == [0x06, 0x07, 0x0F]
        n = len(drive.received)
        drive.inject_fault(0x2310)              # EMCY 0x2310; no TPDO says it
        assert running(s, drive, lambda: s.devtab.get("x").status.value == "failed"
                       and value("x.state") == "FAULT" and value("x.fault") == 0x2310)
        assert "drive fault, error code 0x603F 0x2310" in s.devtab.get("x").reason
        assert drive.state == FAULT
        (op, err), = do(("enable",))             # judged on a statusword read now
        assert op == "enable" and isinstance(err, AxisCommandFailed)
        assert "FAULT" in str(err) and "0x603F 0x2310" in str(err)
        assert drive.received[n:] == []          # nothing sent to the faulted drive
        answer = s.execute("axis x fault-reset")
        assert drive.received[n:] == [0x00, 0x80] and drive.state == SOD
        assert answer.startswith("axis x: fault reset done (state SWITCH_ON_DISABLED")
        assert "0x603F 0x0000" in answer          # the drive's new 0x603F, read after it
        assert running(s, drive, lambda: s.devtab.get("x").status.value == "OK"
                       and value("x.fault") == 0)
        assert do(("enable",)) == [("enable", "ok")] and drive.state == ENABLED
    finally:
        s.shutdown()
        drive.close()


PLAIN = """
[[bus]]
name = "drives"
kind = "canopen"
interface = "virtual"
channel = "{channel}"
sdo_timeout = 0.2
nodes = [{{ id = {node}, eds = "{eds}" }}]

[[device]]
name = "cw"
direction = "actuator"
bus = "drives"
address = {{ node = {node}, index = 0x6040 }}
limits = [0, 65535]

[[device]]
name = "sw"
direction = "sensor"
bus = "drives"
address = {{ node = {node}, index = 0x6041, poll_period = 0.05 }}
"""


def test_a_plain_map_writes_the_fault_reset_to_a_faulted_drive(tmp_path: Path) -> None:
    drive, eds, channel = no_pdo_drive(tmp_path)
    path = tmp_path / "plain.toml"
    path.write_text(PLAIN.format(channel=channel, node=NODE, eds=eds), encoding="utf-8")
    s = System([path], clock=VirtualClock(), machines=[0])
    try:
        cw, sw = s.devtab.get("cw"), s.devtab.get("sw")
        assert running(s, drive, lambda: sw.value is not None and sw.status.value == "OK")
        for word in (0x06, 0x07, 0x0F):
            s.devtab.write("cw", word)
            assert running(s, drive, lambda w=word: drive.received[-1:] == [w])
        assert drive.state == ENABLED
        drive.inject_fault(0x2310)
        assert running(s, drive, lambda: drive.state == FAULT and sw.status.value == "failed")
        assert "EMCY" in sw.reason and "0x2310" in sw.reason
        assert cw.status.value == "OK"            # the fault reset must get through
        n = len(drive.received)
        s.devtab.write("cw", 0x00)
        assert running(s, drive, lambda: drive.received[n:] == [0x00])
        s.devtab.write("cw", 0x80)                # the rising edge of bit 7
        assert running(s, drive, lambda: drive.state == SOD)
        assert drive.received[n:] == [0x00, 0x80] and drive.read(0x603F) == 0
        assert running(s, drive, lambda: sw.status.value == "OK")   # the error-reset EMCY
    finally:
        s.shutdown()
        drive.close()
