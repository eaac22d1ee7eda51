"""modbus_csv - a device map from a Modbus register list (``chcos import modbus LIST.csv``).

The list is a CSV file (comma, semicolon or tab separated, detected) with a header row. Columns
are found by name, case and punctuation ignored:

========== ==================================================================================
column     names accepted
========== ==================================================================================
name       ``name``, ``tag``, ``signal``, ``variable``, ``symbol``
table      ``table``, ``area``, ``register type``, ``object type``, ``function``: coil / ``0x``
           / ``DO``, discrete / ``discrete input`` / ``1x`` / ``DI``, input / ``input
           register`` / ``3x`` / ``IR``, holding / ``holding register`` / ``4x`` / ``HR``
address    ``address``, ``register``, ``addr``, ``offset address``; without a table column a
           Modicon number (``40001``, ``300001``) gives table and address
type       ``type``, ``data type``, ``datatype``, ``format``: int16/INT, uint16/UINT/WORD,
           int32/DINT, uint32/UDINT/DWORD, float32/REAL/FLOAT, float64/LREAL, bool/BOOL
word order ``word order``, ``word swap``, ``byte order``: big/ABCD/high first/no, little/
           CDAB/low first/yes (written ``big``/``little``), BADC/byte swap, DCBA/little endian
           bytes
scale      ``scale``, ``factor``, ``gain``, ``multiplier``; ``offset``
units      ``units``, ``eng unit``, ``uom`` (a ``unit`` column is the unit id when it holds
           whole numbers, else the units)
unit id    ``unit id``, ``slave``, ``slave id``, ``device id``
access     ``access``, ``rw``, ``direction``: rows whose access contains W (``RW``, ``W``,
           ``write``, ``actuator``) become actuators, all others sensors
limits     ``min``/``low``, ``max``/``high`` (engineering units)
comment    ``description``, ``comment``
========== ==================================================================================

Addresses are the protocol's (0-based) unless ``one_based``. Every error names the file, the
row and the column.
"""

from __future__ import annotations

import csv
import re
from pathlib import Path
from typing import Any

from chcos.devices.importers.draft import MapDraft, limits
from chcos.errors import ConfigError

COLUMNS = {
    "name": ("name", "tag", "signal", "variable", "symbol", "tagname"),
    "table": ("table", "area", "registertype", "objecttype", "function", "space"),
    "address": ("address", "register", "addr", "offsetaddress", "regaddress"),
    "type": ("type", "datatype", "format", "dtype"),
    "word_order": ("wordorder", "wordswap", "byteorder", "swap", "endianness"),
    "scale": ("scale", "factor", "gain", "multiplier"),
    "offset": ("offset",),
    "units": ("units", "engunit", "engineeringunit", "engunits", "uom"),
    "unit_id": ("unitid", "slave", "slaveid", "deviceid", "station"),
    "unit": ("unit",),
    "access": ("access", "rw", "direction", "readwrite", "mode"),
    "min": ("min", "low", "minimum", "lowlimit"),
    "max": ("max", "high", "maximum", "highlimit"),
    "comment": ("description", "comment", "remarks", "text"),
}
TABLES = {"coil": "coil", "coils": "coil", "0x": "coil", "do": "coil", "digitaloutput": "coil",
          "discrete": "discrete", "discreteinput": "discrete", "discreteinputs": "discrete",
          "1x": "discrete", "di": "discrete", "digitalinput": "discrete",
          "input": "input", "inputregister": "input", "inputregisters": "input", "3x": "input",
          "ir": "input", "holding": "holding", "holdingregister": "holding",
          "holdingregisters": "holding", "4x": "holding", "hr": "holding"}
TYPES = {"int16": "int16", "int": "int16", "short": "int16", "sint16": "int16",
         "uint16": "uint16", "uint": "uint16", "word": "uint16", "ushort": "uint16",
         "int32": "int32", "dint": "int32", "long": "int32", "uint32": "uint32",
         "udint": "uint32", "dword": "uint32", "float32": "float32", "real": "float32",
         "float": "float32", "single": "float32", "float64": "float64", "lreal": "float64",
         "double": "float64", "bool": "bool", "boolean": "bool", "bit": "bool"}
ORDERS = {"big": "big", "abcd": "big", "highfirst": "big", "no": "big", "false": "big",
          "bigendian": "big", "little": "little", "cdab": "little", "lowfirst": "little",
          "yes": "little", "true": "little", "swapped": "little", "littleendian": "little",
          "badc": "BADC", "byteswap": "BADC", "bytesswapped": "BADC", "dcba": "DCBA",
          "littleendianbytes": "DCBA", "byteandwordswap": "DCBA"}
MODICON = {"0": "coil", "1": "discrete", "3": "input", "4": "holding"}


def _key(text: str) -> str:
    return re.sub(r"[^0-9a-z]", "", text.lower())


def _columns(header: list[str], path: Path) -> dict[str, int]:
    found: dict[str, int] = {}
    for i, h in enumerate(header):
        k = _key(h)
        for col, names in COLUMNS.items():
            if k in names and col not in found:
                found[col] = i
    for need in ("name", "address"):
        if need not in found:
            raise ConfigError(f"{path}: header {header!r}: no {need} column (accepted names: "
                              f"{', '.join(COLUMNS[need])})")
    return found


