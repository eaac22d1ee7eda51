"""Serial driver: framers on byte literals, then line/binary over a pty and socket://."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from chcos.apps.sim.serial_device import PtySerialSim, SerialSim, TcpSerialSim
from drivers.codecs.serial import BinaryFramer, LineFramer, checksum
from drivers.serial_line import SerialDriver
from vcan_tests.support_dev import WAIT, FakeHost, bus, device

PATTERN = r"W=(?P<w>-?\d+(\.\d+)?)( T=(?P<t>-?\w+))?"


def test_line_framer_splits_matches_and_flags_garbage() -> None:
    f = LineFramer(PATTERN, max_line=32)
    assert f.feed(b"W=1.5 T=2\r\nW=") == [("values", {"w": 1.5, "t": 2.0})]
    assert f.feed(b"-3\n\nhello\n") == [("values", {"w": -3.0}),
                                        ("garbage", "line 'hello' does not match "
                                                    f"{PATTERN!r}")]
    kind, detail = f.feed(b"W=1 T=x\n")[0]
    assert kind == "malformed" and "group t = 'x'" in detail
    assert f.feed(b"\xff\n")[0][0] == "garbage"
    assert f.feed(b"x" * 40) == [("garbage", "40 bytes without an end of line")]


def test_binary_framer_resyncs_and_checks_sum() -> None:
    f = BinaryFramer(b"\xaa\x55", "<hB", ["pos", "_"], "sum8")
    good = b"\xaa\x55" + b"\x10\x00\x07" + checksum("sum8", b"\x10\x00\x07")
    assert good[-1] == 0x17
    assert f.feed(b"\x01") == []                        # a run is reported when it ends
    assert f.feed(b"\x02\xaa") == []                    # \xaa may start a sync: kept
    assert f.feed(good[1:3]) == [("garbage", "2 bytes that are no frame (sync aa55)")]
    assert f.feed(good[3:]) == [("values", {"pos": 16})]
    bad = good[:-1] + b"\x00"
    events = f.feed(bad + good)
    assert [k for k, _ in events] == ["checksum", "values"]   # no double count
    assert f.feed(b"\x00" * 5 + good) == [("garbage", "5 bytes that are no frame (sync aa55)"),
                                          ("values", {"pos": 16})]
    assert f.feed(b"\x00" * 1030)[0][0] == "garbage"      # endless noise is still reported
    assert checksum("xor8", b"\x01\x03") == b"\x02" and checksum("none", b"\x01") == b""


@pytest.fixture(params=["pty", "socket"])
def sim(request: pytest.FixtureRequest) -> Iterator[tuple[SerialSim, str]]:
    s: SerialSim = PtySerialSim() if request.param == "pty" else TcpSerialSim()
    url = s.path if isinstance(s, PtySerialSim) else s.url   # type: ignore[attr-defined]
    try:
        yield s, url
    finally:
        s.close()


def connected(sim: SerialSim, host: FakeHost, n: int = 1) -> bool:
    """The driver has the port open (socket: the server accepted connection n)."""
    if isinstance(sim, TcpSerialSim):
        return sim.wait_connected(n, WAIT)
    return True


def start(spec: Any, devs: list[Any], host: FakeHost) -> SerialDriver:
    assert SerialDriver.check_bus(spec) == []
    for d in devs:
        assert SerialDriver.check_device(spec, d) == []
    drv = SerialDriver(spec, devs, host)
    drv.start()
    return drv


def test_line_protocol_delivers_counts_garbage_and_writes(sim: Any) -> None:
    s, url = sim
    host = FakeHost()
    spec = bus("serial", url=url, protocol="line", pattern=PATTERN, baudrate=115200)
    devs = [device("W", "sensor", i=0, group="w"), device("T", "sensor", i=1, group="t"),
            device("Tare", "actuator", i=2, format="TARE {value:.1f}")]
    drv = start(spec, devs, host)
    try:
        assert connected(s, host)
        drv.write("Tare", 2.25)                      # also proves the port is open (pty)
        assert s.wait_received(lambda b: b == b"TARE 2.2\n", WAIT)
        s.send_line("W=12.5 T=3")
        s.send_bytes(b"noise\n")
        s.send_line("W=13")
        assert host.wait(lambda h: len(h.values("W")) == 2)
        assert host.values("W") == [12.5, 13.0] and host.values("T") == [3.0]
        assert host.error_kinds() == ["garbage"] and drv.error_counts == {"garbage": 1}
        assert drv.settle(WAIT)
    finally:
        drv.stop()


def test_binary_protocol_frames_garbage_and_commands(sim: Any) -> None:
    s, url = sim
    host = FakeHost()
    spec = bus("serial", url=url, protocol="binary", sync="AA 55", struct="<hH",
               fields=["pos", "status"], checksum="xor8")
    devs = [device("Pos", "sensor", i=0, field="pos"),
            device("Status", "sensor", i=1, field="status"),
            device("Zero", "actuator", i=2, struct="<h", prefix="01")]
    drv = start(spec, devs, host)
    try:
        assert connected(s, host)
        drv.write("Zero", -2.6)
        frame = b"\xaa\x55\x01\xfd\xff" + checksum("xor8", b"\x01\xfd\xff")
        assert s.wait_received(lambda b: b == frame, WAIT)
        s.send_frame(b"\xaa\x55", "<hH", [-300, 7], "xor8")
        s.send_bytes(b"\x13\x37")
        s.send_frame(b"\xaa\x55", "<hH", [5, 0], "xor8")
        assert host.wait(lambda h: len(h.values("Pos")) == 2)
        assert host.values("Pos") == [-300, 5] and host.values("Status") == [7, 0]
        assert host.error_kinds() == ["garbage"]
    finally:
        drv.stop()


def test_socket_reconnects_after_the_port_goes_away() -> None:
    host = FakeHost()
    with TcpSerialSim() as s:
        spec = bus("serial", url=s.url, protocol="line", pattern=PATTERN, reconnect_min=0.01,
                   reconnect_max=0.05)
        drv = start(spec, [device("W", "sensor", i=0, group="w")], host)
        try:
            assert s.wait_connected(1, WAIT) and drv.wait_open(WAIT)   # open flushes input
            s.send_line("W=1")
            assert host.wait(lambda h: h.values("W") == [1.0])
            s.drop()
            assert host.wait(lambda h: h.failures)
            assert host.failures[0][0] == "W" and "lost" in host.failures[0][1]
            assert s.wait_connected(2, WAIT)
            assert host.wait(lambda h: h.recoveries == ["W"])
            s.send_line("W=2")
            assert host.wait(lambda h: h.values("W") == [1.0, 2.0])
            assert drv.connects == 2
        finally:
            drv.stop()


def test_unreachable_port_fails_devices_then_recovers_when_it_appears() -> None:
    from vcan_tests.netutil import free_port
    port = free_port()
    host = FakeHost()
    spec = bus("serial", url=f"socket://127.0.0.1:{port}", protocol="line", pattern=PATTERN,
               reconnect_min=0.01, reconnect_max=0.02)
    drv = start(spec, [device("W", "sensor", i=0, group="w")], host)
    try:
        assert host.wait(lambda h: h.failures)
        assert "cannot open" in host.failures[0][1]
        assert drv.settle(0.05)    # nothing open, nothing can arrive: quiet (no stalled settle)
        with TcpSerialSim(port) as s:
            assert s.wait_connected(1, WAIT)
            assert host.wait(lambda h: h.recoveries == ["W"])
            s.send_line("W=4")
            assert host.wait(lambda h: h.values("W") == [4.0])
    finally:
        drv.stop()


def test_write_while_port_is_down_fails_the_actuator() -> None:
    from vcan_tests.netutil import free_port
    host = FakeHost()
    spec = bus("serial", url=f"socket://127.0.0.1:{free_port()}", protocol="line",
               pattern=PATTERN)
    devs = [device("W", "sensor", i=0, group="w"),
            device("Tare", "actuator", i=1, format="TARE {value}")]
    drv = start(spec, devs, host)
    try:
        assert host.wait(lambda h: len(h.failures) >= 2)
        drv.write("Tare", 1)
        assert host.wait(lambda h: any("not open" in r for d, r in h.failures if d == "Tare"))
        assert drv.error_counts == {}
    finally:
        drv.stop()


def test_check_device_rejects_bad_actuator_formats() -> None:
    spec = bus("serial", url="loop://", protocol="line", pattern=PATTERN)
    assert SerialDriver.check_device(spec, device("A", "actuator", format="{val}")) == [
        "device[0].address.format: expected a str.format string using {value}: 'val'"]
    bspec = bus("serial", url="loop://", protocol="binary", sync="AA", struct="<h", fields=["a"])
    assert SerialDriver.check_device(bspec, device("A", "actuator", struct="<hh")) == [
        "device[0].address.struct: expected a format of exactly one item"]


def test_settle_before_the_port_opens_waits_for_it_and_hands_over_waiting_input() -> None:
    """The kernel settles drivers before virtual time moves; a settle that comes before the
    reader has opened the port waits for the open (not for its whole timeout) and drains what
    the peer had already sent, so a virtual-time run never races the reader thread."""
    import socket
    import threading

    from drivers.threaded import ReaderThread

    go = threading.Event()
    drained: list[str] = []

    rx: ReaderThread

    def loop() -> None:
        go.wait(WAIT)
        rx.set_drain(lambda: drained.append("x"))
        while rx.running:
            rx.pause(1.0)

    rx = ReaderThread(loop, "settle-before-open")
    rx.start()
    try:
        opener = threading.Thread(target=go.set)
        opener.start()                  # the open may come before or during settle: same result
        assert rx.settle(WAIT)
        assert drained                  # the drain ran once the link opened
        opener.join()
    finally:
        rx.stop()
    # and the simulated serial peer's TCP server (chcos sim --from; a virtual cell's is a direct
    # line) accepts on the thread that ticks: data set after the driver connected reaches it
    # with no accept thread in between
    from chcos.apps.sim.serial_peer import SerialPeer
    from chcos.helpers import free_port
    peer = SerialPeer(bus("serial", url=f"socket://127.0.0.1:{free_port()}", protocol="line",
                          pattern=r"W=(?P<w>\d+)"),
                      (device("W", "sensor", group="w"),), rewrite=False)
    try:
        port = int(str(peer.bus.options["url"]).rsplit(":", 1)[1])
        with socket.create_connection(("127.0.0.1", port), timeout=WAIT) as c:
            peer.tick(0.0)              # accepts the waiting connection, then sends
            c.settimeout(WAIT)
            assert c.recv(64) == b"W=0\n"
    finally:
        peer.close()


class _ClosingPort:
    """A port whose write fails the way pyserial's socket:// does when the reader closes it
    during the write (a TypeError from select on the socket that is gone)."""

    def __init__(self, is_open: bool) -> None:
        self.is_open = is_open

    def write(self, data: bytes) -> int:
        raise TypeError("argument must be an int, or have a fileno() method.")

    def flush(self) -> None:
        pass


def test_a_port_closed_during_a_write_fails_that_write_and_the_actuator() -> None:
    """The reader closes the port (link lost) while the writer thread writes: the write is
    reported failed and the actuator failed, as for any write error. The same TypeError from
    a port that is still open is a bug and is not dressed up as a bus error (the writer thread
    reports it as an internal error instead)."""
    host = FakeHost()
    spec = bus("serial", url="socket://127.0.0.1:9", protocol="line", pattern=PATTERN)
    drv = SerialDriver(spec, [device("Tare", "actuator", i=1, format="TARE {value}")], host)
    drv._port = _ClosingPort(is_open=False)
    drv._send("Tare", 1)
    assert host.writes == [("Tare", 1, "write to socket://127.0.0.1:9 failed: the port was "
                                       "closed during the write")]
    assert host.failures == [("Tare", host.writes[0][2])]
    drv._port = _ClosingPort(is_open=True)
    with pytest.raises(TypeError):
        drv._send("Tare", 2)
