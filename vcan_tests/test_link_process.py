"""The link between separate processes on loopback: a satellite killed with SIGKILL is seen
leaving within its lease, a late joiner is seen joining and fetches the current state, a
restarted satellite rejoins, and messages cross processes with their priority."""

from __future__ import annotations

import contextlib
import ipaddress
import json
import os
import signal
import time
from pathlib import Path

from chcos.comm import LinkConfig, LinkMessage, MessageKind, Transport, decode
from chcos.comm.config import DEFAULT_LEASE_MS
from vcan_tests.conftest import require
from vcan_tests.netutil import free_port
from vcan_tests.support_link import Child, Collector, child_args

LEASE_S = DEFAULT_LEASE_MS / 1000


def test_sigkilled_satellite_is_seen_leaving_within_its_lease() -> None:
    host_port, sat_port = free_port(), free_port()
    with Transport(LinkConfig(host_port)) as host:
        joins, leaves = Collector(), Collector()
        host.watch("chcos/alive/*", joins, leaves)
        args = child_args(listen=sat_port, connect=[host_port], token="chcos/alive/sat1")
        with Child(args) as child:
            child.expect("ready")
            assert joins.get() == "chcos/alive/sat1"
            start = time.monotonic()
            child.kill()
            assert leaves.get(timeout=LEASE_S + 2) == "chcos/alive/sat1"
            elapsed = time.monotonic() - start
        assert elapsed < LEASE_S + 1, f"leave seen after {elapsed:.3f} s"
        assert host.alive("chcos/alive/*", timeout=0.5) == []
        assert joins.empty()


