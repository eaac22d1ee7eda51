"""Record a CAN session through the can driver and replay it onto another bus."""

from __future__ import annotations

from pathlib import Path

import can
import pytest

from chcos.apps.sim.can_device import CanDeviceSim
from chcos.errors import BusError
from drivers.can_raw import CanDriver
from drivers.recording import BusRecording, Recorder, read_log, replay
from vcan_tests.netutil import unique_channel
from vcan_tests.support_dev import CELL_DBC, WAIT, FakeHost, bus, device

DEVS = [device("T1", "sensor", i=0, message="Temps", signal="T1"),
        device("Spindle", "actuator", i=1, message="Drive", signal="Speed")]


def record_session(path: Path) -> None:
    """A driver with ``record`` sees 3 Temps frames and sends 1 Drive frame."""
    channel = unique_channel("rec")
    host = FakeHost()
    drv = CanDriver(bus("can", interface="virtual", channel=channel, dbc=str(CELL_DBC),
                        record=str(path)), DEVS, host)
    with CanDeviceSim(CELL_DBC, interface="virtual", channel=channel) as sim:
        drv.start()
        try:
            for t in (20.0, 20.5, 21.0):
                sim.set("Temps", T1=t)
                sim.send("Temps")
            assert drv.settle(WAIT)                 # received frames are logged first
            drv.write("Spindle", -150)
            assert sim.wait_for("Drive", "Speed", lambda v: v == -150, WAIT)
            assert drv.settle(WAIT)
        finally:
            drv.stop()


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_record_then_replay_round_trip(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"session{suffix}"
    record_session(path)
    frames = list(read_log(path))
    assert [(f.arbitration_id, f.is_rx) for f in frames] == [
        (0x101, True), (0x101, True), (0x101, True), (0x201, False)]
    channel = unique_channel("replay")
    host = FakeHost()
    drv = CanDriver(bus("can", interface="virtual", channel=channel, dbc=str(CELL_DBC)), DEVS,
                    host)
    drv.start()
    try:
        with can.Bus(interface="virtual", channel=channel) as player:
            assert replay(path, player, rx_only=True) == 3
            assert drv.settle(WAIT)
        assert host.values("T1") == [pytest.approx(v) for v in (20.0, 20.5, 21.0)]
        assert host.errors == []
    finally:
        drv.stop()


class _VirtualTime:
    """Stands in for the ``time`` module of python-can's player: a clock that moves only when
    the player sleeps, so the recorded gaps are checked exactly, whatever the machine's load."""

    def __init__(self) -> None:
        self.now = 0.0
        self.sleeps: list[float] = []

    def perf_counter(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += seconds


def test_realtime_replay_keeps_gaps_and_can_be_stopped(tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    import threading

    import can.io.player

    path = tmp_path / "gaps.log"
    rec = Recorder(path)
    for i, ts in enumerate((100.0, 100.02, 100.04)):
        rec.on_message_received(can.Message(timestamp=ts, arbitration_id=0x101,
                                            data=bytes([i, 0, 0, 0])))
    rec.stop()
    clock = _VirtualTime()
    monkeypatch.setattr(can.io.player, "time", clock)
    channel = unique_channel("rt")
    with can.Bus(interface="virtual", channel=channel) as player, \
            can.Bus(interface="virtual", channel=channel) as listener:
        assert replay(path, player, realtime=True) == 3
        got = [listener.recv(WAIT) for _ in range(3)]
        assert [m.data[0] for m in got if m is not None] == [0, 1, 2]
        # the recorded 20 ms gaps are kept (the first frame goes at once)
        assert clock.sleeps == pytest.approx([0.02, 0.02], abs=1e-6)
        assert replay(path, player) == 3 and clock.sleeps == pytest.approx([0.02, 0.02])
        stop = threading.Event()
        stop.set()
        assert replay(path, player, stop=stop) == 0


def test_bad_record_and_log_files_raise_bus_error(tmp_path: Path) -> None:
    with pytest.raises(BusError, match=r"x\.txt: expected a suffix in \.log"):
        Recorder(tmp_path / "x.txt")
    with pytest.raises(BusError, match="cannot open for writing"):
        Recorder(tmp_path / "no" / "dir" / "x.log")
    (tmp_path / "bad.log").write_text("this is not a candump line\n")
    with pytest.raises(BusError, match="malformed content"):
        list(read_log(tmp_path / "bad.log"))


def test_bus_recording_taps_a_bus_fed_by_the_realtime_simulator(tmp_path: Path) -> None:
    channel = unique_channel("tap")
    path = tmp_path / "tap.asc"
    host = FakeHost()
    drv = CanDriver(bus("can", interface="virtual", channel=channel, dbc=str(CELL_DBC)), DEVS,
                    host)
    drv.start()
    try:
        with can.Bus(interface="virtual", channel=channel) as tap, \
                BusRecording(tap, path) as rec, \
                CanDeviceSim(CELL_DBC, interface="virtual", channel=channel,
                             periods={"Temps": 0.01, "Pressure": 1e9}) as sim:
            sim.set("Temps", T1=5.0)
            sim.start()                                  # real-time thread mode
            assert host.wait(lambda h: len(h.values("T1")) >= 3)
            sim.close()
            assert drv.settle(WAIT)
            delivered = len(host.values("T1"))
        assert rec.recorder.count == sim.frames_out
        frames = [f for f in read_log(path) if f.arbitration_id == 0x101]
        assert len(frames) == sim.frames_out - 1 == delivered   # Pressure sent once at t0
    finally:
        drv.stop()
