"""The OPC UA server shows each CANopen node's lifecycle and the SYNC cycle (issue 36), browsed
by asyncua's own client, against a durand node rebooted while the server runs: the server on a
thread of the system's process and in a process of its own (``--opcua``'s default)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from asyncua.sync import Client

from chcos.kernel.clock import RealClock
from chcos.north.opcua import OpcUaServer
from chcos.north.opcua_process import OpcUaProcess
from chcos.system.embedded import System
from vcan_tests.netutil import unique_channel
from vcan_tests.peers.durand_node import WAIT, DurandNode
from vcan_tests.support_canopen_system import NODE, write_devmap

TIMEOUT = 4 * WAIT


class Changes:
    """asyncua subscription handler: every value of every node subscribed, with a condition."""

    def __init__(self) -> None:
        self.values: dict[str, list[Any]] = {}
        self.cond = threading.Condition()

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        with self.cond:
            self.values.setdefault(node.nodeid.Identifier, []).append(val)
            self.cond.notify_all()

    def wait(self, pred: Any) -> bool:
        with self.cond:
            return bool(self.cond.wait_for(pred, TIMEOUT))

    def last(self, key: str) -> Any:
        got = self.values.get(key)
        return got[-1] if got else None


def until(pred: Any) -> bool:
    """Poll ``pred`` (the server's address space, browsed) until it holds; False on timeout."""
    deadline = time.monotonic() + TIMEOUT
    pause = threading.Event()
    while not pred():
        if time.monotonic() > deadline:
            return False
        pause.wait(0.05)
    return True


@pytest.fixture(params=["thread", "process"])
def served(tmp_path: Path, request: pytest.FixtureRequest
           ) -> Iterator[tuple[System, Any, DurandNode]]:
    node = DurandNode(unique_channel("opcua"), NODE)
    s = System([write_devmap(tmp_path, node)], clock=RealClock(), machines=[0],
               base_dir=tmp_path)
    s.start()
    kind = OpcUaServer if request.param == "thread" else OpcUaProcess
    o = kind(s, "opc.tcp://127.0.0.1:0/chcos/").start()
    try:
        yield s, o, node
    finally:
        o.stop()
        s.shutdown()
        node.close()


def test_opcua_browses_the_nodes_lifecycle_and_the_sync_cycle(
        served: tuple[System, Any, DurandNode]) -> None:
    _s, o, node = served
    c = Client(o.endpoint, timeout=TIMEOUT)
    c.connect()
    try:
        i = c.get_namespace_index("urn:chcos")
        buses = c.get_node(f"ns={i};s=Buses")
        changes = Changes()
        sub = c.create_subscription(20, changes)
        # the bus object appears with the first refresh of the slow figures
        n5 = f"Buses.co.Node{NODE}"
        assert until(lambda: any(ch.read_browse_name().Name == "co"
                                 for ch in buses.get_children()))
        bus = next(ch for ch in buses.get_children() if ch.read_browse_name().Name == "co")
        assert {ch.read_browse_name().Name for ch in bus.get_children()} >= {f"Node{NODE}",
                                                                              "Sync"}
        fields = {ch.read_browse_name().Name for ch in c.get_node(f"ns={i};s={n5}")
                  .get_children()}
        assert fields == {"State", "Ready", "HeartbeatLost", "Boots", "NmtStarts",
                          "HeartbeatLosses", "Emcys", "ErrorRegister", "LastEmcy", "Reason"}
        for name in ("State", "Boots", "Ready", "HeartbeatLost", "HeartbeatLosses", "Emcys"):
            sub.subscribe_data_change(c.get_node(f"ns={i};s={n5}.{name}"))
        sub.subscribe_data_change(c.get_node(f"ns={i};s=Buses.co.Sync.Cycles"))
        assert changes.wait(lambda: changes.last(f"{n5}.State") == "OPERATIONAL"
                            and changes.last(f"{n5}.Boots") == 0)
        node.power_cycle()                           # a reboot: seen, configured again
        assert changes.wait(lambda: changes.last(f"{n5}.Boots") == 1
                            and changes.last(f"{n5}.State") == "OPERATIONAL"
                            and changes.last(f"{n5}.Ready") is True)
        assert node.read(0x1017) == 20               # what the node holds
        assert changes.wait(lambda: (changes.last("Buses.co.Sync.Cycles") or 0) >= 10)
        assert c.get_node(f"ns={i};s=Buses.co.Sync.Period").read_value() == 0.01
        assert c.get_node(f"ns={i};s={n5}.ErrorRegister").read_value() == 0
        assert c.get_node(f"ns={i};s={n5}.NmtStarts").read_value() == 2
        # an EMCY and its reset, then the node's heartbeat stops and comes back: counted
        assert changes.last(f"{n5}.Emcys") == 0
        losses = c.get_node(f"ns={i};s={n5}.HeartbeatLosses").read_value()
        node.emcy(0x1000, 0x01)
        node.emcy(0x0000, 0x00)
        assert changes.wait(lambda: changes.last(f"{n5}.Emcys") == 2)
        node.write(0x1017, 0, 0)
        assert changes.wait(lambda: changes.last(f"{n5}.HeartbeatLost") is True
                            and changes.last(f"{n5}.HeartbeatLosses") >= losses + 1)
        node.write(0x1017, 0, 20)
        assert changes.wait(lambda: changes.last(f"{n5}.HeartbeatLost") is False)
        assert c.get_node(f"ns={i};s={n5}.HeartbeatLosses").read_value() >= losses + 1
    finally:
        c.disconnect()
