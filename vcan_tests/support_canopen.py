"""support_canopen - the rig of the CANopen driver tests against durand
(:mod:`vcan_tests.peers.durand_node`): a durand node, an observer of the wire, the driver on the
same virtual channel reporting to a :class:`vcan_tests.support_fb.FakeHost`."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from chcos.devices.spec import BusSpec, DeviceSpec
from drivers.canopen_node import CanopenDriver
from vcan_tests.netutil import unique_channel
from vcan_tests.peers.durand_node import DurandNode, Wire
from vcan_tests.support_fb import FakeHost

NODE = 5
IDENTITY = {"vendor": 0x1234, "product": 0x42, "revision": 0x10001}


@dataclass
class Rig:
    """A durand node, the wire, the driver and its host."""

    node: DurandNode
    wire: Wire
    driver: CanopenDriver
    host: FakeHost
    channel: str
    eds: Path


def canopen_bus(channel: str, eds: Path, bus_opts: dict[str, Any] | None = None,
                **node_opts: Any) -> BusSpec:
    """A canopen bus on virtual ``channel`` with node :data:`NODE` described by ``eds``."""
    node = {"id": NODE, "eds": str(eds), **node_opts}
    return BusSpec(name="co", kind="canopen", key="bus[0]",
                   options={"interface": "virtual", "channel": channel, "nodes": [node],
                            "sdo_timeout": 0.2, **(bus_opts or {})})


@contextmanager
def durand_rig(tmp_path: Path, devices: list[DeviceSpec], *, node_kw: dict[str, Any] | None = None,
               eds_defaults: dict[str, int] | None = None, bus_opts: dict[str, Any] | None = None,
               start: bool = True, node_cls: type[DurandNode] = DurandNode,
               **node_opts: Any) -> Iterator[Rig]:
    """Node first (it boots before the driver), then the observer, then the driver;
    ``node_cls`` the node's class (a :class:`DurandNode`, or one with more of CiA 301:
    :mod:`vcan_tests.support_canopen_node`)."""
    channel = unique_channel("co")
    node = node_cls(channel, NODE, **(node_kw or {}))
    eds = node.write_eds(tmp_path / "node.eds", eds_defaults)
    wire = Wire(channel)
    host = FakeHost()
    driver = CanopenDriver(canopen_bus(channel, eds, bus_opts, **node_opts), devices, host)
    try:
        if start:
            driver.start()
        yield Rig(node, wire, driver, host, channel, eds)
    finally:
        driver.stop()
        wire.close()
        node.close()
