"""The raw CAN driver's fast path (issue 21): a write that finds nothing queued is sent in the
caller's thread with ``timeout=0``; a bus that cannot take it at once hands it to the writer
thread, in order, and it still reaches a python-can peer; safe values after such a fallback;
stop() with writes queued; outcomes confirmed on the kernel thread applied in order."""

from __future__ import annotations

import errno
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import pytest

from chcos.devices.entry import Write
from chcos.devices.table import DeviceTable
from chcos.devices.writes import WriteTracking
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System
from chcos.user.context import TaskContext
from drivers.base import Driver
from drivers.can_raw import INLINE_INTERFACES, CanDriver
from vcan_tests.netutil import unique_channel
from vcan_tests.support_dev import WAIT, FakeHost, bus, device

M = "vcan_tests.test_dev_can_inline"
A_ID = 0x201


class GateBus:
    """A python-can bus in front of a real one: ``full`` makes a send with timeout 0 raise
    "Transmit buffer full" (as SocketCAN does); a send with a timeout (the writer thread's)
    waits for ``gate`` and first fails ``fail_writer`` times; every send is noted (thread,
    timeout, data) and ``on_inline`` runs inside a timeout-0 send."""

    def __init__(self, real: can.BusABC) -> None:
        self.real = real
        self.full = False
        self.fail_writer = 0
        self.crash_writer = 0      # the writer's next sends raise what no driver expects
        self.enobufs = 0
        self.gate = threading.Event()
        self.gate.set()
        self.waiting = threading.Event()
        self.sends: list[tuple[str, float | None, bytes, bool]] = []   # (thread, timeout, data, ok)
        self.on_inline: Any = None

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        who = threading.current_thread().name
        if timeout == 0:
            if self.on_inline is not None:
                self.on_inline()
            if self.full:
                self.sends.append((who, timeout, bytes(msg.data), False))
                raise can.CanOperationError("Transmit buffer full")
        else:
            self.waiting.set()
            assert self.gate.wait(WAIT)
            if self.enobufs > 0:       # SocketCAN's full interface queue; python-can gives up
                self.enobufs -= 1
                self.sends.append((who, timeout, bytes(msg.data), False))
                raise can.CanOperationError("Failed to transmit: No buffer space available",
                                            errno.ENOBUFS)
            if self.crash_writer > 0:
                self.crash_writer -= 1
                self.sends.append((who, timeout, bytes(msg.data), False))
                raise RuntimeError("a bug under the driver")
            if self.fail_writer > 0:
                self.fail_writer -= 1
                self.sends.append((who, timeout, bytes(msg.data), False))
                raise can.CanOperationError("Failed to transmit: No buffer space available")
        self.sends.append((who, timeout, bytes(msg.data), True))
        self.real.send(msg, timeout)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.real, name)


def value_data(v: int) -> bytes:
    return v.to_bytes(2, "little")


@pytest.fixture(params=["virtual", pytest.param("socketcan", marks=pytest.mark.socketcan)])
def can_iface(request: pytest.FixtureRequest) -> tuple[str, str]:
    """(interface, channel): a fresh virtual channel, or the SocketCAN channel UML provides."""
    if request.param == "virtual":
        return "virtual", unique_channel("inline")
    from vcan_tests import uml

    return "socketcan", uml.can_channel("socketcan")


@pytest.fixture
def rig(can_iface: tuple[str, str]) -> Iterator[tuple[CanDriver, FakeHost, GateBus, can.BusABC]]:
    interface, channel = can_iface
    host = FakeHost()
    peer = can.Bus(interface=interface, channel=channel)
    drv = CanDriver(bus("can", interface=interface, channel=channel),
                    [device("A", "actuator", id=A_ID, start=0, length=16, dlc=2)], host)
    drv.start()
    assert drv._bus is not None
    gate = GateBus(drv._bus)
    drv._bus = gate
    try:
        yield drv, host, gate, peer
    finally:
        gate.gate.set()
        drv.stop()
        peer.shutdown()


def received(peer: can.BusABC, n: int) -> list[bytes]:
    """The data of the next ``n`` frames the peer receives (each within WAIT)."""
    out = []
    for _ in range(n):
        msg = peer.recv(WAIT)
        assert msg is not None, f"peer received {out} and then nothing"
        assert msg.arbitration_id == A_ID
        out.append(bytes(msg.data))
    return out


