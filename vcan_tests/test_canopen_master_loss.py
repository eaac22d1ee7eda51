"""The master heartbeat watched by the node (issue 36): durand given a heartbeat consumer
(:class:`vcan_tests.support_canopen_node.Cia301Node`) and configured by the driver with
``master_consumer_ms`` (0x1016:01) and ``error_behaviour`` (0x1029:01) notices when the
controller's heartbeat stops and reacts as its error behaviour says: EMCY 0x8130, then
PRE-OPERATIONAL, STOPPED or no change. In one process (the driver stopped) here; a controller
process killed with SIGKILL in :mod:`vcan_tests.test_canopen_master_kill`. What is asserted is
what the node did and what an independent observer saw on the wire."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from durand.services.nmt import StateEnum

from vcan_tests.support_canopen import NODE, durand_rig
from vcan_tests.support_canopen_node import EMCY_HEARTBEAT, Cia301Node
from vcan_tests.support_fb import make_device

DEVICES = [make_device("target", "actuator", "co", node=NODE, index=0x607A)]
MASTER = 0x700 + 127


@pytest.mark.parametrize(("behaviour", "after"), [(0, StateEnum.PRE_OPERATIONAL),
                                                   (1, StateEnum.OPERATIONAL),
                                                   (2, StateEnum.STOPPED)])
def test_the_node_reacts_to_the_master_heartbeat_stopping(tmp_path: Path, behaviour: int,
                                                          after: StateEnum) -> None:
    config = {"heartbeat_producer_ms": 20, "master_consumer_ms": 150,
              "error_behaviour": behaviour}
    with durand_rig(tmp_path, DEVICES, heartbeat_timeout=0.3, config=config,
                    bus_opts={"master_heartbeat_ms": 30}, node_cls=Cia301Node) as r:
        node = r.node
        assert isinstance(node, Cia301Node)
        assert node.wait(lambda: r.driver.node_states()[NODE].ready
                         and node.seen("consumer armed"))
        assert node.read(0x1016, 1) == (127 << 16) | 150 and node.read(0x1029, 1) == behaviour
        assert node.state == StateEnum.OPERATIONAL and node.consumer_losses == 0
        r.driver.stop()                              # the controller is gone
        stopped = time.monotonic()
        assert node.wait(lambda: node.consumer_losses == 1)
        assert node.wait(lambda: node.state == after)
        # the node said so on the wire, after the master's last heartbeat (the observer
        # records frames in the order they were sent)
        assert r.wire.wait_for(lambda w: len(w.of(0x080 + NODE, stopped)) >= 1)
        emcy = r.wire.of(0x080 + NODE, stopped)[0]
        assert int.from_bytes(emcy.data[:2], "little") == EMCY_HEARTBEAT
        frames = list(r.wire.frames)
        at = frames.index(emcy)
        assert any(f.cob_id == MASTER for f in frames[:at])
        assert not any(f.cob_id == MASTER for f in frames[at:])
        assert r.wire.wait_for(lambda w: any(f.data == bytes((after.value,))
                                             for f in w.of(0x700 + NODE, stopped)))
