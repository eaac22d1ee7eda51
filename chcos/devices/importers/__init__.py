"""importers - device maps from what an integrator already has: an EDS, a DBC, a register list.

Each importer (:mod:`.eds`, :mod:`.dbc`, :mod:`.modbus_csv`) turns a vendor file into a
:class:`MapDraft` - buses and devices as plain tables, with a comment per device saying where it
came from - that :func:`render` writes as a device-map TOML file ``chcos check`` accepts and the
user then edits (names, limits, safe values, stale_after). ``chcos import KIND FILE`` is the
command (:func:`main`).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from chcos.errors import ConfigError


@dataclass
class MapDraft:
    """A device map being written: header comment lines, bus tables, device tables (each with
    the comment lines printed above it)."""

    header: list[str] = field(default_factory=list)
    buses: list[dict[str, Any]] = field(default_factory=list)
    devices: list[tuple[list[str], dict[str, Any]]] = field(default_factory=list)
    _names: set[str] = field(default_factory=set)

    def name(self, text: str, prefix: str = "") -> str:
        """A device name from ``text`` (letters, digits, ``_``), unique in this draft."""
        snake = re.sub(r"(?<=[a-z0-9])(?=[A-Z])", "_", text)  # OilPressure -> Oil_Pressure
        base = prefix + (re.sub(r"[^0-9A-Za-z_]+", "_", snake).strip("_").lower() or "device")
        if not re.match(r"[A-Za-z_]", base):
            base = f"d_{base}"
        name, n = base, 2
        while name in self._names:
            name, n = f"{base}_{n}", n + 1
        self._names.add(name)
        return name

    def add(self, comments: list[str], device: dict[str, Any]) -> None:
        """Add one device table with its comment lines."""
        self.devices.append((comments, device))


class Hex(int):
    """An integer written in hexadecimal (CAN ids, object indices)."""

    __slots__ = ()


def toml_value(v: Any) -> str:
    """``v`` as a TOML value (strings, numbers, booleans, lists and inline tables)."""
    if isinstance(v, Hex):
        return f"0x{int(v):04X}"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"no TOML form for {v!r}")


def render(draft: MapDraft) -> str:
    """The device-map TOML text of ``draft``."""
    out = [f"# {line}".rstrip() for line in draft.header]
    for bus in draft.buses:
        out += ["", "[[bus]]"] + [f"{k} = {toml_value(v)}" for k, v in bus.items()]
    for comments, dev in draft.devices:
        out += [""] + [f"# {c}" for c in comments] + ["[[device]]"]
        out += [f"{k} = {toml_value(v)}" for k, v in dev.items()]
    return "\n".join(out) + "\n"


def limits(lo: Any, hi: Any) -> list[float] | None:
    """A ``limits`` value from optional ends (None when both are open)."""
    if lo is None and hi is None:
        return None
    return [-math.inf if lo is None else float(lo), math.inf if hi is None else float(hi)]


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
    p = sub.add_parser("eds", parents=[common, can_opts], help="a CANopen node from its EDS",
                       description="Devices of one CANopen node from its EDS (canopen's "
                                   "import_od): TPDO-mapped objects as sensors delivered by "
                                   "PDO, RPDO-mapped objects as actuators written by PDO, other "
                                   "application objects (0x2000-0x9FFF) as SDO sensors "
                                   "(read-only and read-write) or actuators (write-only).")
    p.add_argument("file", metavar="EDS")
    p.add_argument("--node", type=int, required=True, help="the node id 1..127")
    p.add_argument("--no-sdo", action="store_true",
                   help="only the PDO-mapped objects, no SDO devices")
    p = sub.add_parser("dbc", parents=[common, can_opts], help="every signal of a CAN DBC",
                       description="Every signal of a DBC (cantools) as a device, with the "
                                   "DBC's units and limits; the DBC's scale and offset are "
                                   "applied by the driver. Messages sent by --node are "
                                   "actuators, all others sensors.")
    p.add_argument("file", metavar="DBC")
    p.add_argument("--node", help="the DBC node chcos plays (its messages become actuators)")
    p = sub.add_parser("modbus", parents=[common], help="a Modbus register list (CSV)",
                       description="Devices from a register list: a CSV with a header row naming "
                                   "the columns name, table, address, type, word order, scale, "
                                   "offset, units, access, unit, min, max, description (aliases "
                                   "accepted; see the README). Only rows whose access includes "
                                   "W become actuators.")
    p.add_argument("file", metavar="CSV")
    p.add_argument("--host", default="127.0.0.1", help="the server's address (default "
                                                       "127.0.0.1)")
    p.add_argument("--port", type=int, default=502, help="the server's TCP port (default 502)")
    p.add_argument("--unit", type=int, default=1, help="unit id when the list has no unit "
                                                       "column (default 1)")
    p.add_argument("--one-based", action="store_true",
                   help="the list's addresses start at 1 (register 1 is protocol address 0)")
    args = ap.parse_args(list(argv))
    try:
        if args.kind == "eds":
            from chcos.devices.importers.eds import import_eds

            draft = import_eds(args.file, args.node, bus=args.bus or f"canopen{args.node}",
                               machine=args.machine, prefix=args.prefix, sdo=not args.no_sdo,
                               eds_ref=_file_ref(args.file, args.output),
                               interface=args.interface, channel=args.channel)
        elif args.kind == "dbc":
            from chcos.devices.importers.dbc import import_dbc

            draft = import_dbc(args.file, bus=args.bus or "can0", node=args.node,
                               machine=args.machine, prefix=args.prefix,
                               dbc_ref=_file_ref(args.file, args.output),
                               interface=args.interface, channel=args.channel)
        else:
            from chcos.devices.importers.modbus_csv import import_modbus_csv

            draft = import_modbus_csv(args.file, bus=args.bus or "plc", host=args.host,
                                      port=args.port, unit=args.unit, machine=args.machine,
                                      prefix=args.prefix, one_based=args.one_based)
        _write(render(draft), args.output)
    except (ConfigError, OSError) as exc:
        print(f"chcos import {args.kind}: {exc}", file=sys.stderr)
        return 2
    return 0
