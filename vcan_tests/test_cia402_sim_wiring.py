"""test_cia402_sim_wiring - the simulated CiA 402 drive where users meet it: ``chcos sim cia402``,
the node's own life on the drive (heartbeat producer on the tick clock, heartbeat consumer acting
through 0x6007, SYNC TPDOs, reset node), and ``from_map`` simulating a CiA 402 drive for any map
whose node EDS is a drive's (``chcos sim --from``, ``run --virtual``, the pytest plugin).

Every exchange is on the wire: a raw python-can master sends NMT, SDO and SYNC frames and an
independent observer (:class:`vcan_tests.peers.durand_node.Wire`) records what the drive sent."""

from __future__ import annotations

import shutil
import struct
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import can
import pytest

from chcos.apps.sim import cli as sim_cli
from chcos.apps.sim.canopen_slave import CanopenSlave, Clock
from chcos.apps.sim.cia402_drive import CIA402_EDS, Cia402Drive, main
from vcan_tests.netutil import unique_channel
from vcan_tests.peers.durand_node import Wire

NODE = 6
MASTER = 0x7F
WAIT = 10.0

#: statusword states (mask 0x6F, quick stop bit included)
SWITCH_ON_DISABLED, READY, ENABLED, QUICK_STOP, FAULT = 0x40, 0x21, 0x27, 0x07, 0x08


def state(statusword: int) -> int:
    """The power state bits of a statusword (CiA 402 masks, as one number)."""
    return statusword & (0x4F if statusword & 0x4F in (0x40, 0x08, 0x0F) else 0x6F)


