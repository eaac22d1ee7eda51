"""importers - device maps from what an integrator already has: an EDS, a DBC, a register list.

Each importer (:mod:`.eds`, :mod:`.dbc`, :mod:`.modbus_csv`) turns a vendor file into a
:class:`~chcos.devices.importers.draft.MapDraft` (:mod:`.draft`) - buses and devices as plain
tables, with a comment per device saying where it came from - that
:func:`~chcos.devices.importers.draft.render` writes as a device-map TOML file ``chcos check``
accepts and the user then edits (names, limits, safe values, stale_after). ``chcos import KIND
FILE`` is the command (:func:`main`).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from chcos.devices.importers.draft import MapDraft, render
from chcos.errors import ConfigError


def _write(text: str, output: str | None) -> None:
    if output is None or output == "-":
        sys.stdout.write(text)
        return
    Path(output).write_text(text, encoding="utf-8")
    print(f"wrote {output}; check it with: chcos check {output}", file=sys.stderr)


def _file_ref(path: str, output: str | None) -> str:
    """How the map refers to ``path``: relative to the output file's directory (the map
    resolves paths relative to itself), or absolute when printing to stdout."""
    src = Path(path).resolve()
    if output is None or output == "-":
        return str(src)
    base = Path(output).resolve().parent
    try:
        return str(src.relative_to(base))
    except ValueError:
        return str(src)


def _indices(items: Sequence[str]) -> list[int]:
    """``--objects`` values (comma-separated, hex or decimal) as indices; raises ConfigError
    naming the bad item."""
    out = []
    for item in items:
        for text in filter(None, (t.strip() for t in item.split(","))):
            try:
                index = int(text, 0)
            except ValueError:
                index = -1
            if not 0x1000 <= index <= 0xFFFF:
                raise ConfigError(f"--objects {text!r}: expected an object index such as "
                                  "0x2000 (0x1000..0xFFFF)")
            out.append(index)
    return out


def main(argv: Sequence[str]) -> int:
    """``chcos import eds|dbc|modbus FILE``: print or write (``-o``) a device map. Returns 0, or
    2 (the error on stderr names the file and what was expected)."""
    ap = argparse.ArgumentParser(
        prog="chcos import",
        description="Write a device map from a vendor file: a CANopen EDS, a CAN DBC or a "
                    "Modbus register list (CSV). The result passes 'chcos check'; edit names, "
                    "limits, safe values and stale_after before you run it.")
    sub = ap.add_subparsers(dest="kind", required=True)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("-o", "--output", help="write the map here (default: standard output)")
    common.add_argument("--bus", help="the bus's name in the map")
    common.add_argument("--machine", type=int, default=0,
                        help="the machine (satellite) of every device (default 0)")
    common.add_argument("--prefix", default="", help="put this before every device name")
    can_opts = argparse.ArgumentParser(add_help=False)
    can_opts.add_argument("--interface", default="socketcan",
                          help="python-can interface of the bus (default socketcan)")
    can_opts.add_argument("--channel", default="can0",
                          help="python-can channel of the bus (default can0)")
    can_opts.add_argument("--udp-port", type=int, metavar="PORT",
                          help="with --interface udp_multicast: the bus's UDP port (give each "
                               "bus its own group and port)")
    p = sub.add_parser("eds", parents=[common, can_opts], help="a CANopen node from its EDS",
                       description="Devices of one CANopen node from its EDS (canopen's "
                                   "import_od). A CiA 402 drive becomes one axis device "
                                   "(profile = \"cia402\") per axis, and nothing else unless "
                                   "--objects or --all says so; --plain, or another node: "
                                   "TPDO-mapped objects as sensors delivered by "
                                   "PDO, RPDO-mapped objects as actuators written by PDO, other "
                                   "application objects (0x2000-0x9FFF) as SDO sensors "
                                   "(read-only and read-write) or actuators (write-only).")
    p.add_argument("file", metavar="EDS")
    p.add_argument("--node", type=int, required=True, help="the node id 1..127")
    p.add_argument("--no-sdo", action="store_true",
                   help="only the PDO-mapped objects, no SDO devices")
    p.add_argument("--objects", action="append", default=[], metavar="INDEX[,INDEX...]",
                   help="also these objects (e.g. 0x2000,0x6071; repeatable); for a CiA 402 "
                        "drive the default is its axis alone, for another node every object")
    choice = p.add_mutually_exclusive_group()
    choice.add_argument("--all", action="store_true",
                        help="a CiA 402 drive: its axis and every other object")
    choice.add_argument("--plain", action="store_true",
                        help="no axis device: a CiA 402 drive's objects as plain sensors and "
                             "actuators (every object, or those of --objects)")
    p = sub.add_parser("dbc", parents=[common, can_opts], help="every signal of a CAN DBC",
                       description="Every signal of a DBC (cantools) as a device, with the "
                                   "DBC's units and limits; the DBC's scale and offset are "
                                   "applied by the driver. Messages sent by --node are "
                                   "actuators, all others sensors.")
    p.add_argument("file", metavar="DBC")
    p.add_argument("--node", help="the DBC node chcos plays (its messages become actuators)")
    p.add_argument("--signals", nargs="+", default=[], metavar="PATTERN",
                   help="only these signals: SIGNAL or MESSAGE.SIGNAL, shell patterns "
                        "(e.g. 'Status.*' Setpoint)")
    p = sub.add_parser("modbus", parents=[common], help="a Modbus register list (CSV)",
                       description="Devices from a register list: a CSV with a header row naming "
                                   "the columns name, table, address, type, word order, scale, "
                                   "offset, units, access, unit, min, max, description (aliases "
                                   "accepted; see the README). Only rows whose access includes "
                                   "W become actuators.")
    p.add_argument("file", metavar="CSV")
    p.add_argument("--host", default=None, help="the server's address (default 127.0.0.1, "
                                                  "with a warning)")
    p.add_argument("--port", type=int, default=502, help="the server's TCP port (default 502)")
    p.add_argument("--unit", type=int, default=1, help="unit id when the list has no unit "
                                                       "column (default 1)")
    p.add_argument("--one-based", action="store_true",
                   help="the list's addresses start at 1 (register 1 is protocol address 0); "
                        "the same as --addressing one")
    p.add_argument("--addressing", choices=("auto", "zero", "one", "modicon"), default="auto",
                   help="how the list counts: auto (Modicon 40001-style when every address of "
                        "a table is one, else protocol addresses), zero, one or modicon")
    p.add_argument("--rtu", metavar="SERIAL", help="a Modbus RTU bus on this serial port "
                                                   "(e.g. /dev/ttyUSB0) instead of TCP")
    p.add_argument("--baudrate", type=int, default=19200, help="RTU bit/s (default 19200)")
    p.add_argument("--parity", choices=("N", "E", "O"), default="N",
                   help="RTU parity (default N)")
    args = ap.parse_args(list(argv))
    draft: MapDraft
    try:
        if args.kind == "eds":
            from chcos.devices.importers.eds import import_eds

            draft = import_eds(args.file, args.node, bus=args.bus or f"canopen{args.node}",
                               machine=args.machine, prefix=args.prefix, sdo=not args.no_sdo,
                               eds_ref=_file_ref(args.file, args.output),
                               interface=args.interface, channel=args.channel,
                               udp_port=args.udp_port, axes=not args.plain, all_objects=args.all,
                               objects=_indices(args.objects) if args.objects else None)
        elif args.kind == "dbc":
            from chcos.devices.importers.dbc import import_dbc

            draft = import_dbc(args.file, bus=args.bus or "can0", node=args.node,
                               machine=args.machine, prefix=args.prefix,
                               dbc_ref=_file_ref(args.file, args.output),
                               interface=args.interface, channel=args.channel,
                               signals=args.signals, udp_port=args.udp_port)
        else:
            from chcos.devices.importers.modbus_csv import import_modbus_csv

            draft = import_modbus_csv(args.file, bus=args.bus or "plc", host=args.host,
                                      port=args.port, unit=args.unit, machine=args.machine,
                                      prefix=args.prefix, one_based=args.one_based,
                                      addressing=args.addressing, rtu=args.rtu,
                                      baudrate=args.baudrate, parity=args.parity)
        for warning in draft.warnings:
            print(f"warning: {warning}", file=sys.stderr)
        _write(render(draft), args.output)
    except (ConfigError, OSError) as exc:
        print(f"chcos import {args.kind}: {exc}", file=sys.stderr)
        return 2
    return 0
