"""Replays and eavesdropping against running satellites (issue 41). The attacker holds what a
system file with ``[link.auth]`` gives away (the password) and the TLS files, but not the
system's sealing secret: it opens a session and hears the satellites' traffic, yet reads
nothing of it, and what it replays is refused and counted, also by a satellite restarted since
the recording (its replay windows start empty, but it takes nothing sealed before it started). A
member (it holds the secret) replaying its own messages, or holding one back beyond the replay
window, gets no further. A liveliness token declared by the password holder does not make a
dead satellite up, neither for the other satellites nor for the host (both want a sealed hello),
and an answer to another hello, replayed, does not either."""

from __future__ import annotations

import json
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from chcos.comm.codec import LinkMessage, MessageKind, decode_batch, encode, encode_batch
from chcos.comm.payloads import Hello, from_wire
from chcos.comm.qos import band_of
from chcos.comm.secret import REPLY_STREAM, WINDOW, Refusal, SealRefused, load_or_create
from chcos.comm.transport import Transport
from chcos.errors import LinkError
from chcos.satellites import sysfile
from vcan_tests.support_faults import wait_until
from vcan_tests.support_sat import Cluster, device, link
from vcan_tests.test_sat_security import _wait_rejected

S = "vcan_tests.support_sat"


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    """Two satellites with a password in the system file: R1 on machine 1 reads S1, R0 on
    machine 0 reads R1 and drives M0 (each reading crosses the link from 1 to 0)."""
    c = Cluster(tmp_path, machines=(0, 1), auth=True)
    c.start(0)
    c.start(1)
    c.host.wait_for([0, 1])
    for line in ("install -m0 sysfile", "install -m1 sysfile",
                 f"install -m1i1 --code={S}:relay R1 S1",
                 f"install -m0i1o1 --code={S}:relay R0 R1 M0", "invoke R1", "invoke R0"):
        c.host.execute(line)
    yield c
    c.close()


def _eavesdropper(c: Cluster) -> Transport:
    """A session with the system file's password and the TLS files but no sealing secret,
    once it sees every satellite."""
    cfg = sysfile.link_config_for(c.sf, None, c.sf.secret())  # the secret only finds the TLS
    assert cfg.auth is not None and cfg.auth.user == "sat"     # files: [link.auth] is used
    t = Transport(cfg)  # no sealer: it cannot seal, and it sees payloads as they travel
    seen: set[str] = set()
    cond = threading.Condition()

    def joined(key: str) -> None:
        with cond:
            seen.add(key)
            cond.notify_all()

    t.watch(f"{c.sf.prefix}/alive/*", joined, lambda _k: None)
    with cond:
        assert cond.wait_for(lambda: len(seen) == len(c.procs), timeout=20)
    return t


def _delivered(n: int) -> Callable[[dict[str, Any]], bool]:
    """True of a map in which link R1 -> R0 delivered ``n`` readings."""
    return lambda doc: bool(link(doc, "R1", "R0")["delivered"] == n)


@pytest.mark.slow
def test_a_password_holder_reads_nothing_and_replays_nothing(cluster: Cluster,
                                                             tmp_path: Path) -> None:
    c = cluster
    p = c.sf.prefix
    spy = _eavesdropper(c)
    captured: list[tuple[str, bytes]] = []
    lock = threading.Lock()

    def record(key: str, payload: bytes) -> None:
        with lock:
            captured.append((key, payload))

    try:
        spy.subscribe(f"{p}/**", record)
        values = [424201 + i for i in range(5)]
        for n, v in enumerate(values, 1):  # one at a time: each reading is delivered
            c.host.execute(f"inject S1 {v}")
            c.wait_until(_delivered(n), machine=0)
        c.host.execute("suspend R1")  # A2 suspended: nothing new crosses the link
        with lock:
            stolen = [(k, d) for k, d in captured if k == f"{p}/m/0/msg"]
            heard = [d for _k, d in captured]
        assert len(stolen) >= len(values)
        for data in heard:  # nothing readable left the members: no value, no task name
            assert not any(str(v).encode() in data for v in values)
            assert b"R1" not in data and b"S1" not in data and b"sensory" not in data
        # what the password and another secret give: nothing opens
        guess = load_or_create(tmp_path / "guess.json", c.sf.name).sealer("satellite")
        for k, d in stolen:
            with pytest.raises(SealRefused) as info:
                guess.open(k, d)
            assert info.value.refusal is Refusal.UNAUTHENTICATED
        for _ in range(5):  # the attack of the issue: five replays of everything recorded
            for k, d in stolen:
                spy.publish(k, d, priority=60, kind=MessageKind.SENSORY)
        counts = _wait_rejected(c, 0, "link seal refused: replayed", 5 * len(stolen))
        assert counts["link seal refused: replayed"] == 5 * len(stolen)
    finally:
        spy.close()
    doc = c.host.map_doc(0)
    assert link(doc, "R1", "R0")["delivered"] == len(values)  # nothing stale delivered
    assert device(doc, "M0")["value"] == values[-1]
    assert device(doc, "M0")["commands"] == len(values)


