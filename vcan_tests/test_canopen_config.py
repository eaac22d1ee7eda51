"""The CANopen node configuration offline (``chcos check``: identity, configuration keys, PDO
mappings against durand's own EDS) and the lifecycle state machine by itself."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from chcos.devices.spec import BusSpec
from drivers.canopen_config import NodeConfig, parse, with_bits
from drivers.canopen_lifecycle import (
    Lifecycle,
    NmtCommand,
    NmtState,
    NodeLifecycle,
    RestartPolicy,
)
from drivers.canopen_node import CanopenDriver
from drivers.canopen_od import load_od
from vcan_tests.netutil import unique_channel
from vcan_tests.peers.durand_node import DurandNode, mapping_entry


@pytest.fixture(scope="module")
def eds(tmp_path_factory: pytest.TempPathFactory) -> Path:
    node = DurandNode(unique_channel("eds"), 5)
    try:
        return node.write_eds(tmp_path_factory.mktemp("eds") / "durand.eds")
    finally:
        node.close()


def errors(eds: Path, bus_opts: dict[str, Any] | None = None, **node: Any) -> list[str]:
    bus = BusSpec(name="co", kind="canopen", key="bus[0]", options={
        "interface": "virtual", "channel": "x", **(bus_opts or {}),
        "nodes": [{"id": 5, "eds": str(eds), **node}]})
    return CanopenDriver.check_bus(bus)


def test_a_valid_configuration_passes(eds: Path) -> None:
    assert errors(eds, {"master_heartbeat_ms": 100},
                  identity={"vendor": 1, "product": 2, "revision": 3, "serial": 4},
                  config={"heartbeat_producer_ms": 50, "master_consumer_ms": 300,
                          "error_behaviour": 1,
                          "pdos": [{"pdo": "rpdo1", "cob_id": 0x205, "transmission_type": 1,
                                    "map": [[0x6040, 0], [0x6060, 0, 8], [0x607A, 0]]},
                                   {"pdo": "tpdo2", "event_timer_ms": 10, "inhibit_100us": 5,
                                    "enabled": False, "map": [[0x6041, 0]]}],
                          "sdo": [{"index": 0x6007, "value": 3}]}) == []


@pytest.mark.parametrize(("config", "expected"), [
    ({"pdos": [{"pdo": "tpdo1", "map": [[0x6064, 0], [0x607A, 0], [0x6081, 0]]}]},
     "config.pdos[0].map: 96 bits mapped, a PDO carries at most 64"),
    ({"pdos": [{"pdo": "rpdo1", "map": [[0x6041, 0]]}]},
     "config.pdos[0].map[0]: 0x6041:00 (Statusword) is read-only; an RPDO writes it"),
    ({"pdos": [{"pdo": "tpdo1", "map": [[0x1018, 1]]}]},
     "is not PDO-mappable in the node's EDS"),
    ({"pdos": [{"pdo": "tpdo1", "map": [[0x6064, 0, 16]]}]},
     "0x6064:00 is 32 bits in the node's EDS, not 16"),
    ({"pdos": [{"pdo": "tpdo1", "map": [[0x2345, 0]]}]},
     "config.pdos[0].map[0]: 0x2345:00 is not in the node's EDS"),
    ({"pdos": [{"pdo": "rpdo9"}]}, "config.pdos[0].pdo: the node's EDS has no rpdo9"),
    ({"pdos": [{"pdo": "xpdo1"}]}, "expected rpdo1..rpdo512 or tpdo1..tpdo512"),
    ({"pdos": [{"pdo": "tpdo1", "transmission_type": 250}]}, "expected 0..240 (synchronous)"),
    ({"pdos": [{"pdo": "tpdo1"}, {"pdo": "tpdo1"}]}, "tpdo1 is configured twice"),
    ({"master_consumer_ms": 300}, "the node would watch a master heartbeat the bus does not "
                                  "produce"),
    ({"heartbeat_producer_ms": 70000}, "config.heartbeat_producer_ms: expected 0..65535"),
    ({"sdo": [{"index": 0x6041, "value": 1}]}, "0x6041:00 (Statusword) is read-only"),
    ({"sdo": [{"index": 0x6060, "value": 300}]}, "does not fit 0x6060:00's data type"),
    ({"sdo": [{"index": 0x6060, "value": 1.5}]}, "expected an integer for 0x6060:00"),
    ({"colour": "red"}, "config.colour: unknown key"),
])
def test_each_configuration_error_names_its_key(eds: Path, config: dict[str, Any],
                                                expected: str) -> None:
    errs = errors(eds, config=config)
    assert len(errs) == 1 and expected in errs[0] and errs[0].startswith("bus[0].nodes[0]."), errs


def test_identity_and_master_options_are_checked(eds: Path) -> None:
    errs = errors(eds, identity={"vendor": -1, "product": 2, "colour": 1})
    assert any("identity.vendor: expected an UNSIGNED32" in e for e in errs)
    assert any("identity.revision: expected an UNSIGNED32" in e for e in errs)
    assert any("identity.colour: unknown key" in e for e in errs)
    assert any("master_consumer_ms: expected more than the bus's master_heartbeat_ms" in e
               for e in errors(eds, {"master_heartbeat_ms": 300},
                               config={"master_consumer_ms": 200}))
    assert any("master_node_id: 5 is also the id of a node" in e
               for e in errors(eds, {"master_node_id": 5}))
    assert any("master_heartbeat_ms: expected 1..65535" in e
               for e in errors(eds, {"master_heartbeat_ms": 0}))


def test_the_writes_of_a_boot_follow_cia_301(eds: Path) -> None:
    """Disable the PDO, its parameters, clear the mapping, the entries, their count, enable."""
    node = {"config": {"heartbeat_producer_ms": 50,
                       "pdos": [{"pdo": "rpdo2", "transmission_type": 255,
                                 "map": [[0x6040, 0], [0x6060, 0]]}],
                       "sdo": [{"index": 0x6081, "value": 10}]}}
    bus = BusSpec(name="co", kind="canopen", key="bus[0]", options={"nodes": []})
    od = load_od(bus, 5, str(eds))
    cfg = with_bits(parse(node), od)
    got = [(w.index, w.subindex, w.value) for w in cfg.writes(od, 5, 127)]
    assert got == [(0x1017, 0, 50), (0x1401, 1, 0x8000_0305), (0x1401, 2, 255),
                   (0x1601, 0, 0), (0x1601, 1, mapping_entry(0x6040, 0, 16)),
                   (0x1601, 2, mapping_entry(0x6060, 0, 8)), (0x1601, 0, 2),
                   (0x1401, 1, 0x305), (0x6081, 0, 10)]
    assert NodeConfig().writes(od, 5, 127) == []


def test_lifecycle_one_start_per_boot_and_held_after_the_start() -> None:
    lc = Lifecycle(5, nmt_start=True, supervised=True)
    assert lc.state is NodeLifecycle.WAITING_BOOT and not lc.ready()
    lc.identity_checked()
    lc.configured()
    lc.started()
    assert lc.state is NodeLifecycle.STARTED and lc.nmt_starts == 1
    lc.heartbeat(NmtState.PRE_OPERATIONAL)         # may have crossed the start on the wire
    assert lc.state is NodeLifecycle.STARTED
    lc.heartbeat(NmtState.PRE_OPERATIONAL)
    assert lc.state is NodeLifecycle.PREOP_HELD and not lc.ready()
    assert "stays PRE-OPERATIONAL" in lc.status().reason
    lc.heartbeat(NmtState.OPERATIONAL)             # it started after all
    assert lc.ready() and lc.status().confirmed
    lc.heartbeat(NmtState.STOPPED, now=13.25)      # confirmed before: it left, at once
    assert lc.state is NodeLifecycle.LEFT_OPERATIONAL and not lc.ready()
    assert lc.status().reason == ("left OPERATIONAL at t=13.2 s (heartbeat says STOPPED); "
                                  "restart 1 of 5 in 1.0 s")
    assert lc.booted() == 1 and lc.boots == 1 and lc.state is NodeLifecycle.WAITING_BOOT
    unsupervised = Lifecycle(6, nmt_start=True, supervised=False)
    unsupervised.configured()
    unsupervised.started()
    assert unsupervised.ready() and not unsupervised.status().confirmed
    passive = Lifecycle(7, nmt_start=False, supervised=True)
    passive.configured()
    assert passive.ready()
    passive.heartbeat(NmtState.STOPPED)
    assert not passive.ready()


def running(policy: RestartPolicy) -> Lifecycle:
    lc = Lifecycle(5, nmt_start=True, supervised=True, policy=policy)
    lc.configured()
    lc.started(0.0)
    lc.heartbeat(NmtState.OPERATIONAL, 0.5)
    assert lc.ready()
    return lc


def test_the_recovery_policy_counts_restarts_backs_off_and_ends_refusing() -> None:
    lc = running(RestartPolicy(limit=3, backoff=0.5))
    lc.heartbeat(NmtState.PRE_OPERATIONAL, 4.0)
    assert lc.state is NodeLifecycle.LEFT_OPERATIONAL
    assert lc.next_restart() == (1, 0.5)
    lc.waiting_for_cause("error register 0x1001 = 0x11")     # not cleared: no restart counted
    assert lc.next_restart() == (1, 0.5) and lc.restarts == 0
    assert "restart 1 of 3 in 0.5 s; error register 0x1001 = 0x11" in lc.status().reason
    lc.restarted()
    assert lc.state is NodeLifecycle.STARTED and lc.nmt_starts == 2
    assert "restart 1 of 3 sent" in lc.status().reason
    for _ in range(2):                                   # not taken: the next one, longer
        lc.heartbeat(NmtState.PRE_OPERATIONAL, 5.0)
    assert lc.state is NodeLifecycle.LEFT_OPERATIONAL and lc.next_restart() == (2, 1.0)
    assert "restart 1 not taken" in lc.status().reason
    lc.restarted()
    lc.heartbeat(NmtState.OPERATIONAL, 6.0)              # taken
    assert lc.ready() and lc.status().restarts == 2
    lc.heartbeat(NmtState.PRE_OPERATIONAL, 7.0)          # again, soon: the count goes on
    assert lc.next_restart() == (3, 2.0)
    lc.restarted()
    lc.heartbeat(NmtState.STOPPED, 8.0)
    lc.heartbeat(NmtState.STOPPED, 8.1)
    assert lc.state is NodeLifecycle.PREOP_HELD and lc.next_restart() is None
    assert "3 restart(s) of 3 did not keep it OPERATIONAL: it refuses" in lc.status().reason
    assert lc.cause_cleared()                            # an error-reset EMCY: a new round
    assert lc.state is NodeLifecycle.LEFT_OPERATIONAL and lc.next_restart() == (1, 0.5)


def test_restarts_count_from_zero_after_a_stable_run_and_a_boot() -> None:
    lc = running(RestartPolicy(limit=2, backoff=1.0))
    lc.heartbeat(NmtState.PRE_OPERATIONAL, 1.0)
    lc.restarted()
    lc.heartbeat(NmtState.OPERATIONAL, 2.0)
    lc.heartbeat(NmtState.PRE_OPERATIONAL, 30.0)         # ran for 28 s: counts from 0
    assert lc.next_restart() == (1, 1.0)
    lc.booted()
    assert lc.restarts == 0 and lc.status().restarts == 0


def test_a_policy_of_no_restarts_holds_the_node_saying_so() -> None:
    lc = running(RestartPolicy(limit=0))
    lc.heartbeat(NmtState.PRE_OPERATIONAL, 2.0)
    assert lc.state is NodeLifecycle.PREOP_HELD
    assert "not restarted (restart_limit = 0)" in lc.status().reason
    assert not lc.cause_cleared()


def test_the_hosts_commands_hold_and_release_a_node() -> None:
    lc = running(RestartPolicy())
    lc.host_command(NmtCommand.START, 1.0)               # running: nothing changes
    assert lc.ready() and lc.nmt_starts == 2
    lc.host_command(NmtCommand.STOP, 2.0)
    assert lc.state is NodeLifecycle.HOST_HELD and not lc.ready()
    lc.heartbeat(NmtState.STOPPED, 2.1)                  # what it was told: no recovery
    assert lc.state is NodeLifecycle.HOST_HELD and "nmt stop at t=2.0 s" in lc.reason
    lc.host_command(NmtCommand.START, 3.0)
    assert lc.state is NodeLifecycle.STARTED
    lc.heartbeat(NmtState.OPERATIONAL, 3.1)
    assert lc.ready()
    lc.host_command(NmtCommand.RESET, 4.0)
    lc.booted()
    assert lc.reason == "rebooted by the host's nmt reset (boot-up message)"
    assert NmtCommand.of_word("reset-comm") is NmtCommand.RESET_COMM
    with pytest.raises(ValueError, match="reset-comm"):
        NmtCommand.of_word("halt")


def test_a_lost_heartbeat_makes_the_status_not_ready() -> None:
    lc = running(RestartPolicy())
    lc.heartbeat_lost()
    st = lc.status("no heartbeat for more than heartbeat_timeout 0.3 s")
    assert not st.ready and st.heartbeat_lost and "heartbeat_timeout 0.3 s" in st.reason
    lc.heartbeat(NmtState.OPERATIONAL, 1.0)
    assert lc.status().ready
