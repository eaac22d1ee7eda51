"""Raw CAN faults on python-can's virtual bus (issue 38): multiplexed DBC messages, malformed
frames failing their sensors after a bound, readings judged by their frame's receive time stamp,
ids of no device on a shared wire (ignore_ids, unknown_ids, aggregated warnings), the receive
filters, and what ``check`` refuses (counters, checksums, actuators on multiplexed messages)."""

from __future__ import annotations

import dataclasses
import logging
import re
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import cantools
import pytest

from chcos.devices.entry import DeviceStatus
from chcos.kernel.clock import RealClock, VirtualClock
from chcos.system.embedded import System
from drivers.can_raw import CanDriver
from drivers.canbus import NOTHING, can_filters, filters_admit, parse_ids
from vcan_tests.netutil import unique_channel
from vcan_tests.support_dev import FakeHost, bus, device
from vcan_tests.support_faults import wait_until

MUX_DBC = """VERSION ""

NS_ :

BS_:

BU_: PLC Sensor

BO_ 1024 Mux: 4 Sensor
 SG_ Sel M : 0|8@1+ (1,0) [0|255] "" PLC
 SG_ A m0 : 8|16@1+ (0.1,0) [0|6553.5] "C" PLC
 SG_ B m1 : 8|16@1- (1,0) [-32768|32767] "" PLC
 SG_ Common : 24|8@1+ (1,0) [0|255] "" PLC

BO_ 1025 Plain: 2 Sensor
 SG_ P : 0|16@1+ (1,0) [0|65535] "" PLC

BO_ 1026 MuxCmd: 4 PLC
 SG_ Page M : 0|8@1+ (1,0) [0|255] "" Sensor
 SG_ X m0 : 8|16@1+ (1,0) [0|65535] "" Sensor
"""


class StampHost(FakeHost):
    """A FakeHost that says which clock it runs on and records each delivery's receive time
    (``deliver_many(readings, at=...)``, as Devtab takes it); ``now`` is the real monotonic
    clock unless the clock is virtual."""

    def __init__(self, virtual: bool) -> None:
        super().__init__()
        self.virtual_clock = virtual
        self.stamps: list[tuple[float | None, float]] = []   # (at, now at delivery)

    def deliver_many(self, readings: list[tuple[str, Any]], at: float | None = None) -> None:
        now = self.now()
        with self._cond:
            self.stamps.append((at, now))
        for d, v in readings:
            self.deliver(d, v)

    def now(self) -> float:
        return self.clock if self.virtual_clock else time.monotonic()


@pytest.fixture
def mux_dbc(tmp_path: Path) -> Path:
    path = tmp_path / "mux.dbc"
    path.write_text(MUX_DBC, encoding="utf-8")
    return path


@pytest.fixture
def channel() -> Iterator[str]:
    yield unique_channel("canfault")


def start(host: FakeHost, channel: str, devices: list[Any], **options: Any) -> CanDriver:
    drv = CanDriver(bus("can", interface="virtual", channel=channel, **options), devices, host)
    drv.start()
    return drv


# -- multiplexed messages ----------------------------------------------------------------------


def test_a_multiplexed_signal_takes_its_value_only_from_frames_that_select_it(
        mux_dbc: Path, channel: str) -> None:
    db = cantools.database.load_file(str(mux_dbc))
    mux = db.get_message_by_name("Mux")
    host = FakeHost()
    devs = [device("A", "sensor", i=0, message="Mux", signal="A"),
            device("B", "sensor", i=1, message="Mux", signal="B"),
            device("Common", "sensor", i=2, message="Mux", signal="Common")]
    drv = start(host, channel, devs, dbc=str(mux_dbc))
    peer = can.Bus(interface="virtual", channel=channel)
    try:
        for sel, val, common in ((0, 12.5, 1), (1, -7, 2), (0, 30.0, 3), (1, 9, 4)):
            data = mux.encode({"Sel": sel, "A" if sel == 0 else "B": val, "Common": common})
            peer.send(can.Message(arbitration_id=0x400, data=data, is_extended_id=False))
        # a multiplexer value the DBC does not list: counted, no error, no failure
        peer.send(can.Message(arbitration_id=0x400, data=b"\x05\x00\x00\x00",
                              is_extended_id=False))
        assert drv.settle(5.0)
        assert host.wait(lambda h: len(h.values("Common")) == 4)
    finally:
        drv.stop()
        peer.shutdown()
    assert host.values("A") == [pytest.approx(12.5), pytest.approx(30.0)]
    assert host.values("B") == [-7, 9]
    assert host.values("Common") == [1, 2, 3, 4]
    assert host.errors == [] and host.failures == []
    assert host.stats.get("unknown-mux") == 1


