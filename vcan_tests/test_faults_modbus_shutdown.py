"""Shutdown truthfulness on the Modbus driver's side (issue 38): a write is reported ``written``
only once the server answered it, a write while the link is down fails at once, and once the
shutdown flush began a lost link is retried every ``reconnect_delay`` - not after the backoff
grown while the server was away - so a pyModbusTCP server that returns within the 5 s window
gets the safe value that is re-issued meanwhile (what the device table does at shutdown)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from chcos.devices.spec import BusSpec
from drivers.modbus import ModbusTcpDriver
from vcan_tests.netutil import free_port
from vcan_tests.support_faults import ModbusPeer
from vcan_tests.support_fb import WAIT, FakeHost, make_device

HEATER = 100
WINDOW = 5.0           # s: the shutdown flush's window (Devtab's SHUTDOWN_FLUSH)


@pytest.fixture
def peer(tmp_path: Path) -> Iterator[ModbusPeer]:
    p = ModbusPeer(free_port(), tmp_path / "peer.log", {str(HEATER): 555})
    p.start()
    try:
        yield p
    finally:
        p.kill()


def test_a_server_back_within_the_window_gets_the_reissued_safe_value(peer: ModbusPeer) -> None:
    bus = BusSpec(name="mb", kind="modbus-tcp", key="bus[0]",
                  options={"host": "127.0.0.1", "port": peer.port, "timeout": 0.3,
                           "retries": 0, "reconnect_delay": 0.2, "reconnect_delay_max": 30.0})
    host = FakeHost()
    driver = ModbusTcpDriver(bus, [make_device("heater", "actuator", "mb", table="holding",
                                               address=HEATER)], host)
    driver.start()
    try:
        driver.write("heater", 300)
        assert host.wait_for(lambda h: ("heater", 300, "") in h.writes)
        peer.kill()
        driver.write("heater", 301)                   # the lost link is noticed
        # failed connects after 0.2, 0.4, 0.8, 1.6, 3.2 s: the next backoff is 6.4 s, longer
        # than the whole window
        assert host.wait_for(lambda h: h.stats.get("connect-failed", 0) >= 6, 20.0)
        driver.write("heater", 0)                     # the link is down: fails at once
        assert host.wait_for(lambda h: len(h.writes) == 3)
        assert host.writes[1][:2] == ("heater", 301) and host.writes[1][2]
        assert host.writes[2][:2] == ("heater", 0) and "not connected" in host.writes[2][2]

        peer.start()                                  # the server returns...
        back = peer.started_at
        end = back + WINDOW                           # ...and shutdown begins
        confirmed = False
        while not confirmed and time.monotonic() < end:   # the re-issue of an unconfirmed
            n = len(host.writes)                          # safe value, as Devtab's shutdown
            driver.write("heater", 0)
            assert driver.flush(max(0.0, end - time.monotonic()))
            confirmed = host.writes[n:] == [("heater", 0, "")]
            if not confirmed:
                threading.Event().wait(0.1)               # its re-issue period
        assert confirmed, f"the safe value was not confirmed within {WINDOW} s: {host.writes}"
    finally:
        driver.stop()
    assert peer.holding(HEATER) == 0
    assert [(w.values, w.outcome) for w in peer.writes(since=back)] == [([0], "ok")]
    # every write reported written was answered by the server
    answered = [w.values[0] for w in peer.writes() if w.outcome == "ok"]
    assert [v for d, v, why in host.writes if not why] == answered == [300, 0]


def test_nothing_is_written_unless_the_server_answered(peer: ModbusPeer) -> None:
    bus = BusSpec(name="mb", kind="modbus-tcp", key="bus[0]",
                  options={"host": "127.0.0.1", "port": peer.port, "timeout": 0.3,
                           "retries": 0, "reconnect_delay": 0.05})
    host = FakeHost()
    driver = ModbusTcpDriver(bus, [make_device("heater", "actuator", "mb", table="holding",
                                               address=HEATER)], host)
    driver.start()
    try:
        peer.freeze()                                 # accepts, never answers
        try:
            driver.write("heater", 7)
            driver.write("heater", 8)
            assert driver.flush(WAIT)
        finally:
            peer.thaw()
    finally:
        driver.stop()
    assert [v for _, v, _ in host.writes] == [7, 8]
    assert all(why for _, _, why in host.writes), host.writes     # both failed, none "written"
