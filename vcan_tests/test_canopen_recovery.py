"""A CANopen node that leaves OPERATIONAL by itself comes back by the driver's recovery policy
(issue 46): durand nodes (an independent CANopen stack) that drop to PRE-OPERATIONAL on their own,
with or without an error register set, that lose their heartbeat and come back, that refuse every
restart; the host's NMT commands; a command queued before a reboot is not sent before the node's
configuration; a sensor that receives only NaN fails. What is asserted is what the node did and
saw (its NMT state, the NMT starts on the wire as an independent observer recorded them, its
object dictionary) and what the driver reported. The policy's backoff runs on the host's clock:
the test's fake host moves it (``tick``), so the waits are exact."""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from durand.datatypes import DatatypeEnum as DT
from durand.services.nmt import StateEnum

from chcos.devices.spec import BusSpec
from chcos.errors import BusError, CommandSyntaxError, InstallError
from drivers.canopen_lifecycle import NodeLifecycle
from drivers.canopen_node import CanopenDriver
from vcan_tests.netutil import unique_channel
from vcan_tests.peers.durand_node import DRIVE_OBJECTS, DurandNode, Stored, Wire
from vcan_tests.support_canopen import NODE, Rig, durand_rig
from vcan_tests.support_faults import run_until
from vcan_tests.support_fb import WAIT, FakeHost, make_device

DEVICES = [
    make_device("pos", "sensor", "co", node=NODE, index=0x6064),
    make_device("target", "actuator", "co", node=NODE, index=0x607A),
]
CONFIG = {"heartbeat_producer_ms": 20,
          "pdos": [{"pdo": "rpdo1", "transmission_type": 255, "map": [[0x607A, 0]]}]}
EMCY_CAN_OVERRUN = 0x8110
REGISTER_COMMUNICATION = 0x11


class DroppingNode(DurandNode):
    """A durand node that leaves OPERATIONAL by itself (:meth:`drop`: a transient error, a
    missed master heartbeat), clears its error (:meth:`clear`: the error-reset EMCY and 0x1001
    back to 0) and, with :attr:`refuse` set, goes back to PRE-OPERATIONAL at every start."""

    refuse = False

    def _build(self, network: Any) -> Any:
        node = super()._build(network)
        node.nmt.state_callbacks.add(self._maybe_refuse)
        return node

    def _maybe_refuse(self, state: StateEnum) -> None:
        if self.refuse and state == StateEnum.OPERATIONAL:
            self.node.nmt.set_state(StateEnum.PRE_OPERATIONAL)

    def drop(self, code: int | None = None, register: int = 0) -> None:
        """To PRE-OPERATIONAL by itself, after an EMCY ``code`` with ``register`` if given."""
        if code is not None:
            self.emcy(code, register)
        self.node.nmt.set_state(StateEnum.PRE_OPERATIONAL)

    def clear(self) -> None:
        """The error is gone: error-reset EMCY (code 0000), 0x1001 = 0."""
        self.emcy(0x0000, 0x00)


def rig(tmp_path: Path, **node_opts: Any) -> Any:
    return durand_rig(tmp_path, DEVICES, heartbeat_timeout=0.3, config=CONFIG,
                      node_cls=DroppingNode, **node_opts)


def reason(r: Rig, device: str = "target") -> str:
    """The last failure reason reported for ``device``."""
    failed = r.host.failed(device)
    return failed[-1] if failed else ""


def beats(r: Rig, state: int, n: int) -> bool:
    """Wait until ``n`` heartbeats of the node showing ``state`` went out from now on."""
    since = time.monotonic()
    return r.wire.wait_for(lambda w: sum(1 for f in w.of(0x700 + NODE, since)
                                         if f.data == bytes((state,))) >= n)


