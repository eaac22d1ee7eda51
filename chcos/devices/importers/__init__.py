"""importers - device maps from what an integrator has: an EDS, a DBC, a register list, SunSpec.

Each importer (:mod:`.eds`, :mod:`.dbc`, :mod:`.modbus_csv`, :mod:`.sunspec`) turns a vendor file
into a :class:`~chcos.devices.importers.draft.MapDraft` (:mod:`.draft`) - buses and devices as
plain tables, with a comment per device saying where it came from - that
:func:`~chcos.devices.importers.draft.render` writes as device-map TOML. ``chcos import KIND
FILE`` is the command (:func:`main`): it validates its own options (``--bus``, ``--prefix``,
``--rename``), runs the written map through ``chcos check`` before anything is written (a map
check refuses is never written: the import refuses, naming why), names the vendor file
relative to the map's folder, and prints what the importer could not know as warnings.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from chcos.devices.importers.draft import MapDraft, check_name, rename, render
from chcos.errors import ConfigError

#: the extra of the chcos distribution each importer's library comes with
NEEDS = {"eds": "canopen", "dbc": "can", "modbus": "modbus", "sunspec": "sunspec"}


def write_checked(text: str, output: str | None) -> None:
    """Write ``text`` (a device map) to ``output`` (None or ``-``: standard output) once
    ``chcos check`` accepts it: it is checked as a file in ``output``'s folder (so the vendor
    files it names resolve as they will), then moved into place. Raises ConfigError naming
    check's errors when it refuses; nothing is written then."""
    from chcos.devices.devmap import check

    to_stdout = output is None or output == "-"
    folder = Path.cwd() if to_stdout else Path(str(output)).resolve().parent
    if not folder.is_dir():
        raise ConfigError(f"-o {output}: no folder {folder}")
    with tempfile.TemporaryDirectory(prefix="chcos-import-") as scratch:
        where = Path(scratch) if to_stdout or not os.access(folder, os.W_OK) else folder
        fd, tmp = tempfile.mkstemp(prefix=".chcos-import-", suffix=".toml", dir=where)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(text)
            dmap, errors, _warnings = check([tmp])
            if dmap is None:
                shown = [e.replace(tmp, str(output or "the map")) for e in errors[:6]]
                more = f" (and {len(errors) - 6} more)" if len(errors) > 6 else ""
                raise ConfigError("the map would not pass chcos check, so nothing was "
                                  "written: " + "; ".join(shown) + more)
            if to_stdout:
                sys.stdout.write(text)
            else:
                os.replace(tmp, str(output))
                print(f"wrote {output}; check it with: chcos check {output}", file=sys.stderr)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)


def _file_ref(path: str, output: str | None) -> str:
    """How the map refers to ``path``: relative to the output file's directory (the map
    resolves paths relative to itself, so map and vendor file move together), or absolute when
    printing to stdout."""
    src = Path(path).resolve()
    if output is None or output == "-":
        return str(src)
    base = Path(output).resolve().parent
    try:
        return os.path.relpath(src, base)
    except ValueError:   # another drive (Windows): no relative path exists
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


