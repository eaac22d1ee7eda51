"""The link transport between two sessions in this process: pub/sub with QoS, request/reply,
liveliness, and callbacks that fail without harming the transport."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator

import pytest
import zenoh

from chcos.comm import LinkConfig, LinkMessage, MessageKind, Transport, decode
from chcos.comm.qos import congestion_for, is_express, zenoh_priority
from chcos.errors import LinkError
from vcan_tests.netutil import free_port
from vcan_tests.support_link import WAIT, Collector


@pytest.fixture
def pair() -> Iterator[tuple[Transport, Transport]]:
    """Two connected transports: ``a`` listens, ``b`` listens and connects to ``a``."""
    pa, pb = free_port(), free_port()
    with Transport(LinkConfig(pa)) as a, Transport(LinkConfig(pb, (pa,))) as b:
        joined = Collector()
        a.watch("test/ready/b", joined, lambda _k: None)
        b.announce("test/ready/b")
        assert joined.get() == "test/ready/b"
        yield a, b


def test_priority_mapping() -> None:
    assert zenoh_priority(99) == zenoh.Priority.REAL_TIME
    assert zenoh_priority(90) == zenoh.Priority.REAL_TIME
    assert zenoh_priority(89) == zenoh.Priority.INTERACTIVE_HIGH
    assert zenoh_priority(75) == zenoh.Priority.INTERACTIVE_HIGH
    assert zenoh_priority(60) == zenoh.Priority.INTERACTIVE_LOW
    assert zenoh_priority(45) == zenoh.Priority.DATA_HIGH
    assert zenoh_priority(30) == zenoh.Priority.DATA
    assert zenoh_priority(15) == zenoh.Priority.DATA_LOW
    assert zenoh_priority(0) == zenoh.Priority.BACKGROUND
    assert is_express(75) and not is_express(74)
    for bad in (-1, 100, 1.5, True):
        with pytest.raises(LinkError, match="priority"):
            zenoh_priority(bad)  # type: ignore[arg-type]
    assert congestion_for(MessageKind.SENSORY) == zenoh.CongestionControl.DROP
    assert congestion_for(MessageKind.STATUS) == zenoh.CongestionControl.DROP
    assert congestion_for(MessageKind.COMMAND) == zenoh.CongestionControl.BLOCK
    assert congestion_for(MessageKind.PREEMPTION) == zenoh.CongestionControl.BLOCK


def test_publish_subscribe(pair: tuple[Transport, Transport]) -> None:
    a, b = pair
    got = Collector()
    a.subscribe("cell/**", got)
    ready = Collector()
    b.watch("test/ready/a", ready, lambda _k: None)
    a.announce("test/ready/a")  # declarations travel in order: a's subscriber is known to b now
    ready.get()
    b.publish("cell/sat1/S1", b"\x00\x01", priority=10, kind=MessageKind.SENSORY)
    msg = LinkMessage(MessageKind.COMMAND, "B1", "A1", 4, 80, 1, 5, {"go": True})
    b.send("cell/sat1/A1", msg)
    # different priorities travel in different Zenoh queues: the order between them is free
    received = dict([got.get(), got.get()])
    assert received["cell/sat1/S1"] == b"\x00\x01"
    assert decode(received["cell/sat1/A1"]) == msg


def test_subscribe_messages_decodes_and_drops_malformed_payloads(
    pair: tuple[Transport, Transport],
) -> None:
    a, b = pair
    got = Collector()
    a.subscribe_messages("m/**", got)
    ready = Collector()
    b.watch("test/ready/m", ready, lambda _k: None)
    a.announce("test/ready/m")
    ready.get()
    # same priority as the good one: same Zenoh queue, so it arrives first
    b.publish("m/1", b"not a link message", priority=99, kind=MessageKind.PREEMPTION)
    msg = LinkMessage(MessageKind.PREEMPTION, "C1", "B1", 9, 99, 2, 3, {"by": "C1"})
    b.send("m/2", msg)
    assert got.get() == ("m/2", msg)
    assert a.malformed == 1
    assert a.callback_errors == 0


def test_qos_on_the_wire(pair: tuple[Transport, Transport]) -> None:
    """Priority, express and congestion control arrive as chosen by priority and kind."""
    a, b = pair
    samples = Collector()
    raw = a._session.declare_subscriber("qos/**", samples)
    ready = Collector()
    b.watch("test/ready/raw", ready, lambda _k: None)
    a.announce("test/ready/raw")
    ready.get()
    try:
        b.publish("qos/1", b"s", priority=95, kind=MessageKind.SENSORY)
        b.publish("qos/2", b"c", priority=20, kind=MessageKind.COMMAND)
        b.publish("qos/3", b"x", priority=20, kind=MessageKind.STATUS, express=True)
        seen = {}
        for _ in range(3):
            s = samples.get()
            seen[str(s.key_expr)] = (s.priority, s.express, s.congestion_control)
    finally:
        raw.undeclare()  # type: ignore[no-untyped-call]
    assert seen["qos/1"] == (zenoh.Priority.REAL_TIME, True, zenoh.CongestionControl.DROP)
    assert seen["qos/2"] == (zenoh.Priority.DATA_LOW, False, zenoh.CongestionControl.BLOCK)
    assert seen["qos/3"] == (zenoh.Priority.DATA_LOW, True, zenoh.CongestionControl.DROP)


def test_bad_publish_arguments(pair: tuple[Transport, Transport]) -> None:
    a, _ = pair
    with pytest.raises(LinkError, match="concrete key"):
        a.publish("cell/*", b"", priority=1, kind=MessageKind.COMMAND)
    with pytest.raises(LinkError, match=r"priority: expected 0\.\.99, got 100"):
        a.publish("cell/x", b"", priority=100, kind=MessageKind.COMMAND)
    with pytest.raises(LinkError, match="expected a MessageKind, got 77"):
        a.publish("cell/x", b"", priority=1, kind=77)  # type: ignore[arg-type]
    with pytest.raises(LinkError, match="expected bytes payload"):
        a.publish("cell/x", "text", priority=1, kind=MessageKind.COMMAND)  # type: ignore[arg-type]
    with pytest.raises(LinkError, match="not a valid Zenoh key expression"):
        a.subscribe("cell//x", lambda _k, _p: None)
    with pytest.raises(LinkError, match="non-empty key"):
        a.announce("")


def test_a_failing_callback_is_counted_and_the_transport_goes_on(
    pair: tuple[Transport, Transport], caplog: pytest.LogCaptureFixture
) -> None:
    a, b = pair
    got = Collector()

    def flaky(key: str, payload: bytes) -> None:
        if payload == b"boom":
            raise RuntimeError("boom")
        got(key, payload)

    a.subscribe("f/x", flaky)
    ready = Collector()
    b.watch("test/ready/f", ready, lambda _k: None)
    a.announce("test/ready/f")
    ready.get()
    b.publish("f/x", b"boom", priority=50, kind=MessageKind.COMMAND)
    b.publish("f/x", b"fine", priority=50, kind=MessageKind.COMMAND)
    assert got.get() == ("f/x", b"fine")
    assert a.callback_errors == 1
    assert any("subscriber f/x" in r.getMessage() for r in caplog.records)


def test_request_reply(pair: tuple[Transport, Transport]) -> None:
    a, b = pair
    table = {"A1": {"machine": 0, "priority": 40}}
    a.serve("sys/table", lambda payload: json.dumps({"asked": payload.decode(), **table}).encode())
    ready = Collector()
    b.watch("test/ready/srv", ready, lambda _k: None)
    a.announce("test/ready/srv")
    ready.get()
    answer = json.loads(b.request("sys/table", b"all", timeout=WAIT))
    assert answer == {"asked": "all", **table}
    # a request with no payload arrives as b""
    assert json.loads(b.request("sys/table", timeout=WAIT))["asked"] == ""


def test_request_errors(pair: tuple[Transport, Transport]) -> None:
    a, b = pair

    def broken(_payload: bytes) -> bytes:
        raise ValueError("no such table")

    a.serve("sys/broken", broken)
    a.serve("sys/wrongtype", lambda _p: "text")  # type: ignore[arg-type,return-value]
    ready = Collector()
    b.watch("test/ready/err", ready, lambda _k: None)
    a.announce("test/ready/err")
    ready.get()
    with pytest.raises(LinkError, match=r"the server failed: .*ValueError: no such table"):
        b.request("sys/broken", timeout=WAIT)
    with pytest.raises(LinkError, match="handler returned str, expected bytes"):
        b.request("sys/wrongtype", timeout=WAIT)
    assert a.callback_errors == 2
    with pytest.raises(LinkError, match="no server answers this key"):
        b.request("sys/nobody", timeout=WAIT)
    with pytest.raises(LinkError, match="expected a timeout > 0"):
        b.request("sys/table", timeout=0)
    with pytest.raises(LinkError, match="concrete key"):
        b.request("sys/*", timeout=1)


def test_slow_server_times_out(pair: tuple[Transport, Transport]) -> None:
    a, b = pair
    release = threading.Event()

    def slow(_p: bytes) -> bytes:
        release.wait(WAIT)
        return b"late"

    a.serve("sys/slow", slow)
    ready = Collector()
    b.watch("test/ready/slow", ready, lambda _k: None)
    a.announce("test/ready/slow")
    ready.get()
    try:
        with pytest.raises(LinkError, match=r"no answer within 0\.3 s"):
            b.request("sys/slow", timeout=0.3)
    finally:
        release.set()


def test_liveliness_join_leave_and_alive(pair: tuple[Transport, Transport]) -> None:
    a, b = pair
    joins, leaves = Collector(), Collector()
    a.watch("sat/*", joins, leaves)
    token = b.announce("sat/2")
    assert joins.get() == "sat/2"
    assert b.alive("sat/*") == ["sat/2"]
    assert a.alive("sat/*") == ["sat/2"]
    token.close()
    assert leaves.get() == "sat/2"
    b.announce("sat/3")
    assert joins.get() == "sat/3"
    b.close()  # closing the transport withdraws its tokens too
    assert leaves.get() == "sat/3"
    assert a.alive("sat/*", timeout=0.5) == []


def test_watch_reports_tokens_that_already_exist(pair: tuple[Transport, Transport]) -> None:
    a, b = pair
    b.announce("old/1")
    b.announce("old/2")
    marker = Collector()
    a.watch("test/ready/old", marker, lambda _k: None)
    b.announce("test/ready/old")  # declarations arrive in order: old/1 and old/2 are known now
    marker.get()
    assert a.alive("old/*") == ["old/1", "old/2"]
    joins = Collector()
    a.watch("old/*", joins, lambda _k: None)
    assert sorted([joins.get(), joins.get()]) == ["old/1", "old/2"]


def test_closed_transport_refuses_everything() -> None:
    t = Transport(LinkConfig(free_port()))
    sub = t.subscribe("x/**", lambda _k, _p: None)
    t.close()
    t.close()
    assert t.closed and sub.closed
    sub.close()
    with pytest.raises(LinkError, match="publish: the link transport is closed"):
        t.publish("x/y", b"", priority=1, kind=MessageKind.COMMAND)
    with pytest.raises(LinkError, match="subscribe: the link transport is closed"):
        t.subscribe("x/**", lambda _k, _p: None)
    with pytest.raises(LinkError, match="request: the link transport is closed"):
        t.request("x/y", timeout=1)
    with pytest.raises(LinkError, match="watch: the link transport is closed"):
        t.watch("x/*", lambda _k: None, lambda _k: None)


def test_a_taken_listen_port_is_a_link_error() -> None:
    port = free_port()
    with Transport(LinkConfig(port)), pytest.raises(LinkError, match="cannot open the Zenoh"):
        Transport(LinkConfig(port))


def test_a_peer_that_comes_up_later_is_reached_by_retries() -> None:
    """``a`` is told about ``b`` before ``b`` exists; ``b`` (connecting to nobody) still gets
    ``a``'s messages once up, through ``a``'s background retries."""
    pa, pb = free_port(), free_port()
    with Transport(LinkConfig(pa, (pb,), retry_ms=20)) as a:
        assert a.peers() == []
        with Transport(LinkConfig(pb)) as b:
            joins = Collector()
            b.watch("late/a", joins, lambda _k: None)
            a.announce("late/a")
            assert joins.get() == "late/a"
            assert a.peers() == [b.zid]
