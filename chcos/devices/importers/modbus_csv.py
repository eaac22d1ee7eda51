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

Addresses: decimal, ``0x9C40`` or ``9C40h`` (a whole number; anything else, ``1e400``, ``nan``,
is refused naming the row). How the list counts (:class:`Addressing`, ``--addressing``):

* ``auto`` (the default): without a table column a Modicon number (``30001``, ``40001``,
  ``300001``) names the table and the register (``40001`` is holding 0); a table whose every
  address is a 6-digit Modicon number is read as Modicon; a 5-digit Modicon number in a table
  column's table is **ambiguous** (``holding, 40072``: Modicon 40072 is holding 71, a SunSpec
  list means holding 40072) and refused naming the row: say ``--addressing``;
* ``zero`` (protocol addresses), ``one`` (register 1 is protocol address 0): honoured as given;
  without a table column the table comes from ``table`` (``--table``), and a list with neither is
  refused naming the row (``40072`` counted from zero or one names no table);
* ``modicon``: every address is a Modicon number of its table.

Types: the usual PLC names, and the SunSpec point types (``enum16``, ``bitfield16/32``,
``acc16/32/64``, ``count``, ``sunssf``, ``string``; :data:`.modbus_types.SUNSPEC`) with their
"not implemented" value written as ``unimplemented``; a ``string`` takes its registers from the
size column (or ``string(N)``, N characters). An ``sf`` column names the row of a point's
scale-factor register (``sunssf``; by name or address) or gives a fixed exponent (``-2``):
``scale_factor = ADDRESS`` or ``scale = 10^N``. A type the driver does not read (``uint64``
where it has none) is left out with a warning. A ``size``/``words`` column gives a 32/64-bit
type when the type is missing.

