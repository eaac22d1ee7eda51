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

Addresses: decimal, ``0x9C40`` or ``9C40h``. How the list counts (:class:`Addressing`): by
default a table whose every address is a Modicon number (``40001``..) is read as Modicon, the
others as protocol addresses (0-based); ``zero``, ``one`` (register 1 is protocol address 0) and
``modicon`` force it. A ``size``/``words`` column gives a 32/64-bit type when the type is
missing. Every error names the file, the row and the column; what will not work on a real bus
as imported (no host given, 32-bit values without a word order, overlapping registers, writes
to a read-only table, no access column) is a warning.
"""

from __future__ import annotations

import csv
import enum
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from chcos.devices.importers.draft import MapDraft, limits
from chcos.errors import ConfigError

COLUMNS = {
    "name": ("name", "tag", "signal", "variable", "symbol", "tagname", "parameter",
             "parametername", "registername", "pointname", "point", "datapoint", "item",
             "label", "measurement", "quantity", "object", "objectname", "variablename"),
    "table": ("table", "area", "registertype", "objecttype", "function", "space"),
    "address": ("address", "register", "addr", "offsetaddress", "regaddress",
                "registeraddress", "startaddress", "startingaddress", "modbusaddress",
                "regaddr", "addressdec", "decimaladdress", "addressdecimal", "registerno",
                "registernumber", "regno", "modbusregister", "addresshex", "hexaddress"),
    "type": ("type", "datatype", "format", "dtype", "valuetype", "variabletype"),
    "words": ("words", "size", "length", "registers", "numberofregisters", "count", "regs",
              "len"),
    "word_order": ("wordorder", "wordswap", "byteorder", "swap", "endianness"),
    "scale": ("scale", "factor", "gain", "multiplier", "scaling", "scalefactor",
              "resolution"),
    "offset": ("offset",),
    "units": ("units", "engunit", "engineeringunit", "engunits", "uom", "unitofmeasure",
              "unitofmeasurement", "measuringunit", "dimension"),
    "unit_id": ("unitid", "slave", "slaveid", "deviceid", "station"),
    "unit": ("unit",),
    "access": ("access", "rw", "direction", "readwrite", "mode", "accesstype",
               "typeofaccess", "permission", "permissions", "attribute"),
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
         "double": "float64", "bool": "bool", "boolean": "bool", "bit": "bool",
         "u16": "uint16", "s16": "int16", "i16": "int16", "u32": "uint32", "s32": "int32",
         "i32": "int32", "f32": "float32", "f64": "float64", "int16t": "int16",
         "uint16t": "uint16", "int32t": "int32", "uint32t": "uint32", "signed": "int16",
         "unsigned": "uint16", "signed16": "int16", "unsigned16": "uint16",
         "signed32": "int32", "unsigned32": "uint32", "ieee754": "float32",
         "floatieee754": "float32", "ieeefloat": "float32", "float32bit": "float32"}
INT_RANGES = {"int16": (-2**15, 2**15 - 1), "uint16": (0, 2**16 - 1),
              "int32": (-2**31, 2**31 - 1), "uint32": (0, 2**32 - 1)}
"""Raw values each integer register type carries."""
WIDE = ("int32", "uint32", "float32", "float64")
"""Register types of more than one register: their word order matters."""
MODICON_RANGES = {"coil": (1, 0), "discrete": (10001, 100001), "input": (30001, 300001),
                  "holding": (40001, 400001)}
"""First Modicon number of each table, 5-digit and 6-digit forms."""
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


class Addressing(enum.Enum):
    """How the list counts register addresses."""

    AUTO = "auto"        # Modicon if every address of a table is in its Modicon range, else zero
    ZERO = "zero"        # protocol addresses (register 40001 is holding 0)
    ONE = "one"          # counted from 1 (register 1 is protocol address 0)
    MODICON = "modicon"  # 40001-style: the table's first digit, then a count from 1


def _address(text: str, where: str) -> int:
    """A register address cell: decimal, ``0x9C40`` or ``9C40h``. Raises ConfigError."""
    t = text.strip().replace("_", "")
    try:
        if t.lower().startswith("0x"):
            return int(t, 16)
        if t[-1:] in ("h", "H") and re.fullmatch(r"[0-9A-Fa-f]+", t[:-1]):
            return int(t[:-1], 16)
        value = float(t)
    except ValueError:
        raise ConfigError(f"{where}: address {text!r}: expected a whole number (decimal, 0x... "
                          "or ...h)") from None
    if value != int(value):
        raise ConfigError(f"{where}: address {text!r}: expected a whole number")
    return int(value)


def _modicon(table: str, number: int) -> int | None:
    """The protocol address of Modicon ``number`` in ``table``, None if it is not one."""
    five, six = MODICON_RANGES[table]
    if table == "coil":
        return number - 1 if 1 <= number <= 9999 else None
    if five <= number <= five + 9998:
        return number - five
    if six <= number <= six + 65535:
        return number - six
    return None


@dataclass
class _Row:
    no: int
    cells: dict[str, str]
    table: str
    number: int
    modicon_given: bool     # the address was a Modicon number that named the table itself


def import_modbus_csv(path: str | Path, *, bus: str = "plc", host: str | None = None,
                      port: int = 502, unit: int = 1, machine: int = 0, prefix: str = "",
                      one_based: bool = False, addressing: Addressing | str = Addressing.AUTO,
                      rtu: str | None = None, baudrate: int = 19200,
                      parity: str = "N") -> MapDraft:
    """The device-map draft of the register list at ``path`` (see the module doc): a
    ``modbus-tcp`` bus to ``host:port``, or with ``rtu`` (a serial port) a ``modbus-rtu`` bus.
    ``addressing`` says how the list counts (``one_based`` is ``Addressing.ONE``). What will not
    work on a real bus as imported is in the draft's ``warnings``. Raises ConfigError naming the
    file, row and column of the first bad cell."""
    path = Path(path)
    how = Addressing.ONE if one_based else Addressing(addressing)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the register list: {exc}") from exc
    except UnicodeDecodeError:
        text = path.read_text(encoding="latin-1")   # vendor lists in a legacy code page
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
        unit_cells = [r[unit_col].strip() for r in rows[1:]
                      if len(r) > unit_col and r[unit_col].strip()]
        if unit_cells and all(c.isdigit() for c in unit_cells):
            cols.setdefault("unit_id", unit_col)
        else:
            cols.setdefault("units", unit_col)
    draft = MapDraft()
    warnings = draft.warnings
    if rtu is not None:
        if parity not in ("N", "E", "O"):
            raise ConfigError(f"--parity {parity!r}: expected N, E or O")
        draft.header = [f"Modbus RTU bus on {rtu} ({baudrate} bit/s, parity {parity}), imported "
                        f"from {path.name} by chcos import modbus."]
        draft.buses.append({"name": bus, "kind": "modbus-rtu", "port": rtu,
                            "baudrate": baudrate, "parity": parity})
    else:
        if host is None:
            host = "127.0.0.1"
            warnings.append(f"{path}: no --host: the map names 127.0.0.1 (a simulator on this "
                            "machine); give the device's address for a real bus")
        draft.header = [f"Modbus TCP server {host}:{port}, imported from {path.name} by chcos "
                        "import modbus."]
        draft.buses.append({"name": bus, "kind": "modbus-tcp", "host": host, "port": port})
    draft.header.append("Check with chcos check; set safe_value on the actuators and "
                        "stale_after on the sensors.")
    parsed: list[_Row] = []
    for no, row in enumerate(rows[1:], 2):
        where = f"{path}: row {no}"
        cells = {col: (row[i].strip() if i < len(row) else "") for col, i in cols.items()}
        if not cells.get("name"):
            raise ConfigError(f"{where}: name column is empty")
        addr_text, table_text = cells.get("address", ""), cells.get("table", "")
        if not addr_text:
            raise ConfigError(f"{where}: address column is empty")
        number = _address(addr_text, where)
        if table_text:
            table = TABLES.get(_key(table_text))
            if table is None:
                raise ConfigError(f"{where}: table {table_text!r}: expected coil, discrete, "
                                  "input or holding (or 0x/1x/3x/4x, DO/DI/IR/HR)")
            parsed.append(_Row(no, cells, table, number, False))
        elif addr_text.isdigit() and len(addr_text) in (5, 6) and addr_text[0] in MODICON:
            parsed.append(_Row(no, cells, MODICON[addr_text[0]], number, True))
        else:
            raise ConfigError(f"{where}: no table column and address {addr_text!r} is not a "
                              "Modicon number (00001, 10001, 30001, 40001...)")
    modicon_tables: set[str] = set()
    if how is Addressing.AUTO:
        for table in MODICON_RANGES:
            numbers = [r for r in parsed if r.table == table and not r.modicon_given]
            if numbers and all(_modicon(table, r.number) is not None for r in numbers) \
                    and table != "coil":
                modicon_tables.add(table)
                warnings.append(f"{path}: {table} addresses "
                                f"{min(r.number for r in numbers)}..."
                                f"{max(r.number for r in numbers)} read as Modicon numbers "
                                f"(40001 is holding 0); give --addressing zero if they are "
                                "protocol addresses")
        tables = {r.table for r in parsed if not r.modicon_given} - modicon_tables
        lows = [r.number for r in parsed if r.table in tables and not r.modicon_given]
        if lows and min(lows) == 1:
            warnings.append(f"{path}: the lowest address is 1: taken as a protocol address "
                            "(0-based); give --addressing one if the list counts from 1")
    used: dict[tuple[int, str, int], int] = {}
    wide_unordered = 0
    has_access = "access" in cols
    for r in parsed:
        where = f"{path}: row {r.no}"
        cells, table = r.cells, r.table

        def cell(col: str, cells: dict[str, str] = cells) -> str:
            return cells.get(col, "")

        name = cell("name")
        addr_text = cell("address")
        address: int | None
        if r.modicon_given or how is Addressing.MODICON or table in modicon_tables:
            address = _modicon(table, r.number)
            if address is None:
                raise ConfigError(f"{where}: address {addr_text!r} is not a Modicon number of "
                                  f"the {table} table")
        else:
            address = r.number - (1 if how is Addressing.ONE else 0)
        if address < 0:
            raise ConfigError(f"{where}: address {addr_text!r}: expected >= "
                              f"{1 if how is Addressing.ONE else 0}")
        type_text = cell("type")
        words_text = cell("words")
        words = int(_number(words_text, where, "size")) if words_text else None
        if table in ("coil", "discrete"):
            typ = "bool"
        elif type_text:
            typ = TYPES.get(_key(type_text), "")
            if not typ or typ == "bool":
                raise ConfigError(f"{where}: type {type_text!r}: expected one of int16, uint16, "
                                  "int32, uint32, float32, float64 (or INT, WORD, DINT, REAL...)")
        elif words == 2:
            typ = "uint32"
            warnings.append(f"{where}: {name}: no type, 2 registers: imported as uint32 (check "
                            "the manual: it may be int32 or float32)")
        elif words == 4:
            typ = "float64"
            warnings.append(f"{where}: {name}: no type, 4 registers: imported as float64")
        else:
            typ = "uint16"
        width = 1 if typ in ("bool", "int16", "uint16") else 4 if typ == "float64" else 2
        if words is not None and table not in ("coil", "discrete") and words != width:
            warnings.append(f"{where}: {name}: size {words} register(s) but type {typ} takes "
                            f"{width}: imported as {typ}")
        if address + width - 1 > 65535:
            raise ConfigError(f"{where}: address {addr_text!r}: {table} {address} ({width} "
                              "register(s)) is beyond 65535, the protocol's last address")
        address_table: dict[str, Any] = {}
        uid = cell("unit_id")
        unit_id = int(_number(uid, where, "unit id")) if uid else unit
        if not 0 <= unit_id <= 255:
            raise ConfigError(f"{where}: unit id {unit_id}: expected 0..255")
        if rtu is not None and not 1 <= unit_id <= 247:
            raise ConfigError(f"{where}: unit id {unit_id}: an RTU slave answers only at "
                              "1..247 (0 is broadcast)")
        address_table["unit"] = unit_id
        address_table.update(table=table, address=address, type=typ)
        order_text = cell("word_order")
        if typ in WIDE:
            if order_text:
                order = ORDERS.get(_key(order_text))
                if order is None:
                    raise ConfigError(f"{where}: word order {order_text!r}: expected big/ABCD, "
                                      "little/CDAB, BADC or DCBA")
                address_table["word_order"] = order
            else:
                wide_unordered += 1
        for reg in range(address, address + width):
            other = used.get((unit_id, table, reg))
            if other is not None:
                warnings.append(f"{where}: {name}: {table} {reg} of unit {unit_id} is also read "
                                f"by row {other}: overlapping registers")
                break
        for reg in range(address, address + width):
            used.setdefault((unit_id, table, reg), r.no)
        access = cell("access").lower()
        wants_write = "w" in access or "actuator" in access or "output" in access
        writable = table in ("coil", "holding") and wants_write
        if wants_write and not writable:
            warnings.append(f"{where}: {name}: access {cell('access')!r} on a read-only {table} "
                            "table: imported as a sensor")
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
        if lim is None and writable and typ in INT_RANGES:
            # what the register can carry, in engineering units: writes beyond fail on the bus
            lo, hi = (v * dev.get("scale", 1.0) + dev.get("offset", 0.0)
                      for v in INT_RANGES[typ])
            lim = [float(f"{min(lo, hi):.12g}"), float(f"{max(lo, hi):.12g}")]
        if lim is not None:
            dev["limits"] = lim
        if cell("units"):
            dev["units"] = cell("units")
        notes = [f"row {r.no}: {name}" + (f" - {cell('comment')}" if cell("comment") else "")
                 + f" ({table} {addr_text})"]
        if writable:
            notes.append("set safe_value: written on e-stop, task failure and shutdown")
        draft.add(notes, dev)
    if wide_unordered:
        warnings.append(f"{path}: {wide_unordered} register(s) of 32/64 bits without a word "
                        "order: imported as big (high word first, ABCD); vendors differ: if the "
                        "values read wrong, set word_order = \"little\"")
    if not has_access:
        warnings.append(f"{path}: no access column: every register is imported as a sensor "
                        "(mark writable rows RW for actuators)")
    return draft
