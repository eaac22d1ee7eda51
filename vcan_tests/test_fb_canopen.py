"""CANopen driver end to end against the simulated servo drive, on virtual CAN (and vcan0)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import can
import pytest

from chcos.apps.sim.canopen_slave import SERVO_EDS, CanopenSlave
from chcos.devices.spec import BusSpec
from chcos.errors import BusError
from drivers.canopen_node import CanopenDriver
from vcan_tests.netutil import unique_channel
from vcan_tests.support_fb import WAIT, FakeHost, make_device

NODE = 5


@pytest.fixture(params=["virtual", pytest.param("socketcan", marks=pytest.mark.socketcan)])
def can_link(request: pytest.FixtureRequest) -> tuple[str, str]:
    """(interface, channel): a fresh virtual channel, or vcan0 when real SocketCAN is up."""
    if request.param == "virtual":
        return "virtual", unique_channel("fb")
    from vcan_tests import uml

    return "socketcan", uml.can_channel("socketcan")


@dataclass
class Rig:
    """A slave, a driver on the same channel, and the fake host the driver reports to."""

    slave: CanopenSlave
    driver: CanopenDriver
    host: FakeHost
    interface: str
    channel: str


def bus_spec(interface: str, channel: str, **node_opts: Any) -> BusSpec:
    node = {"id": NODE, "eds": str(SERVO_EDS), **node_opts}
    return BusSpec(name="co", kind="canopen", key="bus[0]",
                   options={"interface": interface, "channel": channel, "nodes": [node],
                            "sdo_timeout": 0.1})


DEVICES = [
    make_device("pos", "sensor", "co", node=NODE, index=0x6064),          # TPDO1
    make_device("vel", "sensor", "co", node=NODE, index=0x606C),          # SDO polled
    make_device("temp", "sensor", "co", node=NODE, index=0x2000, poll_period=0.5),
    make_device("target", "actuator", "co", node=NODE, index=0x607A),     # RPDO1
    make_device("speed", "actuator", "co", node=NODE, index=0x6081),      # SDO download
]


@pytest.fixture
def rig(can_link: tuple[str, str]) -> Iterator[Rig]:
    interface, channel = can_link
    slave = CanopenSlave(NODE, channel=channel, interface=interface, heartbeat_period=0.02)
    slave.start()
    host = FakeHost()
    driver = CanopenDriver(bus_spec(interface, channel, heartbeat_timeout=0.2), DEVICES, host)
    driver.start()
    try:
        assert slave.wait_state("OPERATIONAL", WAIT), "driver did not start the node"
        yield Rig(slave, driver, host, interface, channel)
    finally:
        driver.stop()
        slave.stop()


def test_tpdo_sensor_value_is_delivered(rig: Rig) -> None:
    rig.slave.set(0x6064, 0, 1234)
    assert rig.host.wait_for(lambda h: 1234 in h.values("pos"))
    rig.slave.set(0x6064, 0, -77)
    assert rig.host.wait_for(lambda h: h.values("pos")[-1] == -77)


def test_servo_physics_reaches_target_on_virtual_time(rig: Rig) -> None:
    rig.slave.set(0x6081, 0, 1000)            # counts/s
    rig.driver.write("target", 300)
    assert rig.slave.rpdo_received.wait(WAIT)
    for _ in range(10):
        rig.slave.tick(0.1)                    # 1 s of virtual time, 100 counts per tick
    assert rig.host.wait_for(lambda h: 300 in h.values("pos"))
    # on change, plus the 100 ms event timer repeating the last value
    assert list(dict.fromkeys(rig.host.values("pos"))) == [100, 200, 300]
    assert rig.slave.get(0x6041) & 0x0400     # target reached


def test_sdo_polled_sensor_on_host_ticks(rig: Rig) -> None:
    # one poll armed per period, one period from start: vel (bus default) and temp; pos rides
    # the TPDO
    assert sorted(p.due for p in rig.host.periodics) == [0.1, 0.5]
    rig.slave.set(0x606C, 0, 4321)
    rig.host.tick(0.1)
    assert rig.driver.settle(WAIT)
    assert rig.host.values("vel") == [4321]
    assert rig.host.values("temp") == []      # not due yet
    assert sorted(p.due for p in rig.host.periodics) == [0.2, 0.5]  # taking it armed the next
    rig.host.tick(0.4)
    assert rig.driver.settle(WAIT)
    assert rig.host.values("temp") == [25]
    # vel, due at 0.2, was taken at 0.5: its successor (due at 0.3) went at once, behind it,
    # and the one after that is armed a period later; temp stays on its grid
    assert rig.host.stats.get("polls-late") == 1
    assert rig.host.values("vel") == [4321, 4321, 4321]
    assert sorted(p.due for p in rig.host.periodics) == [0.6, 1.0]


def test_actuator_writes_by_rpdo_and_by_sdo(rig: Rig) -> None:
    rig.slave.rpdo_received.clear()
    rig.driver.write("target", 2500.4)         # rounded to the INTEGER32 object
    assert rig.slave.rpdo_received.wait(WAIT)
    assert rig.slave.get(0x607A) == 2500
    rig.driver.write("speed", 777)
    assert rig.driver.settle(WAIT)
    assert rig.slave.get(0x6081) == 777


def test_write_out_of_range_and_to_unknown_device_are_reported(rig: Rig) -> None:
    rig.driver.write("speed", -1)              # UNSIGNED32
    rig.driver.write("pos", 1)                 # a sensor
    assert rig.driver.settle(WAIT)
    assert sorted(rig.host.error_kinds()) == ["range", "unknown-device"]
    assert rig.slave.get(0x6081) == 10000     # unchanged


def test_what_the_driver_accepts_unasked_its_check_accepts(rig: Rig) -> None:
    """CanopenDriver.accepts (Devtab's check without asking check_value) is the object's data
    type range: its ends pass check_value, a step beyond them and a fraction do not."""
    drv = rig.driver
    assert drv.accepts("speed") == (0.0, 4294967295.0, True)        # UNSIGNED32
    lo, hi, integral = drv.accepts("target")                         # INTEGER32
    assert (lo, hi, integral) == (-2147483648.0, 2147483647.0, True)
    for dev in ("speed", "target"):
        acc = drv.accepts(dev)
        assert acc is not None
        lo, hi, _ = acc
        assert drv.check_value(dev, lo) is None and drv.check_value(dev, hi) is None
        assert drv.check_value(dev, lo - 1) is not None
        assert drv.check_value(dev, hi + 1) is not None
        assert drv.check_value(dev, lo + 0.5) is not None
    assert drv.accepts("nope") is None


def test_a_boolean_object_takes_0_and_1_only() -> None:
    """A BOOLEAN object: canopen would write bool(value), so 7 would reach the node as true;
    the check refuses anything but 0, 1, False and True, naming the object, and agrees with
    the range Devtab compares first (accepted)."""
    from canopen.objectdictionary import BOOLEAN, ODVariable

    from drivers.canopen_od import accepted, value_error

    var = ODVariable("enable", 0x2100, 0)
    var.data_type = BOOLEAN
    assert accepted(var) == (0.0, 1.0, True)
    for ok in (0, 1, 0.0, 1.0, False, True):
        assert value_error(var, 0x2100, 0, ok) is None, ok
        assert var.encode_raw(bool(ok)) == bytes([int(ok)])
    for bad in (7, 2, -1, 0.5):
        why = value_error(var, 0x2100, 0, bad)
        assert why == f"expected 0 or 1 for BOOLEAN object 0x2100:00, got {bad!r}"
    assert "finite" in str(value_error(var, 0x2100, 0, float("nan")))


def test_heartbeat_loss_fails_node_devices_and_recovers(rig: Rig) -> None:
    rig.slave.stop_heartbeat()
    names = {d.name for d in DEVICES}
    assert rig.host.wait_for(lambda h: {d for d, _ in h.failures} == names)
    reason = rig.host.failed("pos")[0]
    assert f"node {NODE}" in reason and "0.2 s" in reason
    rig.slave.start_heartbeat()
    assert rig.host.wait_for(lambda h: set(h.recoveries) == names)


def test_a_heartbeat_waiting_for_the_reader_is_not_a_loss(
        rig: Rig, monkeypatch: pytest.MonkeyPatch) -> None:
    """After a stall of the process the watchdog thread may run before the reader: it has
    the reader hand over what was received first. Here the only heartbeat after a 10 s "stall"
    is the one that hand-over delivers."""
    driver = rig.driver
    events = driver._events
    state = events.nodes[NODE]
    rx = events.rx
    assert rx is not None
    handed_over: list[float] = []

    def settle(timeout: float) -> bool:
        handed_over.append(timeout)
        events.on_heartbeat(state, 5)    # the OPERATIONAL heartbeat waiting in the socket
        return True

    rig.slave.stop_heartbeat()
    monkeypatch.setattr(rx, "settle", settle)
    with state.lock:
        state.last_heartbeat -= 10.0
    events.check_heartbeats()
    assert handed_over and not state.lost
    assert rig.host.failures == []


def test_emcy_is_reported_and_fatal_codes_fail_until_reset(rig: Rig) -> None:
    rig.slave.send_emcy(0x6100, 0x01)          # software: reported, not fatal
    assert rig.host.wait_for(lambda h: h.error_kinds() == ["emcy"])
    assert f"node {NODE}" in rig.host.errors[0][2] and "Code 0x6100" in rig.host.errors[0][2]
    assert rig.host.failures == []
    rig.slave.send_emcy(0x4210, 0x08)          # temperature: fatal
    assert rig.host.wait_for(lambda h: len(h.failures) == len(DEVICES))
    assert "Temperature" in rig.host.failed("target")[0]
    rig.slave.send_emcy(0)                     # error reset
    assert rig.host.wait_for(lambda h: len(h.recoveries) == len(DEVICES))


def test_sdo_abort_fails_device_with_abort_code_and_recovers(rig: Rig) -> None:
    rig.slave.inject_sdo_abort(0x606C, 0, 0x06060000)
    rig.host.tick(0.1)
    assert rig.driver.settle(WAIT)
    reason = rig.host.failed("vel")[0]
    assert "Code 0x06060000, Access failed due to a hardware error" in reason
    assert "0x606C" in reason and "vel" in reason
    rig.slave.clear_sdo_abort(0x606C, 0)
    rig.slave.set(0x606C, 0, 9)
    rig.host.tick(0.1)
    assert rig.driver.settle(WAIT)
    assert rig.host.recoveries == ["vel"] and rig.host.values("vel") == [9]


def test_malformed_and_unknown_frames_are_reported_without_crashing(rig: Rig) -> None:
    with can.Bus(interface=rig.interface, channel=rig.channel) as raw:
        raw.send(can.Message(arbitration_id=0x180 + NODE, data=b"\x01", is_extended_id=False))
        raw.send(can.Message(arbitration_id=0x700 + 9, data=b"\x05", is_extended_id=False))
        raw.send(can.Message(arbitration_id=0x80 + NODE, data=b"\x10\x42", is_extended_id=False))
        assert rig.host.wait_for(
            lambda h: {"malformed", "unknown-node"} <= set(h.error_kinds())
            and h.error_kinds().count("malformed") == 2)
    rig.slave.set(0x6064, 0, 55)               # the driver still works
    assert rig.host.wait_for(lambda h: 55 in h.values("pos"))


def test_sdo_timeout_of_absent_node(can_link: tuple[str, str]) -> None:
    interface, channel = can_link
    bus = BusSpec(name="co", kind="canopen", key="bus[0]",
                  options={"interface": interface, "channel": channel, "sdo_timeout": 0.02,
                           "nodes": [{"id": 42, "eds": str(SERVO_EDS), "nmt_start": False}]})
    host = FakeHost()
    driver = CanopenDriver(bus, [make_device("v", "sensor", "co", node=42, index=0x606C)], host)
    driver.start()
    try:
        host.tick(0.1)
        assert driver.settle(WAIT)
        assert "No SDO response" in host.failed("v")[0] and "node 42" in host.failed("v")[0]
    finally:
        driver.stop()
    driver.stop()                              # idempotent


def test_start_rejects_invalid_options_and_bad_interface() -> None:
    bad = BusSpec(name="co", kind="canopen", key="bus[3]", options={"nodes": []})
    with pytest.raises(BusError, match=r"bus\[3\]\.nodes"):
        CanopenDriver(bad, [], FakeHost()).start()
    wrong = BusSpec(name="co", kind="canopen", key="bus[0]",
                    options={"interface": "no-such-interface", "channel": "x",
                             "nodes": [{"id": 1, "eds": str(SERVO_EDS)}]})
    with pytest.raises(BusError, match="cannot open CAN bus"):
        CanopenDriver(wrong, [], FakeHost()).start()


def test_sync_producer_runs_at_the_configured_period(can_link: tuple[str, str]) -> None:
    interface, channel = can_link
    bus = BusSpec(name="co", kind="canopen", key="bus[0]",
                  options={"interface": interface, "channel": channel, "sync_period": 0.01,
                           "nodes": [{"id": 43, "eds": str(SERVO_EDS), "nmt_start": False}]})
    driver = CanopenDriver(bus, [], FakeHost())
    with can.Bus(interface=interface, channel=channel) as raw:
        driver.start()
        try:
            syncs = 0
            while syncs < 3:
                msg = raw.recv(WAIT)
                assert msg is not None, "no SYNC within the wait"
                syncs += msg.arbitration_id == 0x80
        finally:
            driver.stop()


def test_rebooted_node_is_put_operational_again(rig: Rig) -> None:
    rig.slave.stop()
    reborn = CanopenSlave(NODE, channel=rig.channel, interface=rig.interface,
                          heartbeat_period=0.02)
    reborn.start()                             # boot-up, then PRE-OPERATIONAL heartbeats
    try:
        assert reborn.wait_state("OPERATIONAL", WAIT)
        reborn.set(0x6064, 0, 31337)
        assert rig.host.wait_for(lambda h: 31337 in h.values("pos"))
    finally:
        reborn.stop()


def test_bus_from_python_can_environment_config(monkeypatch: pytest.MonkeyPatch) -> None:
    channel = unique_channel("fbenv")
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", channel)
    bus = BusSpec(name="co", kind="canopen", key="bus[0]",
                  options={"nodes": [{"id": NODE, "eds": str(SERVO_EDS)}]})
    host = FakeHost()
    with CanopenSlave(NODE, channel=channel, heartbeat_period=0) as slave:
        driver = CanopenDriver(bus, [make_device("pos", "sensor", "co", node=NODE,
                                                 index=0x6064)], host)
        driver.start()
        try:
            assert slave.wait_state("OPERATIONAL", WAIT)
            slave.set(0x6064, 0, 8)
            assert host.wait_for(lambda h: h.values("pos") == [8])
        finally:
            driver.stop()


def test_frames_received_are_counted_by_the_time_settle_returns(
        can_link: tuple[str, str]) -> None:
    # the reader counts frames without a host call each; every settle hands the count over, so
    # the bus statistics are exact whenever the kernel looks (before virtual time moves)
    interface, channel = can_link
    seen = can.Bus(interface=interface, channel=channel)       # an independent observer
    slave = CanopenSlave(NODE, channel=channel, interface=interface, heartbeat_period=0)
    slave.start()
    host = FakeHost()
    driver = CanopenDriver(bus_spec(interface, channel, nmt_start=False),
                           [make_device("vel", "sensor", "co", node=NODE, index=0x606C)], host)
    driver.start()
    try:
        assert driver.settle(WAIT)            # the node's boot procedure (SDO) is done
        base = host.stats.get("frames", 0)
        while seen.recv(0) is not None:       # the boot-up and the boot procedure's frames
            pass
        for n in (1, 2, 3):
            host.tick(0.1)
            assert driver.settle(WAIT)
            assert host.stats.get("frames") == base + n
        slave.send_emcy(0x1000)               # a frame no job waits for: the settle counts it
        assert driver.settle(WAIT)
        assert host.stats.get("frames") == base + 4
        ids = []
        while (msg := seen.recv(0)) is not None:
            ids.append(msg.arbitration_id)
        assert ids.count(0x580 + NODE) == 3 and ids.count(0x80 + NODE) == 1
        assert len(host.values("vel")) == 3
    finally:
        driver.stop()
        slave.stop()
        seen.shutdown()