Ranges: ``min``/``max`` are clamped to what the register type carries with the row's scale and
offset (a warning says so); an integer actuator without them gets that capacity as limits.
Every error names the file, the row and the column; what will not work on a real bus as
imported (no host given, 32-bit values without a word order, overlapping registers, writes to
a read-only table, no access column) is a warning. A cell longer than :data:`MAX_CELL`
characters is refused naming its row.
"""

from __future__ import annotations

import csv
import enum
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from chcos.devices.importers.draft import Hex, MapDraft, clamp_limits, limits, tidy
from chcos.devices.importers.modbus_types import SUNSPEC, WIDTH, capacity, supported
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
    "sf": ("sf", "sfname", "sfpoint", "sfregister", "scalefactorregister", "sfref"),
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
         "floatieee754": "float32", "ieeefloat": "float32", "float32bit": "float32",
         "string": "string", "str": "string", "ascii": "string", "char": "string",
         "uint64": "uint64", "u64": "uint64", "int64": "int64", "s64": "int64",
         "lint": "int64", "ulint": "uint64"}
#: SunSpec point types a register list may name (SunSpec models typed as published)
SUNSPEC_NAMES = {t: t for t in SUNSPEC if SUNSPEC[t].register_type
                 and t not in ("int16", "uint16", "int32", "uint32", "int64", "uint64",
                               "float32", "float64", "string")}
INT_TYPES = ("int16", "uint16", "int32", "uint32", "int64", "uint64")
"""Integer register types (an actuator gets its capacity as limits)."""
WIDE = ("int32", "uint32", "float32", "float64", "int64", "uint64")
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


#: characters of one cell of the list (a longer one is refused naming its row)
MAX_CELL = 4096
#: characters of a description kept in the map's comment, of a units text kept
MAX_COMMENT, MAX_UNITS = 300, 40
#: registers of one string point (a Modbus read carries at most 125)
MAX_STRING = 125


def _key(text: str) -> str:
    return re.sub(r"[^0-9a-z]", "", text[:200].lower())


def _columns(header: list[str], path: Path) -> dict[str, int]:
    found: dict[str, int] = {}
    for i, h in enumerate(header):
        k = _key(h)
        for col, names in COLUMNS.items():
            if k in names and col not in found:
                found[col] = i
    for need in ("name", "address"):
        if need not in found:
            shown = [h[:40] for h in header[:20]]
            raise ConfigError(f"{path}: row 1 (header) {shown!r}: no {need} column (accepted "
                              f"names: {', '.join(COLUMNS[need])})")
    return found


def _number(text: str, where: str, what: str) -> float:
    """A finite number cell (a decimal comma accepted); raises ConfigError naming ``where``."""
    t = text.strip()
    try:
        value = float(t.replace(",", ".")) if t.count(",") == 1 and "." not in t \
            else float(t)
    except ValueError:
        raise ConfigError(f"{where}: {what} {text[:40]!r}: expected a number") from None
    if not math.isfinite(value):
        raise ConfigError(f"{where}: {what} {text[:40]!r}: expected a finite number")
    return value


class Addressing(enum.Enum):
    """How the list counts register addresses (see the module doc)."""

    AUTO = "auto"        # Modicon where it cannot be anything else; ambiguity refused
    ZERO = "zero"        # protocol addresses (register 40001 is holding 40001)
    ONE = "one"          # counted from 1 (register 1 is protocol address 0)
    MODICON = "modicon"  # 40001-style: the table's first digit, then a count from 1


_HEX = re.compile(r"0[xX]([0-9A-Fa-f]{1,8})|([0-9A-Fa-f]{1,8})[hH]")
_DEC = re.compile(r"([0-9]{1,9})(?:\.0*)?")


def _address(text: str, where: str) -> int:
    """A register address cell: decimal (``40001``, ``40001.0``), ``0x9C40`` or ``9C40h``.
    Raises ConfigError naming ``where`` for anything else (``1e400``, ``nan``, ``-3``)."""
    t = text.strip().replace("_", "")
    if m := _HEX.fullmatch(t):
        return int(m.group(1) or m.group(2), 16)
    if m := _DEC.fullmatch(t):
        return int(m.group(1))
    raise ConfigError(f"{where}: address {text[:40]!r}: expected a whole number (decimal, "
                      "0x... or ...h)")


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


def _six_digit(table: str, number: int) -> bool:
    six = MODICON_RANGES[table][1]
    return table != "coil" and six <= number <= six + 65535


@dataclass
class _Row:
    no: int
    cells: dict[str, str]
    table: str
    number: int
    modicon_given: bool     # no table column: the Modicon number named the table itself
    address: int = -1       # the protocol address, once resolved

    @property
    def where(self) -> str:
        return f"row {self.no}"


def _read_rows(path: Path) -> tuple[list[list[str]], dict[str, int]]:
    """The CSV rows of the list at ``path`` (header first) and its columns; raises ConfigError
    naming the file and row."""
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the register list: {exc.strerror or exc}") \
            from exc
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")   # vendor lists in a legacy code page
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if len(lines) < 2:
        raise ConfigError(f"{path}: expected a header row and at least one register row")
    try:
        dialect: Any = csv.Sniffer().sniff(lines[0][:MAX_CELL], delimiters=",;\t")
    except csv.Error:
        dialect = csv.excel
    rows: list[list[str]] = []
    reader = csv.reader(lines, dialect)
    try:
        for row in reader:
            for cell in row:
                if len(cell) > MAX_CELL:
                    raise ConfigError(f"{path}: row {reader.line_num}: a cell of {len(cell)} "
                                      f"characters (at most {MAX_CELL})")
            rows.append(row)
    except csv.Error as exc:
        limit = csv.field_size_limit()
        why = f"a cell longer than {limit} characters" if "field limit" in str(exc) else exc
        raise ConfigError(f"{path}: row {reader.line_num}: {why}") from None
    return rows, _columns([c.strip() for c in rows[0]], path)


def _rows(path: Path, rows: list[list[str]], cols: dict[str, int], how: Addressing,
          default_table: str | None) -> list[_Row]:
    """Each register row with its table (from its cells, a Modicon number or ``default_table``);
    raises ConfigError naming the row."""
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
        modicon_like = addr_text.isdigit() and len(addr_text) in (5, 6) \
            and addr_text[0] in MODICON
        if table_text:
            table = TABLES.get(_key(table_text))
            if table is None:
                raise ConfigError(f"{where}: table {table_text[:40]!r}: expected coil, discrete, "
                                  "input or holding (or 0x/1x/3x/4x, DO/DI/IR/HR)")
            parsed.append(_Row(no, cells, table, number, False))
        elif modicon_like and how in (Addressing.AUTO, Addressing.MODICON) \
                and default_table is None:
            parsed.append(_Row(no, cells, MODICON[addr_text[0]], number, True))
        elif default_table is not None:
            parsed.append(_Row(no, cells, default_table, number, False))
        elif modicon_like:
            raise ConfigError(
                f"{where}: address {addr_text!r} with --addressing {how.value} and no table "
                f"column: which table? (as a Modicon number it is "
                f"{MODICON[addr_text[0]]} {_modicon(MODICON[addr_text[0]], number)}); give "
                f"--table TABLE (a SunSpec list: --table holding) or --addressing modicon")
        else:
            raise ConfigError(f"{where}: no table column and address {addr_text[:40]!r} is not "
                              "a Modicon number (00001, 10001, 30001, 40001...): add a table "
                              "column or give --table TABLE")
    return parsed


def _resolve(path: Path, parsed: list[_Row], how: Addressing, warnings: list[str]) -> None:
    """Set each row's protocol address as ``how`` says (see the module doc); raises
    ConfigError naming the row for an ambiguous or impossible address."""
    modicon_tables: set[str] = set()
    if how is Addressing.AUTO:
        for table in MODICON_RANGES:
            given = [r for r in parsed if r.table == table and not r.modicon_given]
            if not given or table == "coil":
                continue
            if all(_six_digit(table, r.number) for r in given):
                modicon_tables.add(table)
                warnings.append(f"{path}: {table} addresses {min(r.number for r in given)}..."
                                f"{max(r.number for r in given)} read as Modicon numbers "
                                f"(400001 is holding 0); give --addressing zero if they are "
                                "protocol addresses")
            elif all(_modicon(table, r.number) is not None for r in given):
                first = next(r for r in given if not _six_digit(table, r.number))
                raise ConfigError(
                    f"{path}: {first.where}: {table} address {first.cells.get('address')!r} is "
                    f"ambiguous: Modicon {first.number} is {table} "
                    f"{_modicon(table, first.number)}, a protocol address {first.number} "
                    f"(as SunSpec lists count, base 40000) is {table} {first.number}: give "
                    f"--addressing modicon, zero or one")
        lows = [r.number for r in parsed if r.table not in modicon_tables
                and not r.modicon_given]
        if lows and min(lows) == 1:
            warnings.append(f"{path}: the lowest address is 1: taken as a protocol address "
                            "(0-based); give --addressing one if the list counts from 1")
    for r in parsed:
        addr_text = r.cells.get("address", "")
        if r.modicon_given or how is Addressing.MODICON or r.table in modicon_tables:
            address = _modicon(r.table, r.number)
            if address is None:
                raise ConfigError(f"{path}: {r.where}: address {addr_text!r} is not a Modicon "
                                  f"number of the {r.table} table")
        else:
            address = r.number - (1 if how is Addressing.ONE else 0)
        if address < 0:
            raise ConfigError(f"{path}: {r.where}: address {addr_text!r}: expected >= "
                              f"{1 if how is Addressing.ONE else 0}")
        r.address = address


@dataclass
class _Type:
    """A row's register type: the driver's type, registers, "not implemented" raw value."""

    name: str
    width: int
    unimplemented: int | None = None


def _type(r: _Row, where: str, warnings: list[str]) -> _Type | None:
    """The register type of row ``r`` (None: a type the driver does not read, warned about);
    raises ConfigError naming the row."""
    name = r.cells.get("name", "")
    type_text, words_text = r.cells.get("type", ""), r.cells.get("words", "")
    words = _number(words_text, where, "size") if words_text else None
    if words is not None and (words != int(words) or not 1 <= words <= MAX_STRING):
        raise ConfigError(f"{where}: size {words_text!r}: expected 1..{MAX_STRING} registers")
    nwords = None if words is None else int(words)
    if r.table in ("coil", "discrete"):
        return _Type("bool", 1)
    key = _key(type_text)
    text_type = re.fullmatch(r"(?:string|str|char|ascii)(\d{1,4})?", key) if key else None
    if text_type:
        chars = int(text_type.group(1)) if text_type.group(1) else None
        count = nwords if nwords is not None else (None if chars is None else (chars + 1) // 2)
        if count is None or not 1 <= count <= MAX_STRING:
            raise ConfigError(f"{where}: type {type_text[:40]!r}: a string needs its size in "
                              f"registers (1..{MAX_STRING}: a size column, or string(N) for N "
                              "characters)")
        return _Type("string", count)
    if key in SUNSPEC_NAMES:
        point = SUNSPEC[key]
        typ, unimpl = point.register_type, point.unimplemented
    elif key:
        typ, unimpl = TYPES.get(key, ""), None
        if not typ or typ == "bool":
            raise ConfigError(f"{where}: type {type_text[:40]!r}: expected one of int16, "
                              "uint16, int32, uint32, float32, float64, string (or INT, WORD, "
                              "DINT, REAL...; or a SunSpec type: enum16, bitfield32, acc32, "
                              "sunssf...)")
    elif nwords == 2:
        typ, unimpl = "uint32", None
        warnings.append(f"{where}: {name}: no type, 2 registers: imported as uint32 (check "
                        "the manual: it may be int32 or float32)")
    elif nwords == 4:
        typ, unimpl = "float64", None
        warnings.append(f"{where}: {name}: no type, 4 registers: imported as float64")
    else:
        typ, unimpl = "uint16", None
    if not supported(typ):
        warnings.append(f"{where}: {name}: type {typ}: the modbus driver does not read it; "
                        "left out of the map")
        return None
    width = WIDTH[typ]
    if nwords is not None and nwords != width:
        warnings.append(f"{where}: {name}: size {nwords} register(s) but type {typ} takes "
                        f"{width}: imported as {typ}")
    return _Type(typ, width, unimpl)


def _bus(draft: MapDraft, path: Path, bus: str, host: str | None, port: int, rtu: str | None,
         baudrate: int, parity: str, command: str = "chcos import modbus") -> None:
    """The map's Modbus bus: TCP to ``host:port`` or RTU on ``rtu``; the header names
    ``command``."""
    if rtu is not None:
        if parity not in ("N", "E", "O"):
            raise ConfigError(f"--parity {parity!r}: expected N, E or O")
        draft.header = [f"Modbus RTU bus on {rtu} ({baudrate} bit/s, parity {parity}), imported "
                        f"from {path.name} by {command}."]
        draft.buses.append({"name": bus, "kind": "modbus-rtu", "port": rtu,
                            "baudrate": baudrate, "parity": parity})
    else:
        if host is None:
            host = "127.0.0.1"
            draft.warnings.append(f"{path}: no --host: the map names 127.0.0.1 (a simulator on "
                                  "this machine); give the device's address for a real bus")
        draft.header = [f"Modbus TCP server {host}:{port}, imported from {path.name} by "
                        f"{command}."]
        draft.buses.append({"name": bus, "kind": "modbus-tcp", "host": host, "port": port})
    draft.header.append("Check with chcos check; set safe_value on the actuators and "
                        "stale_after on the sensors.")


def device_limits(dev: dict[str, Any], typ: str, lo: float | None, hi: float | None,
                  what: str, warnings: list[str]) -> None:
    """Set ``dev``'s limits: the vendor's ``lo``..``hi`` clamped to what register type ``typ``
    carries with the device's scale and offset; an integer actuator without them gets that
    capacity. A device scaled by a SunSpec scale factor (unknown until read) keeps the vendor's
    limits as given."""
    writable = dev["direction"] == "actuator"
    if typ in ("bool", "string"):
        return
    if "scale_factor" in dev["address"]:
        lim = limits(lo, hi)
    elif lo is None and hi is None and not (writable and typ in INT_TYPES):
        return
    else:
        cap = capacity(typ, dev.get("scale", 1.0), dev.get("offset", 0.0))
        lim = clamp_limits(lo, hi, cap, what, warnings)
        if lim is not None and not all(map(math.isfinite, lim)):
            lim = [tidy(v) if math.isfinite(v) else v for v in lim]
    if lim is not None:
        dev["limits"] = lim


def _scale_of(r: _Row, where: str, dev: dict[str, Any]) -> None:
    """The row's ``scale`` and ``offset`` cells into ``dev``."""
    cells = r.cells
    if cells.get("scale"):
        scale = _number(cells["scale"], where, "scale")
        if scale == 0:
            raise ConfigError(f"{where}: scale 0: expected a non-zero factor")
        if scale != 1:
            dev["scale"] = scale
    if cells.get("offset"):
        off = _number(cells["offset"], where, "offset")
        if off:
            dev["offset"] = off


