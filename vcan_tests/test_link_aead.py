"""Link seals (issue 41): every payload is encrypted under a key derived from the system's secret
and carries its sender, run, sequence number and time stamp. A process holding the Zenoh
password but not the secret reads nothing and cannot replay; receivers refuse duplicates,
reorderings beyond the window, old and future time stamps and a sender's earlier runs, and
count each refusal by kind. Time is a virtual clock handed to the seals."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import pytest

from chcos.comm import LinkConfig, UsrPwdAuth
from chcos.comm.codec import MessageKind
from chcos.comm.qos import band_of
from chcos.comm.secret import (
    MAX_AGE_S,
    MAX_AHEAD_S,
    SEAL_BYTES,
    WINDOW,
    Refusal,
    Sealer,
    SealRefused,
    SystemSecret,
    load_or_create,
)
from chcos.comm.transport import Transport
from vcan_tests.netutil import free_port
from vcan_tests.support_faults import wait_until

SECOND = 1_000_000_000
KEY = "sys/m/0/msg"


class Clock:
    """A virtual wall clock in ns, moved by hand."""

    def __init__(self) -> None:
        self.now = 1_800_000_000 * SECOND

    def __call__(self) -> int:
        return self.now


@pytest.fixture
def secret(tmp_path: Path) -> SystemSecret:
    return load_or_create(tmp_path / "secret.json", "sys")


def _pair(secret: SystemSecret, clock: Clock, sender: str | None = "m1"
          ) -> tuple[Sealer, Sealer]:
    tx = Sealer("satellite", secret.keys, secret.identity, sender=sender, clock=clock)
    rx = Sealer("satellite", secret.keys, secret.identity, sender="m0", clock=clock)
    return tx, rx


def _refusal(rx: Sealer, data: bytes, key: str = KEY, receiver: int = 0) -> Refusal:
    with pytest.raises(SealRefused) as info:
        rx.open(key, data, receiver)
    return info.value.refusal


def test_payloads_are_encrypted_and_only_the_secret_opens_them(
        secret: SystemSecret, tmp_path: Path) -> None:
    clock = Clock()
    tx, rx = _pair(secret, clock)
    plain = json.dumps({"device": "S1", "value": 123456789}).encode()
    sealed = tx.seal(KEY, plain)
    assert len(sealed) == len(plain) + SEAL_BYTES
    assert b"S1" not in sealed and b"123456789" not in sealed and b"value" not in sealed
    assert rx.open(KEY, sealed) == ("satellite", plain)
    # the same password, another secret (what a holder of [link.auth] alone can make)
    other = load_or_create(tmp_path / "other.json", "sys")
    thief = Sealer("satellite", other.keys, other.identity, sender="m0", clock=clock)
    assert _refusal(thief, sealed) is Refusal.UNAUTHENTICATED
    # altered anywhere (header, ciphertext, tag) or moved to another key: refused
    for i in (1, 10, 20, 40, len(sealed) - 1):
        bad = bytearray(sealed)
        bad[i] ^= 0x01
        assert _refusal(rx, bytes(bad)) is Refusal.UNAUTHENTICATED
    assert _refusal(rx, tx.seal("sys/m/1/msg", plain), key=KEY) is Refusal.UNAUTHENTICATED
    assert _refusal(rx, sealed[:SEAL_BYTES - 1]) is Refusal.UNAUTHENTICATED
    assert rx.refused[Refusal.UNAUTHENTICATED] == 7
    assert thief.refused[Refusal.UNAUTHENTICATED] == 1


def test_the_same_payload_never_seals_alike(secret: SystemSecret) -> None:
    tx, _ = _pair(secret, Clock())
    a, b = tx.seal(KEY, b"same"), tx.seal(KEY, b"same")
    assert a[-(4 + 16):] != b[-(4 + 16):]  # a fresh nonce each time: no repeated ciphertext


def test_a_replay_is_refused_and_counted(secret: SystemSecret) -> None:
    clock = Clock()
    tx, rx = _pair(secret, clock)
    sealed = tx.seal(KEY, b"reading 1")
    assert rx.open(KEY, sealed)[1] == b"reading 1"
    for _ in range(5):
        assert _refusal(rx, sealed) is Refusal.REPLAYED
    assert rx.refused[Refusal.REPLAYED] == 5
    # another receiver of the same node (a second subscriber) gets it once too
    assert rx.open(KEY, sealed, receiver=7)[1] == b"reading 1"
    assert _refusal(rx, sealed, receiver=7) is Refusal.REPLAYED


def test_reordering_within_the_window_is_delivered_beyond_it_refused(
        secret: SystemSecret) -> None:
    clock = Clock()
    tx, rx = _pair(secret, clock)
    held = tx.seal(KEY, b"first")
    late = [tx.seal(KEY, b"%d" % i) for i in range(3)]
    assert [rx.open(KEY, m)[1] for m in reversed(late)] == [b"2", b"1", b"0"]
    assert rx.open(KEY, held)[1] == b"first"  # reordered by 4: inside the window
    old = tx.seal(KEY, b"held back")
    for _ in range(WINDOW - 1):
        tx.seal(KEY, b"never sent")  # what the receiver does not see is a gap, not an error
    newest = tx.seal(KEY, b"newest")
    assert rx.open(KEY, newest)[1] == b"newest"
    assert _refusal(rx, old) is Refusal.BEHIND_WINDOW
    assert rx.refused[Refusal.BEHIND_WINDOW] == 1
    # another stream (a priority band the transport may let overtake) has its own window
    other = tx.seal(KEY, b"band 6", stream=6)
    slow = tx.seal(KEY, b"band 1", stream=1)
    assert rx.open(KEY, other)[1] == b"band 6" and rx.open(KEY, slow)[1] == b"band 1"


def test_old_and_future_time_stamps_are_refused(secret: SystemSecret) -> None:
    clock = Clock()
    tx, rx = _pair(secret, clock)
    stolen = tx.seal(KEY, b"stolen")
    clock.now += int((MAX_AGE_S + 1) * SECOND)
    assert _refusal(rx, stolen) is Refusal.STALE  # never seen by rx, but too old
    clock.now += int((MAX_AHEAD_S + MAX_AGE_S + 5) * SECOND)
    ahead = tx.seal(KEY, b"ahead")
    clock.now -= int((MAX_AHEAD_S + 2) * SECOND)
    assert _refusal(rx, ahead) is Refusal.FUTURE
    clock.now += int(3 * SECOND)
    assert rx.open(KEY, ahead)[1] == b"ahead"  # within the skew allowance now
    assert rx.refused[Refusal.STALE] == 1 and rx.refused[Refusal.FUTURE] == 1


def test_a_senders_earlier_run_is_refused_after_its_restart(secret: SystemSecret) -> None:
    clock = Clock()
    before, rx = _pair(secret, clock)
    captured = [before.seal(KEY, b"old %d" % i) for i in range(3)]
    assert rx.open(KEY, captured[0])[1] == b"old 0"
    clock.now += SECOND
    after = Sealer("satellite", secret.keys, secret.identity, sender="m1", clock=clock)
    assert after.epoch != before.epoch and after.sender == before.sender
    assert rx.open(KEY, after.seal(KEY, b"new 0"))[1] == b"new 0"  # its sequence starts again
    for m in captured[1:]:  # never delivered, fresh enough, but from the replaced run
        assert _refusal(rx, m) is Refusal.OLD_RUN
    # a receiver that starts after the restart refuses the earlier run as well (sealed before
    # it started), and, once it has heard the new run, anything of an earlier one
    late_rx = Sealer("satellite", secret.keys, secret.identity, sender="m2", clock=clock)
    assert _refusal(late_rx, captured[2]) is Refusal.BEFORE_START
    assert late_rx.open(KEY, after.seal(KEY, b"new 1"))[1] == b"new 1"
    assert rx.refused[Refusal.OLD_RUN] == 2


def test_a_restarted_receiver_takes_nothing_recorded_before_its_restart(
        secret: SystemSecret) -> None:
    """Issue 41's gap: a receiver's replay windows die with it, so a message recorded before
    it restarted, younger than the age bound, must not be delivered to its next run."""
    clock = Clock()
    tx, rx = _pair(secret, clock)
    recorded = [tx.seal(KEY, b"reading %d" % i) for i in range(3)]
    assert [rx.open(KEY, m)[1] for m in recorded] == [b"reading 0", b"reading 1", b"reading 2"]
    clock.now += SECOND // 10  # the receiver restarts 0.1 s later: well inside MAX_AGE_S
    restarted = Sealer("satellite", secret.keys, secret.identity, sender="m0", clock=clock)
    for m in recorded:  # delivered once before, replayed to the new run: refused
        assert _refusal(restarted, m) is Refusal.BEFORE_START
    clock.now += 1
    fresh = tx.seal(KEY, b"reading 3")  # the sender's run goes on: its new messages pass
    assert restarted.open(KEY, fresh)[1] == b"reading 3"
    assert _refusal(restarted, fresh) is Refusal.REPLAYED
    assert restarted.refused[Refusal.BEFORE_START] == 3


def test_a_clock_stepped_back_after_the_start_refuses_nothing_sealed_since(
        secret: SystemSecret) -> None:
    """A receiver's start bound follows its wall clock being stepped back (NTP at boot): what
    is sealed after the start, on the stepped clock, is delivered; what was sealed before the
    step's reach is still refused."""
    clock = Clock()
    mono = Clock()
    tx = Sealer("satellite", secret.keys, secret.identity, sender="m1", clock=clock)
    early = tx.seal(KEY, b"sealed 10 s before the receiver started")
    clock.now += 10 * SECOND
    mono.now += 10 * SECOND
    rx = Sealer("satellite", secret.keys, secret.identity, sender="m0", clock=clock,
                monotonic=mono)
    clock.now -= 3 * SECOND  # the wall clock is stepped back 3 s ...
    mono.now += SECOND // 10  # ... 0.1 s after the start
    after = tx.seal(KEY, b"sealed after the start, on the stepped clock")
    assert rx.open(KEY, after)[1] == b"sealed after the start, on the stepped clock"
    assert _refusal(rx, early) is Refusal.BEFORE_START
    assert rx.refused[Refusal.BEFORE_START] == 1


