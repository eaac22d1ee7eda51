"""The OPC UA server seen by an independent client (python-opcua, not asyncua): devices as
variables with units, range, status and timestamps; a subscription sees every new sample;
anonymous sessions read but cannot command; an operator's EStop is obeyed and arrives as an
event; roles decide Suspend; tasks and links are there with their figures."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from opcua import Client, ua

from chcos.devices.spec import BusSpec, DeviceMap, DeviceSpec
from chcos.kernel.clock import RealClock
from chcos.north import NorthError
from chcos.north.opcua import OpcUaServer
from chcos.north.opcua_process import OpcUaProcess
from chcos.system.embedded import System
from vcan_tests.support_view import PASSWORDS, viewer_users

ME = "vcan_tests.support_view"
TIMEOUT = 15.0


def cell(workdir: Path) -> System:
    """Sensor P1 (bar), actuator V1 (%, limits ±100, safe 0) driven by T1 from P1, X2 above
    T1 crashes when invoked; on real time, running."""
    devmap = DeviceMap((BusSpec("mem", "memory"),), (
        DeviceSpec("P1", "sensor", 0, "mem", units="bar"),
        DeviceSpec("V1", "actuator", 0, "mem", safe_value=0.0, limits=(-100, 100),
                   units="%")))
    s = System(devmap, clock=RealClock(), base_dir=workdir)
    for line in ("install -m0 sysfile", f"install -m0i1o1 --code={ME}:follow T1 P1 V1",
                 f"install -m0i1 --code={ME}:crash X2 T1"):
        s.execute(line)
    s.start()
    return s


@pytest.fixture(params=["process", "thread"])
def served(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[tuple[System, Any]]:
    """The running cell and its OPC UA server on a free loopback port, with users: in a
    process of its own (the default of ``--opcua``) and on a thread of this one."""
    s = cell(tmp_path)
    kind = OpcUaProcess if request.param == "process" else OpcUaServer
    o = kind(s, "opc.tcp://127.0.0.1:0/chcos/", users=viewer_users()).start()
    yield s, o
    o.stop()
    s.shutdown()


def client(o: Any, user: str | None = None) -> Client:
    """A connected python-opcua client, anonymous or as ``user``."""
    c = Client(o.endpoint, timeout=TIMEOUT)
    if user is not None:
        c.set_user(user)
        c.set_password(PASSWORDS[user])
    c.connect()
    return c


class Collector:
    """python-opcua subscription handler: data changes and events, with a condition."""

    def __init__(self) -> None:
        self.values: list[Any] = []
        self.events: list[Any] = []
        self.cond = threading.Condition()

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        with self.cond:
            self.values.append(val)
            self.cond.notify_all()

    def event_notification(self, event: Any) -> None:
        with self.cond:
            self.events.append(event)
            self.cond.notify_all()

    def wait(self, pred: Any) -> bool:
        with self.cond:
            return bool(self.cond.wait_for(pred, TIMEOUT))


def ns(c: Client) -> int:
    return int(c.get_namespace_index("urn:chcos"))


def test_devices_tasks_links_and_a_subscription(served: tuple[System, Any]) -> None:
    system, o = served
    c = client(o)
    try:
        i = ns(c)
        p1 = c.get_node(f"ns={i};s=Devices.P1")
        v1 = c.get_node(f"ns={i};s=Devices.V1")
        with pytest.raises(ua.UaStatusCodeError, match="BadWaitingForInitialData"):
            p1.get_data_value()  # no value yet: python-opcua raises the Bad status
        units = c.get_node(f"ns={i};s=Devices.P1.EngineeringUnits").get_value()
        assert units.DisplayName.Text == "bar"
        rng = c.get_node(f"ns={i};s=Devices.V1.EURange").get_value()
        assert (rng.Low, rng.High) == (-100.0, 100.0)
        handler = Collector()
        sub = c.create_subscription(20, handler)
        sub.subscribe_data_change(p1)
        for k, value in enumerate((1.5, 2.5, 3.5, 4.5)):  # every sample reaches the client
            system.execute(f"inject P1 {value}")
            assert handler.wait(lambda v=value: v in handler.values), (k, handler.values)
        dv = p1.get_data_value()
        assert dv.StatusCode.is_good() and dv.Value.Value == 4.5
        assert dv.SourceTimestamp is not None
        assert c.get_node(f"ns={i};s=Devices.P1.Status").get_value() == "OK"
        # the task and its links
        system.execute("invoke T1")
        state = c.get_node(f"ns={i};s=Tasks.T1.Owner")
        h2 = Collector()
        c.create_subscription(20, h2).subscribe_data_change(state)
        assert h2.wait(lambda: "host" in h2.values)
        assert c.get_node(f"ns={i};s=Tasks.T1.Level").get_value() == 1
        sent = c.get_node(f"ns={i};s=Links.P1/T1.Sent")
        system.execute("inject P1 5.5")
        h3 = Collector()
        c.create_subscription(20, h3).subscribe_data_change(sent)
        assert h3.wait(lambda: any(v >= 1 for v in h3.values))
        assert c.get_node(f"ns={i};s=Links.P1/T1.Status").get_value() == "OK"
        h4 = Collector()  # the actuator's last command, as T1 wrote it
        c.create_subscription(20, h4).subscribe_data_change(v1)
        assert h4.wait(lambda: system.devtab.get("V1").value in h4.values)
    finally:
        c.disconnect()


@pytest.mark.parametrize("kind", [OpcUaProcess, OpcUaServer])
def test_tasks_and_links_are_there_as_soon_as_it_serves(tmp_path: Path, kind: Any) -> None:
    """What was installed before the server started is in its address space when start()
    returns, not only after its first refresh (a refresh period longer than the test: none
    happens meanwhile)."""
    s = cell(tmp_path)
    o = kind(s, "opc.tcp://127.0.0.1:0/chcos/", period=30.0).start()
    c = client(o)
    try:
        i = ns(c)
        assert c.get_node(f"ns={i};s=Tasks.T1.Level").get_value() == 1
        assert c.get_node(f"ns={i};s=Tasks.X2.Level").get_value() == 2
        assert c.get_node(f"ns={i};s=Links.P1/T1.Status").get_value() == "OK"
    finally:
        c.disconnect()
        o.stop()
        s.shutdown()


def test_anonymous_estop_refused_operator_obeyed(served: tuple[System, Any]) -> None:
    system, o = served
    system.call(system.devtab.write, "V1", 42.0)
    anon = client(o)
    try:
        i = ns(anon)
        root = anon.get_node(f"ns={i};s=chcos")
        with pytest.raises(ua.UaStatusCodeError, match="BadUserAccessDenied"):
            root.call_method(f"{i}:EStop", "from an HMI without login")
        assert system.devtab.get("V1").value == 42.0
        if isinstance(o, OpcUaProcess):
            assert o.wait_refused(1, TIMEOUT)
        assert o.refused[-1][:2] == ("anonymous", "estop")
        handler = Collector()
        anon.create_subscription(20, handler).subscribe_events(root)
    finally:
        pass
    alice = client(o, "alice")
    try:
        root = alice.get_node(f"ns={i};s=chcos")
        answer = root.call_method(f"{i}:EStop", "operator pressed stop")
        assert answer == "estop: 1 actuator(s) at safe values"
        assert system.devtab.get("V1").value == 0.0
        assert handler.wait(lambda: any("operator pressed stop" in e.Message.Text
                                        for e in handler.events))
        ev = next(e for e in handler.events if "estop" in e.Message.Text)
        assert ev.Severity == 900
        # an operator may invoke, not suspend; a supervisor may suspend
        with pytest.raises(ua.UaStatusCodeError, match="BadUserAccessDenied"):
            root.call_method(f"{i}:Suspend", "T1")
        assert root.call_method(f"{i}:Invoke", "T1", "", -1).startswith("T1 invoked")
        with pytest.raises(ua.UaStatusCodeError, match="BadInvalidArgument"):
            root.call_method(f"{i}:SetPri", "P1", "NOPE", 9)
        assert root.call_method(f"{i}:SetPri", "P1", "T1", 12) == "P1/T1 priority 12"
        # an abnormal completion is an event too
        root.call_method(f"{i}:Invoke", "X2", "", -1)
        assert handler.wait(lambda: any("X2 crashed on purpose" in e.Message.Text
                                        for e in handler.events))
    finally:
        alice.disconnect()
        anon.disconnect()
    sam = client(o, "sam")
    try:
        root = sam.get_node(f"ns={i};s=chcos")
        assert root.call_method(f"{i}:Suspend", "T1") == "T1: suspend"
        assert system.tsktab.get("T1").frozen
        assert root.call_method(f"{i}:Resume", "T1") == "T1: resume"
    finally:
        sam.disconnect()


def test_bad_password_and_remote_endpoint_refused(served: tuple[System, Any]) -> None:
    system, o = served
    c = Client(o.endpoint, timeout=TIMEOUT)
    c.set_user("alice")
    c.set_password("wrong")
    with pytest.raises(Exception):  # noqa: B017 - python-opcua raises its own errors
        c.connect()
    c.disconnect()
    with pytest.raises(NorthError, match="certificate"):
        OpcUaServer(system, "opc.tcp://192.0.2.1:4840/")
    with pytest.raises(NorthError, match=r"opc\.tcp://HOST:PORT"):
        OpcUaServer(system, "http://127.0.0.1:4840/")


def _certificate(tmp: Path, name: str) -> tuple[str, str]:
    """A self-signed application certificate (DER) and key (PEM) from asyncua's helper."""
    import asyncio

    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    key, cert = tmp / f"{name}-key.pem", tmp / f"{name}-cert.der"
    asyncio.run(setup_self_signed_certificate(
        key, cert, f"urn:chcos:test:{name}", "127.0.0.1",
        [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH],
        {"commonName": name}))
    return str(cert), str(key)


