"""The communications manager in one process: two satellites' Systems joined by an in-memory
stand-in for the Zenoh transport, on virtual time. Checks what the link does to messages:
newest-wins sensory messages that wait in a batch are replaced by newer ones (and the receiving
satellite counts them as overwritten), queued links carry every message and are never dropped
under congestion, batches go out when the kernel idles; world-model queries (``ctx.ask``) to a
task on the other satellite are answered, refused, timed out, or failed when it dies."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from chcos.comm.codec import MessageKind, decode_batch
from chcos.comm.manager import CommManager
from chcos.devices.devmap import DeviceMap
from chcos.errors import MessageError, ReadTimeout
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System
from chcos.user.context import TaskContext
from chcos.user.worldmodel import WorldModel, task

M = "vcan_tests.test_sat_comm"


async def producer(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    """Puts ``values`` upward in one step (no wait in between), then idles."""
    for v in cmd["values"]:
        ctx.put(v)
    await ctx.sleep(1000.0)


async def reader(ctx: TaskContext, cmd: Any) -> None:
    """Keeps every value it reads."""
    got = ctx.world.sensory.setdefault("got", [])
    while True:
        got.append(await ctx.read(0))


class SeamModel(WorldModel):
    """Answers "ahead" with a prediction from the arguments; fails on "broken"."""

    def answer(self, topic: str, *args: Any) -> Any:
        if topic == "ahead":
            return self.sensory["centre"] + args[0]
        if topic == "broken":
            raise ZeroDivisionError("division by zero")
        return super().answer(topic, *args)


@task(world_model=SeamModel)
async def modelled(ctx: TaskContext, cmd: Any) -> None:
    """Keeps a seam centre in its world model and sends it upward."""
    ctx.world.sensory["centre"] = 12.5
    ctx.put(12.5)
    await ctx.sleep(1000.0)




async def asker(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    """Asks W each ``topic`` or ``topic:number`` of the comma-separated ``cmd["ask"]``; keeps
    answers and errors in its model."""
    log = ctx.world.sensory.setdefault("answers", [])
    for item in str(cmd["ask"]).split(","):
        topic, *rest = item.split(":")
        args = [float(x) for x in rest]
        try:
            log.append(await ctx.ask("W", topic, *args, timeout=cmd.get("timeout")))
        except (MessageError, ReadTimeout) as exc:
            log.append(f"{type(exc).__name__}: {exc}")


class _Handle:
    def close(self) -> None:
        pass


class LoopNet:
    """Both satellites' transports: a publish is held until :meth:`deliver`."""

    def __init__(self) -> None:
        self.subs: dict[str, list[Callable[[str, bytes], None]]] = {}
        self.held: list[tuple[str, bytes, MessageKind]] = []
        self.left: list[Callable[[str], object]] = []

    def kill(self, machine: int) -> None:
        """What every satellite sees when ``machine`` dies: its liveliness token vanishes."""
        for cb in self.left:
            cb(f"chcos/t/alive/{machine}")

    def deliver(self) -> int:
        held, self.held = self.held, []
        for key, payload, _kind in held:
            for cb in self.subs.get(key, []):
                cb(key, payload)
        return len(held)


class LoopTransport:
    """The part of :class:`chcos.comm.transport.Transport` the communications manager uses."""

    def __init__(self, net: LoopNet) -> None:
        self.net = net

    def subscribe(self, key: str, cb: Callable[[str, bytes], None], roles: Any = None) -> _Handle:
        self.net.subs.setdefault(key, []).append(cb)
        return _Handle()

    def watch(self, key: str, joined: Any, left: Any) -> _Handle:
        for m in (0, 1):  # both satellites are up (as Zenoh reports existing tokens)
            joined(f"chcos/t/alive/{m}")
        self.net.left.append(left)
        return _Handle()

    def announce(self, key: str) -> _Handle:
        return _Handle()

    def publish(self, key: str, payload: bytes, *, priority: int, kind: MessageKind,
                express: bool | None = None) -> None:
        self.net.held.append((key, bytes(payload), kind))


