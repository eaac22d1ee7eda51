"""bench_faults - time from a fault to the safe value on the wire, per bus, against peers chcos
did not write (pyModbusTCP's server, canopen's LocalNode, a python-can listener, a TCP socket
standing in for a serial device), on the real-time clock.

``python -m tools.bench_faults [--runs N]`` prints, per bus, the median and worst time from
``Devtab.estop`` to the peer receiving the safe value, and (Modbus TCP, CANopen) from the end of
the fault (server back, heartbeat back) to the peer receiving the safe value. Times are taken
with ``time.monotonic`` on both sides (one machine). Needs the dev extras (pyModbusTCP).
"""

from __future__ import annotations

import argparse
import itertools
import os
import socket
import statistics
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can

from chcos.helpers import free_port
from chcos.kernel.clock import RealClock
from chcos.system.embedded import System
from tools.peers import CANOPEN_MAP, NODE, SPEED, CanopenPeer, ModbusPeer

_CHANNELS = itertools.count()
WAIT = 20.0


def _wait(pred: Callable[..., bool], what: str, *args: Any) -> None:
    deadline = time.monotonic() + WAIT
    while not pred(*args):
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out waiting for {what}")
        time.sleep(0.0005)


def _system(tmp: Path, text: str) -> System:
    path = tmp / "map.toml"
    path.write_text(text, encoding="utf-8")
    s = System([path], clock=RealClock(), machines=[0])
    s.start()
    return s


def _estops(s: System, device: str, command: int, runs: int,
            first_safe: Callable[[float], float | None]) -> list[float]:
    """``runs`` times: write ``command`` to ``device`` and wait until it is shown, then
    ``Devtab.estop`` and wait until the peer saw the safe value; the seconds from the estop to
    ``first_safe(t0)``, the peer's time of the first safe value at or after ``t0`` (None: not
    yet)."""
    out = []
    for _ in range(runs):
        s.call(s.devtab.write, device, command)
        _wait(lambda: s.devtab.get(device).value == command, "command")
        t0 = time.monotonic()
        s.call(s.devtab.estop, "bench")
        _wait(lambda t0: first_safe(t0) is not None, "safe value", t0)
        out.append((first_safe(t0) or 0.0) - t0)
    return out