def test_check_refuses_an_actuator_on_a_multiplexed_message_and_counters(
        mux_dbc: Path) -> None:
    b = bus("can", interface="virtual", channel="x", dbc=str(mux_dbc))
    errs = CanDriver.check_device(b, device("X", "actuator", message="MuxCmd", signal="X"))
    assert len(errs) == 1 and errs[0].startswith("device[0].address.message: MuxCmd is "
                                                 "multiplexed")
    assert CanDriver.check_device(b, device("A", "sensor", message="Mux", signal="A")) == []
    errs = CanDriver.check_device(b, device("P", "actuator", message="Plain", signal="P",
                                            counter="P"))
    assert len(errs) == 1 and errs[0].startswith("device[0].address.counter: unknown key: a "
                                                 "rolling counter or a checksum is declared "
                                                 "per message, in the bus's [[bus.message]]")
    errs = CanDriver.check_bus(bus("can", interface="virtual", channel="x",
                                   crc={"signal": "P", "kind": "xor"}))
    assert len(errs) == 1 and errs[0].startswith("bus[0].crc: unknown option for a can bus: a "
                                                 "rolling counter or a checksum is declared "
                                                 "per message")


# -- malformed frames ------------------------------------------------------------------------


def test_malformed_frames_fail_the_sensors_after_the_bound_and_a_good_frame_recovers(
        channel: str) -> None:
    host = FakeHost()
    devs = [device("S", "sensor", i=0, id=0x120, start=0, length=16, dlc=2),
            device("Other", "sensor", i=1, id=0x121, start=0, length=8, dlc=1)]
    drv = start(host, channel, devs)
    peer = can.Bus(interface="virtual", channel=channel)

    def send(fid: int, data: bytes) -> None:
        peer.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
        assert drv.settle(5.0)

    try:
        send(0x120, b"\x01\x00")
        send(0x121, b"\x09")
        send(0x120, b"\x01")                 # wrong length, twice: within the bound
        send(0x120, b"\x01\x02\x03")
        assert host.failures == []
        send(0x121, b"\x08")                 # another message's frames do not reset it
        send(0x120, b"")                      # the third in a row: S fails, with the reason
        assert host.wait(lambda h: h.failures)
        assert [d for d, _ in host.failures] == ["S"]
        assert "3 malformed frame(s) of raw_0x120 in a row" in host.failures[0][1]
        assert "wrong-length" in host.failures[0][1]
        send(0x120, b"\x07")                 # more: still one failure, each counted
        send(0x120, b"\x05\x00")
        assert host.wait(lambda h: h.recoveries == ["S"])
    finally:
        drv.stop()
        peer.shutdown()
    assert host.values("S") == [1, 5] and host.values("Other") == [9, 8]
    assert [d for d, _ in host.failures] == ["S"]
    assert host.error_kinds() == ["wrong-length"] * 4


# -- receive time stamps ---------------------------------------------------------------------


def test_a_frame_older_than_stale_after_on_arrival_is_counted_not_delivered(
        channel: str) -> None:
    host = StampHost(virtual=False)
    spec = device("S", "sensor", i=0, id=0x130, start=0, length=8, dlc=1)
    devs = [dataclasses.replace(spec, stale_after=0.2),
            device("Free", "sensor", i=1, id=0x131, start=0, length=8, dlc=1)]
    drv = start(host, channel, devs)
    # the peer sets each frame's time stamp itself (python-can's virtual bus keeps it)
    peer = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    try:
        old = time.time() - 1.0
        peer.send(can.Message(arbitration_id=0x130, data=b"\x01", timestamp=old,
                              is_extended_id=False))
        peer.send(can.Message(arbitration_id=0x131, data=b"\x02", timestamp=old,
                              is_extended_id=False))
        peer.send(can.Message(arbitration_id=0x130, data=b"\x03", timestamp=time.time(),
                              is_extended_id=False))
        assert drv.settle(5.0)
        assert host.wait(lambda h: h.values("S"))
    finally:
        drv.stop()
        peer.shutdown()
    assert host.values("S") == [3]            # the 1 s old one was not delivered as fresh
    assert host.values("Free") == [2]         # no stale_after: delivered, stamped as old
    assert drv.stale_on_arrival == {"S": 1} and host.stats.get("stale-on-arrival") == 1
    ats = sorted(host.stamps, key=lambda s: s[0] or 0.0)
    old_at, old_now = ats[0]
    assert old_at is not None and 0.9 < old_now - old_at < 30     # its receive time, not now
    new_at, new_now = ats[-1]
    assert new_at is not None and 0 <= new_now - new_at < old_now - old_at


