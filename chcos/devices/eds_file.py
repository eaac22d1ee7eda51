"""eds_file - read a CANopen EDS as vendors write them: canopen's parser behind a tolerant pass.

canopen's ``import_od`` rejects a whole file for one empty numeric field (``VendorNumber=``,
``Lines=``, ``Dummy0001=``, ``PDOMapping=``), and for a file that is not UTF-8. :func:`read_eds`
reads the file first (UTF-8, else Latin-1 with a warning), drops or zeroes each empty numeric field
with a warning naming the file, section and key, and hands the cleaned text to canopen (an
empty ``ObjectType`` is a record when the object has sub-index sections, else a variable).
Fields CiA 306 lets be empty (``LowLimit``, ``HighLimit``, ``DefaultValue``,
``ParameterValue``) are read as absent without a warning. A field nothing can stand in for
(an empty ``DataType`` or ``NrOfEntries``) is an error naming the file, section and key.
Used by ``chcos check`` (through the canopen driver's object-dictionary loader),
``chcos import eds`` and the simulated node.
"""

from __future__ import annotations

import configparser
import io
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: DeviceInfo keys that hold text; every other DeviceInfo key is a number.
DEVICE_INFO_TEXT = frozenset({"VendorName", "ProductName", "OrderCode"})
#: Object keys canopen reads as numbers and can do without (dropped when empty).
OBJECT_OPTIONAL = frozenset({"ObjectType", "PDOMapping", "SubNumber", "CompactSubObj",
                             "ObjFlags"})
#: Object keys CiA 306 allows to be empty (read as absent, no warning).
OBJECT_MAY_BE_EMPTY = frozenset({"LowLimit", "HighLimit", "DefaultValue", "ParameterValue"})
#: Keys nothing can stand in for.
REQUIRED = frozenset({"DataType", "NrOfEntries"})
COMMISSIONING_NUMBERS = frozenset({"Baudrate", "NodeID", "NetNumber", "CANopenManager",
                                   "LSS_SerialNumber"})

_OBJECT = re.compile(r"^[0-9A-Fa-f]{4}(?:[Ss]ub[0-9A-Fa-f]+|Name)?$")


@dataclass(frozen=True)
class EdsRead:
    """An EDS read by :func:`read_eds`: canopen's object dictionary and what was tolerated."""

    od: Any
    warnings: tuple[str, ...]


def clean(text: str, where: str) -> tuple[str, list[str]]:
    """``text`` (an EDS) with its empty numeric fields dropped or zeroed, and one warning per
    field naming ``where`` (the file), the section and the key. Raises ``ValueError`` naming
    them for an empty required field or text that is not INI."""
    parser = configparser.RawConfigParser(inline_comment_prefixes=(";",), strict=False,
                                          interpolation=None)
    parser.optionxform = str  # type: ignore[assignment,method-assign]
    try:
        parser.read_string(text, source=where)
    except configparser.Error as exc:
        raise ValueError(f"{where}: not an EDS (INI) file: {exc}") from exc
    warnings: list[str] = []
    with_subs = {name[:4].upper() for name in parser.sections()
                 if re.match(r"^[0-9A-Fa-f]{4}[Ss]ub[0-9A-Fa-f]+$", name)}
    for section in parser.sections():
        for key, value in list(parser.items(section)):
            if value.strip():
                continue
            action = _empty(section, key)
            if action == "keep":
                continue
            if key == "ObjectType" and section.upper() in with_subs:
                parser.set(section, key, "0x9")   # its sub-indices make it a record
                warnings.append(f"{where}: [{section}] {key}: empty value; read as 0x9 "
                                f"(a record: the object has sub-indices)")
                continue
            if action == "error":
                raise ValueError(f"{where}: [{section}] {key}: empty; expected a number")
            if action == "zero":
                parser.set(section, key, "0")
                warnings.append(f"{where}: [{section}] {key}: empty value; read as 0")
            elif action == "drop":
                parser.remove_option(section, key)
                warnings.append(f"{where}: [{section}] {key}: empty value; read as absent")
            else:
                parser.remove_option(section, key)
    out = io.StringIO()
    parser.write(out)
    return out.getvalue(), warnings


def _empty(section: str, key: str) -> str:
    """What an empty ``key`` of ``section`` becomes: keep, drop (warned), silent (dropped
    without a warning), zero (warned) or error."""
    if section == "DeviceInfo":
        return "keep" if key in DEVICE_INFO_TEXT else "drop"
    if section == "Comments":
        return "zero" if key == "Lines" else "keep"
    if section.lower() == "dummyusage":
        return "zero"
    if section == "DeviceComissioning":
        return "drop" if key in COMMISSIONING_NUMBERS else "keep"
    if _OBJECT.match(section):
        if key in REQUIRED:
            return "error"
        if key in OBJECT_OPTIONAL:
            return "drop"
        if key in OBJECT_MAY_BE_EMPTY:
            return "silent"
    return "keep"


def read_eds(path: str | Path, node_id: int | None) -> EdsRead:
    """canopen's object dictionary of the EDS at ``path`` for node ``node_id`` (``$NODEID``
    resolved), read tolerantly (see the module doc). Raises ``ValueError`` naming the file when
    it cannot be read or canopen rejects what is left."""
    from canopen.objectdictionary import eds as canopen_eds

    import_eds: Any = canopen_eds.import_eds
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise ValueError(f"{p}: cannot read the EDS: {exc.strerror or exc}") from exc
    warnings: list[str] = []
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
        warnings.append(f"{p}: not UTF-8; read as Latin-1")
    cleaned, more = clean(text, str(p))
    warnings.extend(more)
    try:
        od = import_eds(io.StringIO(cleaned), node_id)
    except Exception as exc:  # canopen raises assorted types for a malformed file
        raise ValueError(f"{p}: not a readable EDS: {type(exc).__name__}: {exc}") from exc
    return EdsRead(od, tuple(warnings))