def _sf(r: _Row, where: str, by_name: dict[str, _Row], dev: dict[str, Any],
        types: dict[int, _Type]) -> None:
    """The row's ``sf`` cell: a fixed exponent (``scale`` x 10^N) or the row of its SunSpec
    scale-factor register (``scale_factor = ADDRESS``); raises ConfigError naming the row."""
    text = r.cells.get("sf", "")
    if not text:
        return
    if re.fullmatch(r"[+-]?\d{1,2}", text):
        exp = int(text)
        if not -10 <= exp <= 10:
            raise ConfigError(f"{where}: sf {text!r}: expected an exponent -10..10 or the name "
                              "of a scale-factor row")
        if exp:
            dev["scale"] = tidy(dev.get("scale", 1.0) * 10.0 ** exp)
        return
    ref = by_name.get(text) or by_name.get(text.lower())
    if ref is None:
        raise ConfigError(f"{where}: sf {text[:40]!r}: no row of that name (the name of its "
                          "scale-factor row, e.g. W_SF, or an exponent such as -2)")
    if ref.table != r.table or ref.cells.get("unit_id", "") != r.cells.get("unit_id", "") \
            or types.get(ref.no, _Type("", 0)).name != "int16":
        raise ConfigError(f"{where}: sf {text!r}: row {ref.no} is not an int16 (sunssf) "
                          f"register of the same table and unit")
    dev["address"]["scale_factor"] = ref.address