def test_secure_endpoint_refuses_security_none(tmp_path: Path) -> None:
    """With security asked for (as off loopback), only Basic256Sha256 Sign&Encrypt is offered:
    a client without security is refused, one with it logs in and its EStop is obeyed."""
    s = cell(tmp_path)
    cert, key = _certificate(tmp_path, "server")
    ccert, ckey = _certificate(tmp_path, "client")
    o = OpcUaServer(s, "opc.tcp://127.0.0.1:0/chcos/", users=viewer_users(), certificate=cert,
                    private_key=key, secure=True).start()
    try:
        plain = Client(o.endpoint, timeout=TIMEOUT)
        with pytest.raises(Exception):  # noqa: B017 - python-opcua's own error types
            plain.connect()
        plain.disconnect()
        c = Client(o.endpoint, timeout=TIMEOUT)
        c.set_security_string(f"Basic256Sha256,SignAndEncrypt,{ccert},{ckey}")
        c.set_user("alice")
        c.set_password(PASSWORDS["alice"])
        c.connect()
        try:
            s.call(s.devtab.write, "V1", 42.0)
            i = ns(c)
            root = c.get_node(f"ns={i};s=chcos")
            assert root.call_method(f"{i}:EStop", "secure") == \
                "estop: 1 actuator(s) at safe values"
            assert s.devtab.get("V1").value == 0.0
        finally:
            c.disconnect()
    finally:
        o.stop()
        s.shutdown()


