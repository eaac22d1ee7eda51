"""Raw CAN under a flood and on a shared wire, on real SocketCAN (vcan0 inside User-Mode Linux)
against can-utils (cangen, cansend) as the independent senders (issue 38): the kernel filters keep
frames of other ids out of user space, ignore_ids keeps another protocol's ids quiet, unknown ids
are counted and reported once per period, and a frame that waited in the socket is judged by the
kernel's receive time stamp. Marked ``socketcan``: run inside the guest by
test_uml_socketcan.py::test_socketcan_suite_passes_inside_uml."""

from __future__ import annotations

import dataclasses
import logging
import re
import select
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from drivers.can_raw import CanDriver
from vcan_tests.conftest import require
from vcan_tests.support_dev import WAIT, FakeHost, bus, device
from vcan_tests.test_faults_can_frames import StampHost

pytestmark = pytest.mark.socketcan

OWN = device("S", "sensor", i=0, id=0x120, start=0, length=8, dlc=1)


@pytest.fixture
def channel() -> Iterator[str]:
    from vcan_tests import uml

    ch = uml.socketcan_channel()
    require(ch is not None, f"a SocketCAN channel: {uml.socketcan_skip_reason()}")
    for tool in ("cansend", "cangen"):
        require(shutil.which(tool), f"{tool} on PATH (apt-get install can-utils)")
    assert ch is not None
    yield ch


def run(*argv: str) -> None:
    subprocess.run(list(argv), check=True, timeout=60)


def started(host: Any, channel: str, devices: list[Any], **options: Any) -> CanDriver:
    drv = CanDriver(bus("can", interface="socketcan", channel=channel, **options), devices, host)
    drv.start()
    return drv


def test_kernel_filters_keep_a_cangen_flood_out_of_user_space(channel: str) -> None:
    """Both readers are held while cangen sends 3,000 frames of another id and cansend one of
    the cell's own: the filtered driver gets its frame and loses nothing; the unfiltered one
    has its socket buffer overflow, the kernel's drops counted as ``lost``."""
    fhost, uhost = FakeHost(), FakeHost()
    filtered = started(fhost, channel, [OWN])
    unfiltered = started(uhost, channel, [OWN], filter=False, unknown_ids="ignore")
    try:
        with filtered._rx.lock, unfiltered._rx.lock:       # neither reader drains meanwhile
            run("cangen", channel, "-I", "555", "-L", "8", "-D", "r", "-g", "0", "-n", "3000")
            run("cansend", channel, "120#2A")
        assert fhost.wait(lambda h: h.values("S") == [42])
        assert uhost.wait(lambda h: unfiltered.received + unfiltered.overrun_lost >= 3001, 30)
        assert filtered.settle(WAIT) and unfiltered.settle(WAIT)
    finally:
        filtered.stop()
        unfiltered.stop()
    assert filtered.received == 1 and filtered.overrun_lost == 0
    assert filtered.unknown_ids == 0 and "lost" not in fhost.stats and fhost.errors == []
    assert unfiltered.overrun_lost > 0
    assert unfiltered.received + unfiltered.overrun_lost == 3001
    assert uhost.stats.get("lost") == unfiltered.overrun_lost
    assert uhost.stats.get("unknown-id", 0) == unfiltered.unknown_ids > 0


def tx_packets(channel: str) -> int:
    """Frames the interface has sent (every sender on the guest's vcan)."""
    return int(Path(f"/sys/class/net/{channel}/statistics/tx_packets").read_text())


def test_a_flood_from_the_kernels_broadcast_manager_costs_the_filtered_reader_nothing(
        channel: str) -> None:
    """Four CAN_BCM cyclic jobs (the benchmark's flood, made by the guest kernel) send ids
    0x555-0x558 while cangen sends 200 of the cell's own frames, each with its sequence number:
    the filtered driver delivers every one of them, in order, receives no flood frame and
    loses none; an unfiltered python-can socket on the same wire sees the flood."""
    import can

    from tools.bench_can_flood import BcmFlood

    host = FakeHost()
    drv = started(host, channel, [OWN])
    spy = can.Bus(interface="socketcan", channel=channel)
    try:
        before = tx_packets(channel)
        with BcmFlood(channel, jobs=4, interval_us=1000, first_id=0x555):
            run("cangen", channel, "-I", "120", "-L", "1", "-D", "i", "-g", "2", "-n", "200")
            assert host.wait(lambda h: len(h.values("S")) >= 200, 30)
        sent = tx_packets(channel) - before
        seen = {m.arbitration_id for m in iter(lambda: spy.recv(0), None)}
        assert drv.settle(WAIT)
    finally:
        spy.shutdown()
        drv.stop()
    assert host.values("S") == list(range(200))
    assert drv.received == 200 and drv.overrun_lost == 0 and drv.unknown_ids == 0
    assert sent > 200 and seen & {0x555, 0x556, 0x557, 0x558}
    assert "lost" not in host.stats and host.errors == []