def import_modbus_csv(path: str | Path, *, bus: str = "plc", host: str | None = None,
                      port: int = 502, unit: int = 1, machine: int = 0, prefix: str = "",
                      one_based: bool = False, addressing: Addressing | str = Addressing.AUTO,
                      rtu: str | None = None, baudrate: int = 19200,
                      parity: str = "N", table: str | None = None) -> MapDraft:
    """The device-map draft of the register list at ``path`` (see the module doc): a
    ``modbus-tcp`` bus to ``host:port``, or with ``rtu`` (a serial port) a ``modbus-rtu`` bus.
    ``addressing`` says how the list counts (``one_based`` is ``Addressing.ONE``); ``table``
    is the table of rows without one. What will not work on a real bus as imported is in the
    draft's ``warnings``. Raises ConfigError naming the file, row and column of the first bad
    cell, or an ambiguous address."""
    path = Path(path)
    how = Addressing.ONE if one_based else Addressing(addressing)
    if table is not None and table not in MODICON_RANGES:
        raise ConfigError(f"--table {table!r}: expected coil, discrete, input or holding")
    rows, cols = _read_rows(path)
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
    _bus(draft, path, bus, host, port, rtu, baudrate, parity)
    parsed = _rows(path, rows, cols, how, table)
    _resolve(path, parsed, how, warnings)
    types = {r.no: t for r in parsed if (t := _type(r, f"{path}: row {r.no}", warnings))}
    by_name: dict[str, _Row] = {}
    for r in parsed:
        by_name.setdefault(r.cells["name"], r)
        by_name.setdefault(r.cells["name"].lower(), r)
    used: dict[tuple[int, str, int], int] = {}
    wide_unordered = 0
    for r in parsed:
        typ = types.get(r.no)
        if typ is None:
            continue
        wide_unordered += _row_device(draft, path, r, typ, used, by_name, types, unit=unit,
                                      rtu=rtu, bus=bus, machine=machine, prefix=prefix)
    if wide_unordered:
        warnings.append(f"{path}: {wide_unordered} register(s) of 32/64 bits without a word "
                        "order: imported as big (high word first, ABCD); vendors differ: if the "
                        "values read wrong, set word_order = \"little\"")
    if "access" not in cols:
        warnings.append(f"{path}: no access column: every register is imported as a sensor "
                        "(mark writable rows RW for actuators)")
    if not draft.devices:
        raise ConfigError(f"{path}: no register the modbus driver can read")
    return draft