def _inet_sockets(pid: int) -> list[tuple[str, str, str]]:
    """(table, local address, remote address) of every IP socket process ``pid`` holds."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        with contextlib.suppress(OSError):
            target = os.readlink(fd)
            if target.startswith("socket:["):
                inodes.add(target[8:-1])
    found = []
    for table in ("tcp", "tcp6", "udp", "udp6", "raw", "raw6"):
        lines = Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]
        for line in lines:
            cols = line.split()
            if cols[9] in inodes:
                found.append((table, _address(cols[1]), _address(cols[2])))
    return found


def _address(hex_addr: str) -> str:
    host, port = hex_addr.split(":")
    raw = bytes.fromhex(host)
    if len(raw) == 4:
        ip = ipaddress.ip_address(raw[::-1])
    else:  # IPv6: four little-endian 32-bit words
        ip = ipaddress.ip_address(b"".join(raw[i : i + 4][::-1] for i in range(0, 16, 4)))
    return f"{ip}:{int(port, 16)}"


def test_a_satellite_holds_only_loopback_tcp_sockets() -> None:
    """No multicast/UDP scouting socket, no wildcard listener, no peer off the loopback."""
    require(Path("/proc/self/net/tcp").exists(), "Linux /proc/self/net/tcp")
    host_port, sat_port = free_port(), free_port()
    with Transport(LinkConfig(host_port)) as host:
        joins = Collector()
        host.watch("chcos/alive/*", joins, lambda _k: None)
        args = child_args(listen=sat_port, connect=[host_port], token="chcos/alive/sat1")
        with Child(args) as child:
            child.expect("ready")
            assert joins.get() == "chcos/alive/sat1"
            sockets = _inet_sockets(child.proc.pid)
            assert child.stop() == 0
    assert ("tcp", f"127.0.0.1:{sat_port}", "0.0.0.0:0") in sockets  # its listener
    assert any(remote == f"127.0.0.1:{host_port}" for _, _, remote in sockets)  # its link
    for table, local, remote in sockets:
        assert table == "tcp", (table, local, remote)
        assert local.startswith("127.0.0.1:"), local
        assert remote.startswith("127.0.0.1:") or remote == "0.0.0.0:0", remote


def test_frozen_satellite_is_seen_leaving_when_its_lease_expires() -> None:
    """SIGSTOP keeps the TCP connection open: only the lease (here 400 ms) can tell."""
    host_port, sat_port = free_port(), free_port()
    lease_ms = 400
    with Transport(LinkConfig(host_port, lease_ms=lease_ms)) as host:
        joins, leaves = Collector(), Collector()
        host.watch("chcos/alive/*", joins, leaves)
        args = child_args(
            listen=sat_port, connect=[host_port], token="chcos/alive/sat1", lease_ms=lease_ms
        )
        with Child(args) as child:
            child.expect("ready")
            assert joins.get() == "chcos/alive/sat1"
            start = time.monotonic()
            os.kill(child.proc.pid, signal.SIGSTOP)
            try:
                assert leaves.get(timeout=lease_ms / 1000 + 3) == "chcos/alive/sat1"
                elapsed = time.monotonic() - start
            finally:
                os.kill(child.proc.pid, signal.SIGCONT)
            child.kill()
        assert lease_ms / 1000 * 0.5 < elapsed < lease_ms / 1000 + 1.5, elapsed


def test_late_joiner_is_seen_joining_and_fetches_the_current_state() -> None:
    host_port, p1, p2 = free_port(), free_port(), free_port()
    table = {"A1": {"machine": 1, "priority": 40}, "B1": {"machine": 0, "priority": 60}}
    with Transport(LinkConfig(host_port, (p1, p2))) as host:
        host.serve("chcos/sys/msgtab", lambda _p: json.dumps(table).encode())
        joins, leaves = Collector(), Collector()
        host.watch("chcos/alive/*", joins, leaves)
        host.announce("chcos/alive/host")
        first = child_args(
            listen=p1, connect=[host_port, p2], token="chcos/alive/sat1", watch="chcos/alive/*"
        )
        with Child(first) as sat1:
            sat1.expect("ready")
            sat1.expect("join", key="chcos/alive/host")
            assert joins.get_until("chcos/alive/sat1")[-1] == "chcos/alive/sat1"
            late = child_args(
                listen=p2,
                connect=[host_port, p1],
                token="chcos/alive/sat2",
                watch="chcos/alive/*",
                fetch=("chcos/sys/msgtab", "chcos/alive/host"),
            )
            with Child(late) as sat2:
                sat2.expect("ready")
                # the host and the first satellite both see it join...
                assert joins.get() == "chcos/alive/sat2"
                sat1.expect("join", key="chcos/alive/sat2")
                # ...it sees everybody already there...
                sat2.expect("join", key="chcos/alive/host")
                sat2.expect("join", key="chcos/alive/sat1")
                # ...and it fetched the current table by request/reply
                assert json.loads(sat2.expect("fetched")["answer"]) == table
                assert sat2.stop() == 0
            assert leaves.get() == "chcos/alive/sat2"
            sat1.expect("leave", key="chcos/alive/sat2")
            assert sat1.stop() == 0
        assert leaves.get() == "chcos/alive/sat1"


def test_killed_satellite_restarted_on_its_port_rejoins() -> None:
    host_port, sat_port = free_port(), free_port()
    with Transport(LinkConfig(host_port, (sat_port,), retry_ms=20)) as host:
        joins, leaves = Collector(), Collector()
        host.watch("chcos/alive/*", joins, leaves)
        args = child_args(listen=sat_port, token="chcos/alive/sat1")  # it connects to nobody
        with Child(args) as child:
            child.expect("ready")
            assert joins.get() == "chcos/alive/sat1"  # the host reached it by retrying
            child.kill()
        assert leaves.get() == "chcos/alive/sat1"
        with Child(args) as again:
            again.expect("ready")
            assert joins.get() == "chcos/alive/sat1"
            assert again.stop() == 0
        assert leaves.get() == "chcos/alive/sat1"


def test_messages_cross_processes_both_ways() -> None:
    host_port, sat_port = free_port(), free_port()
    with Transport(LinkConfig(host_port)) as host:
        replies = Collector()
        host.subscribe("cell/host/in", replies)
        joins = Collector()
        host.watch("chcos/alive/*", joins, lambda _k: None)
        args = child_args(
            listen=sat_port,
            connect=[host_port],
            token="chcos/alive/sat1",
            echo=("cell/sat1/in", "cell/host/in"),
        )
        with Child(args) as child:
            child.expect("ready")
            assert joins.get() == "chcos/alive/sat1"  # its subscriber was declared before
            for seq in range(20):
                msg = LinkMessage(
                    MessageKind.COMMAND, "C1", "B1", 3, 70, seq, time.time_ns(), {"n": seq}
                )
                host.send("cell/sat1/in", msg)
            got = [decode(replies.get()[1]) for _ in range(20)]
            assert [m.seq for m in got] == list(range(20))  # reliable, in order
            assert got[7].value == {"n": 7}
            assert child.stop() == 0