def test_a_shared_wire_with_ignore_ids_warns_once_per_period_about_the_rest(
        channel: str, caplog: pytest.LogCaptureFixture) -> None:
    """CANopen heartbeats and SYNC on the same wire (ignore_ids) are never warned about; 400
    frames of an id nobody owns give a couple of aggregated warnings whose counts add up, not
    400 lines, and no bus error (the run stays healthy unless unknown_ids = "fail")."""
    caplog.set_level(logging.WARNING, logger="chcos.drivers.can")
    host = FakeHost()
    drv = started(host, channel, [OWN], filter=False, ignore_ids=["0x700-0x77F", 0x80])
    try:
        run("cangen", channel, "-I", "705", "-L", "1", "-D", "05", "-g", "0", "-n", "100")
        run("cangen", channel, "-I", "080", "-L", "0", "-g", "0", "-n", "100")
        run("cangen", channel, "-I", "555", "-L", "2", "-g", "0", "-n", "400")
        run("cansend", channel, "120#07")
        assert host.wait(lambda h: h.values("S") == [7])
        assert drv.settle(WAIT)
    finally:
        drv.stop()
    # every frame is accounted for (the kernel may drop some if the guest falls behind)
    assert drv.received == drv.ignored_ids + drv.unknown_ids + 1
    assert drv.received + drv.overrun_lost == 601
    assert drv.ignored_ids > 0 and drv.unknown_ids > 0
    counts = [int(m.group(1)) for r in caplog.records
              if (m := re.search(r"unknown-id: (\d+) frame\(s\)", r.getMessage()))]
    assert sum(counts) == drv.unknown_ids and 1 <= len(counts) < 20
    assert all("0x7" not in r.getMessage() for r in caplog.records)
    assert "unknown-id" not in host.error_kinds()     # warned, not a bus error


def test_a_frame_that_waited_in_the_socket_is_judged_by_its_kernel_time_stamp(
        channel: str) -> None:
    """cansend's frames sit 0.4 s in the socket (the reader held, as a stalled process would
    be): the sensor with stale_after 0.2 s does not get them as fresh readings (counted
    stale-on-arrival); one without stale_after gets its frame with the kernel's receive time
    (0.4 s old), not the time the reader took it."""
    host = StampHost(virtual=False)
    devs = [dataclasses.replace(OWN, stale_after=0.2),
            device("Free", "sensor", i=1, id=0x121, start=0, length=8, dlc=1)]
    drv = started(host, channel, devs)
    try:
        with drv._rx.lock:
            run("cansend", channel, "120#01")
            run("cansend", channel, "121#02")
            time.sleep(0.4)                 # the fault: a reader 0.4 s late
        assert host.wait(lambda h: h.values("Free"))
        run("cansend", channel, "120#03")
        assert host.wait(lambda h: h.values("S"))
    finally:
        drv.stop()
    assert host.values("S") == [3] and host.values("Free") == [2]
    assert drv.stale_on_arrival == {"S": 1} and host.stats.get("stale-on-arrival") == 1
    late = [now - at for at, now in host.stamps if at is not None]
    assert len(late) == 2 and late[0] >= 0.4 and late[1] < late[0]


def take_within(receiver: Any, sock: Any, n: int) -> list[Any]:
    """Up to ``n`` frames from ``receiver``, waiting on ``sock`` (select) at most WAIT s."""
    got: list[Any] = []
    deadline = time.monotonic() + WAIT
    while len(got) < n and select.select([sock], [], [], max(0.0, deadline - time.monotonic()))[0]:
        while len(got) < n and (msg := receiver.take()) is not None:
            got.append(msg)
    return got


FRAMES = ("120#2A", "1ABCDE01#0102030405060708", "121#R", "7FF#")


def test_frames_taken_off_the_socket_match_python_cans_own_receive(channel: str) -> None:
    """The driver's receive (SocketcanReceive: recvmsg without select, the drop count from
    each frame's ancillary data) gives the frames python-can's own recv gives for the same
    frames from cansend - ids, extended and remote flags, data, length - with the kernel's
    wall-clock stamp, and a drop count of 0."""
    import can

    from drivers.canbus import SocketcanReceive

    ours = can.Bus(interface="socketcan", channel=channel)
    ref = can.Bus(interface="socketcan", channel=channel)
    try:
        receiver = SocketcanReceive(ours)
        assert receiver.take() is None                    # nothing queued: None, no wait
        for frame in FRAMES:
            run("cansend", channel, frame)
        want = [ref.recv(WAIT) for _ in FRAMES]
        got = take_within(receiver, ours.socket, len(FRAMES))
    finally:
        ours.shutdown()
        ref.shutdown()
    assert None not in want and len(got) == len(FRAMES)
    assert [(m.arbitration_id, m.is_extended_id, m.is_remote_frame, bytes(m.data), m.dlc)
            for m in got] == [(m.arbitration_id, m.is_extended_id, m.is_remote_frame,
                               bytes(m.data), m.dlc) for m in want if m is not None]
    assert [m.timestamp for m in got] == [m.timestamp for m in want if m is not None]
    assert receiver.drops == 0


def test_the_drop_count_rides_on_the_frames_after_an_overrun(channel: str) -> None:
    """A socket nobody reads overflows under cangen; the frame queued after the reader made
    room carries the kernel's drop count, the count the socket reports (SO_MEMINFO)."""
    import can

    from drivers.canbus import SocketcanReceive, socket_drops

    bus = can.Bus(interface="socketcan", channel=channel)
    try:
        receiver = SocketcanReceive(bus)
        run("cangen", channel, "-I", "555", "-L", "8", "-g", "0", "-n", "3000")
        while receiver.take() is not None:               # the frames the buffer held
            pass
        dropped = socket_drops(bus.socket)
        assert dropped is not None and dropped > 0
        run("cansend", channel, "120#01")
        got = take_within(receiver, bus.socket, 1)
    finally:
        bus.shutdown()
    assert [m.arbitration_id for m in got] == [0x120]
    assert receiver.drops == dropped
