"""The typed driver status (chcos.devices.status): what a driver shows beyond the counters
travels as frozen dataclasses, becomes JSON only at the edge and is read back strictly; a driver
still on the older status_doc is read through the same type."""

from __future__ import annotations

import re
from typing import Any

import pytest

from chcos.devices.status import BusState, DriverStatus, ErrorState, NodeStatus, SyncStatus
from chcos.system.textview import bus_status_lines, render_text
from drivers.memory import MemoryDriver
from vcan_tests.support_dev import FakeHost, bus, device

NODE = NodeStatus(node=5, state="OPERATIONAL", ready=True, confirmed=True, nmt="OPERATIONAL",
                  boots=2, nmt_starts=1, error_register=0x81, last_emcy="0x8130")
SYNC = SyncStatus(period=0.01, cycles=100, complete=98, missing=2, late=1, jitter_p50=1e-4,
                  jitter_p99=3e-4, jitter_max=5e-4, late_writes=3)
STATE = BusState(ErrorState.ERROR_PASSIVE, tx_errors=130, rx_errors=0, bus_offs=1)


def test_the_json_edge_round_trips_and_keeps_the_documented_keys() -> None:
    st = DriverStatus((NODE,), SYNC, STATE)
    doc = st.to_json()
    assert doc["nodes"][0]["node"] == 5 and doc["nodes"][0]["error_register"] == 0x81
    assert doc["sync"]["late_writes"] == 3 and doc["bus_state"]["state"] == "error-passive"
    assert DriverStatus.from_json(doc) == st
    assert not DriverStatus() and DriverStatus().to_json() == {}
    assert DriverStatus(sync=SYNC).to_json().keys() == {"sync"}


@pytest.mark.parametrize(("doc", "message"), [
    ({"node": []}, "status: unknown key 'node'"),
    ({"nodes": [{"node": 1, "state": "X", "ready": True, "colour": 1}]},
     "nodes[0]: unknown key 'colour'"),
    ({"nodes": [{"node": 1}]}, "nodes[0]:"),
    ({"bus_state": {"state": "asleep"}}, "bus_state.state: expected one of error-active"),
    ({"sync": 3}, "sync: expected an object"),
])
def test_a_document_it_does_not_know_is_refused_naming_the_key(doc: dict[str, Any],
                                                               message: str) -> None:
    with pytest.raises(ValueError, match=re.escape(message)):
        DriverStatus.from_json(doc)


class _OldStyle(MemoryDriver):
    kind = "memory"

    def status_doc(self) -> dict[str, Any]:
        return {"nodes": [{"node": 3, "state": "BOOTING", "ready": False, "reason": "no boot-up"}]}


def test_a_driver_on_status_doc_is_read_through_the_type() -> None:
    drv = _OldStyle(bus("memory"), [device("A", "actuator")], FakeHost())
    assert drv.status() == DriverStatus((NodeStatus(3, "BOOTING", False, reason="no boot-up"),))
    plain = MemoryDriver(bus("memory"), [device("A", "actuator")], FakeHost())
    assert plain.status() == DriverStatus() and not plain.status()


def test_the_text_view_reads_the_type_and_the_map_reads_the_json() -> None:
    lines = bus_status_lines({"axis": DriverStatus((NODE,), SYNC, STATE)})
    assert lines[0].startswith("node     axis/5") and "error register 0x81" in lines[0]
    assert "100 cycles of 10 ms, 98 complete, 2 TPDOs missing" in lines[1]
    assert lines[2].split() == ["CAN", "axis", "error-passive,", "TEC", "130,", "REC", "0,",
                                "1", "bus-off(s),", "0", "restart(s),", "0", "time(s)",
                                "error-passive,", "0", "error", "frame(s)"]
    text = render_text({"tasks": [], "links": [], "machines": [0],
                        "bus_status": {"axis": DriverStatus((NODE,)).to_json()}})
    assert "node     axis/5" in text
