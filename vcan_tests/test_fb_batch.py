"""A poll's readings reach the host as one batch (one kernel interrupt): the helper
``drivers.base.deliver_all``, ``Devtab.deliver_many``, and the Modbus and CANopen drivers' polls
against servers they did not write (pymodbus' server under chcos' simulator, canopen's LocalNode
under the simulated drive)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from chcos.apps.sim.canopen_slave import SERVO_EDS, CanopenSlave
from chcos.apps.sim.modbus_server import ModbusSimServer, RegisterStore
from chcos.devices.devtab import Devtab
from chcos.devices.spec import BusSpec, DeviceMap, DeviceSpec
from chcos.kernel.clock import VirtualClock
from chcos.kernel.scheduler import Kernel
from drivers.base import deliver_all
from drivers.canopen_node import CanopenDriver
from drivers.modbus import ModbusTcpDriver
from vcan_tests.conftest import memory_map
from vcan_tests.netutil import free_port, unique_channel
from vcan_tests.support_fb import WAIT, FakeHost, make_device


class BatchHost(FakeHost):
    """A FakeHost that also takes batches: each ``deliver_many`` call is kept as one batch (and
    its readings recorded as delivered, in order)."""

    def __init__(self) -> None:
        super().__init__()
        self.batches: list[list[tuple[str, Any]]] = []

    def deliver_many(self, readings: Sequence[tuple[str, Any]],
                     at: float | None = None) -> None:
        with self.cond:
            self.batches.append(list(readings))
            self.delivered.extend(readings)
            self.cond.notify_all()


def test_deliver_all_uses_deliver_many_where_the_host_has_it_else_deliver() -> None:
    plain, batching = FakeHost(), BatchHost()
    readings = [("a", 1), ("b", 2.5), ("a", 3)]
    deliver_all(plain, readings)
    deliver_all(batching, readings)
    deliver_all(batching, [])            # nothing read: no interrupt at all
    assert plain.delivered == readings
    assert batching.batches == [readings] and batching.delivered == readings


def test_devtab_takes_a_batch_as_one_interrupt_and_keeps_the_others_past_a_bad_one() -> None:
    heard: list[tuple[str, Any]] = []

    class Listener:
        def reading(self, device: str, value: Any) -> bool:
            if value == "boom":
                raise RuntimeError("listener failed")
            heard.append((device, value))
            return False

        def sensor_failed(self, device: str, failure: Any) -> None:
            """Not part of this test."""

    clock = VirtualClock(7.0)
    k = Kernel(clock)
    dt = Devtab(k, local=[0])
    dm = memory_map(["S1", "S2"], [])
    scaled = DeviceSpec("S3", "sensor", 0, dm.buses[0].name, scale=2.0, offset=1.0)
    dt.load(DeviceMap(dm.buses, (*dm.devices, scaled)))
    dt.listen(Listener())
    dt.deliver_many([("S1", 1.0), ("S2", "boom"), ("nobody", 4.0), ("S3", 10)])
    assert len(k._irq) == 1                     # one interrupt for the whole poll
    k.run()
    assert heard == [("S1", 1.0), ("S3", 21.0)]
    assert dt.get("S1").value == 1.0 and dt.get("S3").value == 21.0
    assert dt.get("S1").rx_at == 7.0 and dt.get("S3").rx_at == 7.0
    assert dt.bus_errors[("?", "unknown-device")] == 1
    assert any("listener failed" in e for e in k.irq_errors)   # recorded, not swallowed


def test_modbus_poll_delivers_its_readings_as_one_batch_and_failures_apart() -> None:
    store = RegisterStore((1,), size=40)
    for a in (0, 2, 4):
        store.set_value(1, "holding", a, 100 + a, "uint16")
    store.set_value(1, "holding", 10, 2.5, "float32")
    devices = [make_device("r0", "sensor", "mb", table="holding", address=0),
               make_device("r2", "sensor", "mb", table="holding", address=2),
               make_device("r4", "sensor", "mb", table="holding", address=4),
               make_device("f", "sensor", "mb", table="holding", address=10, type="float32"),
               make_device("edge", "sensor", "mb", table="holding", address=39, type="float32")]
    port = free_port()
    host = BatchHost()
    bus = BusSpec(name="mb", kind="modbus-tcp", key="bus[0]",
                  options={"host": "127.0.0.1", "port": port, "timeout": 0.5, "retries": 0})
    with ModbusSimServer(store, port):
        driver = ModbusTcpDriver(bus, devices, host)
        driver.start()
        try:
            for _ in range(2):
                host.tick(0.1)
                assert driver.settle(WAIT)
        finally:
            driver.stop()
    # 5 requests per poll (gaps between the registers); each poll's 4 readings in one batch
    want = [("r0", 100), ("r2", 102), ("r4", 104), ("f", 2.5)]
    assert host.batches == [want, want]
    assert "exception code 2" in host.failed("edge")[0]
    assert host.values("edge") == []


def test_canopen_sdo_poll_delivers_its_objects_as_one_batch() -> None:
    channel = unique_channel("batch")
    slave = CanopenSlave(5, channel=channel, heartbeat_period=0)
    slave.start()
    slave.set(0x606C, 0, -321)
    slave.set(0x2000, 0, 45)
    slave.set(0x6081, 0, 1500)
    host = BatchHost()
    bus = BusSpec(name="co", kind="canopen", key="bus[0]",
                  options={"interface": "virtual", "channel": channel, "sdo_timeout": 0.5,
                           "nodes": [{"id": 5, "eds": str(SERVO_EDS), "nmt_start": False}]})
    devices = [make_device("vel", "sensor", "co", node=5, index=0x606C),
               make_device("temp", "sensor", "co", node=5, index=0x2000),
               make_device("speed", "sensor", "co", node=5, index=0x6081)]
    driver = CanopenDriver(bus, devices, host)
    try:
        driver.start()
        host.tick(0.1)
        assert driver.settle(WAIT)
    finally:
        driver.stop()
        slave.stop()
    assert len(host.batches) == 1
    assert host.batches[0] == [("vel", -321), ("temp", 45), ("speed", 1500)]
    assert host.failures == []


def test_raw_can_frames_received_together_reach_the_host_as_one_batch_in_order() -> None:
    """The raw CAN driver hands the frames one drain takes (up to 64) to the host as one
    batch, in the order a python-can peer sent them, and counts them once; an undecodable
    frame among them is reported as it is met and does not hold the others back."""
    import can

    from drivers.can_raw import CanDriver

    channel = unique_channel("canbatch")
    host = BatchHost()
    bus = BusSpec(name="c0", kind="can", key="bus[0]",
                  options={"interface": "virtual", "channel": channel})
    devices = [make_device("s1", "sensor", "c0", id=0x101, start=0, length=16, dlc=2),
               make_device("s2", "sensor", "c0", key="device[1]", id=0x102, start=0,
                           length=8, dlc=1)]
    driver = CanDriver(bus, devices, host)
    peer = can.Bus(interface="virtual", channel=channel)
    driver.start()
    try:
        with driver._rx.lock:          # the reader cannot drain while the peer sends
            for v in (1, 2, 3):
                peer.send(can.Message(arbitration_id=0x101, data=v.to_bytes(2, "little"),
                                      is_extended_id=False))
            peer.send(can.Message(arbitration_id=0x102, data=b"\x01\x02",   # wrong length
                                  is_extended_id=False))
            peer.send(can.Message(arbitration_id=0x102, data=b"\x07", is_extended_id=False))
        assert driver.settle(WAIT)     # one drain takes all five
    finally:
        driver.stop()
        peer.shutdown()
    assert host.batches == [[("s1", 1), ("s1", 2), ("s1", 3), ("s2", 7)]]
    assert host.stats.get("frames") == 5 and driver.received == 5
    assert [e[1] for e in host.errors] == ["wrong-length"]
