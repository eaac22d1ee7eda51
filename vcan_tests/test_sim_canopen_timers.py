"""The simulated node's timers on virtual time: each period counts from its due time, so over a
long run (60 s of the node's clock, advanced in 10 ms steps as the kernel's slaves are) the
heartbeat producer and the TPDO event timer send exactly one frame per period, each at the first
step at or after its due time, whatever the period's relation to the step; the TPDO inhibit
time and the EMCY inhibit time (0x1015) hold frames back to their due time; and no wall clock
is read on the way (time.monotonic, time.time, time.sleep and time.perf_counter are made to
fail). Frames are read and written as CiA 301 lays them out, on the node's pure core."""

from __future__ import annotations

import math
import struct
import time

import pytest

from chcos.apps.sim.canopen_slave import SERVO_EDS, CanopenSlave, Clock
from chcos.apps.sim.canopen_timers import CATCH_UP, Periodic, TpdoTimer
from chcos.apps.sim.cia402_drive import CIA402_EDS, Cia402Drive
from drivers.codecs.can import CanFrame
from vcan_tests.support_cosim import Script, download, upload

NODE = 9
STEP = 0.01


@pytest.mark.parametrize(("heartbeat_ms", "event_ms"), [(25, 33), (33, 25), (7, 3), (100, 50)])
def test_heartbeat_and_event_timer_do_not_drift_over_a_minute(heartbeat_ms: int,
                                                              event_ms: int) -> None:
    wire = Script(NODE)
    assert wire.sdo1(download(0x1017, 0, struct.pack("<H", heartbeat_ms)))[0] == 0x60
    assert wire.sdo1(download(0x1800, 5, struct.pack("<H", event_ms)))[0] == 0x60
    wire.nmt(0x01)
    start = wire.now
    seen = wire.run(60.0, STEP)
    for cob, ms in ((0x700 + NODE, heartbeat_ms), (0x180 + NODE, event_ms)):
        times = [s.at - start for s in seen if s.cob_id == cob]
        period = ms / 1000
        expected = math.floor(60.0 / period + 1e-6)
        assert abs(len(times) - expected) <= 1, (cob, len(times), expected)
        assert abs(len(times) - 60.0 / period) / (60.0 / period) < 0.005
        # the n-th frame goes out at the first step at or after n periods: no lateness builds up
        for n, at in enumerate(times, 1):
            assert n * period - 1e-6 <= at < n * period + STEP + 1e-6, (cob, n, at)


def test_the_heartbeat_carries_the_state_and_follows_0x1017_from_the_write() -> None:
    wire = Script(NODE)
    wire.run(0.1)
    assert wire.sdo1(download(0x1017, 0, struct.pack("<H", 40)))[0] == 0x60   # at 0.1 s
    wire.nmt(0x01)
    beats = [s for s in wire.run(0.2) if s.cob_id == 0x700 + NODE]
    assert [round(s.at, 3) for s in beats] == [0.14, 0.18, 0.22, 0.26, 0.3]
    assert {s.data for s in beats} == {b"\x05"}


def test_the_inhibit_time_holds_a_change_until_it_is_over() -> None:
    wire = Script(NODE)
    assert wire.sdo1(download(0x1800, 3, struct.pack("<H", 300)))[0] == 0x60   # 30 ms
    wire.nmt(0x01)
    for value in range(1, 8):                  # a change every 10 ms
        wire.set(0x2008, 0, value)
        wire.run(STEP)
    tpdos = [(round(s.at, 3), struct.unpack("<I", s.data)[0]) for s in wire.seen
             if s.cob_id == 0x180 + NODE]
    # at once, then at the end of each inhibit time the value it found (never within 30 ms)
    assert tpdos == [(0.0, 1), (0.03, 3), (0.06, 6)]
    wire.run(0.05)
    tpdos = [round(s.at, 3) for s in wire.seen if s.cob_id == 0x180 + NODE]
    assert tpdos == [0.0, 0.03, 0.06, 0.09]    # the last change (7 at 0.06 s) after 0.09 s


def test_a_transmission_on_change_restarts_the_event_timer() -> None:
    wire = Script(NODE)
    assert wire.sdo1(download(0x1800, 5, struct.pack("<H", 50)))[0] == 0x60
    wire.nmt(0x01)
    wire.run(0.02)
    wire.set(0x2008, 0, 5)                     # at 20 ms: out at once ...
    wire.run(0.2)
    tpdos = [round(s.at, 3) for s in wire.seen if s.cob_id == 0x180 + NODE]
    assert tpdos == [0.02, 0.07, 0.12, 0.17, 0.22]   # ... and the event timer counts from it