def _actuator(value: int) -> bytes:
    return encode_batch([encode(LinkMessage(MessageKind.COMMAND, "", "M0", 0, 98, 1, 0,
                                            {"op": "actuator", "device": "M0",
                                             "value": value}))])


@pytest.mark.slow
def test_a_restarted_satellite_refuses_what_was_recorded_before_its_restart(
        cluster: Cluster) -> None:
    c = cluster
    p = c.sf.prefix
    spy = _eavesdropper(c)
    captured: list[tuple[str, bytes]] = []
    lock = threading.Lock()

    def record(key: str, payload: bytes) -> None:
        with lock:
            captured.append((key, payload))

    values = [515101 + i for i in range(3)]
    try:
        spy.subscribe(f"{p}/m/0/msg", record)
        for n, v in enumerate(values, 1):
            c.host.execute(f"inject S1 {v}")
            c.wait_until(_delivered(n), machine=0)
        c.host.execute("suspend R1")  # nothing new crosses the link from here on
        with lock:
            stolen = list(captured)
        assert len(stolen) >= len(values)
        c.kill(0)  # the receiver restarts: its replay windows start empty
        c.start(0)
        c.host.wait_for([0, 1])
        before = link(c.host.map_doc(0), "R1", "R0")
        for k, d in stolen:  # seconds old: well within the age bound
            spy.publish(k, d, priority=60, kind=MessageKind.SENSORY)
        counts = _wait_rejected(c, 0, "link seal refused: sealed before this receiver started",
                                len(stolen))
    finally:
        spy.close()
    assert counts["link seal refused: sealed before this receiver started"] == len(stolen)
    doc = c.host.map_doc(0)
    after = link(doc, "R1", "R0")
    for what in ("delivered", "overwritten", "queued"):  # nothing recorded reached the link
        assert after[what] == before[what], what
    assert device(doc, "M0")["value"] not in values


@pytest.mark.slow
def test_a_member_replaying_or_holding_back_its_own_traffic_is_refused(
        cluster: Cluster) -> None:
    c = cluster
    key = f"{c.sf.prefix}/m/0/msg"
    member = c.sf.secret().sealer("satellite")  # holds the secret: its seals are good
    wire = _eavesdropper(c)  # what it sends, byte for byte, over a session of the system
    band = band_of(98)

    def send(data: bytes) -> None:
        wire.publish(key, data, priority=98, kind=MessageKind.COMMAND)

    try:
        first = member.seal(key, _actuator(41), band)
        send(first)
        c.wait_until(lambda d: device(d, "M0")["value"] == 41, machine=0)
        for _ in range(3):
            send(first)  # its own message again
        _wait_rejected(c, 0, "link seal refused: replayed", 3)
        held = member.seal(key, _actuator(43), band)
        for _ in range(WINDOW):
            member.seal(key, _actuator(0), band)  # sealed, never sent
        send(member.seal(key, _actuator(44), band))
        c.wait_until(lambda d: device(d, "M0")["value"] == 44, machine=0)
        send(held)  # reordered further back than the window
        counts = _wait_rejected(c, 0, "link seal refused: behind the replay window", 1)
    finally:
        wire.close()
    assert counts["link seal refused: replayed"] == 3
    assert counts["link seal refused: behind the replay window"] == 1
    doc = c.host.map_doc(0)
    assert device(doc, "M0")["value"] == 44 and device(doc, "M0")["commands"] == 2


