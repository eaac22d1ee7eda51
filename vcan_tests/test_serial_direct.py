"""The serial driver on the in-process direct line of virtual time (drivers.serial_direct): the
bytes on it are those the driver writes to a real line (a pty read with os.read, an independent
peer), a virtual cell's simulated instrument runs on the kernel thread with no thread and no
socket, and a write the line refuses fails the actuator and is probed on the kernel clock."""

from __future__ import annotations

import os
import threading
import tty
from collections.abc import Callable
from pathlib import Path

import pytest

from chcos.testing import TestCell
from drivers.serial_direct import open_end
from drivers.serial_line import SerialDriver
from vcan_tests.support_dev import FakeHost, bus, device

OPTIONS = {"protocol": "binary", "sync": "AA 55", "struct": "<hH", "fields": ["t", "_"],
           "checksum": "xor8"}


def _actuators() -> list:
    return [device("m1", "actuator", struct="<h", prefix="10"),
            device("lamp", "actuator", i=1, struct="<B", prefix="20")]


def test_the_direct_line_carries_the_bytes_a_pty_carries(request: pytest.FixtureRequest) -> None:
    values = [("m1", 5), ("m1", -300), ("lamp", 1), ("m1", 32767)]
    master, slave = os.openpty()
    tty.setraw(master)
    pty_host, direct_host = FakeHost(), FakeHost()
    on_pty = SerialDriver(bus("serial", url=os.ttyname(slave), **OPTIONS), _actuators(),
                          pty_host)
    url = f"chcos-direct://{request.node.name}"
    far = open_end(url)                      # the instrument's end: keeps what arrives
    on_line = SerialDriver(bus("serial", url=url, **OPTIONS), _actuators(), direct_host)
    on_pty.start()
    on_line.start()
    try:
        assert on_pty.wait_open(5)
        for name, v in values:
            on_pty.write(name, v)
            on_line.write(name, v)          # written before this returns: nothing in flight
        assert direct_host.writes == [(n, v, "") for n, v in values]
        want = far.read()
        got = b""
        while len(got) < len(want):
            got += os.read(master, 4096)
        assert got == want                   # the same bytes on both lines
        assert want.startswith(b"\xaa\x55\x10\x05\x00")   # sync, prefix, <h 5
    finally:
        on_pty.stop()
        on_line.stop()
        far.close()
        os.close(master)
        os.close(slave)


def test_a_refused_write_fails_the_actuator_and_the_probe_runs_on_the_kernel_clock(
        request: pytest.FixtureRequest) -> None:
    url = f"chcos-direct://{request.node.name}"
    far = open_end(url)
    host = FakeHost()
    drv = SerialDriver(bus("serial", url=url, reconnect_min=0.05, reconnect_max=0.4,
                           **OPTIONS), [device("m1", "actuator", struct="<h", prefix="10")],
                       host)
    drv.start()
    try:
        drv.write("m1", 7)
        far.close()                          # the cable pulled
        drv.write("m1", 8)
        assert host.writes[-1][0:2] == ("m1", 8) and "nobody at the other end" in \
            host.writes[-1][2]
        assert host.failures and host.failures[0][0] == "m1"
        host.advance(1.0)                    # probes at 0.05, 0.15, 0.35, 0.75 s: all refused
        assert drv.probe.failed_tries == 4 and host.recoveries == []
        far = open_end(url)                  # plugged in again
        host.advance(0.4)
        assert host.recoveries == ["m1"] and far.read() == b"\xaa\x55\x10\x07\x00\x17"
    finally:
        drv.stop()
        far.close()


SERIAL_MAP = """
[[bus]]
name = "scale"
kind = "serial"
url = "socket://127.0.0.1:7001"
protocol = "line"
pattern = 'W=(?P<w>[-0-9.]+)'

[[device]]
name = "weight"
direction = "sensor"
bus = "scale"
address = { group = "w" }
stale_after = 0.5

[[device]]
name = "tare"
direction = "actuator"
bus = "scale"
address = { format = "TARE {value:.1f}" }
safe_value = 0
"""


def test_a_virtual_cell_talks_to_its_instrument_without_threads_or_sockets(
        tmp_path: Path, chcos_cell: Callable[..., TestCell]) -> None:
    (tmp_path / "scale.toml").write_text(SERIAL_MAP)
    (tmp_path / "system.toml").write_text('[system]\nname = "s"\ndevmaps = ["scale.toml"]\n')
    before = {t.name for t in threading.enumerate()}
    cell = chcos_cell(tmp_path / "system.toml")
    cell.set("weight", 12.5)
    cell.run_for(1.0)
    assert cell.value("weight") == pytest.approx(12.5) and cell.status("weight") == "OK"
    cell.system.devtab.write("tare", 3.0)
    assert cell.peer("tare") == pytest.approx(3.0)     # in the instrument before run_for
    new = {t.name for t in threading.enumerate()} - before
    assert not [n for n in new if n.startswith("serial-")]
    assert cell.cell.slaves is not None
    assert str(cell.cell.slaves.devmap.bus("scale").options["url"]).startswith("chcos-direct://")
    cell.silence("scale")
    cell.run_for(1.0)
    assert cell.status("weight") == "stale"