def _number(text: str, where: str, what: str) -> float:
    try:
        return float(text.replace(",", ".")) if text.count(",") == 1 and "." not in text \
            else float(text)
    except ValueError:
        raise ConfigError(f"{where}: {what} {text!r}: expected a number") from None


def import_modbus_csv(path: str | Path, *, bus: str = "plc", host: str = "127.0.0.1",
                      port: int = 502, unit: int = 1, machine: int = 0, prefix: str = "",
                      one_based: bool = False) -> MapDraft:
    """The device-map draft of the register list at ``path`` (see the module doc). Raises
    ConfigError naming the file, row and column of the first bad cell."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the register list: {exc}") from exc
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if len(lines) < 2:
        raise ConfigError(f"{path}: expected a header row and at least one register row")
    try:
        dialect: Any = csv.Sniffer().sniff(lines[0], delimiters=",;\t")
    except csv.Error:
        dialect = csv.excel
    rows = list(csv.reader(lines, dialect))
    cols = _columns([c.strip() for c in rows[0]], path)
    unit_col = cols.get("unit")
    if unit_col is not None:  # 'unit': the unit id if whole numbers, else the units
        cells = [r[unit_col].strip() for r in rows[1:] if len(r) > unit_col and r[unit_col].strip()]
        if cells and all(c.isdigit() for c in cells):
            cols.setdefault("unit_id", unit_col)
        else:
            cols.setdefault("units", unit_col)
    draft = MapDraft()
    draft.header = [f"Modbus TCP server {host}:{port}, imported from {path.name} by chcos "
                    "import modbus.", "Check with chcos check; set safe_value on the actuators "
                    "and stale_after on the sensors."]
    draft.buses.append({"name": bus, "kind": "modbus-tcp", "host": host, "port": port})
    for no, row in enumerate(rows[1:], 2):
        where = f"{path}: row {no}"

        def cell(col: str, row: list[str] = row) -> str:
            i = cols.get(col)
            return row[i].strip() if i is not None and i < len(row) else ""

        name = cell("name")
        if not name:
            raise ConfigError(f"{where}: name column is empty")
        addr_text = cell("address")
        table_text = cell("table")
        if not addr_text:
            raise ConfigError(f"{where}: address column is empty")
        if table_text:
            table = TABLES.get(_key(table_text))
            if table is None:
                raise ConfigError(f"{where}: table {table_text!r}: expected coil, discrete, "
                                  "input or holding (or 0x/1x/3x/4x, DO/DI/IR/HR)")
            address = int(_number(addr_text, where, "address")) - (1 if one_based else 0)
        elif addr_text.isdigit() and len(addr_text) in (5, 6) and addr_text[0] in MODICON:
            table = MODICON[addr_text[0]]
            address = int(addr_text[1:]) - 1
        else:
            raise ConfigError(f"{where}: no table column and address {addr_text!r} is not a "
                              "Modicon number (00001, 10001, 30001, 40001...)")
        if address < 0:
            raise ConfigError(f"{where}: address {addr_text!r}: expected >= "
                              f"{1 if one_based else 0}")
        type_text = cell("type")
        if table in ("coil", "discrete"):
            typ = "bool"
        elif type_text:
            typ = TYPES.get(_key(type_text), "")
            if not typ or typ == "bool":
                raise ConfigError(f"{where}: type {type_text!r}: expected one of int16, uint16, "
                                  "int32, uint32, float32, float64 (or INT, WORD, DINT, REAL...)")
        else:
            typ = "uint16"
        address_table: dict[str, Any] = {}
        uid = cell("unit_id")
        address_table["unit"] = int(_number(uid, where, "unit id")) if uid else unit
        address_table.update(table=table, address=address, type=typ)
        order_text = cell("word_order")
        if order_text and typ in ("int32", "uint32", "float32", "float64"):
            order = ORDERS.get(_key(order_text))
            if order is None:
                raise ConfigError(f"{where}: word order {order_text!r}: expected big/ABCD, "
                                  "little/CDAB, BADC or DCBA")
            address_table["word_order"] = order
        access = cell("access").lower()
        writable = table in ("coil", "holding") and ("w" in access or "actuator" in access
                                                     or "output" in access)
        dev: dict[str, Any] = {"name": draft.name(name, prefix),
                               "direction": "actuator" if writable else "sensor",
                               "machine": machine, "bus": bus, "address": address_table}
        if cell("scale"):
            scale = _number(cell("scale"), where, "scale")
            if scale == 0:
                raise ConfigError(f"{where}: scale 0: expected a non-zero factor")
            if scale != 1:
                dev["scale"] = scale
        if cell("offset"):
            off = _number(cell("offset"), where, "offset")
            if off:
                dev["offset"] = off
        lim = limits(_number(cell("min"), where, "min") if cell("min") else None,
                     _number(cell("max"), where, "max") if cell("max") else None)
        if lim is not None:
            dev["limits"] = lim
        if cell("units"):
            dev["units"] = cell("units")
        notes = [f"row {no}: {name}" + (f" - {cell('comment')}" if cell("comment") else "")]
        if writable:
            notes.append("set safe_value: written on e-stop, task failure and shutdown")
        draft.add(notes, dev)
    return draft