def _address_of(r: _Row, typ: _Type, where: str, *, unit: int,
                rtu: str | None) -> tuple[dict[str, Any], int]:
    """Row ``r``'s address table, and 1 when it is a wide value without a word order (else 0).
    Raises ConfigError naming the row."""
    cells = r.cells
    if r.address + typ.width - 1 > 65535:
        raise ConfigError(f"{where}: address {cells.get('address')!r}: {r.table} {r.address} "
                          f"({typ.width} register(s)) is beyond 65535, the protocol's last "
                          "address")
    uid = cells.get("unit_id", "")
    unit_id = int(_number(uid, where, "unit id")) if uid else unit
    if not 0 <= unit_id <= 255:
        raise ConfigError(f"{where}: unit id {unit_id}: expected 0..255")
    if rtu is not None and not 1 <= unit_id <= 247:
        raise ConfigError(f"{where}: unit id {unit_id}: an RTU slave answers only at "
                          "1..247 (0 is broadcast)")
    address: dict[str, Any] = {"unit": unit_id, "table": r.table, "address": r.address,
                               "type": typ.name}
    if typ.name == "string":
        address["count"] = typ.width
    unordered = 0
    order_text = cells.get("word_order", "")
    if typ.name in WIDE:
        if order_text:
            order = ORDERS.get(_key(order_text))
            if order is None:
                raise ConfigError(f"{where}: word order {order_text[:40]!r}: expected big/ABCD, "
                                  "little/CDAB, BADC or DCBA")
            address["word_order"] = order
        else:
            unordered = 1
    if typ.unimplemented is not None:
        address["unimplemented"] = Hex(typ.unimplemented)
    return address, unordered


