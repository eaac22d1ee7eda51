"""The parallel Modbus TCP poll (``connections`` > 1): its requests are outstanding at once, each
still reports its own failure, and a server that takes fewer connections is polled over those.

The peer is a Modbus TCP server written here on purpose: it holds read requests back until it has
seen N of them at once (a barrier), which no library server does; a poll that sent its requests one
after the other would wait for its first answer forever (and time out).
"""

from __future__ import annotations

import asyncio
import struct
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest

from chcos.apps.sim.modbus_server import ModbusSimServer, RegisterStore
from chcos.devices.spec import BusSpec
from drivers.modbus import ModbusTcpDriver
from vcan_tests.netutil import free_port
from vcan_tests.support_fb import WAIT, FakeHost, make_device

#: Holding registers with gaps between them: one request each.
ADDRESSES = (0, 2, 4, 6)
#: The register the server answers with exception code 2 (illegal data address).
REFUSED = 4


@dataclass
class BarrierServer:
    """A Modbus TCP server (function 3 only) on 127.0.0.1 in its own thread. Until
    :meth:`arm` it answers at once; armed with ``n``, it holds requests until ``n`` are held,
    then answers them all. It closes every connection beyond ``max_connections`` and never
    answers a read of the register ``silent``."""

    port: int
    max_connections: int = 16
    held: list[tuple[asyncio.StreamWriter, bytes, int, int]] = field(default_factory=list)
    most_outstanding: int = 0
    connections: int = 0
    barrier: int = 0
    silent: int | None = None
    loop: asyncio.AbstractEventLoop = field(default_factory=asyncio.new_event_loop)
    thread: threading.Thread | None = None
    ready: threading.Event = field(default_factory=threading.Event)

    def start(self) -> None:
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()
        assert self.ready.wait(WAIT)

    def stop(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        assert self.thread is not None
        self.thread.join(WAIT)

    def arm(self, n: int) -> None:
        """From now on hold requests until ``n`` are held (0: answer at once)."""
        async def set_barrier() -> None:
            self.barrier = n
            self.most_outstanding = 0
        asyncio.run_coroutine_threadsafe(set_barrier(), self.loop).result(WAIT)

    def _run(self) -> None:
        asyncio.set_event_loop(self.loop)
        server = self.loop.run_until_complete(
            asyncio.start_server(self._serve, "127.0.0.1", self.port))
        self.ready.set()
        self.loop.run_forever()
        server.close()
        self.loop.run_until_complete(server.wait_closed())

    @staticmethod
    def _answer(writer: asyncio.StreamWriter, head: bytes, address: int, count: int) -> None:
        tid, _, _, unit = struct.unpack(">HHHB", head)
        if address == REFUSED:
            pdu = bytes([0x83, 2])
        else:
            pdu = bytes([3, 2 * count]) + b"".join(struct.pack(">H", address * 10 + 1 + i)
                                                   for i in range(count))
        writer.write(struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        if self.connections > self.max_connections:
            writer.close()
            return
        try:
            while True:
                head = await reader.readexactly(7)
                length = struct.unpack(">H", head[4:6])[0]
                pdu = await reader.readexactly(length - 1)
                assert pdu[0] == 3, f"the test server reads holding registers only: {pdu!r}"
                address, count = struct.unpack(">HH", pdu[1:5])
                if address == self.silent:
                    continue
                if not self.barrier:
                    self._answer(writer, head, address, count)
                    continue
                self.held.append((writer, head, address, count))
                self.most_outstanding = max(self.most_outstanding, len(self.held))
                if len(self.held) >= self.barrier:
                    for args in self.held:
                        self._answer(*args)
                    self.held.clear()
        except (asyncio.IncompleteReadError, ConnectionError):
            writer.close()


@dataclass
class Rig:
    server: BarrierServer
    driver: ModbusTcpDriver
    host: FakeHost


def rig_with(connections: int, max_connections: int = 16) -> Iterator[Rig]:
    port = free_port()
    server = BarrierServer(port, max_connections=max_connections)
    server.start()
    bus = BusSpec(name="mb", kind="modbus-tcp", key="bus[1]",
                  options={"host": "127.0.0.1", "port": port, "timeout": 1.0, "retries": 0,
                           "reconnect_delay": 0.02, "connections": connections})
    devices = [make_device(f"r{a}", "sensor", "mb", table="holding", address=a)
               for a in ADDRESSES]
    host = FakeHost()
    driver = ModbusTcpDriver(bus, devices, host)
    driver.start()
    try:
        yield Rig(server, driver, host)
    finally:
        driver.stop()
        server.stop()


@pytest.fixture
def parallel() -> Iterator[Rig]:
    yield from rig_with(len(ADDRESSES))


def test_poll_sends_its_requests_at_once_and_reports_each_failure(parallel: Rig) -> None:
    parallel.host.tick(0.1)                # lanes opened and probed, unarmed
    assert parallel.driver.settle(WAIT)
    before = len(parallel.host.values("r0"))
    parallel.server.arm(len(ADDRESSES))    # nothing is answered before all 4 are outstanding
    parallel.host.tick(0.1)
    assert parallel.driver.settle(WAIT)
    assert parallel.server.most_outstanding == len(ADDRESSES)
    assert len(parallel.host.values("r0")) == before + 1
    assert parallel.host.values("r0")[-1] == 1
    assert parallel.host.values("r2")[-1] == 21
    assert parallel.host.values("r6")[-1] == 61
    assert parallel.host.values("r4") == []
    assert any("exception code 2" in why for why in parallel.host.failed("r4"))
    assert all(parallel.host.failed(d) == [] for d in ("r0", "r2", "r6"))
    assert "exception-2" in parallel.host.error_kinds()
    assert "timeout" not in parallel.host.error_kinds()
    assert "connections" not in parallel.host.error_kinds()


def test_a_register_never_answered_costs_its_device_not_the_connection(parallel: Rig) -> None:
    """One connection of a parallel poll gets no answer for one register (issue 46): the
    requests on the other connections are answered and delivered, the silent register's device
    fails with the timeout, nobody else fails, the connection is kept (no reconnect), and the
    device recovers once its register answers again."""
    rig = parallel
    rig.host.tick(0.1)                     # lanes opened and probed
    assert rig.driver.settle(WAIT)
    before = {d: len(rig.host.values(d)) for d in ("r0", "r2")}
    mark = len(rig.host.errors)
    rig.server.silent = 6
    for _ in range(3):
        rig.host.tick(0.1)
        assert rig.driver.settle(WAIT)
    assert {d: len(rig.host.values(d)) for d in ("r0", "r2")} == {"r0": before["r0"] + 3,
                                                                    "r2": before["r2"] + 3}
    poll = [(k, detail) for _, k, detail in rig.host.errors[mark:]]
    assert [k for k, _ in poll] == ["timeout"], poll          # reported once, at its start
    assert "unit 1 holding 6..6" in dict(poll)["timeout"]
    assert rig.host.error_counts == {"timeout": 2, "exception-2": 3}   # repeats: counted only
    assert "unit 1 holding 6..6 (device r6): no response" in rig.host.failed("r6")[-1]
    assert all(rig.host.failed(d) == [] for d in ("r0", "r2"))
    assert "disconnected" not in rig.host.error_kinds() and "reconnects" not in rig.host.stats
    rig.server.silent = None
    rig.host.tick(0.1)
    assert rig.driver.settle(WAIT)
    assert rig.host.values("r6")[-1] == 61 and rig.host.recoveries == ["r6"]


def test_a_server_taking_fewer_connections_is_polled_over_those() -> None:
    for rig in rig_with(len(ADDRESSES), max_connections=2):
        rig.host.tick(0.1)                 # the third connection is closed: two lanes
        assert rig.driver.settle(WAIT)
        assert "connections" in rig.host.error_kinds()
        rig.server.arm(2)                  # two outstanding at once is what it can take
        rig.host.tick(0.1)
        assert rig.driver.settle(WAIT)
        assert rig.server.most_outstanding == 2
        assert rig.host.values("r0")[-1] == 1 and rig.host.values("r6")[-1] == 61
        assert len(rig.host.values("r2")) == 2
        assert all(rig.host.failed(d) == [] for d in ("r0", "r2", "r6"))
        assert "timeout" not in rig.host.error_kinds()
        assert "disconnected" not in rig.host.error_kinds()


def test_connections_option_is_checked() -> None:
    for bad, text in ((0, "1..16"), (17, "1..16"), ("4", "an integer"), (True, "an integer")):
        bus = BusSpec(name="mb", kind="modbus-tcp", key="bus[1]",
                      options={"host": "127.0.0.1", "connections": bad})
        errs: list[Any] = ModbusTcpDriver.check_bus(bus)
        assert any(e.startswith("bus[1].connections: expected") and text in e
                   for e in errs), (bad, errs)


def test_lost_server_fails_every_device_and_its_return_recovers_them() -> None:
    """Against pymodbus' own server: the parallel poll keeps the link rules (every device fails
    with the reason when the server goes, all recover when it is back, values flow again)."""
    store = RegisterStore((1,), size=20)
    port = free_port()
    server = ModbusSimServer(store, port)
    server.start()
    bus = BusSpec(name="mb", kind="modbus-tcp", key="bus[1]",
                  options={"host": "127.0.0.1", "port": port, "timeout": 0.5, "retries": 0,
                           "reconnect_delay": 0.02, "reconnect_delay_max": 0.1,
                           "connections": 3})
    devices = [make_device(f"r{a}", "sensor", "mb", table="holding", address=a)
               for a in ADDRESSES]
    names = {d.name for d in devices}
    host = FakeHost()
    driver = ModbusTcpDriver(bus, devices, host)
    driver.start()
    try:
        store.set_value(1, "holding", 6, 7, "uint16")
        host.tick(0.1)
        assert driver.settle(WAIT)
        assert host.values("r6") == [7] and host.values("r0") == [0]
        server.stop()
        host.tick(0.1)
        assert driver.settle(WAIT)
        assert host.wait_for(lambda h: {d for d, _ in h.failures} == names)
        assert f"127.0.0.1:{port}" in host.failed("r2")[0]
        server.start()
        assert host.wait_for(lambda h: set(h.recoveries) == names)
        store.set_value(1, "holding", 6, 99, "uint16")
        host.tick(0.1)
        assert driver.settle(WAIT)
        assert host.values("r6")[-1] == 99
    finally:
        driver.stop()
        server.stop()