def test_fast_path_is_the_documented_set_and_a_record_bus_keeps_the_writer(
        tmp_path: Path) -> None:
    assert {"virtual", "socketcan"} == INLINE_INTERFACES
    drv = CanDriver(bus("can", interface="virtual", channel=unique_channel("rec"),
                        record=str(tmp_path / "s.log")),
                    [device("A", "actuator", id=A_ID, start=0, length=16, dlc=2)], FakeHost())
    drv.start()
    try:
        assert drv._inline is False
    finally:
        drv.stop()


def test_a_write_is_sent_and_confirmed_in_the_callers_thread(rig: Any) -> None:
    drv, host, gate, peer = rig
    assert drv._inline
    drv.write("A", 7)
    # confirmed before write() returned, by this thread, without waiting
    assert host.writes == [("A", 7, "")]
    assert gate.sends == [(threading.current_thread().name, 0, value_data(7), True)]
    assert received(peer, 1) == [value_data(7)]
    assert drv.sent == drv.sent_inline == 1 and not drv.error_counts


def test_writes_queued_behind_a_busy_writer_keep_their_order(rig: Any) -> None:
    drv, host, gate, peer = rig
    gate.full = True
    gate.gate.clear()
    drv.write("A", 1)                  # bus full: to the writer, which waits at the gate
    assert gate.waiting.wait(WAIT)
    gate.full = False                  # the bus has room again, but the writer is sending
    drv.write("A", 2)
    drv.write("A", 3)
    assert host.writes == []           # queued, not sent here out of order
    gate.gate.set()
    assert drv.settle(WAIT)
    drv.write("A", 4)                  # nothing queued now: the fast path again
    assert received(peer, 4) == [value_data(v) for v in (1, 2, 3, 4)]
    me, tx = threading.current_thread().name, "can-b-tx"
    assert [(w, t > 0, d) for w, t, d, ok in gate.sends if ok] == [   # t > 0: it waits
        (tx, True, value_data(1)), (tx, True, value_data(2)), (tx, True, value_data(3)),
        (me, False, value_data(4))]
    assert host.writes == [("A", v, "") for v in (1, 2, 3, 4)]


@pytest.mark.parametrize("full", [False, True])
def test_the_writer_waits_while_the_fast_path_holds_the_send(rig: Any, full: bool) -> None:
    """A write queued by another thread meanwhile goes after the fast path's frame, also when
    that frame falls back to the writer (it goes to the front of the queue)."""
    drv, host, gate, peer = rig
    gate.full = full
    early: list[bool] = []

    def meanwhile() -> None:       # another thread writes while write 1 is in send()
        gate.on_inline = None
        t = threading.Thread(target=drv.write, args=("A", 2))
        t.start()
        t.join(WAIT)
        early.append(gate.waiting.wait(0.2))   # the writer must not start sending it now

    gate.on_inline = meanwhile
    drv.write("A", 1)
    assert early == [False]
    assert received(peer, 2) == [value_data(1), value_data(2)]
    assert drv.settle(WAIT) and host.writes == [("A", 1, ""), ("A", 2, "")]


def test_a_full_bus_hands_the_write_to_the_writer_and_reports_no_failure(rig: Any) -> None:
    drv, host, gate, peer = rig
    gate.full = True
    drv.write("A", 300)
    assert received(peer, 1) == [value_data(300)]
    assert host.wait(lambda h: h.writes)
    assert drv.settle(WAIT)
    assert host.writes == [("A", 300, "")]
    assert [(w, t > 0, ok) for w, t, _d, ok in gate.sends] == [
        (threading.current_thread().name, False, False), ("can-b-tx", True, True)]
    assert not drv.error_counts and host.errors == [] and host.failures == []
    assert (drv.sent, drv.sent_inline) == (1, 0)


