"""Storing a node's configuration (0x1010, the node key ``store_config``) against durand given
store parameters (:class:`vcan_tests.support_canopen_node.Cia301Node`), issue 36: the "save"
signature goes to the chosen sub-index once the download was read back, confirmed by the node's
answer; a node that came up with its stored configuration is not stored again (flash wear); a
refused store fails the configuration naming the object; ``check`` refuses ``store_config`` for
an EDS without 0x1010. Asserted: what the node's dictionary received and what it keeps over a
power cycle, and the frames an independent observer saw."""

from __future__ import annotations

from pathlib import Path

from durand.services.nmt import StateEnum

from drivers.canopen_lifecycle import NodeLifecycle
from drivers.canopen_node import CanopenDriver
from vcan_tests.peers.durand_node import mapping_entry, sdo_downloads
from vcan_tests.support_canopen import NODE, canopen_bus, durand_rig
from vcan_tests.support_canopen_node import SAVE, Cia301Node
from vcan_tests.support_fb import make_device

DEVICES = [make_device("pos", "sensor", "co", node=NODE, index=0x6064),
           make_device("target", "actuator", "co", node=NODE, index=0x607A)]
CONFIG = {"heartbeat_producer_ms": 20,
          "pdos": [{"pdo": "rpdo1", "map": [[0x607A, 0]]},
                   {"pdo": "tpdo1", "map": [[0x6064, 0]]}]}


def test_the_configuration_is_stored_once_and_kept_over_a_power_cycle(tmp_path: Path) -> None:
    with durand_rig(tmp_path, DEVICES, heartbeat_timeout=0.3, config=CONFIG,
                    store_config=True, node_cls=Cia301Node) as r:
        node = r.node
        assert isinstance(node, Cia301Node)
        assert node.wait(lambda: r.driver.node_states()[NODE].ready)
        # the node received the save signature at 0x1010:01, after the configuration
        saves = sdo_downloads(r.wire.frames, NODE, 0x1010, 1)
        assert saves == [SAVE] and node.saves == 1
        frames = r.wire.frames
        save_at = next(f.at for f in frames if sdo_downloads([f], NODE, 0x1010, 1))
        mapped_at = max(f.at for f in frames if sdo_downloads([f], NODE, 0x1A00, 1))
        assert mapped_at < save_at
        assert node.stored.heartbeat_ms == 20 and node.stored.tpdo == {1: [(0x6064, 0)]}
        assert node.stored.rpdo == {1: [(0x607A, 0)]}
        assert r.driver.status_doc()["nodes"][0]["config_stores"] == 1
        # a power cycle: the node comes back with what it stored, so nothing is stored again
        node.power_cycle()
        assert node.read(0x1017, 0) == 20 and node.read(0x1A00, 1) == mapping_entry(
            0x6064, 0, 32)
        assert node.wait(lambda: (st := r.driver.node_states()[NODE]).boots == 1 and st.ready)
        assert node.state == StateEnum.OPERATIONAL
        assert sdo_downloads(r.wire.frames, NODE, 0x1010, 1) == [SAVE] and node.saves == 1
        assert r.driver.node_states()[NODE].stores == 1
        node.write(0x6064, 0, 99)                     # the stored TPDO mapping still works
        assert r.host.wait_for(lambda h: 99 in h.values("pos"))


def test_the_sub_index_chosen_is_the_one_written(tmp_path: Path) -> None:
    with durand_rig(tmp_path, DEVICES, heartbeat_timeout=0.3, config=CONFIG,
                    store_config=2, node_cls=Cia301Node) as r:
        assert r.node.wait(lambda: r.driver.node_states()[NODE].ready)
        assert sdo_downloads(r.wire.frames, NODE, 0x1010, 2) == [SAVE]
        assert sdo_downloads(r.wire.frames, NODE, 0x1010, 1) == []
        assert r.node.seen("saved 0x1010:02")           # type: ignore[attr-defined]


def test_a_refused_store_fails_the_configuration_naming_the_object(tmp_path: Path) -> None:
    with durand_rig(tmp_path, DEVICES, heartbeat_timeout=0.3, config=CONFIG,
                    store_config=True, node_cls=Cia301Node, start=False) as r:
        r.node.abort_writes(0x1010, 1)
        r.driver.start()
        assert r.host.wait_for(lambda h: "config" in h.error_kinds())
        detail = next(d for _, k, d in r.host.errors if k == "config")
        assert "0x1010:01 (store parameters (\"save\")) = 1702257011 aborted" in detail
        assert "0x08000020" in detail
        st = r.driver.node_states()[NODE]
        assert st.lifecycle is NodeLifecycle.FAILED and st.stores == 0
        assert r.node.saves == 0                        # type: ignore[attr-defined]
        assert r.wire.nmt_starts(NODE) == 0


def test_check_refuses_store_config_without_0x1010_in_the_eds(tmp_path: Path) -> None:
    with durand_rig(tmp_path, [], start=False) as r:       # durand's own EDS: no 0x1010
        errs = CanopenDriver.check_bus(canopen_bus(r.channel, r.eds, store_config=True))
        assert errs == ["bus[0].nodes[0].store_config: the node's EDS has no object 0x1010 "
                        "(store parameters): the node cannot store its configuration; remove "
                        "store_config"]
        assert CanopenDriver.check_bus(canopen_bus(r.channel, r.eds, store_config=False)) == []
    with durand_rig(tmp_path, [], start=False, node_cls=Cia301Node) as r:
        assert CanopenDriver.check_bus(canopen_bus(r.channel, r.eds, store_config=True)) == []
        errs = CanopenDriver.check_bus(canopen_bus(r.channel, r.eds, store_config=9))
        assert errs == ["bus[0].nodes[0].store_config: the node's EDS has no 0x1010:09 "
                        "(store parameters sub-index 9)"]
        errs = CanopenDriver.check_bus(canopen_bus(r.channel, r.eds, store_config="yes"))
        assert len(errs) == 1 and "store_config: expected true, false or a sub-index" in errs[0]
