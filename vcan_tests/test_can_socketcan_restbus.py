"""On real SocketCAN (vcan0 in the User-Mode-Linux guest): chcos' cyclic command on real time
goes out through the kernel's broadcast manager, and candump (can-utils) sees its timing and
content - every frame's counter one more than the last across a change of command, every CRC
right (computed here bitwise); an error frame written with cansend (the bytes a controller
driver sends at bus-off and at its restart) tells the raw CAN driver the controller's state."""

from __future__ import annotations

import itertools
import statistics
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest

from drivers.can_raw import CanDriver
from vcan_tests import uml
from vcan_tests.support_dev import FakeHost, bus, device
from vcan_tests.test_can_e2e import j1850

pytestmark = pytest.mark.socketcan

DBC = """VERSION ""
NS_ :
BS_:
BU_: ECU CHCOS
BO_ 512 CMD: 3 CHCOS
 SG_ CHECKSUM : 0|8@1+ (1,0) [0|255] "" ECU
 SG_ COUNTER : 8|4@1+ (1,0) [0|15] "" ECU
 SG_ SPEED : 16|8@1+ (1,0) [0|200] "" ECU
BO_ 256 STATUS: 1 ECU
 SG_ TEMP : 0|8@1+ (1,0) [0|200] "" CHCOS
BA_DEF_ BO_ "GenMsgCycleTime" INT 0 65535;
BA_DEF_DEF_ "GenMsgCycleTime" 0;
BA_ "GenMsgCycleTime" BO_ 512 20;
"""
STEP = 10.0     # bound on every wait in the guest


def _dump(path: Path) -> list[tuple[float, int, bytes]]:
    """candump -L lines: (time stamp, id, data)."""
    out = []
    for line in path.read_text(encoding="ascii").splitlines():
        parts = line.split()
        if len(parts) == 3 and "#" in parts[2]:
            fid, data = parts[2].split("#")
            out.append((float(parts[0].strip("()")), int(fid, 16), bytes.fromhex(data)))
    return out


def _until(pred: Any, timeout: float = STEP) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.05)
    return bool(pred())


def test_the_cyclic_command_goes_out_through_the_bcm_with_its_counter_and_crc(
        tmp_path: Path) -> None:
    channel = uml.can_channel("socketcan")
    (tmp_path / "d.dbc").write_text(DBC)
    dump = tmp_path / "candump.log"
    with dump.open("w", encoding="ascii") as out:
        candump = subprocess.Popen(["candump", "-L", f"{channel},200:7FF"], stdout=out,
                                   stderr=subprocess.STDOUT)
    host = FakeHost()
    host.virtual_clock = False  # type: ignore[attr-defined]
    drv = CanDriver(bus("can", interface="socketcan", channel=channel,
                        dbc=str(tmp_path / "d.dbc"),
                        message=[{"name": "CMD", "counter": "COUNTER", "checksum": {
                            "signal": "CHECKSUM", "algorithm": "crc8-sae-j1850"}}]),
                    [device("speed", "actuator", message="CMD", signal="SPEED")], host)
    drv.start()
    try:
        drv.write("speed", 10)
        assert _until(lambda: len(_dump(dump)) >= 25), dump.read_text()
        drv.write("speed", 20)                   # modify_data: the kernel keeps its place
        assert _until(lambda: sum(d[2] == 20 for _, _, d in _dump(dump)) >= 25)
    finally:
        drv.stop()
        time.sleep(0.1)                          # candump writes what it has
        candump.terminate()
        candump.wait(timeout=STEP)
    frames = _dump(dump)
    assert all(fid == 0x200 and len(d) == 3 for _, fid, d in frames)
    assert all(d[0] == j1850(d[1:]) for _, _, d in frames), frames
    counters = [d[1] & 0xF for _, _, d in frames]
    assert counters == [(counters[0] + k) % 16 for k in range(len(counters))]
    speeds = [d[2] for _, _, d in frames]
    assert speeds[0] == 10 and speeds[-1] == 20 and sorted(speeds) == speeds
    gaps = [b[0] - a[0] for a, b in itertools.pairwise(frames)]
    assert min(gaps) > 0.010                     # never faster than the cycle
    assert abs(statistics.median(gaps) - 0.020) < 0.004, gaps
    assert drv.status().cyclic[0].period == pytest.approx(0.02)


def test_error_frames_written_with_cansend_tell_the_driver_bus_off_and_the_restart(
        tmp_path: Path) -> None:
    channel = uml.can_channel("socketcan")
    (tmp_path / "d.dbc").write_text(DBC)
    host = FakeHost()
    host.virtual_clock = False  # type: ignore[attr-defined]
    drv = CanDriver(bus("can", interface="socketcan", channel=channel,
                        dbc=str(tmp_path / "d.dbc")),
                    [device("temp", "sensor", message="STATUS", signal="TEMP"),
                     device("speed", "actuator", i=1, message="CMD", signal="SPEED")], host)
    drv.start()
    try:
        # CAN_ERR_FLAG | CAN_ERR_BUSOFF | CAN_ERR_CNT, TX errors 255: as can_bus_off() sends
        subprocess.run(["cansend", channel, "20000240#000000000000FF00"], check=True,
                       timeout=STEP)
        assert host.wait(lambda h: len(h.failures) == 2, STEP), host.errors
        assert all("bus-off" in why for _, why in host.failures)
        assert drv.status().bus_state.state == "bus-off"
        # CAN_ERR_FLAG | CAN_ERR_RESTARTED | CAN_ERR_CNT: the restart
        subprocess.run(["cansend", channel, "20000300#0000000000000000"], check=True,
                       timeout=STEP)
        assert host.wait(lambda h: "speed" in h.recoveries, STEP)
        bs = drv.status().bus_state
        assert bs is not None and bs.state == "error-active" and bs.bus_offs == 1
        assert bs.restarts == 1
        subprocess.run(["cansend", channel, "100#2A"], check=True, timeout=STEP)
        assert host.wait(lambda h: h.values("temp") == [42], STEP)
        assert "temp" in host.recoveries
    finally:
        drv.stop()
