"""Typed link payloads and collected errors (issue 14): every payload the communications manager
sends survives the codec as its own type, malformed ones are refused naming the field, a remote
``open`` is answered with an :class:`OpenAnswer`, and what a satellite collects (a batch the
link refused, a message it could not act on, an interrupt handler that failed) is raised by
``check()`` and shown in the map, its text view and the viewer's stream."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from chcos.comm.codec import (
    LinkMessage,
    MessageKind,
    decode,
    decode_batch,
    encode,
    encode_batch,
)
from chcos.comm.payloads import (
    KIND_OF,
    ActuatorCommand,
    CloseRequest,
    EmergencyStop,
    OpenAnswer,
    OpenOutcome,
    OpenReply,
    OpenRequest,
    Payload,
    Query,
    QueryAnswer,
    QueryFailed,
    Report,
    StatusChange,
    from_wire,
    to_wire,
)
from chcos.devices.devmap import DeviceMap
from chcos.errors import ChcosError, LinkError, MessageError
from chcos.kernel.clock import VirtualClock
from chcos.satellites import control
from chcos.system.embedded import System
from chcos.system.textview import render_text
from chcos.tables.messages import LinkStatus
from chcos.viewer.snapshot import Snapshotter, stream_state

M = "vcan_tests.test_sat_comm"

PAYLOADS: list[Payload] = [
    OpenRequest({"seam": 3, "speed": 1.5}, True), OpenRequest(None, False), CloseRequest(),
    ActuatorCommand("M1", -2.5), ActuatorCommand("valve", True),
    EmergencyStop("door open", 2), OpenReply(OpenAnswer.owner()),
    OpenReply(OpenAnswer.queued()), OpenReply(OpenAnswer.busy("W is held by host at 90")),
    StatusChange("S1", "failed", "no answer", 1), Query(7, "ahead", [1.0, "x"]),
    QueryAnswer(7, {"centre": 12.5}), QueryFailed(7, "W's world model: no such topic"),
]


@pytest.mark.parametrize("payload", PAYLOADS, ids=lambda p: type(p).__name__)
def test_every_payload_survives_the_wire_as_its_type(payload: Payload) -> None:
    kind = KIND_OF[type(payload)]
    data = encode(LinkMessage(kind, "A", "B", 3, 50, 1, 0, to_wire(payload)))
    msg = decode(data)
    assert from_wire(msg.kind, msg.value) == payload


@pytest.mark.parametrize("kind", [MessageKind.COMPLETION, MessageKind.PREEMPTION])
def test_reports_survive_the_wire(kind: MessageKind) -> None:
    report = Report(LinkStatus.PREEMPTED, {"welded_mm": 12}, "pre-empted by B2")
    msg = decode(encode(LinkMessage(kind, "A", "B", 3, 50, 1, 0, to_wire(report))))
    assert from_wire(msg.kind, msg.value) == report


@pytest.mark.parametrize(("kind", "value", "expected"), [
    (MessageKind.COMMAND, {"op": "frobnicate"}, "unknown op 'frobnicate'"),
    (MessageKind.COMMAND, ["open"], "expected a JSON object"),
    (MessageKind.COMMAND, {"op": "open", "command": 1}, "'wait': expected true/false"),
    (MessageKind.COMMAND, {"op": "actuator", "device": "M1"}, "'value'"),
    (MessageKind.COMMAND, {"op": "estop", "reason": "x", "from": True}, "'from'"),
    (MessageKind.REPLY, {"op": "open", "answer": "maybe"}, "expected owner, queued or busy"),
    (MessageKind.REPLY, {"op": "answer", "qid": "7"}, "'qid': expected a query id"),
    (MessageKind.STATUS, {"device": "S1", "status": "broken", "reason": "", "from": 0},
     "'status': expected one of OK, suspended, failed, stale"),
    (MessageKind.COMPLETION, {"status": "done"}, "'status': expected a link status"),
    (MessageKind.QUERY, {"qid": 1, "topic": "t", "args": "x"}, "'args': expected a list"),
    (MessageKind.ERROR, {"qid": 1}, "'error': expected a text"),
    (MessageKind.INSTALL, {}, "unexpected message kind INSTALL"),
])
def test_malformed_payloads_are_refused_naming_the_field(kind: MessageKind, value: Any,
                                                          expected: str) -> None:
    with pytest.raises(MessageError) as err:
        from_wire(kind, value)
    assert expected in str(err.value)


def _install(s: System) -> None:
    s.execute(f"install -m0 --code={M}:producer P")
    s.execute(f"install -m1i1 --code={M}:reader R P")
    s.execute(f"install -m1 --code={M}:modelled W")
    s.execute(f"install -m0i1 --code={M}:asker A W")


class _Refusing:
    """A link transport that keeps what is published, or refuses every publish (the link to
    the peer is down) if ``refuse``."""

    def __init__(self, refuse: bool = True) -> None:
        self.refuse = refuse
        self.subs: dict[str, Callable[[str, bytes], object]] = {}
        self.sent: list[bytes] = []

    def subscribe(self, key: str, cb: Callable[[str, bytes], object],
                  roles: Any = None) -> _Refusing:
        self.subs[key] = cb
        return self

    def watch(self, key: str, joined: Callable[[str], object], left: Any) -> _Refusing:
        joined("chcos/t/alive/1")
        return self

    def announce(self, key: str) -> _Refusing:
        return self

    def publish(self, key: str, payload: bytes, *, priority: int, kind: MessageKind,
                express: bool | None = None) -> None:
        if self.refuse:
            raise LinkError(f"publish {key!r}: Zenoh refused: link down")
        self.sent.append(payload)

    def close(self) -> None:
        pass


def test_a_remote_open_is_answered_with_a_type(tmp_path: Path) -> None:
    with System(DeviceMap(), clock=VirtualClock(), machines=(0, 1), base_dir=tmp_path,
                local_machines={1}, transport=_Refusing(refuse=False), prefix="chcos/t") as s:
        _install(s)
        s.execute(f"install -m0o1 --code={M}:asker B W")
        link = s.msgtab.find("B", "W")      # B runs on machine 0, W here on machine 1
        assert s.msgmgr.remote_open(link, {"ask": "x"}, False) == OpenAnswer.owner()
        s.execute("setpri -90 host W")       # the host takes W, at a higher priority
        s.execute("invoke W")
        s.run_for(0.001)                     # B's satellite is told, as a typed Report
        transport = s.comm.transport if s.comm is not None else None
        assert isinstance(transport, _Refusing)
        reports = [from_wire(m.kind, m.value) for data in transport.sent
                   for m in decode_batch(data) if m.kind is MessageKind.PREEMPTION]
        assert reports == [Report(LinkStatus.PREEMPTED, None,
                                  "pre-empted by host at priority 90")]
        answer = s.msgmgr.remote_open(link, {"ask": "x"}, False)
        assert answer.outcome is OpenOutcome.BUSY and "W" in answer.reason
        assert s.msgmgr.remote_open(link, {"ask": "x"}, True) == OpenAnswer.queued()


@pytest.fixture
def refused(tmp_path: Path) -> Iterator[tuple[System, _Refusing]]:
    transport = _Refusing()
    with System(DeviceMap(), clock=VirtualClock(), machines=(0, 1), base_dir=tmp_path,
                map_path=tmp_path / "sysfile.map", local_machines={0},
                transport=transport, prefix="chcos/t") as s:
        assert s.comm is not None
        s.comm.start()
        _install(s)
        s.run_for(0.001)
        yield s, transport


def test_check_raises_what_the_link_collected(refused: tuple[System, _Refusing],
                                              tmp_path: Path) -> None:
    s, transport = refused
    assert s.comm is not None
    s.check()                                  # nothing collected yet
    s.execute("invoke P values=[1,2]")         # P's values go to R on machine 1: refused
    s.run_for(0.01)
    with pytest.raises(LinkError, match="machine 0: 1 link error") as err:
        s.check()
    assert "lost: publish 'chcos/t/m/1/msg': Zenoh refused: link down" in str(err.value)
    # an incoming message this satellite cannot act on is collected too
    bad = encode(LinkMessage(MessageKind.COMMAND, "B", "W", 0, 50, 1, 0, {"op": "frobnicate"}))
    transport.subs["chcos/t/m/0/msg"]("chcos/t/m/0/msg", encode_batch([bad]))
    s.run_for(0.01)
    with pytest.raises(LinkError, match="2 link error"):
        s.comm.check()
    doc = s.sysmgr.map_doc()
    assert [e.split(":")[0] for e in doc["errors"]] == ["link", "link"]
    assert "unknown op 'frobnicate'" in doc["errors"][1]
    s.sysmgr.save_map()
    assert "frobnicate" in (tmp_path / "sysfile.map").read_text()
    assert "collected errors (2; System.check raises them)" in render_text(doc)
    state = stream_state(Snapshotter(s).take(svg=False))
    assert state["errors"] == doc["errors"]
    assert len(s.comm.clear_errors()) == 2
    s.check()
    assert s.sysmgr.map_doc()["errors"] == []


def test_check_raises_a_failed_interrupt_handler(tmp_path: Path) -> None:
    def broken() -> None:
        raise ZeroDivisionError("division by zero")

    with System(DeviceMap(), clock=VirtualClock(), machines=(0,), base_dir=tmp_path) as s:
        s.kernel.interrupt(broken)
        s.run_for(0.01)
        with pytest.raises(ChcosError, match="division by zero"):
            s.check()
        assert any("ZeroDivisionError" in e for e in s.sysmgr.map_doc()["errors"])


CONTROL: list[control.ControlRequest] = [
    control.MapRequest(), control.LogRequest(), control.HeadRequest(),
    control.HelloRequest("9f" * 16), control.SyncRequest(2, 14),
    control.ExecRequest("invoke D2 gap=1.5"),
    control.ChangeRequest(control.Phase.PREPARE, "install -m1 A1 S1", 3, 0),
    control.ChangeRequest(control.Phase.ACCEPT, "setpri -9 A4 C1", 4),
    control.ChangeRequest(control.Phase.COMMIT, "install -m0 sysfile", 0, 1),
]


@pytest.mark.parametrize("req", CONTROL, ids=lambda r: type(r).__name__)
def test_every_host_request_survives_the_wire_as_its_type(req: control.ControlRequest) -> None:
    assert control.decode(control.encode(req)) == req


@pytest.mark.parametrize(("raw", "expected"), [
    (b"[1]", "expected a JSON object, got list"),
    (b'{"op": "drop-tables"}', "op: expected one of map, log"),
    (b'{"op": "sync", "source": true, "need": 3}', "source: expected a machine"),
    (b'{"op": "hello"}', "nonce: expected 1 to 64 characters"),
    (b'{"op": "hello", "nonce": "' + b"n" * 65 + b'"}', "nonce: expected 1 to 64 characters"),
    (b'{"op": "prepare", "line": "install -m0 A", "seq": -1}', "seq: expected a log position"),
    (b'{"op": "commit", "line": 7, "seq": 0}', "line: expected a command line string"),
    (b'{"op": "accept", "line": "x", "seq": 0, "leader": "0"}', "leader: expected a machine"),
])
def test_malformed_host_requests_are_refused_naming_the_key(raw: bytes, expected: str) -> None:
    with pytest.raises(TypeError) as err:
        control.decode(raw)
    assert expected in str(err.value)