@dataclass
class Master:
    """A raw CANopen master on a virtual channel: NMT, expedited SDO, SYNC, its heartbeat."""

    bus: can.BusABC
    wire: Wire
    node: int = NODE

    def send(self, cob_id: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

    def nmt(self, command: int) -> None:
        self.send(0x000, bytes((command, self.node)))

    def _answer(self, since: int, index: int, sub: int) -> bytes:
        def answered(w: Wire) -> bool:
            return any(f.data[1:4] == struct.pack("<HB", index, sub)
                       for f in w.of(0x580 + self.node)[since:])
        assert self.wire.wait_for(answered, WAIT), f"no SDO answer for 0x{index:04X}:{sub}"
        return next(f.data for f in self.wire.of(0x580 + self.node)[since:]
                    if f.data[1:4] == struct.pack("<HB", index, sub))

    def write(self, index: int, sub: int, value: int, size: int) -> None:
        """An expedited SDO download; fails the test on an abort."""
        since = len(self.wire.of(0x580 + self.node))
        command = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
        self.send(0x600 + self.node, struct.pack("<BHB", command, index, sub)
                  + value.to_bytes(size, "little").ljust(4, b"\x00"))
        answer = self._answer(since, index, sub)
        assert answer[0] == 0x60, f"0x{index:04X}:{sub} write aborted: {answer.hex()}"

    def read(self, index: int, sub: int = 0) -> int:
        """An expedited SDO upload of an unsigned value."""
        since = len(self.wire.of(0x580 + self.node))
        self.send(0x600 + self.node, struct.pack("<BHB", 0x40, index, sub) + bytes(4))
        answer = self._answer(since, index, sub)
        assert answer[0] & 0xE0 == 0x40, f"0x{index:04X}:{sub} read aborted: {answer.hex()}"
        size = 4 - ((answer[0] >> 2) & 3) if answer[0] & 1 else 4
        return int.from_bytes(answer[4:4 + size], "little")


@pytest.fixture
def channel() -> str:
    return unique_channel("cia402wire")


@pytest.fixture
def master(channel: str) -> Iterator[Master]:
    wire = Wire(channel)
    bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    yield Master(bus, wire)
    bus.shutdown()
    wire.close()


@pytest.fixture
def drive(channel: str, master: Master) -> Iterator[Cia402Drive]:
    d = Cia402Drive(NODE, channel=channel, heartbeat_period=0.1, clock=Clock.TICK)
    d.start()
    yield d
    d.stop()


def enable(drive: Cia402Drive, master: Master) -> None:
    """Shutdown, switch on, enable operation by SDO, one drive cycle after each."""
    drive.tick(0.01)                               # the self test: NOT READY -> disabled
    for cw in (0x06, 0x07, 0x0F):
        master.write(0x6040, 0, cw, 2)
        drive.tick(0.01)
    assert state(master.read(0x6041)) == ENABLED


def test_chcos_sim_cia402_is_a_drive_on_the_wire(channel: str, master: Master) -> None:
    # the CLI's delegation: usage errors come from the drive's own parser and checks
    assert sim_cli.main(["cia402", "--node", "200", "--channel", channel]) == 2
    with pytest.raises(SystemExit) as usage:
        sim_cli.main(["cia402", "--help"])
    assert usage.value.code == 0
    stop = threading.Event()
    ran: list[int] = []
    runner = threading.Thread(target=lambda: ran.append(main(
        ["--node", str(NODE), "--channel", channel, "--heartbeat", "0.05"], stop)))
    runner.start()
    try:
        assert master.wire.wait_for(lambda w: any(f.data == b"\x00"
                                                  for f in w.of(0x700 + NODE)), WAIT)
        master.nmt(0x01)
        assert master.wire.wait_for(lambda w: any(f.data == b"\x05"
                                                  for f in w.of(0x700 + NODE)), WAIT)
        assert master.read(0x605A) == 2                       # --quick-stop-option default
        for cw in (0x06, 0x07, 0x0F):
            master.write(0x6040, 0, cw, 2)
        # TPDO1 (statusword, modes display, error code) shows the drive enabled, on its own
        assert master.wire.wait_for(lambda w: any(
            state(int.from_bytes(f.data[:2], "little")) == ENABLED
            for f in w.of(0x180 + NODE)), WAIT)
    finally:
        stop.set()
        runner.join(WAIT)
    assert ran == [0]


def test_chcos_sim_cia402_overheats_on_request(channel: str, master: Master,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--channel", channel, "--overheat", "5-2"]) == 2
    assert "--overheat '5-2': expected START >= 0 and END after START" in \
        capsys.readouterr().err
    stop = threading.Event()
    ran: list[int] = []
    runner = threading.Thread(target=lambda: ran.append(main(
        ["--node", str(NODE), "--channel", channel, "--overheat", "0"], stop)))
    runner.start()
    try:
        # EMCY 0x4310 with the temperature bit in 0x1001's byte, then FAULT with 0x603F
        assert master.wire.wait_for(lambda w: any(f.data[:3] == b"\x10\x43\x09"
                                                  for f in w.of(0x080 + NODE)), WAIT)
        deadline = time.monotonic() + WAIT          # fault reaction, then FAULT (real time)
        while state(master.read(0x6041)) != FAULT and time.monotonic() < deadline:
            pass
        assert state(master.read(0x6041)) == FAULT and master.read(0x603F) == 0x4310
        for cw in (0x00, 0x80):                       # refused while it is still hot
            master.write(0x6040, 0, cw, 2)
        assert state(master.read(0x6041)) == FAULT and master.read(0x603F) == 0x4310
    finally:
        stop.set()
        runner.join(WAIT)
    assert ran == [0]


def test_heartbeat_producer_runs_on_the_drives_tick(drive: Cia402Drive, master: Master) -> None:
    for _ in range(10):
        drive.tick(0.05)
    # boot-up, then a heartbeat every 0.1 s of tick time (0.5 s: about five)
    assert master.wire.wait_for(lambda w: len([f for f in w.of(0x700 + NODE)
                                               if f.data == b"\x7f"]) >= 4, WAIT)
    assert len([f for f in master.wire.of(0x700 + NODE) if f.data == b"\x7f"]) <= 6


@pytest.mark.parametrize(("abort_option", "ends_in", "error_code"), [
    (1, FAULT, 0x8130),                 # fault: needs a fault reset
    (2, SWITCH_ON_DISABLED, 0),         # disable voltage at once
    (3, SWITCH_ON_DISABLED, 0),         # quick stop, then (0x605A = 2) switch on disabled
])
def test_a_silent_master_stops_the_drive_by_0x6007(drive: Cia402Drive, master: Master,
                                                    abort_option: int, ends_in: int,
                                                    error_code: int) -> None:
    master.write(0x6007, 0, abort_option, 2)
    master.write(0x1016, 1, (MASTER << 16) | 200, 4)          # watch node 0x7F, 200 ms
    master.nmt(0x01)
    assert drive.wait_state("OPERATIONAL", WAIT)
    enable(drive, master)
    master.write(0x6060, 0, 3, 1)                             # profile velocity
    master.write(0x60FF, 0, 4000, 4)
    master.send(0x700 + MASTER, b"\x05")                      # the master's heartbeat,
    assert master.read(0x1017) == 100                         # handled before this answer
    for _ in range(10):
        drive.tick(0.01)
    assert master.read(0x606C) == 4000                        # running
    for _ in range(40):                                       # 0.4 s without a heartbeat
        drive.tick(0.01)
    assert master.wire.wait_for(lambda w: any(f.data[:2] == b"\x30\x81"
                                              for f in w.of(0x080 + NODE)), WAIT)
    assert state(master.read(0x6041)) == ends_in
    assert master.read(0x603F) == error_code
    if abort_option == 2:       # the power stage is off: the motor coasts down by friction
        assert 0 < master.read(0x606C) < 4000
        for _ in range(300):
            drive.tick(0.01)
    assert master.read(0x606C) == 0                           # stopped
    assert drive.nmt_state == "PRE-OPERATIONAL"               # 0x1029 = 0
    if abort_option == 1:                                     # nothing clears the fault itself
        for cw in (0x00, 0x80):
            master.write(0x6040, 0, cw, 2)
        drive.tick(0.01)
        assert state(master.read(0x6041)) == SWITCH_ON_DISABLED


def test_sync_tpdos_go_out_on_sync_only(drive: Cia402Drive, master: Master) -> None:
    master.write(0x1800, 2, 1, 1)                             # TPDO1: every SYNC
    master.nmt(0x01)
    assert drive.wait_state("OPERATIONAL", WAIT)
    enable(drive, master)
    for _ in range(50):                                       # 0.5 s, TPDO1 changed often
        drive.tick(0.01)
    assert master.wire.wait_for(lambda w: len(w.of(0x280 + NODE)) > 0, WAIT)  # TPDO2 events
    assert master.wire.of(0x180 + NODE) == []
    for n in range(3):
        master.send(0x080, b"")
        assert master.wire.wait_for(lambda w, n=n: len(w.of(0x180 + NODE)) == n + 1, WAIT)
    statusword = int.from_bytes(master.wire.of(0x180 + NODE)[-1].data[:2], "little")
    assert state(statusword) == ENABLED


def test_reset_node_reboots_the_drive_disabled(drive: Cia402Drive, master: Master) -> None:
    master.write(0x605A, 0, 6, 2)
    master.write(0x6060, 0, 3, 1)                             # PV, not stored
    assert master.read(0x6061) == 3
    master.nmt(0x01)
    assert drive.wait_state("OPERATIONAL", WAIT)
    enable(drive, master)
    master.nmt(0x81)
    assert master.wire.wait_for(lambda w: [f.data for f in w.of(0x700 + NODE)].count(b"\x00")
                                == 2, WAIT)
    drive.tick(0.01)
    assert state(master.read(0x6041)) == SWITCH_ON_DISABLED    # nothing re-enabled
    assert master.read(0x605A) == 2                           # the power-on value again
    assert master.read(0x6061) == 0                           # and the power-on mode


def test_the_drive_starts_in_its_stored_mode(channel: str, master: Master) -> None:
    d = Cia402Drive(NODE, channel=channel, heartbeat_period=0, clock=Clock.TICK)
    d.set(0x6060, 0, 1)
    d.store()                                                 # 0x1010 'save': PP at power-on
    d.start()
    try:
        d.tick(0.01)
        assert master.read(0x6061) == 1
        master.nmt(0x81)                                      # a reboot keeps what was stored
        assert master.wire.wait_for(lambda w: [f.data for f in w.of(0x700 + NODE)]
                                    .count(b"\x00") == 2, WAIT)
        assert master.read(0x6061) == 1
    finally:
        d.stop()


def _map(tmp_path: Path, eds: Path) -> Path:
    devmap = tmp_path / "drive.toml"
    devmap.write_text(f"""
[[bus]]
name = "axis"
kind = "canopen"
interface = "virtual"
channel = "unused"
nodes = [{{ id = {NODE}, eds = "{eds.name}", heartbeat_timeout = 0.3 }}]

[[device]]
name = "controlword"
direction = "actuator"
bus = "axis"
address = {{ node = {NODE}, index = 0x6040 }}
limits = [0, 65535]
safe_value = 0

[[device]]
name = "statusword"
direction = "sensor"
bus = "axis"
address = {{ node = {NODE}, index = 0x6041 }}
""", encoding="utf-8")
    return devmap


def test_from_map_simulates_a_cia402_node_as_a_drive(tmp_path: Path) -> None:
    from chcos.apps.sim.from_map import simulate
    from chcos.devices.devmap import load

    shutil.copy(CIA402_EDS, tmp_path / "drive.eds")
    slaves = simulate(load([str(_map(tmp_path, tmp_path / "drive.eds"))]))
    try:
        node = slaves.canopen_node("axis", NODE)
        assert isinstance(node, Cia402Drive)
        bus = slaves.devmap.bus("axis")
        wire = Wire(str(bus.options["channel"]))
        master = Master(can.Bus(interface="virtual", channel=str(bus.options["channel"]),
                                receive_own_messages=False), wire)
        try:
            master.nmt(0x01)
            assert node.wait_state("OPERATIONAL", WAIT)
            slaves.tick(0.01)
            for n, cw in enumerate((0x06, 0x07, 0x0F)):
                master.write(0x6040, 0, cw, 2)
                slaves.tick(0.02 * (n + 2))
            assert state(master.read(0x6041)) == ENABLED      # the drive answered the word
            for n in range(10):
                slaves.tick(0.1 + 0.1 * n)                    # heartbeat every 0.1 s of tick
            assert wire.wait_for(lambda w: len([f for f in w.of(0x700 + NODE)
                                                if f.data == b"\x05"]) >= 5, WAIT)
        finally:
            master.bus.shutdown()
            wire.close()
    finally:
        slaves.close()


def test_from_map_keeps_a_plain_node_plain(tmp_path: Path) -> None:
    from chcos.apps.sim.canopen_slave import SERVO_EDS
    from chcos.apps.sim.from_map import simulate
    from chcos.devices.devmap import load

    shutil.copy(SERVO_EDS, tmp_path / "servo.eds")
    slaves = simulate(load([str(_map(tmp_path, tmp_path / "servo.eds"))]))
    try:
        node = slaves.canopen_node("axis", NODE)
        assert isinstance(node, CanopenSlave) and not isinstance(node, Cia402Drive)
    finally:
        slaves.close()


def _axis_map(tmp_path: Path, channel: str, option: int) -> Path:
    shutil.copy(CIA402_EDS, tmp_path / "drive.eds")
    devmap = tmp_path / "axis.toml"
    devmap.write_text(f"""
[[bus]]
name = "axis"
kind = "canopen"
interface = "virtual"
channel = "{channel}"
nodes = [{{ id = {NODE}, eds = "drive.eds" }}]

[[device]]
name = "x"
profile = "cia402"
bus = "axis"
address = {{ node = {NODE} }}
quick_stop_option = {option}
""", encoding="utf-8")
    return devmap


def test_an_axis_map_is_simulated_with_the_drive_it_describes(tmp_path: Path) -> None:
    from chcos.apps.sim.from_map import simulate
    from chcos.devices.devmap import load
    from chcos.errors import DeviceError

    slaves = simulate(load([str(_axis_map(tmp_path, "unused", 6))]))
    try:
        drive = slaves.canopen_node("axis", NODE)
        assert isinstance(drive, Cia402Drive)
        assert drive.value(0x605A) == 6            # what the map says the drive holds
        slaves.tick(0.01)
        assert slaves.get("x") == "SWITCH_ON_DISABLED"
        assert slaves.get("x.statusword") == drive.value(0x6041)
        assert slaves.get("x.position") == 0
        with pytest.raises(DeviceError, match=r"'x\.position' is a CiA 402 axis"):
            slaves.set("x.position", 5)
        with pytest.raises(DeviceError, match="cannot follow a script"):
            slaves.script("x.position", "ramp(0, 10, 1)")
    finally:
        slaves.close()


def test_chcos_sim_from_an_axis_map_shows_the_drive(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str],
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    from chcos.apps.sim import from_map
    from chcos.apps.sim.from_map import main as sim_from

    # the map's process-local virtual channel, which `chcos sim --from` refuses for a run in
    # another process, is enough here: only what the simulator prints is looked at
    monkeypatch.setattr(from_map, "process_local", lambda devmap: [])
    devmap = _axis_map(tmp_path, unique_channel("simfrom"), 2)
    assert sim_from(["--from", str(devmap), "--duration", "1.2"]) == 0
    out = capsys.readouterr().out
    assert "x=SWITCH_ON_DISABLED" in out and "x.statusword=" in out
