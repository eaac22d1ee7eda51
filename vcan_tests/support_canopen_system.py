"""support_canopen_system - a whole chcos system (device map, tasks, system file) driving one
durand node (:mod:`vcan_tests.peers.durand_node`) on a python-can virtual channel, for the tests
of what users see of the node's lifecycle and the SYNC cycle (map, metrics, OPC UA, ``chcos
run``) and of tasks waiting for the cycle."""

from __future__ import annotations

from pathlib import Path

from vcan_tests.peers.durand_node import DurandNode

NODE = 5

#: target (0x607A) in RPDO1, position (0x6064) in a synchronous TPDO1: one per SYNC
DEVMAP = """
[[bus]]
name = "co"
kind = "canopen"
interface = "virtual"
channel = "{channel}"
sdo_timeout = 0.2
sync_period = {sync_period}

[[bus.nodes]]
id = {node}
eds = "{eds}"
heartbeat_timeout = 0.3

[bus.nodes.config]
heartbeat_producer_ms = 20
pdos = [
  {{ pdo = "rpdo1", transmission_type = 255, map = [[0x607A, 0]] }},
  {{ pdo = "tpdo1", transmission_type = 1, map = [[0x6064, 0]] }},
]

[[device]]
name = "pos"
direction = "sensor"
machine = 0
bus = "co"
address = {{ node = {node}, index = 0x6064 }}

[[device]]
name = "target"
direction = "actuator"
machine = 0
bus = "co"
address = {{ node = {node}, index = 0x607A }}
limits = [-1000000, 1000000]
safe_value = 0
"""


def write_devmap(tmp_path: Path, node: DurandNode, sync_period: float = 0.01) -> Path:
    """The device map of ``node`` (its EDS written beside it) in ``tmp_path``."""
    eds = node.write_eds(tmp_path / "node.eds")
    path = tmp_path / "devices.toml"
    path.write_text(DEVMAP.format(channel=node.channel, node=node.node_id, eds=eds,
                                  sync_period=sync_period), encoding="utf-8")
    return path
