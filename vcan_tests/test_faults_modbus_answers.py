"""Wrong answers from a Modbus TCP server are never values (issue 46): against a server of the
test's own (vcan_tests/support_modbus_tcp.py) that answers a register with the wrong function
code, a short byte count, another transaction or unit id, late, or not at all. Each is counted
by its cause and never delivered; the device fails at once when it never had a good answer, else
after three unusable answers in a row (as CAN fails a sensor after three malformed frames); one
register's trouble costs its device, never the connection (the server saw one connection) nor
the other devices; a late answer is thrown away, never taken for the next request's."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest

from chcos.devices.spec import BusSpec
from drivers.modbus import ModbusTcpDriver
from vcan_tests.support_fb import WAIT, FakeHost, make_device
from vcan_tests.support_modbus_tcp import Fault, ScriptedTcpServer

#: one register each, with gaps: one request each
SENSORS = {"a": 0, "b": 10, "c": 20}


@dataclass
class Rig:
    server: ScriptedTcpServer
    driver: ModbusTcpDriver
    host: FakeHost

    def poll(self, n: int = 1) -> None:
        for _ in range(n):
            self.host.tick(0.1)
            assert self.driver.settle(WAIT)


def rig_with(faults: dict[int, Fault], **devices: Any) -> Iterator[Rig]:
    server = ScriptedTcpServer(late=0.3, faults=dict(faults))
    bus = BusSpec(name="mb", kind="modbus-tcp", key="bus[0]",
                  options={"host": "127.0.0.1", "port": server.port, "timeout": 0.2,
                           "retries": 0, "reconnect_delay": 0.02})
    specs = [make_device(name, "sensor", "mb", table="holding", address=addr, **extra)
             for name, (addr, extra) in ({n: (a, {}) for n, a in SENSORS.items()}
                                         | devices).items()]
    host = FakeHost()
    driver = ModbusTcpDriver(bus, specs, host)
    driver.start()
    try:
        yield Rig(server, driver, host)
    finally:
        driver.stop()
        server.close()


@pytest.fixture
def rig() -> Iterator[Rig]:
    yield from rig_with({})


def kept_the_connection(r: Rig) -> None:
    assert r.server.connections == 1
    assert "disconnected" not in r.host.error_kinds() and "reconnects" not in r.host.stats


def test_a_wrong_function_code_fails_the_device_after_three_in_a_row(rig: Rig) -> None:
    rig.poll(1)
    assert rig.host.values("a") == [100]
    rig.server.set(0, Fault.FUNCTION)
    rig.poll(2)
    assert rig.host.values("a") == [100] and rig.host.failed("a") == []   # two: not yet
    rig.poll(1)
    reason = rig.host.failed("a")[-1]
    assert "unit 1 holding 0..0 (device a): 3 unusable answers in a row" in reason
    assert "answer with function code 4 to a request with function code 3" in reason
    assert rig.host.values("a") == [100]                        # never the wrong answer
    assert rig.host.error_kinds().count("function") == 1        # reported once, at its start
    assert rig.host.error_counts["function"] == 2               # the repeats counted
    assert rig.driver.unanswered == {"function": 3}
    assert rig.host.values("b")[-1] == 110 and rig.host.failed("b") == []
    kept_the_connection(rig)
    rig.server.set(0, Fault.GOOD)
    rig.poll(1)
    assert rig.host.values("a") == [100, 100] and rig.host.recoveries == ["a"]
    assert [s.function for s in rig.server.requests(0)] == [3] * 6   # its probe, then polls


def test_a_short_byte_count_for_an_int32_is_never_a_value() -> None:
    for rig in rig_with({30: Fault.SHORT}, wide=(30, {"type": "int32"})):
        rig.poll(3)
        assert rig.host.values("wide") == []
        reason = rig.host.failed("wide")[0]     # never answered well: failed at the first one
        assert "answer of 2 data bytes to a request for 4" in reason
        assert len(rig.host.failed("wide")) == 1 and rig.driver.unanswered == {"count": 3}
        assert [(s.address, s.count) for s in rig.server.requests(30)] == [(30, 2)] * 3
        assert rig.host.values("a") == [100] * 3
        kept_the_connection(rig)


def test_another_transaction_or_unit_id_costs_that_device_alone() -> None:
    for rig in rig_with({10: Fault.TID, 20: Fault.UNIT}):
        rig.poll(4)
        assert rig.host.values("b") == [] and rig.host.values("c") == []
        assert "transaction id" in rig.host.failed("b")[0]
        assert "answer from unit 2 to a request to unit 1" in rig.host.failed("c")[0]
        assert rig.host.values("a") == [100] * 4 and rig.host.failed("a") == []
        assert rig.driver.unanswered == {"transaction": 4, "unit": 4}
        kept_the_connection(rig)


def test_a_late_answer_is_thrown_away_never_taken_for_the_next_request() -> None:
    """Register 0 answers 0.3 s late (timeout 0.2 s): its answer reaches the connection while
    the requests for b and c are outstanding; they get their own values, a's late answer is
    counted (``late-answers``) and dropped, a fails with the timeout, the connection stays."""
    for rig in rig_with({0: Fault.LATE}):
        rig.poll(5)
        assert rig.host.values("a") == []
        assert set(rig.host.values("b")) == {110} and set(rig.host.values("c")) == {120}
        assert len(rig.host.values("b")) == 5 and len(rig.host.values("c")) == 5
        assert "unit 1 holding 0..0 (device a): no response" in rig.host.failed("a")[0]
        assert rig.host.stats.get("late-answers", 0) >= 3
        assert rig.driver.unanswered == {"timeout": 6}         # its probe after connect too
        kept_the_connection(rig)


def test_a_register_that_never_answers_costs_its_device_not_the_connection() -> None:
    """The flapping of issue 46: one register always timing out made every device of the
    connection fail and recover every ~0.7 s, while the broken device ended OK with no value."""
    for rig in rig_with({10: Fault.SILENT}):
        rig.poll(6)
        assert rig.host.values("b") == []
        assert rig.host.failed("b") and "reconnect" not in str(rig.host.failed("b"))
        assert rig.host.recoveries == []
        assert rig.host.values("a") == [100] * 6 and rig.host.values("c") == [120] * 6
        assert rig.host.failed("a") == [] and rig.host.failed("c") == []
        kept_the_connection(rig)


def test_a_frozen_server_is_still_a_lost_connection() -> None:
    """Every register silent: the server answers nothing at all, which is the connection's
    failure - every device fails with the link and the driver reconnects."""
    for rig in rig_with({0: Fault.SILENT, 10: Fault.SILENT, 20: Fault.SILENT}):
        rig.poll(2)
        assert rig.host.wait_for(
            lambda h: all(any("accepted the connection but sent no response" in why
                              for why in h.failed(n)) for n in SENSORS))
        assert [s.address for s in rig.server.seen][:2] == [0, 10]   # two different probes
        assert "disconnected" in rig.host.error_kinds()
        assert rig.host.wait_for(lambda h: h.stats.get("reconnects", 0) >= 1)
        assert rig.server.connections >= 2