def _parser() -> argparse.ArgumentParser:
    """The ``chcos import`` command line."""
    ap = argparse.ArgumentParser(
        prog="chcos import",
        description="Write a device map from a vendor file: a CANopen EDS, a CAN DBC, a Modbus "
                    "register list (CSV) or SunSpec models. The map is checked as 'chcos check' "
                    "does before it is written (an import that would write an invalid map "
                    "refuses, naming why); what the file cannot say is a warning on stderr. "
                    "Edit names, limits, safe values and stale_after before you run it.")
    sub = ap.add_subparsers(dest="kind", required=True)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("-o", "--output", help="write the map here (default: standard output)")
    common.add_argument("--bus", help="the bus's name in the map")
    common.add_argument("--machine", type=int, default=0,
                        help="the machine (satellite) of every device (default 0)")
    common.add_argument("--prefix", default="", help="put this before every device name")
    common.add_argument("--rename", action="append", default=[], metavar="OLD=NEW",
                        help="rename a device the importer named OLD (repeatable)")
    common.add_argument("--names", choices=("full", "short"), default="full",
                        help="device names: full (the vendor's, joined: an EDS record's and "
                             "entry's names, a SunSpec model's and point's) or short (the "
                             "entry's or point's own, filler words dropped)")
    can_opts = argparse.ArgumentParser(add_help=False)
    can_opts.add_argument("--interface", default="socketcan",
                          help="python-can interface of the bus (default socketcan)")
    can_opts.add_argument("--channel", default="can0",
                          help="python-can channel of the bus (default can0)")
    can_opts.add_argument("--udp-port", type=int, metavar="PORT",
                          help="with --interface udp_multicast: the bus's UDP port (give each "
                               "bus its own group and port)")
    modbus_opts = argparse.ArgumentParser(add_help=False)
    modbus_opts.add_argument("--host", default=None, help="the server's address (default "
                                                          "127.0.0.1, with a warning)")
    modbus_opts.add_argument("--port", type=int, default=502,
                             help="the server's TCP port (default 502)")
    modbus_opts.add_argument("--unit", type=int, default=1,
                             help="unit id when the list has no unit column (default 1)")
    modbus_opts.add_argument("--rtu", metavar="SERIAL", help="a Modbus RTU bus on this serial "
                                                             "port (e.g. /dev/ttyUSB0)")
    modbus_opts.add_argument("--baudrate", type=int, default=19200,
                             help="RTU bit/s (default 19200)")
    modbus_opts.add_argument("--parity", choices=("N", "E", "O"), default="N",
                             help="RTU parity (default N)")
    _eds_parser(sub, common, can_opts)
    _dbc_parser(sub, common, can_opts)
    _modbus_parser(sub, common, modbus_opts)
    _sunspec_parser(sub, common, modbus_opts)
    return ap


def _eds_parser(sub: Any, common: argparse.ArgumentParser,
                can_opts: argparse.ArgumentParser) -> None:
    p = sub.add_parser("eds", parents=[common, can_opts], help="a CANopen node from its EDS",
                       description="Devices of one CANopen node from its EDS (canopen's "
                                   "import_od). A CiA 402 drive becomes one axis device "
                                   "(profile = \"cia402\") per axis, and nothing else unless "
                                   "--objects or --all says so; --plain, or another node: "
                                   "TPDO-mapped objects as sensors delivered by PDO (stale "
                                   "after five event-timer or SYNC periods), RPDO-mapped "
                                   "objects as actuators written by PDO, other application "
                                   "objects (0x2000-0x9FFF) as SDO sensors (read-only and "
                                   "read-write) or actuators (write-only). Limits: LowLimit/"
                                   "HighLimit within the data type's range.")
    p.add_argument("file", metavar="EDS")
    p.add_argument("--node", type=int, required=True, help="the node id 1..127")
    p.add_argument("--no-sdo", action="store_true",
                   help="only the PDO-mapped objects, no SDO devices")
    p.add_argument("--objects", action="append", default=[], metavar="INDEX[,INDEX...]",
                   help="also these objects (e.g. 0x2000,0x6071; repeatable); for a CiA 402 "
                        "drive the default is its axis alone, for another node every object")
    p.add_argument("--event-timer", type=int, metavar="MS",
                   help="give every asynchronous TPDO without an event timer this one in the "
                        "node's configuration (written at boot); without it such a TPDO is a "
                        "warning: the node never sends it on its own")
    choice = p.add_mutually_exclusive_group()
    choice.add_argument("--all", action="store_true",
                        help="a CiA 402 drive: its axis and every other object")
    choice.add_argument("--plain", action="store_true",
                        help="no axis device: a CiA 402 drive's objects as plain sensors and "
                             "actuators (every object, or those of --objects)")