def test_the_replay_window_matches_a_reference_model(secret: SystemSecret) -> None:
    """Deliveries out of order, duplicated and far behind, in a seeded random order: accepted
    exactly when never accepted before and less than WINDOW behind the highest accepted."""
    import random

    rnd = random.Random(41)
    clock = Clock()
    tx, rx = _pair(secret, clock)
    sealed = [tx.seal(KEY, b"%d" % i) for i in range(3 * WINDOW)]
    order: list[int] = []
    i = 0
    while i < len(sealed):  # mostly in order, some jumps ahead, back and repeated
        step = rnd.choice((1, 1, 1, 2, 70, 300, WINDOW + 5))
        order.extend(range(i, min(i + step, len(sealed))))
        i += step
        if rnd.random() < 0.3:
            order.append(rnd.randrange(max(0, i - 2 * WINDOW), min(i, len(sealed))))
    tail = order[len(order) // 2:]
    rnd.shuffle(tail)
    order[len(order) // 2:] = tail
    accepted: set[int] = set()
    top = -1
    for n in order:
        fresh = n not in accepted and top - n < WINDOW
        try:
            assert rx.open(KEY, sealed[n])[1] == b"%d" % n
            ok = True
        except SealRefused as exc:
            ok = False
            assert exc.refusal is (Refusal.REPLAYED if n in accepted and top - n < WINDOW
                                   else Refusal.BEHIND_WINDOW)
        assert ok == fresh, (n, top)
        if ok:
            accepted.add(n)
            top = max(top, n)
    assert rx.refused[Refusal.REPLAYED] + rx.refused[Refusal.BEHIND_WINDOW] > 0
    assert len(accepted) > WINDOW


def test_roles_keep_their_keys(secret: SystemSecret) -> None:
    clock = Clock()
    host = Sealer("host", secret.keys, secret.identity, clock=clock)
    _, rx = _pair(secret, clock)
    assert rx.open(KEY, host.seal(KEY, b"install"))[0] == "host"
    forged = bytearray(host.seal(KEY, b"install"))
    forged[1] = 2  # claim the satellite role: the key derived for it does not open it
    assert _refusal(rx, bytes(forged)) is Refusal.UNAUTHENTICATED


# ---- over Zenoh: a session holding the password only ----------------------------------------

def _wait(cond: threading.Condition, pred: object, timeout: float = 20.0) -> None:
    with cond:
        assert cond.wait_for(pred, timeout=timeout)  # type: ignore[arg-type]


def test_a_password_holder_reads_nothing_and_its_replays_are_refused(
        tmp_path: Path, secret: SystemSecret) -> None:
    users = tmp_path / "users.txt"
    users.write_text("sat:s3cret\n")
    auth = UsrPwdAuth("sat", "s3cret", users)
    port, thief_port = free_port(), free_port()
    got: list[bytes] = []
    captured: list[bytes] = []
    cond = threading.Condition()

    def on_member(_k: str, payload: bytes) -> None:
        with cond:
            got.append(payload)
            cond.notify_all()

    def on_thief(_k: str, payload: bytes) -> None:
        with cond:
            captured.append(payload)
            cond.notify_all()

    with Transport(LinkConfig(port, auth=auth), sealer=secret.sealer("satellite", "m0")) as rx, \
            Transport(LinkConfig(thief_port, (port,), auth=auth)) as thief, \
            Transport(LinkConfig(None, (port, thief_port), auth=auth),
                      sealer=secret.sealer("satellite", "m1")) as tx:
        rx.subscribe("t/**", on_member, roles=frozenset({"satellite"}))
        thief.subscribe("t/**", on_thief)
        rx.announce("t/alive/rx")
        thief.announce("t/alive/thief")
        seen: set[str] = set()
        tx.watch("t/alive/*", lambda k: _add(cond, seen, k), lambda _k: None)
        _wait(cond, lambda: len(seen) == 2)
        readings = [json.dumps({"device": "S1", "value": 900_000 + i}).encode() for i in range(5)]
        for r in readings:
            tx.publish("t/m/0/msg", r, priority=60, kind=MessageKind.COMMAND)
        _wait(cond, lambda: len(got) == 5 and len(captured) == 5)
        assert got == readings
        for c in captured:  # nothing readable left the members
            assert b"S1" not in c and b"900" not in c and b"device" not in c
        stolen = list(captured)  # (the thief hears its own publications too)
        # the thief replays everything it captured, five times over
        for _ in range(5):
            for c in stolen:
                thief.publish("t/m/0/msg", c, priority=60, kind=MessageKind.COMMAND)
        # and sends junk of its own, sealed with another secret
        rogue = load_or_create(tmp_path / "rogue.json", "sys").sealer("satellite", "m1")
        thief.publish("t/m/0/msg", rogue.seal("t/m/0/msg", b"forged", band_of(60)),
                      priority=60, kind=MessageKind.COMMAND)
        assert wait_until(lambda: sum(rx.refusals.values()) >= 26), "the refusals counted"
        counts = rx.refusals
        assert counts["replayed"] == 25 and counts["unauthenticated"] == 1
        tx.publish("t/m/0/msg", b"after", priority=60, kind=MessageKind.COMMAND)
        _wait(cond, lambda: len(got) == 6)
        assert got[5:] == [b"after"]  # nothing stale delivered; the link still works
        assert sum(v for k, v in rx.rejected.counts.items()
                   if "replayed payload dropped" in k) == 25




def _add(cond: threading.Condition, seen: set[str], key: str) -> None:
    with cond:
        seen.add(key)
        cond.notify_all()
