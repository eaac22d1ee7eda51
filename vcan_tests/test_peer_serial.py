"""The serial driver against a plain pty peer that sends garbage (issue 15, item 8).

The peer is the test itself on the master side of an ``os.openpty()`` pair (no chcos simulator):
it writes good lines, noise, non-ASCII bytes, an endless line and numbers that Python's
``float()`` would take but an instrument never sends (``nan``, ``inf``, ``1_000``, ``1e999``,
non-ASCII digits); chcos must deliver only the good readings, count every bad line by class and
keep reading; and the peer reads back what chcos wrote to it.
"""

from __future__ import annotations

import math
import os
import select
import tty
from collections.abc import Iterator

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.codecs.serial import BinaryFramer, LineFramer, parse_number
from drivers.serial_line import SerialDriver
from vcan_tests.support_dev import WAIT, FakeHost, bus, device

PATTERN = r"T=(?P<t>\S+)"


@pytest.fixture
def pty_peer() -> Iterator[tuple[int, str]]:
    master, slave = os.openpty()
    tty.setraw(master)
    path = os.ttyname(slave)
    try:
        yield master, path
    finally:
        os.close(master)
        os.close(slave)


def _read_from(fd: int, want: bytes, timeout: float = WAIT) -> bytes:
    got = b""
    while want not in got:
        ready, _, _ = select.select([fd], [], [], timeout)
        if not ready:
            break
        got += os.read(fd, 1024)
    return got


def test_garbage_from_a_pty_peer_is_counted_and_only_numbers_delivered(
        pty_peer: tuple[int, str]) -> None:
    master, path = pty_peer
    host = FakeHost()
    spec = bus("serial", url=path, protocol="line", pattern=PATTERN, max_line=64,
               encoding="utf-8")
    devs = [device("T", "sensor", i=0, group="t"),
            device("Heat", "actuator", i=1, format="H {value:.1f}")]
    drv = SerialDriver(spec, devs, host)
    drv.start()
    try:
        drv.write("Heat", 12.25)                         # the peer sees chcos' command
        assert b"H 12.2\n" in _read_from(master, b"H 12.2\n")
        os.write(master, b"T=21.5\n")
        os.write(master, b"\x00\xff\x13 line noise\n")   # not UTF-8: garbage
        os.write(master, b"hello\n")                     # does not match: garbage
        for bad in (b"nan", b"inf", b"-Infinity", b"1_000", b"1e999", b"0x10",
                    "\u0663".encode()):
            os.write(master, b"T=" + bad + b"\n")        # malformed: no finite decimal
        os.write(master, b"x" * 200)                      # an endless line: garbage
        os.write(master, b"\nT=-3e2\n")
        assert host.wait(lambda h: len(h.values("T")) == 2)
        assert host.values("T") == [21.5, -300.0]
        assert all(math.isfinite(v) for v in host.values("T"))
        assert host.wait(lambda h: len(h.errors) >= 10)
        assert drv.error_counts == {"garbage": 3, "malformed": 7}, drv.error_counts
        assert drv.settle(WAIT)
    finally:
        drv.stop()


@pytest.mark.parametrize("text, value", [("12", 12.0), ("-1.5", -1.5), (".5", 0.5), ("1e3", 1e3),
                                         (" 7 ", 7.0), ("+2.", 2.0)])
def test_parse_number_takes_decimals(text: str, value: float) -> None:
    assert parse_number(text) == value


@pytest.mark.parametrize("text", ["nan", "NaN", "inf", "-inf", "Infinity", "1_000", "1e999",
                                  "0x10", "\u0663", "", "-", "1e", "1.2.3", "١٢"])
def test_parse_number_refuses_what_is_no_reading(text: str) -> None:
    assert parse_number(text) is None


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.binary(max_size=200))
def test_any_bytes_on_a_line_give_finite_values_or_counted_errors(data: bytes) -> None:
    f = LineFramer(r"(?P<a>[^,]*),(?P<b>[^,]*)", max_line=64)
    for chunk in (data[:50], data[50:]):
        for kind, detail in f.feed(chunk):
            assert kind in ("values", "garbage", "malformed")
            if kind == "values":
                assert all(isinstance(v, float) and math.isfinite(v) for v in detail.values())


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.binary(max_size=120))
def test_any_bytes_in_binary_frames_give_finite_values(data: bytes) -> None:
    f = BinaryFramer(b"\xaa", "<fdh", ["f", "d", "h"], "none")
    for kind, detail in f.feed(b"\xaa" + data):
        assert kind in ("values", "garbage", "malformed", "checksum")
        if kind == "values":
            assert all(math.isfinite(v) for v in detail.values())