def _dbc_parser(sub: Any, common: argparse.ArgumentParser,
                can_opts: argparse.ArgumentParser) -> None:
    p = sub.add_parser("dbc", parents=[common, can_opts], help="every signal of a CAN DBC",
                       description="Every signal of a DBC (cantools) as a device, with the "
                                   "DBC's units and limits (within what the signal can carry); "
                                   "the DBC's scale and offset are applied by the driver. The "
                                   "messages chcos sends (--send, and those --node sends) give "
                                   "actuators, all others sensors, stale after five cycles. "
                                   "Rolling counters and checksums are declared on the bus "
                                   "([[bus.message]]) for the driver to compute and check.")
    p.add_argument("file", metavar="DBC")
    p.add_argument("--node", help="the DBC node chcos plays (its messages become actuators)")
    p.add_argument("--send", nargs="+", default=[], metavar="MESSAGE",
                   help="the messages chcos sends (shell patterns; with or without nodes in "
                        "the DBC): their signals become actuators")
    p.add_argument("--checksum", action="append", default=[],
                   metavar="MESSAGE[.SIGNAL]=ALGORITHM",
                   help="a message's checksum algorithm (xor, sum, crc8-sae-j1850, "
                        "crc8-autosar, or python:module:function); with .SIGNAL also which "
                        "signal it is (repeatable)")
    p.add_argument("--signals", nargs="+", default=[], metavar="PATTERN",
                   help="only these signals: SIGNAL or MESSAGE.SIGNAL, shell patterns "
                        "(e.g. 'Status.*' Setpoint)")


def _modbus_parser(sub: Any, common: argparse.ArgumentParser,
                   modbus_opts: argparse.ArgumentParser) -> None:
    p = sub.add_parser("modbus", parents=[common, modbus_opts],
                       help="a Modbus register list (CSV)",
                       description="Devices from a register list: a CSV with a header row naming "
                                   "the columns name, table, address, type, word order, scale, "
                                   "offset, units, access, unit, min, max, sf, description "
                                   "(aliases accepted; see docs/manual.md). Only rows whose "
                                   "access includes W become actuators. SunSpec types (enum16, "
                                   "bitfield32, acc32, sunssf, string...) are read as published.")
    p.add_argument("file", metavar="CSV")
    p.add_argument("--one-based", action="store_true",
                   help="the list's addresses start at 1 (register 1 is protocol address 0); "
                        "the same as --addressing one")
    p.add_argument("--addressing", choices=("auto", "zero", "one", "modicon"), default="auto",
                   help="how the list counts: auto (Modicon numbers where nothing else fits; "
                        "an ambiguous address is refused naming its row), zero (protocol "
                        "addresses), one (counted from 1) or modicon (40001 is holding 0)")
    p.add_argument("--table", choices=("coil", "discrete", "input", "holding"),
                   help="the table of rows that name none (a list without a table column)")


def _sunspec_parser(sub: Any, common: argparse.ArgumentParser,
                    modbus_opts: argparse.ArgumentParser) -> None:
    p = sub.add_parser("sunspec", parents=[common, modbus_opts],
                       help="a SunSpec device from its models",
                       description="Devices of a SunSpec device from SunSpec's official model "
                                   "definitions (pysunspec2): the models as the device holds "
                                   "them (--models 1,103,160:2, or a device file in "
                                   "pysunspec2's JSON form), laid out from --base (the 'SunS' "
                                   "marker; model 1 at base + 2). Scale factors are read from "
                                   "their sunssf registers; not-implemented values report no "
                                   "value.")
    p.add_argument("file", nargs="?", metavar="DEVICE.json",
                   help="a device file (pysunspec2's JSON: models with ID, L and values)")
    p.add_argument("--models", action="append", default=[], metavar="ID[:N],...",
                   help="the model ids in the device's order; ID:N repeats the model's "
                        "repeating group N times (e.g. 1,103,160:2)")
    p.add_argument("--base", type=int, default=40000,
                   help="the protocol address of the 'SunS' marker in the holding table "
                        "(default 40000; SunSpec devices also use 0 and 50000)")
    p.add_argument("--length", action="append", default=[], metavar="ID=L",
                   help="a model's length as the device reports it when it differs from the "
                        "definition (e.g. 1=65, the legacy common model)")