def alarm_filter(c: Client) -> Any:
    """An event filter for OffNormalAlarmType conditions: python-opcua selects the type's
    properties; the two-state flags, the comment and the ConditionId are added by hand."""
    from opcua.common.events import get_filter_from_event_type

    f = get_filter_from_event_type([c.get_node(ua.ObjectIds.OffNormalAlarmType)])
    for var in ("ActiveState", "AckedState"):
        op = ua.SimpleAttributeOperand()
        op.TypeDefinitionId = ua.NodeId(ua.ObjectIds.AlarmConditionType)
        op.BrowsePath = [ua.QualifiedName(var, 0), ua.QualifiedName("Id", 0)]
        op.AttributeId = ua.AttributeIds.Value
        f.SelectClauses.append(op)
    op = ua.SimpleAttributeOperand()  # the last acknowledgement's comment (a variable)
    op.TypeDefinitionId = ua.NodeId(ua.ObjectIds.ConditionType)
    op.BrowsePath = [ua.QualifiedName("Comment", 0)]
    op.AttributeId = ua.AttributeIds.Value
    f.SelectClauses.append(op)
    op = ua.SimpleAttributeOperand()  # the ConditionId: the condition node's NodeId
    op.TypeDefinitionId = ua.NodeId(ua.ObjectIds.ConditionType)
    op.AttributeId = ua.AttributeIds.NodeId
    f.SelectClauses.append(op)
    return f


