"""cli - ``chcos sim ...``: run a simulated field device from the command line, on real time.

``chcos sim can``     a DBC-coded raw CAN node (:mod:`chcos.apps.sim.can_device`)
``chcos sim serial``  a line or binary serial instrument on a pty or 127.0.0.1 TCP
                      (:mod:`chcos.apps.sim.serial_device`)
``chcos sim canopen`` / ``cia402`` / ``modbus`` / ``weld``: handed to
``chcos.apps.sim.canopen_slave``, ``chcos.apps.sim.cia402_drive``, ``chcos.apps.sim.modbus_server``
and ``chcos.apps.weld.plant`` (imported only when asked for).

Every simulator prints what it receives to stdout and runs until Ctrl-C, ``--duration`` seconds,
or ``--count`` send rounds.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Callable, Sequence
from importlib import import_module
from typing import Any

from chcos.errors import BusError, ChcosError
from drivers.codecs.serial import parse_hex

DELEGATED = {"canopen": "chcos.apps.sim.canopen_slave", "cia402": "chcos.apps.sim.cia402_drive",
             "modbus": "chcos.apps.sim.modbus_server", "weld": "chcos.apps.weld.plant"}


def _pairs(items: Sequence[str], what: str) -> list[tuple[str, str]]:
    out = []
    for item in items:
        key, sep, val = item.partition("=")
        if not sep or not key:
            raise BusError(f"{what} {item!r}: expected NAME=VALUE")
        out.append((key, val))
    return out


class _Runner:
    """Runs ``step`` at ``rate_hz`` on real time until a limit or Ctrl-C."""

    def __init__(self, rate_hz: float, count: int | None, duration: float | None) -> None:
        self.period = 1.0 / rate_hz
        self.count = count
        self.duration = duration
        self.stop = threading.Event()

    def run(self, step: Callable[[int, float], None]) -> None:
        start = time.monotonic()
        n = 0
        try:
            while not self.stop.is_set():
                t = time.monotonic() - start
                if self.duration is not None and t >= self.duration:
                    break
                step(n, t)
                n += 1
                if self.count is not None and n >= self.count:
                    break
                self.stop.wait(max(0.0, start + n * self.period - time.monotonic()))
        except KeyboardInterrupt:
            pass


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rate", type=float, default=10.0, help="send rounds per second (10)")
    p.add_argument("--count", type=int, help="stop after this many send rounds")
    p.add_argument("--duration", type=float, help="stop after this many seconds")


def _can(args: argparse.Namespace) -> int:
    from chcos.apps.sim.can_device import CanDeviceSim
    sim = CanDeviceSim(args.dbc, interface=args.interface, channel=args.channel)
    with sim:
        for name, val in _pairs(args.set, "--set"):
            message, _, signal = name.partition(".")
            sim.set(message, **{signal: float(val)})
        messages = list(args.send)
        messages += [m.name for m in sim.db.messages if m.name not in messages
                     and any(node in (m.senders or []) for node in args.node)]
        for m in messages:
            sim.set(m)                       # an unknown name fails here, before the loop
        seen: dict[str, dict[str, Any]] = {}

        def step(n: int, t: float) -> None:
            for m in messages:
                sim.send(m)
            for name, vals in list(sim.received.items()):
                if seen.get(name) != vals:
                    seen[name] = dict(vals)
                    print(f"{t:8.3f} rx {name} {vals}", flush=True)

        _Runner(args.rate, args.count, args.duration).run(step)
        print(f"sent {sim.frames_out} frames, received {sim.frames_in}", flush=True)
    return 0


def _serial(args: argparse.Namespace) -> int:
    from chcos.apps.sim.serial_device import PtySerialSim, SerialSim, TcpSerialSim
    sim: SerialSim
    if args.pty:
        pty = PtySerialSim()
        sim, where = pty, pty.path
    else:
        tcp = TcpSerialSim(args.tcp)
        sim, where = tcp, tcp.url
    print(f"serial device at {where}", flush=True)
    sync = parse_hex(args.sync) if args.struct else b""
    with sim:
        if isinstance(sim, TcpSerialSim) and not sim.wait_connected(1, args.wait_client):
            print(f"no client connected to {where} within {args.wait_client} s", file=sys.stderr)
            return 1
        if args.start_on_rx and not sim.wait_received(bool, args.wait_client):
            print(f"nothing received on {where} within {args.wait_client} s", file=sys.stderr)
            return 1
        shown = 0

        def step(n: int, t: float) -> None:
            nonlocal shown
            if args.struct:
                vals = [float(v.format(n=n, t=t)) for v in args.values.split(",")]
                ints = [round(v) if c in "bBhHiIlLqQ" else v
                        for v, c in zip(vals, args.struct.lstrip("<>!=@"), strict=False)]
                sim.send_frame(sync, args.struct, ints, args.checksum)
            else:
                sim.send_line(args.line.format(n=n, t=t))
            if args.garbage_every and n % args.garbage_every == args.garbage_every - 1:
                sim.send_bytes(b"\x00garbage\xff\n")
            rx = sim.received()
            if len(rx) > shown:
                print(f"{t:8.3f} rx {rx[shown:]!r}", flush=True)
                shown = len(rx)

        _Runner(args.rate, args.count, args.duration).run(step)
    return 0


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="chcos sim",
        description="Run a simulated field device on loopback or a CAN channel, for tests and "
                    "demos without hardware. 'chcos sim --from MAP' simulates every device of "
                    "a device map instead (see 'chcos sim --from MAP --help').")
    sub = parser.add_subparsers(dest="what", required=True)
    c = sub.add_parser("can", help="a DBC-coded raw CAN node",
                       description="A raw CAN node that sends DBC-coded messages every round "
                                   "on a python-can channel (virtual by default).")
    c.add_argument("--dbc", required=True, help="DBC file of the messages")
    c.add_argument("--interface", default="virtual", help="python-can interface (virtual)")
    c.add_argument("--channel", default="vcan0", help="python-can channel (vcan0)")
    c.add_argument("--set", action="append", default=[], metavar="MSG.SIG=VALUE",
                   help="initial signal value (repeatable)")
    c.add_argument("--send", action="append", default=[], metavar="MSG",
                   help="message sent every round (repeatable)")
    c.add_argument("--node", action="append", default=[], metavar="NODE",
                   help="send every message whose DBC sender is NODE (repeatable)")
    _common(c)
    s = sub.add_parser("serial", help="a line or binary serial instrument",
                       description="A serial instrument on a pty or a loopback TCP port "
                                   "(socket://) sending text lines or binary frames every "
                                   "round.")
    where = s.add_mutually_exclusive_group(required=True)
    where.add_argument("--tcp", type=int, metavar="PORT",
                       help="listen on 127.0.0.1:PORT (0: any) for socket://")
    where.add_argument("--pty", action="store_true", help="open a pty pair, print the slave path")
    s.add_argument("--line", default="W={t:.2f}",
                   help="line template, str.format with n (round) and t (seconds)")
    s.add_argument("--sync", default="AA 55", help="binary: sync bytes in hex")
    s.add_argument("--struct", help="binary: struct format of the payload (selects binary)")
    s.add_argument("--values", default="{n}", help="binary: comma-separated value templates")
    s.add_argument("--checksum", default="none", choices=("none", "sum8", "xor8"))
    s.add_argument("--garbage-every", type=int, default=0, metavar="N",
                   help="inject garbage after every N rounds (0: never)")
    s.add_argument("--start-on-rx", action="store_true",
                   help="send only after the driver has written something (e.g. a start command)")
    s.add_argument("--wait-client", type=float, default=60.0, metavar="S",
                   help="seconds to wait for the driver to connect or write (60)")
    _common(s)
    delegated_help = {"canopen": "a CANopen servo drive (SDO, PDOs, heartbeat, EMCY)",
                      "cia402": "a CiA 402 drive (state machine, modes, faults, quick stop)",
                      "modbus": "a Modbus slave as strict as a device (TCP, RTU over TCP, or RTU "
                                "on a serial port or pty: --serial PATH)",
                      "weld": "the whole welding cell on its real protocols"}
    for name in DELEGATED:
        sub.add_parser(name, help=delegated_help.get(name, "a simulated device"),
                       add_help=False)
    return parser


def main(argv: list[str]) -> int:
    """Entry of ``chcos sim``; returns the exit status (2 for usage errors and missing
    simulators, 1 when a simulator fails)."""
    if argv and argv[0] in DELEGATED:
        mod_name = DELEGATED[argv[0]]
        try:
            mod = import_module(mod_name)
        except ImportError as exc:
            print(f"chcos sim {argv[0]}: {mod_name} is not available: {exc}", file=sys.stderr)
            return 2
        return int(mod.main(argv[1:]))
    args = _parser().parse_args(argv)
    try:
        return _can(args) if args.what == "can" else _serial(args)
    except (ChcosError, ValueError, KeyError) as exc:
        print(f"chcos sim {args.what}: {exc}", file=sys.stderr)
        return 1