def modbus(tmp: Path, runs: int) -> dict[str, list[float]]:
    """e-stop and server-restart to safe value, against pyModbusTCP's server."""
    peer = ModbusPeer(free_port(), tmp / "peer.log", {"100": 555})
    peer.start()
    s = _system(tmp, f"""
[[bus]]
name = "mb"
kind = "modbus-tcp"
host = "127.0.0.1"
port = {peer.port}
timeout = 0.3
retries = 0
reconnect_delay = 0.02
reconnect_delay_max = 0.05
[[device]]
name = "heater"
direction = "actuator"
bus = "mb"
address = {{ table = "holding", address = 100, type = "uint16" }}
safe_value = 0
[[device]]
name = "level"
direction = "sensor"
bus = "mb"
address = {{ table = "holding", address = 10, poll_period = 0.02 }}
""")
    out: dict[str, list[float]] = {"estop": [], "server back": []}

    def first_zero(t0: float) -> float | None:
        return next((w.at for w in peer.writes(t0) if w.values == [0]), None)

    try:
        out["estop"] = _estops(s, "heater", 300, runs, first_zero)
        for _ in range(max(1, runs // 4)):
            s.call(s.devtab.write, "heater", 300)
            _wait(lambda: s.devtab.get("heater").value == 300, "command")
            peer.kill()
            _wait(lambda: s.devtab.get("heater").status.value == "failed", "failure")
            peer.start()
            t0 = peer.started_at
            _wait(lambda t0: first_zero(t0) is not None, "safe value", t0)
            out["server back"].append((first_zero(t0) or 0.0) - t0)
    finally:
        s.shutdown()
        peer.kill()
    return out


def canopen_bus(tmp: Path, runs: int) -> dict[str, list[float]]:
    """e-stop and heartbeat-back to safe value (SDO download), against canopen's LocalNode."""
    from chcos.apps.sim.canopen_slave import SERVO_EDS

    channel = f"bench-{os.getpid()}-{next(_CHANNELS)}"
    peer = CanopenPeer(channel)
    s = _system(tmp, CANOPEN_MAP.format(channel=channel, node=NODE, eds=SERVO_EDS))
    out: dict[str, list[float]] = {"estop": [], "heartbeat back": []}

    def first_zero(t0: float) -> float | None:
        for at, cob, data in list(peer.dump.frames):
            if (at >= t0 and cob == 0x600 + NODE and data[0] & 0xE0 == 0x20
                    and int.from_bytes(data[1:3], "little") == SPEED
                    and int.from_bytes(data[4:8], "little") == 0):
                return at
        return None

    try:
        out["estop"] = _estops(s, "speed", 5000, runs, first_zero)
        for _ in range(max(1, runs // 4)):
            s.call(s.devtab.write, "speed", 5000)
            _wait(lambda: s.devtab.get("speed").value == 5000, "command")
            peer.silence()
            _wait(lambda: s.devtab.get("speed").status.value == "failed", "failure")
            t0 = time.monotonic()
            peer.beat()
            _wait(lambda t0: first_zero(t0) is not None, "safe value", t0)
            out["heartbeat back"].append((first_zero(t0) or 0.0) - t0)
    finally:
        s.shutdown()
        peer.close()
    return out


def can_raw(tmp: Path, runs: int) -> dict[str, list[float]]:
    """e-stop to the safe-value frame seen by another python-can bus on the channel."""
    channel = f"bench-{os.getpid()}-{next(_CHANNELS)}"
    rx = can.Bus(interface="virtual", channel=channel)
    seen: list[tuple[float, bytes]] = []
    stop = threading.Event()

    def dump() -> None:
        while not stop.is_set():
            m = rx.recv(0.05)
            if m is not None:
                seen.append((time.monotonic(), bytes(m.data)))

    th = threading.Thread(target=dump, daemon=True)
    th.start()
    s = _system(tmp, f"""
[[bus]]
name = "c"
kind = "can"
interface = "virtual"
channel = "{channel}"
[[device]]
name = "drive"
direction = "actuator"
bus = "c"
address = {{ id = 0x300, start = 0, length = 16, dlc = 2 }}
safe_value = 0
""")
    out: dict[str, list[float]] = {}
    try:
        out["estop"] = _estops(s, "drive", 77, runs, lambda t0: next(
            (a for a, d in list(seen) if a >= t0 and d == b"\0\0"), None))
    finally:
        s.shutdown()
        stop.set()
        th.join()
        rx.shutdown()
    return out


def serial_bus(tmp: Path, runs: int) -> dict[str, list[float]]:
    """e-stop to the safe-value line read by a TCP peer (a serial device server)."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    port = srv.getsockname()[1]
    lines: list[tuple[float, str]] = []
    stop = threading.Event()

    def serve() -> None:
        conn, _ = srv.accept()
        conn.settimeout(0.05)
        buf = b""
        while not stop.is_set():
            try:
                data = conn.recv(4096)
            except TimeoutError:
                continue
            if not data:
                break
            buf += data
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                lines.append((time.monotonic(), line.decode()))
        conn.close()

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    s = _system(tmp, f"""
[[bus]]
name = "ser"
kind = "serial"
url = "socket://127.0.0.1:{port}"
protocol = "line"
pattern = 'V=(?P<v>\\d+)'
[[device]]
name = "out"
direction = "actuator"
bus = "ser"
address = {{ format = "SET {{value:.0f}}" }}
safe_value = 0
""")
    out: dict[str, list[float]] = {}
    try:
        out["estop"] = _estops(s, "out", 5, runs, lambda t0: next(
            (a for a, ln in list(lines) if a >= t0 and ln == "SET 0"), None))
    finally:
        s.shutdown()
        stop.set()
        th.join(2)
        srv.close()
    return out


def main() -> None:
    """Run every bus and print the figures."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=20)
    args = ap.parse_args()
    for name, fn in (("modbus-tcp", modbus), ("canopen", canopen_bus), ("can", can_raw),
                     ("serial", serial_bus)):
        with tempfile.TemporaryDirectory() as d:
            res = fn(Path(d), args.runs)
        for what, xs in res.items():
            ms = [1000 * x for x in xs]
            print(f"{name:<11} {what:<15} n={len(ms):<3} median {statistics.median(ms):7.2f} ms"
                  f"  max {max(ms):7.2f} ms")


if __name__ == "__main__":
    main()