def test_emcys_respect_the_inhibit_time_0x1015() -> None:
    wire = Script(NODE)
    assert wire.sdo1(download(0x1015, 0, struct.pack("<H", 250)))[0] == 0x60   # 25 ms
    wire.slave.inject_fault(0x3210)
    wire.slave.inject_fault(0x4210)
    wire.slave.clear_fault(0x3210)
    first = wire.slave.take()
    assert [f.data[:3] for f in first] == [bytes.fromhex("103205")]
    later = [s for s in wire.run(0.1) if s.cob_id == 0x80 + NODE]
    # due one inhibit time (25 ms) after the one before (sent at the next 10 ms step), each with
    # the register as it stood when raised: 0x4210 on 0x3210 (0x0D), then 0x3210's reset (0x09)
    assert [(round(s.at, 3), s.data[:3]) for s in later] == [
        (0.03, bytes.fromhex("10420d")), (0.05, bytes.fromhex("000009"))]


def test_a_segmented_transfer_times_out_on_the_node_clock_only() -> None:
    wire = Script(NODE)
    assert wire.sdo1(upload(0x1008, 0))[0] == 0x41
    assert wire.slave.next_due() == pytest.approx(1.0)
    wire.run(2.0, 0.5)
    aborts = [s for s in wire.seen if s.cob_id == 0x580 + NODE and s.data[0] == 0x80]
    assert [(s.at, s.data.hex()) for s in aborts] == [(1.0, "8008100000000405")]


# -- the timers alone --------------------------------------------------------------------------


def test_periodic_counts_from_its_due_times_and_catches_up() -> None:
    timer = Periodic()
    timer.start(0.0, 0.03)
    assert timer.fire(0.029) == []
    assert timer.fire(0.04) == [pytest.approx(0.03)]
    assert timer.fire(0.1) == [pytest.approx(0.06), pytest.approx(0.09)]
    assert timer.due == pytest.approx(0.12)
    late = timer.fire(1000.0)                  # a huge jump: CATCH_UP at most, phase kept
    assert len(late) == CATCH_UP
    assert (timer.due - 0.12) / 0.03 == pytest.approx(round((timer.due - 0.12) / 0.03))
    assert 1000.0 < timer.due <= 1000.03
    timer.start(5.0, 0)
    assert timer.due is None and timer.fire(1e9) == []


def test_tpdo_timer_inhibit_and_event() -> None:
    timer = TpdoTimer()
    timer.configure(0.0, inhibit=0.02, event=0.1)
    assert timer.due() == pytest.approx(0.1)
    assert timer.changed(0.05)
    timer.sent(0.05)
    assert not timer.changed(0.06)             # within the inhibit time: held
    assert timer.due() == pytest.approx(0.07)
    assert timer.fire(0.2) == [pytest.approx(0.07), pytest.approx(0.17)]
    assert timer.due() == pytest.approx(0.27)


# -- no wall clock under the virtual one -------------------------------------------------------


@pytest.fixture
def no_wall_clock(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    calls: list[str] = []

    def refuse(name: str) -> object:
        def call(*args: object) -> float:
            calls.append(name)
            raise AssertionError(f"time.{name} read on a virtual-time path")
        return call

    for name in ("monotonic", "time", "sleep", "perf_counter", "monotonic_ns", "time_ns"):
        monkeypatch.setattr(time, name, refuse(name))
    return calls


@pytest.mark.parametrize("kind", ["servo", "cia402"])
def test_a_node_on_tick_time_reads_no_wall_clock(no_wall_clock: list[str], kind: str) -> None:
    node: CanopenSlave
    if kind == "servo":
        node = CanopenSlave(NODE, SERVO_EDS, channel="unused", clock=Clock.TICK,
                            heartbeat_period=0.05)
    else:
        node = Cia402Drive(NODE, CIA402_EDS, channel="unused", clock=Clock.TICK,
                           heartbeat_period=0.05)
    sent: list[CanFrame] = []
    node.attach(sent.append)
    rx = [CanFrame(0x000, bytes([0x01, NODE])),                            # start
          CanFrame(0x600 + NODE, bytes.fromhex("2B17100032000000")),       # 0x1017 = 50 ms
          CanFrame(0x600 + NODE, bytes.fromhex("23161001F4017F00")),       # watch 0x7F, 0.5 s
          CanFrame(0x77F, b"\x05"),                                        # master heartbeat
          CanFrame(0x200 + NODE, struct.pack("<H", 0x06)),                 # RPDO1
          CanFrame(0x200 + NODE, b"\x06"),                                 # RPDO1, too short
          CanFrame(0x600 + NODE, bytes.fromhex("4064600100000000")),       # 0x6064:01: abort
          CanFrame(0x080, b"")]                                            # SYNC
    for frame in rx:
        sent += node.handle(frame)
        node.tick(0.01)
    node.inject_fault(0x4310)
    for _ in range(200):                       # the master falls silent: lost after 0.5 s
        node.tick(0.01)
    node.clear_fault()
    node.stop()
    assert no_wall_clock == []
    assert any(f.arbitration_id == 0x700 + NODE for f in sent)
    assert any(f.arbitration_id == 0x80 + NODE and f.data[:2] == b"\x30\x81" for f in sent)