def _import(args: argparse.Namespace) -> MapDraft:
    """The draft ``args`` ask for; raises ConfigError."""
    bus = check_name("--bus", args.bus) if args.bus is not None else None
    prefix = check_name("--prefix", args.prefix, prefix=True)
    short = args.names == "short"
    if args.kind == "eds":
        from chcos.devices.importers.eds import import_eds

        return import_eds(args.file, args.node, bus=bus or f"canopen{args.node}",
                          machine=args.machine, prefix=prefix, sdo=not args.no_sdo,
                          eds_ref=_file_ref(args.file, args.output),
                          interface=args.interface, channel=args.channel,
                          udp_port=args.udp_port, axes=not args.plain, all_objects=args.all,
                          objects=_indices(args.objects) if args.objects else None,
                          short=short, event_timer=args.event_timer)
    if args.kind == "dbc":
        from chcos.devices.importers.dbc import import_dbc, parse_checksums

        return import_dbc(args.file, bus=bus or "can0", node=args.node,
                          machine=args.machine, prefix=prefix,
                          dbc_ref=_file_ref(args.file, args.output),
                          interface=args.interface, channel=args.channel,
                          signals=args.signals, udp_port=args.udp_port, send=args.send,
                          checksums=parse_checksums(args.checksum))
    if args.kind == "modbus":
        from chcos.devices.importers.modbus_csv import import_modbus_csv

        return import_modbus_csv(args.file, bus=bus or "plc", host=args.host,
                                 port=args.port, unit=args.unit, machine=args.machine,
                                 prefix=prefix, one_based=args.one_based,
                                 addressing=args.addressing, rtu=args.rtu,
                                 baudrate=args.baudrate, parity=args.parity, table=args.table)
    from chcos.devices.importers.sunspec import (
        import_sunspec,
        parse_models,
        read_device,
    )

    if bool(args.file) == bool(args.models):
        raise ConfigError("give the device's models: a device file or --models (one of them)")
    models = read_device(Path(args.file)) if args.file else parse_models(args.models,
                                                                         args.length)
    return import_sunspec(models, source=args.file or "--models", base=args.base,
                          bus=bus or "inverter", host=args.host, port=args.port,
                          unit=args.unit, machine=args.machine, prefix=prefix, short=short,
                          rtu=args.rtu, baudrate=args.baudrate, parity=args.parity)


def main(argv: Sequence[str]) -> int:
    """``chcos import eds|dbc|modbus|sunspec ...``: print or write (``-o``) a device map that
    ``chcos check`` accepts. Returns 0, or 2 (the error on stderr names the file and the line,
    row or key, and what was expected)."""
    args = _parser().parse_args(list(argv))
    try:
        try:
            draft = _import(args)
        except ImportError as exc:     # an optional package of the kind's extra is missing
            extra = NEEDS.get(args.kind, args.kind)
            raise ConfigError(f"needs the Python package {exc.name or exc}: pip install "
                              f"'chcos[{extra}]'") from exc
        rename(draft, args.rename)
        for warning in draft.warnings:
            print(f"warning: {warning}", file=sys.stderr)
        write_checked(render(draft), args.output)
    except (ConfigError, OSError) as exc:
        one_line = " ".join(str(exc).split("\n"))      # a refusal is one line, however long
        print(f"chcos import {args.kind}: {one_line[:2000]}", file=sys.stderr)
        return 2
    return 0