@pytest.fixture
def pair(tmp_path: Path) -> Iterator[tuple[System, System, LoopNet, list[CommManager]]]:
    net = LoopNet()
    systems, comms = [], []
    for m in (0, 1):
        s = System(DeviceMap(), clock=VirtualClock(), machines=(0, 1), base_dir=tmp_path,
                   map_path=tmp_path / f"sysfile{m}.map", local_machines={m},
                   transport=LoopTransport(net), prefix="chcos/t")
        assert s.comm is not None
        c = s.comm
        c.start()
        systems.append(s)
        comms.append(c)
    for s in systems:   # the same install log on both satellites
        s.execute(f"install -m0 --code={M}:producer P")
        s.execute(f"install -m1i1 --code={M}:reader R P")
        s.execute(f"install -m1i1 --queue=P=64 --code={M}:reader Q P")
        s.execute(f"install -m1 --code={M}:modelled W")
        s.execute(f"install -m0i1 --code={M}:asker A W")
    systems[1].execute("invoke R")
    systems[1].execute("invoke Q")
    while True:   # each satellite learns that the other is up: its token, then its hello
        for s in systems:
            s.run_for(0.001)
        if not net.deliver():
            break
    assert all(c.is_up(1 - c.machine) for c in comms)
    yield systems[0], systems[1], net, comms
    for s in systems:
        s.shutdown()


def _step(s: System) -> None:
    s.run_for(0.001)


def test_newest_wins_is_kept_across_the_link(
        pair: tuple[System, System, LoopNet, list[CommManager]]) -> None:
    m0, m1, net, comms = pair
    m0.execute("invoke P values=[1]")
    _step(m0)
    assert net.deliver() >= 1
    _step(m1)
    m0.execute("invoke P values=[2,3,4,5,6,7,8,9,10,11]")
    _step(m0)
    newest = [p for k, p, kind in net.held if kind is MessageKind.SENSORY]
    queued = [p for k, p, kind in net.held if kind is not MessageKind.SENSORY]
    # one newest-wins message left the sender for R; Q's queued link carried all ten, as
    # messages that must arrive (congestion control blocks instead of dropping)
    assert [m.value for p in newest for m in decode_batch(p)] == [11]
    assert [m.value for p in queued for m in decode_batch(p)] == list(range(2, 12))
    assert comms[0].coalesced == 9
    net.deliver()
    _step(m1)
    r, q = m1.tsktab.get("R"), m1.tsktab.get("Q")
    assert r.world is not None and q.world is not None
    assert r.world.sensory["got"] == [1, 11]
    assert q.world.sensory["got"] == list(range(1, 12))
    link = m1.msgtab.find("P", "R")
    # the receiving satellite counts the nine replaced on the way: sent = delivered +
    # overwritten + unread holds on its copy of the link
    assert (link.sent, link.overwritten, link.delivered) == (11, 9, 2)
    assert m1.msgtab.find("P", "Q").overwritten == 0
    assert comms[1].superseded == 9


def test_newest_wins_numbers_are_encoded_only_when_their_batch_leaves(
        pair: tuple[System, System, LoopNet, list[CommManager]]) -> None:
    """A flood on a newest-wins link costs one encoding per batch: the newest message waits
    unencoded in the link's slot and only the one that leaves is encoded, with the sequence
    number of the last message it replaced and its own time stamp. What could fail to encode
    (NaN, an object) is checked in the put and fails there, taking no sequence number."""
    m0, _m1, net, comms = pair
    c = comms[0]
    sent_before = c.sent  # the hellos that made the satellites up
    link = m0.msgtab.find("P", "R")
    encoded: list[Any] = []
    later = c.batches.encode_later
    assert later is not None

    def counting(item: Any) -> bytes | None:
        encoded.append(item)
        return later(item)

    c.batches.encode_later = counting
    # each newer value replaces the one waiting (the message layer counts it overwritten)
    assert [c.sensory(link, v) for v in (1.5, 2, True, -4.25)] == [False, True, True, True]
    with pytest.raises(MessageError, match=r"cannot send sensory P->R.*expected JSON data"):
        c.sensory(link, float("nan"))
    with pytest.raises(MessageError, match=r"cannot send sensory P->R.*expected JSON data"):
        c.sensory(link, object())
    assert encoded == []                    # nothing encoded while the values wait
    c.flush()
    assert len(encoded) == 1
    (msg,) = [m for _k, p, _kind in net.held for m in decode_batch(p)]
    assert (msg.src, msg.dst, msg.link, msg.value, msg.seq) == ("P", "R", link.lid, -4.25, 4)
    net.held.clear()
    c.sensory(link, 7.0)                    # a number, then a structure (checked in its put):
    c.sensory(link, {"x": [1, 2]})          # the newest wins either way
    c.flush()
    assert len(encoded) == 2
    # the puts that failed took no sequence number: no gap for the receiver to count
    assert [(m.value, m.seq) for _k, p, _kind in net.held for m in decode_batch(p)] == [
        ({"x": [1, 2]}, 6)]
    assert c.coalesced == 4 and c.sent - sent_before == 6