def test_a_node_that_drops_by_itself_is_restarted_after_its_backoff(tmp_path: Path) -> None:
    with rig(tmp_path, restart_backoff=0.5) as r:
        node = r.node
        assert isinstance(node, DroppingNode)
        assert node.wait(lambda: r.driver.node_states()[NODE].ready)
        assert r.wire.nmt_starts(NODE) == 1
        node.drop()
        assert r.host.wait_for(lambda h: reason(r).endswith(
            "left OPERATIONAL at t=0.0 s (heartbeat says PRE-OPERATIONAL); restart 1 of 5 in "
            "0.5 s")), r.host.failures
        assert "left-operational" in r.host.error_kinds()
        st = r.driver.node_states()[NODE]
        assert st.lifecycle is NodeLifecycle.LEFT_OPERATIONAL and not st.ready
        # the backoff: heartbeats go by, no start before the host's clock reaches it
        assert beats(r, 0x7F, 5) and r.wire.nmt_starts(NODE) == 1
        r.host.tick(0.5)
        assert r.wire.wait_for(lambda w: w.nmt_starts(NODE) == 2)
        assert node.wait(lambda: node.state == StateEnum.OPERATIONAL)
        assert r.host.wait_for(lambda h: r.driver.node_states()[NODE].ready)
        st = r.driver.node_states()[NODE]
        assert st.restarts == 1 and st.nmt_starts == 2 and st.lifecycle is \
            NodeLifecycle.OPERATIONAL
        assert r.host.recoveries.count("target") >= 1 and r.host.stats["nmt-restarts"] == 1


def test_a_restart_waits_for_the_error_register_and_the_error_reset_emcy(
        tmp_path: Path) -> None:
    with rig(tmp_path, restart_backoff=0.5) as r:
        node = r.node
        assert isinstance(node, DroppingNode)
        assert node.wait(lambda: r.driver.node_states()[NODE].ready)
        node.drop(EMCY_CAN_OVERRUN, REGISTER_COMMUNICATION)
        assert r.host.wait_for(lambda h: "left OPERATIONAL" in reason(r))
        r.host.tick(0.5)                           # due, but 0x1001 still says an error
        assert r.host.wait_for(lambda h: "error register 0x1001 = 0x11: the restart waits "
                                         "for it to read 0 or for an error-reset EMCY"
                                         in reason(r)), r.host.failures
        assert "restart 1 of 5" in reason(r)
        assert beats(r, 0x7F, 5) and r.wire.nmt_starts(NODE) == 1
        node.clear()                               # EMCY 0000: the cause cleared
        r.host.tick(0.5)
        assert r.wire.wait_for(lambda w: w.nmt_starts(NODE) == 2)
        assert node.wait(lambda: node.state == StateEnum.OPERATIONAL)
        assert r.host.wait_for(lambda h: r.driver.node_states()[NODE].ready)
        assert r.driver.node_states()[NODE].restarts == 1


def test_a_node_that_refuses_every_restart_ends_reported_refusing(tmp_path: Path) -> None:
    with rig(tmp_path, restart_limit=2, restart_backoff=0.1) as r:
        node = r.node
        assert isinstance(node, DroppingNode)
        assert node.wait(lambda: r.driver.node_states()[NODE].ready)
        node.refuse = True
        node.drop()
        assert r.host.wait_for(lambda h: "restart 1 of 2 in 0.1 s" in reason(r))
        r.host.tick(0.1)
        assert r.host.wait_for(lambda h: "restart 1 not taken" in reason(r)), r.host.failures
        assert "restart 2 of 2 in 0.2 s" in reason(r)
        r.host.tick(0.2)
        assert r.host.wait_for(lambda h: "preop-held" in h.error_kinds())
        text = next(d for _, k, d in r.host.errors if k == "preop-held")
        assert "2 restart(s) of 2 did not keep it OPERATIONAL: it refuses" in text
        assert "error register 0x1001 = 0x00" in text
        st = r.driver.node_states()[NODE]
        assert st.lifecycle is NodeLifecycle.PREOP_HELD and st.restarts == 2
        assert r.wire.nmt_starts(NODE) == 3        # the boot's, then two restarts
        r.host.tick(30.0)                          # nothing more, however long
        assert beats(r, 0x7F, 5) and r.wire.nmt_starts(NODE) == 3
        assert node.state == StateEnum.PRE_OPERATIONAL


def test_a_node_whose_heartbeat_was_lost_and_comes_back_preoperational_is_restarted(
        tmp_path: Path) -> None:
    """An interface outage as the node lives it: its heartbeat is not heard, it leaves
    OPERATIONAL meanwhile (its master consumer fired), then it is heard again."""
    with rig(tmp_path, restart_backoff=0.2) as r:
        node = r.node
        assert isinstance(node, DroppingNode)
        assert node.wait(lambda: r.driver.node_states()[NODE].ready)
        node.write(0x1017, 0, 0)                   # silent
        assert r.host.wait_for(lambda h: any("no heartbeat" in x for x in h.failed("target")))
        st = r.driver.node_states()[NODE]
        assert not st.ready and st.heartbeat_lost and "heartbeat_timeout 0.3 s" in st.reason
        node.drop()
        node.write(0x1017, 0, 20)                  # heard again, PRE-OPERATIONAL
        assert r.host.wait_for(lambda h: "left OPERATIONAL" in reason(r))
        r.host.tick(0.2)
        assert r.wire.wait_for(lambda w: w.nmt_starts(NODE) == 2)
        assert node.wait(lambda: node.state == StateEnum.OPERATIONAL)
        assert r.host.wait_for(lambda h: r.driver.node_states()[NODE].ready)