def test_an_unexpected_error_fails_that_write_and_the_writer_goes_on(rig: Any) -> None:
    """Something no driver expects raised under the writer thread's send: that write is
    reported failed (and counted as an internal error), and the writer thread lives on - the
    next write is sent, not left waiting in the outbox."""
    drv, host, gate, peer = rig
    gate.full = True
    gate.crash_writer = 1
    drv.write("A", 11)
    assert host.wait(lambda h: h.writes)
    assert host.writes[0][:2] == ("A", 11) and "a bug under the driver" in host.writes[0][2]
    assert drv.error_counts["internal"] == 1
    drv.write("A", 12)
    assert received(peer, 1) == [value_data(12)]
    assert drv.settle(WAIT) and host.writes[1:] == [("A", 12, "")]


def test_the_writer_waits_out_enobufs_instead_of_failing(rig: Any) -> None:
    drv, host, gate, peer = rig
    gate.full = True
    gate.enobufs = 3
    drv.write("A", 9)
    assert received(peer, 1) == [value_data(9)]
    assert drv.settle(WAIT)
    assert host.writes == [("A", 9, "")] and host.failures == [] and not drv.error_counts
    assert [(w, ok) for w, _t, _d, ok in gate.sends] == [
        (threading.current_thread().name, False), *[("can-b-tx", False)] * 3, ("can-b-tx", True)]


def test_stop_reports_queued_writes_failed_once_each(rig: Any) -> None:
    drv, host, gate, _peer = rig
    gate.full = True
    gate.gate.clear()
    drv.write("A", 1)
    assert gate.waiting.wait(WAIT)
    drv.write("A", 2)
    drv.write("A", 3)
    stopper = threading.Thread(target=drv.stop)
    stopper.start()
    with drv._cond:
        assert drv._cond.wait_for(lambda: not drv._running, WAIT)
    gate.gate.set()                    # the frame being sent goes out; the queue does not
    stopper.join(WAIT)
    assert [(d, v, r == "") for d, v, r in host.writes] == [
        ("A", 1, True), ("A", 2, False), ("A", 3, False)]
    assert all("stopped before the write was sent" in r for _d, _v, r in host.writes[1:])


def test_a_fallback_after_stop_is_reported_failed_not_lost(rig: Any) -> None:
    drv, host, gate, _peer = rig
    gate.full = True
    gate.on_inline = drv.stop          # stop() runs to its end while the frame is in send()
    drv.write("A", 5)
    assert host.writes == [("A", 5, "can bus b stopped before the write was sent")]


DBC = """VERSION ""
NS_ :
BS_:
BU_: Node Chcos
BO_ 512 Heater: 2 Chcos
 SG_ Power : 0|16@1+ (0.1,0) [0|100] "%" Node
"""


def cellmap(tmp: Path, channel: str) -> Path:
    (tmp / "cell.dbc").write_text(DBC)
    path = tmp / "cell.toml"
    path.write_text(f"""
[[bus]]
name = "can0"
kind = "can"
interface = "virtual"
channel = "{channel}"
dbc = "cell.dbc"

[[device]]
name = "H1"
direction = "actuator"
bus = "can0"
address = {{ message = "Heater", signal = "Power" }}
safe_value = 0
units = "%"
""")
    return path