def test_on_a_virtual_clock_readings_are_stamped_now_whatever_the_frame_says(
        channel: str) -> None:
    host = StampHost(virtual=True)
    devs = [dataclasses.replace(device("S", "sensor", id=0x130, start=0, length=8, dlc=1),
                                stale_after=0.2)]
    drv = start(host, channel, devs)
    peer = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    try:
        peer.send(can.Message(arbitration_id=0x130, data=b"\x01", timestamp=time.time() - 5,
                              is_extended_id=False))
        assert drv.settle(5.0)
        assert host.wait(lambda h: h.values("S"))
    finally:
        drv.stop()
        peer.shutdown()
    assert host.stamps == [(None, 0.0)] and drv.stale_on_arrival == {}


MEM_MAP = """
[[bus]]
name = "mem"
kind = "memory"

[[device]]
name = "S"
direction = "sensor"
bus = "mem"
stale_after = 0.5
"""


def test_devtab_judges_staleness_from_the_receive_time_it_is_given(tmp_path: Path) -> None:
    path = tmp_path / "mem.toml"
    path.write_text(MEM_MAP, encoding="utf-8")
    s = System([path], clock=VirtualClock(), machines=[0], map_path=tmp_path / "sysfile.map")
    dt = s.devtab
    s.run_for(0.3)
    dt.deliver_many([("S", 1.0)], at=0.25)     # received at 0.25: stale from 0.75 on
    s.run_for(0.4)                              # t = 0.7
    assert dt.get("S").status is DeviceStatus.OK and dt.get("S").rx_at == pytest.approx(0.25)
    s.run_for(0.1)                              # t = 0.8
    assert dt.get("S").status is DeviceStatus.STALE
    dt.deliver("S", 2.0, at=99.0)               # a time after now is taken as now
    s.run_for(0.1)
    assert dt.get("S").status is DeviceStatus.OK and dt.get("S").rx_at == pytest.approx(0.8)


# -- shared wires: ids of no device ----------------------------------------------------------


def unknown_lines(caplog: pytest.LogCaptureFixture) -> list[int]:
    """The counts of the aggregated unknown-id warnings logged so far."""
    return [int(m.group(1)) for r in caplog.records
            if (m := re.search(r"unknown-id: (\d+) frame\(s\)", r.getMessage()))]


@pytest.mark.parametrize("policy", ["warn", "fail", "ignore"])
def test_unknown_ids_are_counted_aggregated_and_ignored_ids_never_warned(
        channel: str, policy: str, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="chcos.drivers.can")
    host = FakeHost()
    devs = [device("S", "sensor", i=0, id=0x120, start=0, length=8, dlc=1)]
    drv = start(host, channel, devs, filter=False, unknown_ids=policy,
                ignore_ids=["0x700-0x77F", 0x80])
    peer = can.Bus(interface="virtual", channel=channel)
    try:
        for k in range(300):
            for fid, data in ((0x700 + k % 0x80, b"\x05"),      # heartbeats
                              (0x80, b""),                       # SYNC
                              (0x555, b"\x01")):                 # nobody's
                peer.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
        peer.send(can.Message(arbitration_id=0x120, data=b"\x2a", is_extended_id=False))
        assert drv.settle(5.0)
        assert host.wait(lambda h: h.values("S") == [42])
    finally:
        drv.stop()                                  # reports what is still pending
        peer.shutdown()
    assert drv.ignored_ids == 600 and drv.unknown_ids == 300
    assert host.stats.get("ignored-id") == 600 and host.stats.get("unknown-id") == 300
    lines = unknown_lines(caplog)
    if policy == "warn":
        assert host.errors == [] and sum(lines) == 300 and len(lines) < 30
    elif policy == "fail":
        assert lines == [] and {k for _, k, _ in host.errors} == {"unknown-id"}
        assert sum(int(re.findall(r"^(\d+) frame", d)[0]) for _, _, d in host.errors) == 300
        assert len(host.errors) < 30 and "0x555" in host.errors[0][2]
    else:
        assert host.errors == [] and lines == []