def test_newer_messages_replace_the_waiting_one(
        pair: tuple[System, System, LoopNet, list[CommManager]]) -> None:
    """While a message of a remote newest-wins link waits in its batch, newer ones replace it:
    only the newest leaves. The sender's copy of the link counts the replaced ones as
    overwritten, the receiver's counts them from the gap in the sequence numbers."""
    m0, m1, net, _comms = pair
    m0.execute("invoke P values=[0]")       # the receiver's first: gaps count after it
    _step(m0)
    net.deliver()
    _step(m1)
    m0.execute("invoke P values=[1,2,3,4,5]")
    _step(m0)
    sender = m0.msgtab.find("P", "R")
    assert (sender.sent, sender.overwritten) == (6, 4)
    newest = [m for _k, p, kind in net.held if kind is MessageKind.SENSORY
              for m in decode_batch(p)]
    assert [(m.value, m.seq) for m in newest] == [(5, 6)]
    net.deliver()
    _step(m1)
    r = m1.tsktab.get("R")
    assert r.world is not None and r.world.sensory["got"] == [0, 5]
    link = m1.msgtab.find("P", "R")
    assert (link.sent, link.overwritten, link.delivered) == (6, 4, 2)


def test_a_newer_value_that_cannot_be_sent_fails_in_the_put_and_the_waiting_one_leaves(
        pair: tuple[System, System, LoopNet, list[CommManager]]) -> None:
    """A newer message that cannot be encoded, while one waits in its batch, is refused in the
    sender's put (MessageError naming the link), not counted as sent; the waiting one leaves
    with the batch, and the next message goes as usual."""
    m0, _m1, net, comms = pair
    c = comms[0]
    link = m0.msgtab.find("P", "R")
    m0.msgmgr.deliver(link, 1.0)            # waits in its batch
    with pytest.raises(MessageError, match="P->R"):
        m0.msgmgr.deliver(link, float("inf"))
    assert (link.sent, link.overwritten) == (1, 0)
    c.flush()
    assert [(m.value, m.seq) for _k, p, _kind in net.held for m in decode_batch(p)] == [(1.0, 1)]
    net.held.clear()
    m0.msgmgr.deliver(link, 2.0)
    c.flush()
    assert [(m.value, m.seq) for _k, p, _kind in net.held for m in decode_batch(p)] == [(2.0, 2)]


def test_a_message_waiting_when_its_link_turns_express_is_replaced_not_sent_late(
        pair: tuple[System, System, LoopNet, list[CommManager]]) -> None:
    """setpri to an express priority while a message waits: the next message goes out at once
    and the waiting one is taken out of its batch (it would arrive after the newer one);
    the receiver counts it as overwritten."""
    m0, m1, net, comms = pair
    link = m0.msgtab.find("P", "R")
    m0.msgmgr.deliver(link, 0.5)            # the receiver's first: gaps count after it
    comms[0].flush()
    net.deliver()
    _step(m1)
    m0.msgmgr.deliver(link, 1.0)
    for s in (m0, m1):
        s.execute("setpri -80 P R")
    m0.msgmgr.deliver(link, 2.0)
    comms[0].flush()
    sent = [(m.value, m.seq, m.priority) for _k, p, _kind in net.held for m in decode_batch(p)]
    assert sent == [(2.0, 3, 80)]
    assert comms[0].coalesced == 1
    net.deliver()
    _step(m1)
    other = m1.msgtab.find("P", "R")
    assert (other.sent, other.overwritten) == (3, 1)
    r = m1.tsktab.get("R")
    assert r.world is not None and r.world.sensory["got"] == [0.5, 2.0]