def _overlaps(r: _Row, address: dict[str, Any], width: int,
              used: dict[tuple[int, str, int], int], where: str, warnings: list[str]) -> None:
    """Warn when row ``r``'s registers are also another row's; record them."""
    unit_id, table, first = address["unit"], address["table"], address["address"]
    for reg in range(first, first + width):
        other = used.get((unit_id, table, reg))
        if other is not None:
            warnings.append(f"{where}: {r.cells['name'][:60]}: {table} {reg} of unit {unit_id} "
                            f"is also read by row {other}: overlapping registers")
            break
    for reg in range(first, first + width):
        used.setdefault((unit_id, table, reg), r.no)


def _row_device(draft: MapDraft, path: Path, r: _Row, typ: _Type,
                used: dict[tuple[int, str, int], int], by_name: dict[str, _Row],
                types: dict[int, _Type], *, unit: int, rtu: str | None, bus: str,
                machine: int, prefix: str) -> int:
    """Add row ``r``'s device to ``draft``; returns 1 when it is a wide value without a word
    order (counted for one warning), else 0. Raises ConfigError naming the row."""
    where = f"{path}: row {r.no}"
    warnings = draft.warnings

    def cell(col: str) -> str:
        return r.cells.get(col, "")

    name, table = cell("name"), r.table
    address, unordered = _address_of(r, typ, where, unit=unit, rtu=rtu)
    _overlaps(r, address, typ.width, used, where, warnings)
    access = cell("access").lower()
    wants_write = "w" in access or "actuator" in access or "output" in access
    writable = table in ("coil", "holding") and wants_write and typ.name != "string"
    if wants_write and not writable:
        what = f"read-only {table} table" if typ.name != "string" else "string register"
        warnings.append(f"{where}: {name[:60]}: access {cell('access')[:20]!r} on a {what}: "
                        "imported as a sensor")
    dev: dict[str, Any] = {"name": draft.name(name, prefix),
                           "direction": "actuator" if writable else "sensor",
                           "machine": machine, "bus": bus, "address": address}
    if typ.name != "string":
        _scale_of(r, where, dev)
        _sf(r, where, by_name, dev, types)
    lo = _number(cell("min"), where, "min") if cell("min") else None
    hi = _number(cell("max"), where, "max") if cell("max") else None
    device_limits(dev, typ.name, lo, hi, f"{where}: {name[:60]}", warnings)
    units = cell("units")
    if len(units) > MAX_UNITS:
        warnings.append(f"{where}: units {units[:20]!r}...: longer than {MAX_UNITS} "
                        "characters, left out")
    elif units:
        dev["units"] = units
    comment = cell("comment")[:MAX_COMMENT]
    notes = [f"row {r.no}: {name[:80]}" + (f" - {comment}" if comment else "")
             + f" ({table} {cell('address')})"]
    if typ.unimplemented is not None:
        notes.append(f"SunSpec: 0x{typ.unimplemented:X} means not implemented (no value)")
    if writable:
        notes.append("set safe_value: written on e-stop, task failure and shutdown")
    draft.add(notes, dev)
    return unordered