async def heat(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    """Writes H1 and notes what the device table shows right after each write."""
    for v in cmd["values"]:
        ctx.write("H1", v)
        e = cmd["devtab"].get("H1")
        cmd["seen"].append((e.value, e.pending))


@pytest.fixture
def cell(tmp_path: Path) -> Iterator[tuple[System, GateBus, can.BusABC]]:
    channel = unique_channel("inlsys")
    mapfile = cellmap(tmp_path, channel)
    peer = can.Bus(interface="virtual", channel=channel)
    s = System([mapfile], clock=VirtualClock(), machines=[0], base_dir=tmp_path)
    drv = s.devtab.drivers[0]
    assert isinstance(drv, CanDriver) and drv._bus is not None
    gate = GateBus(drv._bus)
    drv._bus = gate
    s.execute(f"install -m0o1 --code={M}:heat HT H1")
    try:
        yield s, gate, peer
    finally:
        gate.gate.set()
        s.shutdown()
        peer.shutdown()


def power(peer: can.BusABC) -> float:
    msg = peer.recv(WAIT)
    assert msg is not None and msg.arbitration_id == 512
    return int.from_bytes(msg.data[:2], "little") * 0.1


def test_a_kernel_thread_write_is_shown_written_before_the_task_goes_on(cell: Any) -> None:
    s, gate, peer = cell
    seen: list[Any] = []
    s.invoke("HT", {"values": [40.0, 50.0], "devtab": s.devtab, "seen": seen})
    s.run_for(0.01)
    assert seen == [(40.0, None), (50.0, None)]     # no interrupt round trip in between
    assert [power(peer), power(peer)] == [pytest.approx(40.0), pytest.approx(50.0)]
    assert [(t, ok) for _w, t, _d, ok in gate.sends] == [(0, True), (0, True)]


def test_an_outcome_is_counted_queued_before_its_write_leaves_the_in_flight_queue(
        cell: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """Devtab's fast path asks without a lock whether anything of the device is in flight or
    has an outcome queued: a driver thread ending a write (on the wire or failed) counts the
    queued outcome first, so at the moment it does the write is still in flight - no thread
    switch in between can show the device free too early."""
    s, gate, peer = cell
    dt = s.devtab
    seen: list[tuple[str, bool]] = []
    count = WriteTracking._queue_outcome

    def probe(self: WriteTracking, device: str) -> None:
        # the state just before the outcome is counted: the write must still be outstanding
        seen.append((threading.current_thread().name, self.outstanding(device)))
        count(self, device)

    monkeypatch.setattr(WriteTracking, "_queue_outcome", probe)
    gate.full = True                # both fast paths refuse: the writer thread sends
    gate.fail_writer = 1            # ... and fails the first command once
    s.invoke("HT", {"values": [40.0, 50.0], "devtab": dt, "seen": []})
    s.run_for(0.01)
    assert dt.drivers[0].settle(WAIT)
    s.run_for(0.01)
    # 40 failed; 50 written; the device, failed by the send error, recovers with that frame
    # and gets its safe value first thing (Devtab's recovery), written too
    assert [power(peer), power(peer)] == [pytest.approx(50.0), 0.0]
    assert seen == [("can-can0-tx", True)] * 3
    e = dt.get("H1")
    assert e.value == 0 and e.pending is None and e.write_errors == 1


def test_frames_sent_are_counted_by_the_driver_and_kept_after_it_stops(cell: Any) -> None:
    """The CAN driver counts the frames it sends itself (fast path and writer thread alike);
    the bus statistics pull them in as frames-sent, per device and in all, equal to what the
    peer received, and keep them once the driver has stopped (the shutdown's safe value too)."""
    s, gate, peer = cell
    drv = s.devtab.drivers[0]
    s.invoke("HT", {"values": [40.0, 50.0], "devtab": s.devtab, "seen": []})
    s.run_for(0.01)
    gate.full = True                       # the next one goes by the writer thread
    assert s.devtab.estop("test") == 1
    assert drv.settle(WAIT)
    s.run_for(0.01)
    got = [power(peer) for _ in range(3)]
    assert got == [pytest.approx(40.0), pytest.approx(50.0), 0.0]
    assert (drv.sent, drv.sent_inline, drv.sent_queued) == (3, 2, 1)
    st = s.devtab.bus_stats["can0"]
    assert st.counts["frames-sent"] == 3 and st.devices["H1"]["frames-sent"] == 3
    assert s.devtab.stats_doc()["can0"]["devices"]["H1"]["frames-sent"] == 3
    gate.full = False
    s.devtab.stop_drivers()               # writes the safe value once more, then stops
    assert power(peer) == 0.0
    assert not s.devtab.drivers and s.devtab.bus_stats["can0"].counts["frames-sent"] == 4
    assert (drv.sent, drv.sent_inline, drv.sent_queued) == (4, 3, 1)   # its own, unchanged
    assert s.devtab.bus_stats["can0"].devices["H1"]["frames-sent"] == 4


@pytest.mark.parametrize("on_kernel", [False, True], ids=["caller", "kernel-thread"])
def test_a_safe_value_after_a_fallback_is_retried_until_it_is_on_the_wire(
        cell: Any, on_kernel: bool) -> None:
    """From the caller's thread the estop's tracked write tries the fast path first; on the
    kernel thread the burst (Driver.write_now_many) tries before it. Either way a value that
    cannot go at once is tracked and retried by the writer thread."""
    s, gate, peer = cell
    drv = s.devtab.drivers[0]
    gate.full = True           # the fast path cannot take it ...
    gate.fail_writer = 2       # ... and the writer thread's first two attempts fail
    if on_kernel:
        s.kernel.interrupt(lambda: s.devtab.estop("test"))
    else:
        assert s.devtab.estop("test") == 1
    s.run_for(0.05)
    assert drv.settle(WAIT)
    s.run_for(0.05)
    assert power(peer) == 0.0
    e = s.devtab.get("H1")
    assert e.value == 0 and e.pending is None and s.devtab.safe_failures == []
    # (the burst's try,) the fast path's try, the writer's two failures and its success; then
    # the device's recovery writes its safe value once more (the same way: full bus, writer)
    assert [(w, ok) for w, _t, d, ok in gate.sends if d == b"\0\0"] == [
        ("MainThread", False)] * on_kernel + [
        ("MainThread", False), ("can-can0-tx", False), ("can-can0-tx", False),
        ("can-can0-tx", True), ("MainThread", False), ("can-can0-tx", True)]
    assert drv.error_counts["send"] == 2


def test_an_outcome_on_the_kernel_thread_waits_behind_one_still_queued(cell: Any) -> None:
    """Devtab's write tracking (WriteTracking, on the cell's kernel with a table of the cell's
    devices): an outcome reported on the kernel thread while an earlier one of the same device
    is still queued there is applied after it, not before."""
    s, _gate, _peer = cell
    table = DeviceTable()
    table.load(s.devmap)
    writes = WriteTracking(s.kernel, table, lambda d, why: None)
    log: list[Any] = []

    def step() -> None:        # on the kernel thread, between task steps
        writes.track(Write("H1", 10.0, 100, ""))
        writes.track(Write("H1", 20.0, 200, ""))
        t = threading.Thread(target=writes.written, args=("H1", 100))
        t.start()
        t.join(WAIT)           # w1's outcome is queued to the kernel thread
        assert writes.outstanding("H1")
        writes.written("H1", 200)  # w2's must not overtake it
        log.append(table.get("H1").value)

    s.kernel.interrupt(step)
    s.run_for(0.01)
    assert log == [None]       # neither applied inside the step
    assert table.get("H1").value == 20.0 and table.get("H1").pending is None
    assert not writes.outstanding("H1")


def test_write_now_is_confirmed_by_its_answer_and_reports_nothing(rig: Any) -> None:
    """Driver.write_now: True = on the wire (counted, not reported through host.written);
    False = nothing done (a value the frame cannot carry, a full bus, a stopped driver), so the
    caller's ordinary write reports it."""
    drv, host, gate, peer = rig
    assert drv.write_now("A", 5) is True
    assert received(peer, 1) == [value_data(5)]
    assert host.writes == [] and drv.write_counts["A"] == 1 and drv.sent_inline == 1
    assert drv.write_now("A", 70_000) is False          # 16 bits cannot carry it
    gate.full = True
    assert drv.write_now("A", 6) is False               # the bus cannot take it at once
    assert drv.write_counts["A"] == 1 and host.writes == [] and host.errors == []
    assert drv.write_now("B", 1) is False               # not a device of this bus
    drv.stop()
    gate.full = False
    assert drv.write_now("A", 7) is False
    assert peer.recv(0.05) is None and drv.sent == 1


def test_a_task_write_goes_out_untracked_and_queues_behind_an_outstanding_one(
        cell: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """Devtab's synchronous path: a task's write with nothing of the device outstanding is on
    the wire when write() returns, shown at once, with no Write to confirm; a write while an
    earlier one is still queued (a full bus) takes the tracked path behind it, in order."""
    s, gate, peer = cell
    dt = s.devtab
    confirmed: list[tuple[str, Any]] = []
    real = dt.written
    monkeypatch.setattr(dt, "written", lambda d, v: (confirmed.append((d, v)), real(d, v)))
    seen: list[Any] = []
    s.invoke("HT", {"values": [40.0, 50.0], "devtab": dt, "seen": seen})
    s.run_for(0.01)
    assert seen == [(40.0, None), (50.0, None)] and confirmed == []
    assert [power(peer), power(peer)] == [pytest.approx(40.0), pytest.approx(50.0)]
    drv = dt.drivers[0]
    assert drv.write_counts["H1"] == 2 and dt.get("H1").commands == 2

    log: list[Any] = []

    def step() -> None:        # on the kernel thread, between task steps
        gate.full = True       # write 60 falls back to the writer thread ...
        dt.write("H1", 60.0)
        assert drv.settle(WAIT)     # ... which sends it; its outcome is queued to this thread
        gate.full = False      # the bus has room and the driver nothing queued, yet write 70
        dt.write("H1", 70.0)   # must not overtake 60's outcome: it takes the tracked path
        log.append((dt.get("H1").value, dt.get("H1").pending))

    s.kernel.interrupt(step)
    s.run_for(0.01)
    assert log == [(50.0, 70.0)]
    assert [power(peer), power(peer)] == [pytest.approx(60.0), pytest.approx(70.0)]
    assert [v for _d, v in confirmed] == [60.0, 70.0]   # both tracked and confirmed, in order
    assert dt.get("H1").value == 70.0 and dt.get("H1").pending is None


def test_an_estop_on_the_kernel_thread_puts_the_safe_values_out_first(
        cell: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """On the kernel thread an emergency stop sends every safe value it can back to back, one
    call per driver (Driver.write_now_many), confirmed by the send itself: nothing is tracked,
    and the bookkeeping (value, hooks) comes after the frame."""
    s, gate, peer = cell
    dt = s.devtab
    drv = dt.drivers[0]
    confirmed: list[Any] = []
    real = dt.written
    monkeypatch.setattr(dt, "written", lambda d, v: (confirmed.append(v), real(d, v)))
    hooked: list[Any] = []
    dt.on_write.append(lambda d, v: hooked.append((d, v, len(gate.sends))))
    s.kernel.interrupt(lambda: dt.estop("test"))
    s.run_for(0.01)
    assert power(peer) == 0.0 and confirmed == []
    assert hooked == [("H1", 0, 1)]         # told after its frame was sent
    e = dt.get("H1")
    assert e.value == 0 and e.pending is None and e.commands == 1
    assert drv.sent_inline == 1 and drv.write_counts["H1"] == 1
    assert [(w, t, ok) for w, t, _d, ok in gate.sends] == [("MainThread", 0, True)]


def test_frames_already_on_the_wire_never_change(rig: Any) -> None:
    """The fast path sends one frame object per actuator with its payload replaced: what a
    receiver got stays what was sent, write after write, as python-can's own bytearray."""
    drv, _host, _gate, peer = rig
    got = []
    for v in (5, 6, 7):
        assert drv.write_now("A", v) is True
        msg = peer.recv(WAIT)
        assert msg is not None
        got.append(msg)
    assert [bytes(m.data) for m in got] == [value_data(v) for v in (5, 6, 7)]
    assert all(m.dlc == 2 and m.arbitration_id == A_ID for m in got)
    # the driver's own frame carries immutable bytes; a receiver gets python-can's bytearray
    assert all(type(m.data) is bytearray for m in got)
    assert type(drv._outgoing["A"].data) is bytes
    assert drv.sent_inline == 3


RAW_MAP = """
[[bus]]
name = "can0"
kind = "can"
interface = "virtual"
channel = "{channel}"

[[device]]
name = "A"
direction = "actuator"
bus = "can0"
address = {{ id = 0x201, start = 0, length = 16, dlc = 2 }}

[[device]]
name = "L"
direction = "actuator"
bus = "can0"
address = {{ id = 0x202, start = 0, length = 16, dlc = 2 }}
limits = [10, 1000]

[[device]]
name = "D"
direction = "actuator"
bus = "can0"
address = {{ id = 0x203, start = 0, length = 16, dlc = 2 }}
scale = 0.5
"""


@pytest.fixture
def raw_cell(tmp_path: Path) -> Iterator[tuple[System, can.BusABC]]:
    channel = unique_channel("plain")
    (tmp_path / "raw.toml").write_text(RAW_MAP.format(channel=channel))
    peer = can.Bus(interface="virtual", channel=channel)
    s = System([tmp_path / "raw.toml"], clock=VirtualClock(), machines=[0], base_dir=tmp_path)
    try:
        yield s, peer
    finally:
        s.shutdown()
        peer.shutdown()


def test_a_plain_command_the_driver_accepts_is_not_checked_twice(
        raw_cell: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """Devtab checks a plain number against the limits and the range the driver accepts
    (Driver.accepts) without asking check_value; anything else is asked and refused with the
    rule, and no frame goes out."""
    from chcos.errors import DeviceError

    s, peer = raw_cell
    dt = s.devtab
    drv = dt.drivers[0]
    asked: list[tuple[str, Any]] = []
    real = drv.check_value
    monkeypatch.setattr(drv, "check_value",
                        lambda d, v: (asked.append((d, v)), real(d, v))[1])
    assert drv.accepts("A") == (0.0, 65535.0, True)
    for v in (0, 65535, 7.0):
        dt.write("A", v)
    assert asked == []
    refused = {70_000: "expected 0..65535 for raw signal A", -1: "expected 0..65535",
               3.5: "expected an integer for raw signal A",
               float("nan"): "finite", float("inf"): "finite", 10 ** 400: "finite"}
    for v, why in refused.items():
        with pytest.raises(DeviceError, match=why):
            dt.write("A", v)
    assert [v for _d, v in asked] == [70_000.0, -1.0, 3.5]    # nan, inf, 10**400: by Devtab
    with pytest.raises(DeviceError, match="outside its limits"):
        dt.write("L", 1001)
    with pytest.raises(DeviceError, match="outside its limits"):
        dt.write("L", 9)
    dt.write("L", 1000)
    dt.write("D", 21)              # scaled: raw 42, the whole check (check_value asked)
    assert asked[-1] == ("D", 42.0)
    frames = [peer.recv(WAIT) for _ in range(5)]
    assert [(m.arbitration_id, int.from_bytes(m.data, "little")) for m in frames if m] == [
        (0x201, 0), (0x201, 65535), (0x201, 7), (0x202, 1000), (0x203, 42)]
    assert peer.recv(0.05) is None
    assert dt.get("A").rejected == len(refused) and dt.get("L").rejected == 2


class Strict(Driver):
    """A stand-in driver that takes 0..100 only (and no fast-path range: every value asked)."""

    kind = "strict"

    def start(self) -> None:
        self._running = True

    def stop(self) -> None:
        self._running = False

    def check_value(self, device: str, value: Any) -> str | None:
        return None if 0 <= value <= 100 else f"expected 0..100, got {value!r}"

    def _write(self, device: str, value: Any) -> None:
        self.sent.append((device, value))

    def settle(self, timeout: float) -> bool:
        return True

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self.sent: list[tuple[str, Any]] = []


def test_the_plain_check_follows_the_devices_driver(raw_cell: Any) -> None:
    """The plain check is kept per driver: a device given another driver is checked by that
    one's rules from the next command on."""
    from chcos.errors import DeviceError

    s, peer = raw_cell
    dt = s.devtab
    e = dt.get("A")
    dt.write("A", 300)
    assert e.driver is not None
    strict = Strict(e.driver.bus, list(e.driver.devices.values()), dt)
    strict.start()
    e.driver = strict
    with pytest.raises(DeviceError, match=r"expected 0\.\.100"):
        dt.write("A", 300)
    dt.write("A", 40)
    assert strict.sent == [("A", 40.0)]
    msg = peer.recv(WAIT)
    assert msg is not None and bytes(msg.data) == value_data(300)
    assert peer.recv(0.05) is None


def test_with_outputs_off_a_command_is_refused_as_with_outputs_on(raw_cell: Any) -> None:
    """cellrun's outputs switch (OutputsOff) logs instead of sending, and checks with the
    wrapped driver's rules: what the bus would refuse is refused while commissioning too."""
    from chcos.cli.cellsystem import OutputsOff
    from chcos.errors import DeviceError

    s, peer = raw_cell
    e = s.devtab.get("A")
    assert e.driver is not None
    logged: list[tuple[str, Any]] = []
    e.driver = OutputsOff(e.driver, lambda d, v: logged.append((d, v)))
    with pytest.raises(DeviceError, match=r"expected 0\.\.65535 for raw signal A"):
        s.devtab.write("A", 70_000)
    s.devtab.write("A", 40)
    assert logged == [("A", 40.0)] and peer.recv(0.05) is None