def test_alarms_raised_cleared_and_acknowledged(served: tuple[System, Any]) -> None:
    """A sensor failure arrives at a subscriber of the Server object as an active alarm with
    the device as source, its recovery as inactive; an anonymous Acknowledge is refused, an
    operator's is taken and ends the alarm; an e-stop and an abnormal completion are alarms
    until acknowledged; ConditionRefresh gives a late subscriber what is still retained."""
    system, o = served
    anon = client(o)
    alice = client(o, "alice")
    try:
        i = ns(anon)
        handler = Collector()
        sub = anon.create_subscription(20, handler)
        sub.subscribe_events(ua.ObjectIds.Server, evfilter=alarm_filter(anon))

        def seen(active: bool, acked: bool, source: str) -> Any:
            def pred() -> bool:
                return any(e.ActiveState is active and e.AckedState is acked
                           and e.SourceNode == ua.NodeId(source, i) for e in handler.events)
            assert handler.wait(pred), [(e.SourceNode, e.ActiveState, e.AckedState)
                                        for e in handler.events]
            return [e for e in handler.events if e.ActiveState is active
                    and e.AckedState is acked and e.SourceNode == ua.NodeId(source, i)][-1]

        system.devtab.fail("P1", "wire broken")
        ev = seen(True, False, "Devices.P1")
        assert ev.Severity == 900 and ev.Retain is True
        assert "wire broken" in ev.Message.Text
        assert ev.NodeId == ua.NodeId("Alarms.Devices.P1", i)
        system.devtab.recover("P1", "wire mended")
        ev = seen(False, False, "Devices.P1")
        assert ev.Retain is True  # inactive, not yet acknowledged: clients keep showing it
        cond = anon.get_node(ev.NodeId)
        ack = ua.NodeId(ua.ObjectIds.AcknowledgeableConditionType_Acknowledge)
        with pytest.raises(ua.UaStatusCodeError, match="BadUserAccessDenied"):
            cond.call_method(ack, ev.EventId, ua.LocalizedText("anonymous saw it"))
        if isinstance(o, OpcUaProcess):
            assert o.wait_refused(1, TIMEOUT)
        assert o.refused[-1][:2] == ("anonymous", "acknowledge")
        acond = alice.get_node(ev.NodeId)
        with pytest.raises(ua.UaStatusCodeError, match="BadEventIdUnknown"):
            acond.call_method(ack, b"no-such-event", ua.LocalizedText("stale id"))
        acond.call_method(ack, ev.EventId, ua.LocalizedText("cable replaced"))
        done = seen(False, True, "Devices.P1")
        assert done.Retain is False and done.Comment.Text == "cable replaced"
        assert done.ClientUserId == "alice"
        # an e-stop: active until acknowledged
        root = alice.get_node(f"ns={i};s=chcos")
        root.call_method(f"{i}:EStop", "guard door open")
        ev = seen(True, False, "chcos")
        assert "guard door open" in ev.Message.Text and ev.Severity == 900
        alice.get_node(ev.NodeId).call_method(ack, ev.EventId, ua.LocalizedText("door shut"))
        seen(False, True, "chcos")
        # an abnormal completion: its task is the source
        root.call_method(f"{i}:Invoke", "X2", "", -1)
        ev = seen(True, False, "Tasks.X2")
        assert "X2 crashed on purpose" in ev.Message.Text and ev.Severity == 800
        # a subscriber arriving later gets the alarms still retained by ConditionRefresh
        system.devtab.fail("V1", "drive fault")
        seen(True, False, "Devices.V1")
        late = Collector()
        lsub = anon.create_subscription(20, late)
        lsub.subscribe_events(ua.ObjectIds.Server, evfilter=alarm_filter(anon))
        anon.get_node(ua.ObjectIds.Server).call_method(
            ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh),
            ua.Variant(lsub.subscription_id, ua.VariantType.UInt32))
        assert late.wait(lambda: any(
            getattr(e, "SourceNode", None) == ua.NodeId("Devices.V1", i) and e.ActiveState
            for e in late.events))
        assert not any(getattr(e, "SourceNode", None) == ua.NodeId("Devices.P1", i)
                       for e in late.events)  # acknowledged and inactive: gone
    finally:
        alice.disconnect()
        anon.disconnect()
