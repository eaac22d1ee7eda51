"""chcos' CANopen driver against the strict simulated node: a map that is wrong for the device
fails against its simulation the way it would at the cell, with the device's abort."""

from __future__ import annotations

from chcos.apps.sim.canopen_slave import SERVO_EDS, CanopenSlave, Clock
from chcos.devices.spec import BusSpec
from drivers.canopen_node import CanopenDriver
from vcan_tests.netutil import unique_channel
from vcan_tests.support_fb import WAIT, FakeHost, make_device

NODE = 5


def test_a_sensor_on_sub_index_1_of_a_plain_object_fails_with_the_devices_abort() -> None:
    channel = unique_channel("cosim-master")
    slave = CanopenSlave(NODE, channel=channel, heartbeat_period=0, clock=Clock.TICK)
    bus = BusSpec(name="co", kind="canopen", key="bus[0]",
                  options={"interface": "virtual", "channel": channel, "sdo_timeout": 0.5,
                           "nodes": [{"id": NODE, "eds": str(SERVO_EDS)}]})
    # 0x6064 is a plain INTEGER32: it has sub-index 0 only
    device = make_device("pos", "sensor", "co", node=NODE, index=0x6064, subindex=1)
    host = FakeHost()
    slave.start()
    driver = CanopenDriver(bus, [device], host)
    driver.start()
    try:
        assert slave.wait_state("OPERATIONAL", WAIT)
        host.tick(0.1)
        assert driver.settle(WAIT)
        assert host.values("pos") == []                        # never a value (it was 0)
        reasons = host.failed("pos")
        assert reasons and "0x6064:01" in reasons[0] and "0x06090011" in reasons[0], reasons
    finally:
        driver.stop()
        slave.stop()
