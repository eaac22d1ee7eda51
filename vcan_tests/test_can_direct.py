"""The in-process direct CAN bus of virtual time (drivers.can_direct) and what reads its faults:
the frame handed over in the send, not copied; error frames decoded like SocketCAN's (byte
literals of <linux/can/error.h>); the raw CAN driver's controller state from them; chcos'
cyclic messages on real time through python-can's periodic sender."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import can
import cantools
import pytest

from drivers.can_direct import BusFault, DirectBus
from drivers.can_raw import CanDriver
from drivers.codecs.can_errors import ControllerState, decode_error_frame
from vcan_tests.support_dev import FakeHost, bus, device

DBC = """VERSION ""
NS_ :
BS_:
BU_: ECU CHCOS
BO_ 512 CMD: 2 CHCOS
 SG_ COUNTER : 0|4@1+ (1,0) [0|15] "" ECU
 SG_ SPEED : 8|8@1+ (1,0) [0|200] "" ECU
BO_ 256 STATUS: 1 ECU
 SG_ TEMP : 0|8@1+ (1,0) [0|200] "" CHCOS
BA_DEF_ BO_ "GenMsgCycleTime" INT 0 65535;
BA_DEF_DEF_ "GenMsgCycleTime" 0;
BA_ "GenMsgCycleTime" BO_ 512 20;
"""


@pytest.fixture
def dbc_file(tmp_path: Path) -> Path:
    p = tmp_path / "d.dbc"
    p.write_text(DBC)
    return p


def test_send_hands_the_same_frame_to_every_receiver_before_it_returns(
        request: pytest.FixtureRequest) -> None:
    name = request.node.name
    a, b, c = (DirectBus(channel=name) for _ in range(3))
    try:
        got: list[can.Message] = []
        b.set_receiver(got.append)
        frame = can.Message(arbitration_id=0x123, data=b"\x01\x02", is_extended_id=False)
        a.send(frame)
        assert got == [frame] and got[0] is frame        # no copy for a receiver
        kept = c.recv(0)                                  # one without: a copy to keep
        assert kept is not None and kept is not frame and bytes(kept.data) == b"\x01\x02"
        assert a.recv(0) is None                          # not its own (receive_own off)
        c.set_filters([{"can_id": 0x7, "can_mask": 0x7FF, "extended": False}])
        a.send(frame)
        assert c.recv(0) is None and len(got) == 2        # filtered out, as python-can would
    finally:
        for x in (a, b, c):
            x.shutdown()


def test_a_bus_off_controller_neither_sends_nor_receives_until_restarted(
        request: pytest.FixtureRequest) -> None:
    a, b = DirectBus(channel=request.node.name), DirectBus(channel=request.node.name)
    try:
        got: list[can.Message] = []
        b.set_receiver(got.append)
        a.wire.inject(BusFault.BUS_OFF)
        assert [decode_error_frame(f.arbitration_id, f.data).state for f in got] == [
            ControllerState.BUS_OFF]
        assert a.state is can.BusState.ERROR
        with pytest.raises(can.CanOperationError, match="bus-off"):
            a.send(can.Message(arbitration_id=1, data=b"x"))
        a.wire.inject(BusFault.RECOVER)
        a.send(can.Message(arbitration_id=1, data=b"x", is_extended_id=False))
        assert [f.is_error_frame for f in got] == [True, True, False]
        restart = decode_error_frame(got[1].arbitration_id, got[1].data)
        assert restart.state is ControllerState.ERROR_ACTIVE and restart.tx_errors == 0
    finally:
        a.shutdown()
        b.shutdown()


@pytest.mark.parametrize(("can_id", "data", "state", "tx", "rx", "text"), [
    # bus-off with the counters (can_change_state of a 6.x kernel)
    (0x240, "000000000000ff00", ControllerState.BUS_OFF, 0xFF, 0, "bus-off"),
    # controller problem: TX error-passive, counters 128/0
    (0x204, "0020000000008000", ControllerState.ERROR_PASSIVE, 128, 0, "TX error-passive"),
    # RX warning level, an older kernel without CAN_ERR_CNT
    (0x004, "0004000000000000", ControllerState.ERROR_WARNING, None, None, "RX warning level"),
    # restarted out of bus-off
    (0x100, "0000000000000000", ControllerState.ERROR_ACTIVE, None, None,
     "controller restarted"),
    # back to error-active (CAN_ERR_CRTL_ACTIVE)
    (0x204, "0040000000001000", ControllerState.ERROR_ACTIVE, 16, 0, "back to error-active"),
    # a protocol violation (form error) and bus error: no change of state
    (0x088, "0000020000000000", None, None, None, "protocol violation, bus error"),
])
def test_socketcan_error_frames_decode_from_their_bytes(
        can_id: int, data: str, state: ControllerState | None, tx: int | None, rx: int | None,
        text: str) -> None:
    rep = decode_error_frame(0x20000000 | can_id, bytes.fromhex(data)[:8])
    assert (rep.state, rep.tx_errors, rep.rx_errors) == (state, tx, rx)
    assert text in rep.what


def test_the_driver_reports_bus_off_and_recovers_the_actuators_at_the_restart(
        dbc_file: Path, request: pytest.FixtureRequest) -> None:
    host = FakeHost()
    host.virtual_clock = True  # type: ignore[attr-defined]
    b = bus("can", interface="chcos-direct", channel=request.node.name, dbc=str(dbc_file),
            message=[{"name": "CMD", "counter": "COUNTER"}])
    drv = CanDriver(b, [device("speed", "actuator", message="CMD", signal="SPEED"),
                        device("temp", "sensor", message="STATUS", signal="TEMP")], host)
    ecu = DirectBus(channel=request.node.name)
    seen: list[can.Message] = []
    ecu.set_receiver(seen.append)
    drv.start()
    try:
        drv.write("speed", 50)
        host.advance(0.1)                                  # the cycle: 0, 20, ... 100 ms
        assert [f.data[1] for f in seen] == [50] * 6
        assert [f.data[0] & 0xF for f in seen] == [0, 1, 2, 3, 4, 5]   # its counter
        ecu.wire.inject(BusFault.BUS_OFF)
        assert {d for d, _ in host.failures} == {"speed", "temp"}
        assert drv.status().bus_state.state == "bus-off"
        host.advance(0.1)
        assert sum(not f.is_error_frame for f in seen) == 6   # nothing left while bus-off
        ecu.wire.inject(BusFault.RECOVER)
        assert host.recoveries == ["speed"]                 # the sensor: with its next frame
        ecu.send(can.Message(arbitration_id=256, data=b"\x2A", is_extended_id=False))
        assert host.recoveries == ["speed", "speed", "temp"] and host.values("temp") == [42]
        host.advance(0.02)
        assert seen[-1].data[1] == 50 and not seen[-1].is_error_frame   # the cycle goes on
        bs = drv.status().bus_state
        assert bs is not None and bs.state == "error-active" and bs.bus_offs == 1
        assert bs.restarts == 1
    finally:
        drv.stop()
        ecu.shutdown()


def test_real_time_cycles_go_through_pythons_can_periodic_sender(
        dbc_file: Path, request: pytest.FixtureRequest) -> None:
    db = cantools.database.load_file(str(dbc_file))
    channel = request.node.name
    b = bus("can", interface="virtual", channel=channel, dbc=str(dbc_file),
            message=[{"name": "CMD", "counter": "COUNTER"}])
    host = FakeHost()
    host.virtual_clock = False  # type: ignore[attr-defined]
    drv = CanDriver(b, [device("speed", "actuator", message="CMD", signal="SPEED")], host)
    peer = can.Bus(interface="virtual", channel=channel)
    drv.start()
    try:
        drv.write("speed", 10)
        first = [peer.recv(timeout=5) for _ in range(3)]
        drv.write("speed", 20)                      # modify_data: the counter runs on
        deadline = time.monotonic() + 10
        frames = [f for f in first if f is not None]
        while time.monotonic() < deadline:
            f = peer.recv(timeout=5)
            assert f is not None
            frames.append(f)
            if db.decode_message(0x200, f.data)["SPEED"] == 20 and len(frames) > 6:
                break
        decoded = [db.decode_message(0x200, f.data) for f in frames]
        counters = [d["COUNTER"] for d in decoded]
        assert counters == [n % 16 for n in range(counters[0], counters[0] + len(counters))]
        speeds = [d["SPEED"] for d in decoded]
        assert speeds[:3] == [10, 10, 10] and speeds[-1] == 20
        assert sorted(speeds) == speeds               # 10 until the change, 20 after
    finally:
        drv.stop()
        peer.shutdown()


def test_canopen_networks_talk_over_the_direct_bus_without_a_notifier_thread(
        request: pytest.FixtureRequest) -> None:
    """The direct bus is ready for the CANopen master and nodes: canopen's Network sends
    through it and is fed by network.notify from the receiver, so an SDO upload is answered
    inside the request's send, no thread in between."""
    import canopen

    from chcos.apps.sim.canopen_slave import SERVO_EDS

    master, node_net = canopen.Network(), canopen.Network()
    buses = []
    for net in (master, node_net):
        b = DirectBus(channel=request.node.name)
        b.set_receiver(lambda m, net=net: net.notify(m.arbitration_id, bytes(m.data),
                                                     m.timestamp))
        net.bus = b
        buses.append(b)
    try:
        local = node_net.create_node(5, str(SERVO_EDS))
        local.sdo["Device type"].raw = 0x00020192
        remote = master.add_node(5, str(SERVO_EDS))
        before = threading.active_count()
        assert remote.sdo["Device type"].raw == 0x00020192
        assert threading.active_count() == before
    finally:
        for b in buses:
            b.shutdown()