def test_the_hosts_nmt_commands_hold_release_and_reset_a_node(tmp_path: Path) -> None:
    with rig(tmp_path) as r:
        node = r.node
        assert node.wait(lambda: r.driver.node_states()[NODE].ready)
        answer = r.driver.nmt("stop", NODE)
        assert answer == (f"nmt stop sent to canopen node {NODE} on bus co (it was "
                          f"operational, heartbeat OPERATIONAL)")
        assert node.wait(lambda: node.state == StateEnum.STOPPED)
        assert r.host.wait_for(lambda h: "held by the host (nmt stop at t=0.0 s)" in reason(r))
        r.host.tick(60.0)                          # the policy leaves it alone
        assert beats(r, 0x04, 5) and r.wire.nmt_starts(NODE) == 1
        assert r.driver.node_states()[NODE].lifecycle is NodeLifecycle.HOST_HELD
        r.driver.nmt("start", NODE)
        assert node.wait(lambda: node.state == StateEnum.OPERATIONAL)
        assert r.host.wait_for(lambda h: r.driver.node_states()[NODE].ready)
        assert r.wire.nmt_starts(NODE) == 2
        r.driver.nmt("preop", NODE)
        assert node.wait(lambda: node.state == StateEnum.PRE_OPERATIONAL)
        r.driver.nmt("reset-comm", NODE)           # a boot-up the host asked for
        assert r.host.wait_for(lambda h: h.stats.get("host-resets") == 1)
        assert r.host.wait_for(lambda h: r.driver.node_states()[NODE].ready)
        assert node.state == StateEnum.OPERATIONAL and node.read(0x1017, 0) == 20
        assert "boot-up" not in r.host.error_kinds()
        assert r.driver.node_states()[NODE].boots == 1
        with pytest.raises(BusError, match=r"no node 9 on it \(nodes 5\)"):
            r.driver.nmt("start", 9)
        with pytest.raises(BusError, match="no NMT command 'halt'"):
            r.driver.nmt("halt", NODE)


SYSTEM_MAP = """
[[bus]]
name = "co"
kind = "canopen"
interface = "virtual"
channel = "{channel}"
sdo_timeout = 0.2

[[bus.nodes]]
id = {node}
eds = "{eds}"
heartbeat_timeout = 0.5
[bus.nodes.config]
heartbeat_producer_ms = 20

[[device]]
name = "level"
direction = "sensor"
bus = "co"
address = {{ node = {node}, index = 0x2100, poll_period = 0.05 }}
"""