@pytest.mark.slow
def test_a_forged_liveliness_token_does_not_bring_a_dead_satellite_back(
        cluster: Cluster) -> None:
    c = cluster
    p = c.sf.prefix
    c.kill(1)
    c.wait_until(lambda d: device(d, "S1")["status"] == "failed", machine=0)
    spy = _eavesdropper(c)
    member = c.sf.secret().sealer("satellite")  # the test reads what machine 0 says
    hellos: list[Hello] = []
    cond = threading.Condition()

    def heard(key: str, data: bytes) -> None:
        for m in decode_batch(member.open(key, data)[1]):
            if m.kind is MessageKind.STATUS and isinstance(
                    hello := from_wire(m.kind, m.value), Hello):
                with cond:
                    hellos.append(hello)
                    cond.notify_all()

    try:
        spy.subscribe(f"{p}/all/msg", heard)
        spy.announce(f"{p}/alive/1")  # the password holder poses as machine 1
        with cond:  # machine 0 saw the token and asked machine 1 for a sealed hello
            assert cond.wait_for(lambda: Hello(0, True) in hellos, timeout=20)
        doc = c.host.map_doc(0)
        assert device(doc, "S1")["status"] == "failed"  # no answer: still down there
    finally:
        spy.close()
    # the host's view: the password holder takes the dead satellite's port (the host connects
    # to it) and declares machine 1's token there; a token is a hint, and machine 1 does not
    # answer a sealed hello
    impostor = Transport(sysfile.link_config_for(c.sf, 1, c.sf.secret()))  # no sealer
    try:
        impostor.announce(f"{p}/alive/1")
        assert wait_until(lambda: c.host.tokens() == [0, 1], timeout=60), "host sees the token"
        assert c.host.alive() == [0]
        assert c.host.map_doc()["alive"] == [0]
        with pytest.raises(LinkError, match=r"\[1\] .* not up"):
            c.host.wait_for([1], timeout=2.0)
        # it answers the hellos itself: with an answer a satellite sealed to another hello
        # (what a member once sent), then with that same answer again
        forged = member.seal(f"{p}/m/1/ctl", json.dumps(
            {"ok": True, "machine": 1, "nonce": "0" * 32}).encode(), REPLY_STREAM)
        with impostor.serve(f"{p}/m/1/ctl", lambda _request: forged):
            assert c.host.alive() == [0]  # opens (sealed, fresh), but not this hello's nonce
            assert c.host.alive() == [0]  # the same answer again: a replay, refused
        assert c.host.transport.refusals["replayed"] >= 1
        causes = c.host.unconfirmed.counts
        assert sum(n for k, n in causes.items() if k.startswith("machine 1:")) >= 4
    finally:
        impostor.close()
    c.start(1)  # the real one comes back: its token and its hello
    c.host.wait_for([0, 1])
    c.wait_until(lambda d: device(d, "S1")["status"] == "OK", machine=0)


@pytest.mark.slow
def test_a_password_holder_answering_first_does_not_make_a_live_satellite_look_down(
        tmp_path: Path) -> None:
    c = Cluster(tmp_path, machines=(0, 1, 2), auth=True)
    p = c.sf.prefix
    member = c.sf.secret().sealer("satellite")
    stale = member.seal(f"{p}/m/1/ctl", json.dumps(
        {"ok": True, "machine": 1, "nonce": "0" * 32}).encode(), REPLY_STREAM)
    answers = [b"\x00" * 64, stale]  # wrongly sealed; sealed before the host started
    served: list[int] = []

    def first(_request: bytes) -> bytes:  # answers at once, as machine 1
        served.append(1)
        return answers[len(served) % 2]

    # the password holder takes machine 2's port (not started; the host connects to it) and
    # answers machine 1's requests there, while machine 1 is up
    attacker = Transport(sysfile.link_config_for(c.sf, 2, c.sf.secret()))  # no sealer
    try:
        c.start(0)
        c.start(1)
        with attacker.serve(f"{p}/m/1/ctl", first):
            assert c.host.wait_for([0, 1], timeout=60.0) == [0, 1]
            # each hello goes to both; the attacker's answers are refused, the satellite's taken
            assert wait_until(lambda: c.host.alive() == [0, 1] and len(served) >= 2,
                              timeout=60), "the attacker is asked too"
            for _ in range(3):
                assert c.host.alive() == [0, 1]
            assert c.host.wait_for([0, 1], timeout=20.0) == [0, 1]
            c.host.execute("install -m1 sysfile")  # other requests are answered too
            assert c.host.map_doc(1)["alive"] == [0, 1]
        refusals = c.host.transport.refusals
        assert refusals["unauthenticated"] >= 1 and refusals[Refusal.BEFORE_START.value] >= 1
        assert not any(k.startswith("machine 1:") for k in c.host.unconfirmed.counts)
    finally:
        attacker.close()
        c.close()