def test_a_suspended_remote_link_refuses_even_while_a_message_waits(
        pair: tuple[System, System, LoopNet, list[CommManager]]) -> None:
    m0, _m1, net, comms = pair
    link = m0.msgtab.find("P", "R")
    m0.msgmgr.deliver(link, 1.0)
    from chcos.tables.messages import LinkStatus
    link.status = LinkStatus.SUSPENDED
    assert m0.msgmgr.deliver(link, 2.0) == 0 and link.refused == 1
    comms[0].flush()
    assert [m.value for _k, p, _kind in net.held for m in decode_batch(p)] == [1.0]


def test_a_restarted_sender_does_not_count_as_a_gap(
        pair: tuple[System, System, LoopNet, list[CommManager]]) -> None:
    m0, m1, net, comms = pair
    m0.execute("invoke P values=[1,2,3]")
    _step(m0)
    net.deliver()
    _step(m1)
    comms[0]._seq.clear()          # what a restarted sender looks like: numbering from 1
    m0.execute("invoke P values=[4]")
    _step(m0)
    net.deliver()
    _step(m1)
    link = m1.msgtab.find("P", "R")
    assert link.overwritten == 0 and link.sent == 2


def _exchange(m0: System, m1: System, net: LoopNet, rounds: int = 4) -> None:
    for _ in range(rounds):
        _step(m0)
        net.deliver()
        _step(m1)
        net.deliver()


def _answers(s: System) -> list[Any]:
    a = s.tsktab.get("A")
    assert a.world is not None
    return list(a.world.sensory.get("answers", []))


def test_a_world_model_on_another_satellite_answers(
        pair: tuple[System, System, LoopNet, list[CommManager]]) -> None:
    m0, m1, net, _ = pair
    m1.execute("invoke W")
    _exchange(m0, m1, net)
    m0.execute("invoke A ask=centre,ahead:2.5,nothing,broken")
    _exchange(m0, m1, net, rounds=8)
    assert _answers(m0) == [
        12.5, 15.0,
        "MessageError: W's world model: world model has nothing on 'nothing'",
        "MessageError: W's world model: ZeroDivisionError: division by zero"]
    assert m0.tsktab.get("A").completions == 1


def test_a_query_times_out_and_its_late_answer_is_dropped(
        pair: tuple[System, System, LoopNet, list[CommManager]]) -> None:
    m0, m1, net, _ = pair
    m1.execute("invoke W")
    _exchange(m0, m1, net)
    m0.execute("invoke A timeout=0.5 ask=centre,ahead:1.0")
    m0.run_for(0.6)           # the first query is held on the way past its timeout
    assert _answers(m0) == ["ReadTimeout: task A: no message on the answer of W about "
                            "'centre' within 0.5 s"]
    _exchange(m0, m1, net)    # both answers arrive; the late one finds nobody waiting
    assert _answers(m0)[1:] == [13.5]
    assert m0.msgmgr.queries_pending() == 0


def test_a_query_fails_when_the_peer_satellite_dies(
        pair: tuple[System, System, LoopNet, list[CommManager]]) -> None:
    m0, _m1, net, _ = pair
    m0.execute("invoke A ask=centre,centre")
    _step(m0)                  # the first query left; machine 1 dies before answering
    net.kill(1)
    _step(m0)
    assert _answers(m0) == [
        "MessageError: satellite 1 died before answering A's query",
        "MessageError: cannot ask W: satellite 1 is not up"]
    assert m0.msgmgr.queries_pending() == 0


def test_a_query_that_cannot_be_encoded_is_refused_in_the_asker(
        pair: tuple[System, System, LoopNet, list[CommManager]]) -> None:
    m0 = pair[0]
    a = m0.tsktab.get("A")
    ctx = a.ctx
    assert ctx is not None
    coro = ctx.ask("W", "ahead", object())
    with pytest.raises(MessageError, match="cannot send query A->W"):
        coro.send(None)
    assert a.wait_query is None and m0.msgmgr.queries_pending() == 0