def test_with_filters_frames_of_no_device_never_reach_the_driver(
        channel: str, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="chcos.drivers.can")
    host = FakeHost()
    devs = [device("S", "sensor", i=0, id=0x120, start=0, length=8, dlc=1),
            device("E", "sensor", i=1, id=0x18FF0001, extended=True, start=0, length=8, dlc=1),
            device("Cmd", "actuator", i=2, id=0x200, start=0, length=8, dlc=1)]
    drv = start(host, channel, devs)
    assert drv.filters is not None
    peer = can.Bus(interface="virtual", channel=channel)
    try:
        for k in range(200):
            peer.send(can.Message(arbitration_id=0x555 + k % 7, data=b"\x01",
                                  is_extended_id=False))
            peer.send(can.Message(arbitration_id=0x120, data=b"\x01", is_extended_id=True))
            peer.send(can.Message(arbitration_id=0x200, data=b"\x01",   # an actuator's id
                                  is_extended_id=False))
        peer.send(can.Message(arbitration_id=0x120, data=b"\x2a", is_extended_id=False))
        peer.send(can.Message(arbitration_id=0x18FF0001, data=b"\x07", is_extended_id=True))
        assert drv.settle(5.0)
        assert host.wait(lambda h: h.values("S") and h.values("E"))
    finally:
        drv.stop()
        peer.shutdown()
    assert drv.received == 2 and drv.unknown_ids == 0
    assert host.values("S") == [42] and host.values("E") == [7]
    assert host.errors == [] and unknown_lines(caplog) == []


# -- filters and options -----------------------------------------------------------------------


def test_can_filters_are_exact_for_few_ids_and_compact_for_many() -> None:
    f = can_filters([0x120, 0x7FF], [0x18FF0001])
    assert f == [{"can_id": 0x120, "can_mask": 0x7FF, "extended": False},
                 {"can_id": 0x7FF, "can_mask": 0x7FF, "extended": False},
                 {"can_id": 0x18FF0001, "can_mask": 0x1FFFFFFF, "extended": True}]
    assert not filters_admit(f, 0x120, True) and filters_admit(f, 0x120, False)
    ids = list(range(0x181, 0x1FF)) + list(range(0x581, 0x5FF)) + [0x700 + n for n in (1, 5, 9)]
    f = can_filters(ids, limit=8)
    assert len(f) <= 8
    assert all(filters_admit(f, i, False) for i in ids)
    admitted = sum(filters_admit(f, i, False) for i in range(0x800))
    assert admitted < 2 * len(ids)               # a few neighbours let through, not everything
    assert can_filters([]) == [NOTHING]
    with pytest.raises(ValueError, match="0x800"):
        can_filters([0x800])


def test_check_names_bad_shared_wire_options_and_a_device_in_ignore_ids() -> None:
    errs = CanDriver.check_bus(bus("can", interface="virtual", channel="x", filter="yes",
                                   unknown_ids="loud", ignore_ids=["0x700-0x6FF", 0x80, "x"]))
    assert errs == [
        "bus[0].filter: expected true or false, got 'yes'",
        "bus[0].ignore_ids[0]: expected a CAN id 0..0x1FFFFFFF or a range \"LO-HI\" with "
        "LO <= HI, got '0x700-0x6FF'",
        "bus[0].ignore_ids[2]: expected a CAN id 0..0x1FFFFFFF or a range \"LO-HI\" with "
        "LO <= HI, got 'x'",
        "bus[0].unknown_ids: expected one of ignore, warn, fail, got 'loud'"]
    assert parse_ids(["0x700-0x77F", 0x80], "k") == ([(0x700, 0x77F), (0x80, 0x80)], [])
    b = bus("can", interface="virtual", channel="x", ignore_ids=["0x700-0x77F"])
    devs = [device("S", "sensor", i=0, id=0x701, start=0, length=8),
            device("T", "sensor", i=1, id=0x101, start=0, length=8)]
    found = CanDriver.check_devices(b, devs)
    assert [(d.name, why) for d, why in found] == [
        ("S", "device[0].address: id 0x701 is in bus[0].ignore_ids: the device's frames "
              "would be ignored")]


