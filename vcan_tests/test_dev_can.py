"""Raw CAN driver end to end against the simulated CAN device, on the virtual bus (and vcan0)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from chcos.apps.sim.can_device import CanDeviceSim
from drivers.base import Driver
from drivers.can_raw import CanDriver
from drivers.codecs.can import CanCodec, Decoded
from vcan_tests.netutil import unique_channel
from vcan_tests.support_dev import CELL_DBC, WAIT, FakeHost, bus, device


@pytest.fixture(params=["virtual", pytest.param("socketcan", marks=pytest.mark.socketcan)])
def can_iface(request: pytest.FixtureRequest) -> tuple[str, str]:
    """(interface, channel): a fresh virtual channel, or the SocketCAN channel UML provides."""
    if request.param == "virtual":
        return "virtual", unique_channel("dev")
    from vcan_tests import uml

    return "socketcan", uml.can_channel("socketcan")


DEVICES = [
    device("T1", "sensor", i=0, message="Temps", signal="T1"),
    device("T2", "sensor", i=1, message="Temps", signal="T2"),
    device("Door", "sensor", i=2, id=0x300, start=0, length=1, dlc=1),
    device("Spindle", "actuator", i=3, message="Drive", signal="Speed"),
    device("SpindleOn", "actuator", i=4, message="Drive", signal="Enable"),
]


@pytest.fixture
def rig(can_iface: tuple[str, str]) -> Iterator[tuple[CanDriver, FakeHost, CanDeviceSim]]:
    interface, channel = can_iface
    host = FakeHost()
    drv = CanDriver(bus("can", interface=interface, channel=channel, dbc=str(CELL_DBC)),
                    DEVICES, host)
    sim = CanDeviceSim(CELL_DBC, interface=interface, channel=channel)
    drv.start()
    try:
        yield drv, host, sim
    finally:
        drv.stop()
        sim.close()


def test_sensor_frames_are_decoded_and_delivered(rig: Any) -> None:
    drv, host, sim = rig
    sim.set("Temps", T1=21.5, T2=-3.2)
    sim.send("Temps")
    sim.send_raw(0x300, b"\x01")
    assert host.wait(lambda h: h.values("T2") and h.values("Door"))
    assert host.values("T1") == [pytest.approx(21.5)]
    assert host.values("T2") == [pytest.approx(-3.2)]
    assert host.values("Door") == [1]
    assert host.errors == [] and drv.received == 2


def test_actuator_write_keeps_other_signals_of_the_message(rig: Any) -> None:
    drv, _host, sim = rig
    drv.write("Spindle", 1200)
    assert sim.wait_for("Drive", "Speed", lambda v: v == 1200, WAIT)
    assert sim.value("Drive", "Enable") == 0
    drv.write("SpindleOn", 1)
    assert sim.wait_for("Drive", "Enable", lambda v: v == 1, WAIT)
    assert sim.value("Drive", "Speed") == 1200
    assert drv.settle(WAIT) and drv.sent == 2


def test_unencodable_write_is_refused_and_reported_not_a_device_failure(rig: Any) -> None:
    drv, host, sim = rig
    assert "Drive" in (drv.check_value("Spindle", 5000) or "")    # Devtab refuses it up front
    assert drv.check_value("Spindle", 100) is None
    drv.write("Spindle", 5000)                 # a driver-level write still is not sent
    assert host.wait(lambda h: h.writes)
    assert host.writes[0][0] == "Spindle" and "Drive" in host.writes[0][2]
    assert drv.settle(WAIT) and drv.sent == 0 and host.failures == []
    drv.write("Spindle", 100)
    assert sim.wait_for("Drive", "Speed", lambda v: v == 100, WAIT)
    assert host.wait(lambda h: h.writes[-1] == ("Spindle", 100, ""))


def test_filters_keep_unknown_ids_out_and_malformed_only_data_fails_the_sensors(
        rig: Any) -> None:
    drv, host, sim = rig
    sim.send_raw(0x555, b"\x01\x02")           # no device's id: the receive filter drops it
    sim.send_raw(0x101, b"\x01\x02")           # Temps is 4 bytes
    sim.send_raw(0x201, b"\x00\x00\x00\x00")   # Drive: only actuators, filtered out too
    assert host.wait(lambda h: len(h.failures) == 2)
    assert host.error_kinds() == ["wrong-length"] and "expected 4" in host.errors[0][2]
    # nothing but malformed Temps frames so far: its sensors fail at once, with the reason
    assert sorted(d for d, _ in host.failures) == ["T1", "T2"]
    assert all("only malformed frames of Temps" in why for _, why in host.failures)
    assert drv.unknown_ids == 0 and drv.received == 1
    sim.set("Temps", T1=1.0)
    sim.send("Temps")
    assert host.wait(lambda h: h.values("T1"))
    assert sorted(host.recoveries) == ["T1", "T2"]


def test_settle_returns_after_every_queued_frame_was_delivered() -> None:
    channel = unique_channel("dev")
    host = FakeHost()
    drv = CanDriver(bus("can", interface="virtual", channel=channel, dbc=str(CELL_DBC)),
                    DEVICES, host)
    with CanDeviceSim(CELL_DBC, interface="virtual", channel=channel) as sim:
        drv.start()
        try:
            for i in range(200):
                sim.set("Temps", T1=i / 10)
                sim.send("Temps")
            assert drv.settle(WAIT)
            assert len(host.values("T1")) == 200          # no waiting after settle
        finally:
            drv.stop()
    assert drv.settle(0.0)                                # stopped: trivially quiet


def test_sim_tick_sends_periodic_messages_on_its_owners_clock() -> None:
    channel = unique_channel("dev")
    host = FakeHost()
    drv = CanDriver(bus("can", interface="virtual", channel=channel, dbc=str(CELL_DBC)),
                    DEVICES, host)
    with CanDeviceSim(CELL_DBC, interface="virtual", channel=channel,
                      periods={"Temps": 0.1}) as sim:
        drv.start()
        try:
            # Temps every 0.1 s (override), Pressure every 0.05 s (DBC cycle time).
            sent = sum(sim.tick(t / 100) for t in range(0, 100))
            assert sent == 10 + 20
            assert drv.settle(WAIT)
            assert len(host.values("T1")) == 10
            assert host.errors == [] and drv.received == 10   # Pressure: no device, filtered
        finally:
            drv.stop()


def test_codec_raw_signals_share_one_message() -> None:
    devs = [device("A", "sensor", i=0, id=0x10, start=0, length=4, dlc=2),
            device("B", "sensor", i=1, id=0x10, start=8, length=8, dlc=2, signed=True)]
    codec = CanCodec(bus("can", interface="virtual", channel="x"), devs)
    import can
    result = codec.decode(can.Message(arbitration_id=0x10, data=b"\x0f\xfe",
                                      is_extended_id=False))
    assert isinstance(result, Decoded)
    assert dict(result.readings) == {"A": 15, "B": -2}


def test_driver_is_a_driver_and_check_bus_rejects_unknown_options() -> None:
    assert issubclass(CanDriver, Driver)
    errs = CanDriver.check_bus(bus("can", interface="virtual", channel="x", speed=5))
    assert errs == ["bus[0].speed: unknown option for a can bus; valid options: interface, "
                    "channel, bitrate, fd, dbc, record, poll, filter, ignore_ids, unknown_ids, "
                    "port, message"]