def test_the_host_command_and_python_api_reach_the_node_and_are_logged(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """``nmt stop 5`` at the host's command line and :meth:`System.nmt`; a NaN the node sends
    fails the sensor, a number clears it."""
    from chcos.kernel.clock import VirtualClock
    from chcos.system.embedded import System

    channel = unique_channel("nmt")
    objects = {**DRIVE_OBJECTS, 0x2100: (DT.REAL32, "ro", "Level")}
    node = DurandNode(channel, NODE, objects=objects, stored=Stored(heartbeat_ms=20))
    eds = node.write_eds(tmp_path / "node.eds")
    path = tmp_path / "co.toml"
    path.write_text(SYSTEM_MAP.format(channel=channel, node=NODE, eds=eds), encoding="utf-8")
    s = System([path], clock=VirtualClock(), machines=[0])
    caplog.set_level(logging.INFO)
    try:
        level = s.devtab.get("level")
        node.write(0x2100, 0, 2.5)
        assert run_until(s, lambda: level.value == 2.5 and level.status.value == "OK")
        node.write(0x2100, 0, float("nan"))        # the node has no value to give
        assert run_until(s, lambda: level.status.value == "failed")
        assert level.reason == ("reading is not a finite number: the device sent nan "
                                "(last value 2.5)")
        node.write(0x2100, 0, 3.0)
        assert run_until(s, lambda: level.status.value == "OK" and level.value == 3.0)

        drv = next(d for d in s.devtab.drivers if d.bus.name == "co")
        assert run_until(s, lambda: drv.node_states()[NODE].ready)  # type: ignore[attr-defined]
        answer = s.execute(f"nmt stop {NODE}")
        assert answer == (f"nmt stop sent to canopen node {NODE} on bus co (it was "
                          f"operational, heartbeat OPERATIONAL)")
        assert node.wait(lambda: node.state == StateEnum.STOPPED)
        assert f"nmt: host nmt stop {NODE}: {answer}" in caplog.text
        assert run_until(s, lambda: level.status.value == "failed")
        assert (f"level: canopen node {NODE} on bus co: held by the host (nmt stop at t="
                in caplog.text)
        assert s.nmt("start", NODE, "co").startswith("nmt start sent")
        assert node.wait(lambda: node.state == StateEnum.OPERATIONAL)
        assert run_until(s, lambda: level.status.value == "OK")
        with pytest.raises(InstallError, match=r"no node 9 on any CANopen bus this process "
                                               r"drives \(nodes: co: 5\)"):
            s.execute("nmt start 9")
        with pytest.raises(InstallError, match="no node 5 on bus other"):
            s.execute("nmt start 5 other")
        with pytest.raises(CommandSyntaxError, match="unknown command 'halt'"):
            s.execute("nmt halt 5")
        with pytest.raises(CommandSyntaxError, match=r"node id 0 is out of range \(1..127\)"):
            s.execute("nmt start 0")
        with pytest.raises(CommandSyntaxError, match="expected nmt start"):
            s.execute("nmt start")
    finally:
        s.shutdown()
        node.close()


def test_a_command_queued_before_a_reboot_is_not_sent_before_the_configuration(
        tmp_path: Path) -> None:
    """The driver's I/O thread is held by an SDO write to another node (its answer held back)
    while a command for node 5 is queued and node 5 reboots: that command is dropped, reported
    not sent, and never reaches the node; its configuration and NMT start follow."""
    channel = unique_channel("order")
    node = DurandNode(channel, NODE)
    other = DurandNode(channel, 6)
    held, entered = threading.Event(), threading.Event()

    def hold(value: object) -> None:
        entered.set()
        held.wait(WAIT)
    other.node.object_dictionary.validate_callbacks[(0x6081, 0)].add(hold)
    eds5, eds6 = node.write_eds(tmp_path / "n5.eds"), other.write_eds(tmp_path / "n6.eds")
    wire = Wire(channel)
    bus = BusSpec(name="co", kind="canopen", key="bus[0]", options={
        "interface": "virtual", "channel": channel, "sdo_timeout": 2 * WAIT,
        "nodes": [{"id": NODE, "eds": str(eds5), "heartbeat_timeout": 0.5,
                   "config": CONFIG},
                  {"id": 6, "eds": str(eds6), "nmt_start": False}]})
    host = FakeHost()
    driver = CanopenDriver(bus, [*DEVICES, make_device("slow", "actuator", "co", node=6,
                                                       index=0x6081)], host)
    driver.start()
    try:
        assert node.wait(lambda: driver.node_states()[NODE].ready)
        driver.write("slow", 1)                    # the I/O thread waits for node 6's answer
        assert entered.wait(WAIT)
        driver.write("target", 4321)               # queued behind it
        booted = time.monotonic()
        node.power_cycle()
        assert host.wait_for(lambda h: "boot-up" in h.error_kinds())
        held.set()
        assert host.wait_for(lambda h: any(d == "target" for d, _v, _why in h.writes))
        (outcome,) = [w for w in host.writes if w[0] == "target"]
        assert outcome[2].endswith("not sent: the node rebooted (boot-up) after this command "
                                   "was queued; it gets its configuration, NMT start and safe "
                                   "value first"), outcome
        assert host.wait_for(lambda h: driver.node_states()[NODE].ready)
        assert node.read(0x607A, 0) == 0 and node.read(0x1017, 0) == 20
        value = (4321).to_bytes(4, "little")
        assert not any(f.data[:4] == value for f in wire.frames if f.cob_id == 0x200 + NODE)
        assert wire.nmt_starts(NODE, since=booted) == 1
    finally:
        held.set()
        driver.stop()
        wire.close()
        node.close()
        other.close()