CAN_MAP = """
[[bus]]
name = "can0"
kind = "can"
interface = "virtual"
channel = "{channel}"
filter = false
unknown_ids = "{policy}"

[[device]]
name = "S"
direction = "sensor"
bus = "can0"
stale_after = 0.3
address = {{ id = 0x120, start = 0, length = 8, dlc = 1 }}
"""


@pytest.mark.parametrize("policy", ["warn", "fail"])
def test_in_a_running_system_late_frames_are_not_fresh_and_unknown_ids_fail_only_if_told(
        tmp_path: Path, channel: str, policy: str) -> None:
    """The driver and Devtab together on the real clock: a frame received 1 s ago is counted
    stale-on-arrival in the bus statistics and the sensor has no reading from it; a fresh one
    is read with its receive time; an id of no device is a bus error (what makes ``chcos run``
    unhealthy) only with ``unknown_ids = "fail"``."""
    path = tmp_path / "can.toml"
    path.write_text(CAN_MAP.format(channel=channel, policy=policy), encoding="utf-8")
    s = System([path], clock=RealClock(), machines=[0], map_path=tmp_path / "sysfile.map")
    peer = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    s.start()
    try:
        dt = s.devtab

        def counts() -> dict[str, int]:
            st = s.call(lambda: dt.bus_stats.get("can0"))
            return {} if st is None else dict(st.counts)

        peer.send(can.Message(arbitration_id=0x120, data=b"\x01", is_extended_id=False,
                              timestamp=time.time() - 1.0))
        peer.send(can.Message(arbitration_id=0x555, data=b"\x01", is_extended_id=False,
                              timestamp=time.time()))
        assert wait_until(lambda: counts().get("unknown-id") == 1), "the unknown id counted"
        assert counts()["stale-on-arrival"] == 1 and s.call(lambda: dt.get("S").readings) == 0
        if policy == "fail":       # what chcos run's health reads
            assert wait_until(lambda: "can0" in s.call(lambda: dt.last_bus_error)), "the bus error"
            assert s.call(lambda: dt.last_bus_error["can0"]).startswith(
                "unknown-id: 1 frame(s) with an id of no device")
        else:                      # counted at once when reported, so none is coming
            assert s.call(lambda: dict(dt.bus_errors)) == {}
        sent = time.time()
        peer.send(can.Message(arbitration_id=0x120, data=b"\x02", is_extended_id=False,
                              timestamp=sent))
        assert wait_until(lambda: s.call(lambda: dt.get("S").readings) == 1), "the fresh reading"
        e = s.call(lambda: dt.get("S"))
        now = s.call(s.kernel.clock.now)
        assert e.value == 2 and e.rx_at is not None
        assert 0 <= now - e.rx_at <= time.time() - sent + 0.05
    finally:
        peer.shutdown()
        s.shutdown()


def test_import_dbc_leaves_out_a_multiplexed_message_chcos_would_send_and_checks_clean(
        mux_dbc: Path, tmp_path: Path) -> None:
    from chcos.devices.devmap import check
    from chcos.devices.importers.dbc import import_dbc
    from chcos.devices.importers.draft import render

    draft = import_dbc(mux_dbc, node="PLC", dbc_ref="mux.dbc", interface="virtual",
                       channel="x")
    out = tmp_path / "mux.toml"
    out.write_text(render(draft), encoding="utf-8")
    text = out.read_text(encoding="utf-8")
    assert "MuxCmd (0x402) is multiplexed: not imported" in text
    devmap, errors, _warnings = check(out)
    assert errors == [] and devmap is not None
    assert {d.name: d.direction for d in devmap.devices} == {
        "sel": "sensor", "a": "sensor", "b": "sensor", "common": "sensor", "p": "sensor"}
