"""modbus_types - register types as lists and SunSpec models name them, and what they carry.

:data:`SUNSPEC` maps each SunSpec point type (SunSpec Information Model Specification; the
"not implemented" values as pysunspec2's ``sunspec2.mb`` defines them) to the ``modbus`` driver's
register type, its size in registers and the raw value meaning "not implemented" (the map's
``unimplemented``); :func:`capacity` is the engineering range a register type carries with a scale
and offset; :func:`supported` says whether the driver has a register type
(:data:`DRIVER_TYPES`).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class PointType:
    """How a SunSpec point type is read: the driver's register type (``string``: text, ``""``:
    nothing to read), registers (None: the point's size), the "not implemented" raw value
    (None: there is none; for a string it is an empty, all-NUL value)."""

    register_type: str
    registers: int | None
    unimplemented: int | None


#: SunSpec point type -> how the modbus driver reads it
SUNSPEC: dict[str, PointType] = {
    "int16": PointType("int16", 1, 0x8000),
    "uint16": PointType("uint16", 1, 0xFFFF),
    "count": PointType("uint16", 1, 0xFFFF),
    "acc16": PointType("uint16", 1, 0),
    "enum16": PointType("uint16", 1, 0xFFFF),
    "bitfield16": PointType("uint16", 1, 0xFFFF),
    "int32": PointType("int32", 2, 0x8000_0000),
    "uint32": PointType("uint32", 2, 0xFFFF_FFFF),
    "acc32": PointType("uint32", 2, 0),
    "enum32": PointType("uint32", 2, 0xFFFF_FFFF),
    "bitfield32": PointType("uint32", 2, 0xFFFF_FFFF),
    "ipaddr": PointType("uint32", 2, 0),
    "int64": PointType("int64", 4, 0x8000_0000_0000_0000),
    "uint64": PointType("uint64", 4, 0xFFFF_FFFF_FFFF_FFFF),
    "acc64": PointType("uint64", 4, 0),
    "float32": PointType("float32", 2, 0x7FC0_0000),
    "float64": PointType("float64", 4, 0x7FF8_0000_0000_0000),
    "sunssf": PointType("int16", 1, 0x8000),
    "string": PointType("string", None, None),
    "pad": PointType("", 1, None),
    "eui48": PointType("", 4, None),
    "ipv6addr": PointType("", 8, None),
}

#: raw values each register type carries
RAW_RANGE: dict[str, tuple[float, float]] = {
    "bool": (0, 1), "int16": (-2**15, 2**15 - 1), "uint16": (0, 2**16 - 1),
    "int32": (-2**31, 2**31 - 1), "uint32": (0, 2**32 - 1),
    "int64": (-2**63, 2**63 - 1), "uint64": (0, 2**64 - 1),
    "float32": (-3.4028234663852886e38, 3.4028234663852886e38),
    "float64": (-1.7976931348623157e308, 1.7976931348623157e308)}
#: registers of each numeric register type
WIDTH = {"bool": 1, "int16": 1, "uint16": 1, "int32": 2, "uint32": 2, "float32": 2,
         "int64": 4, "uint64": 4, "float64": 4}


def capacity(register_type: str, scale: float = 1.0, offset: float = 0.0) -> tuple[float, float]:
    """What ``register_type`` carries in engineering units (raw x scale + offset)."""
    ends = [r * scale + offset for r in RAW_RANGE[register_type]]
    return min(ends), max(ends)


#: the register types the ``modbus`` driver reads (its codec's, ``drivers.codecs.modbus``, with
#: ``bool`` and ``string``; ``test_import_vendor`` checks this list against the codec)
DRIVER_TYPES = frozenset({"bool", "int16", "uint16", "int32", "uint32", "int64", "uint64",
                          "float32", "float64", "string"})


def supported(register_type: str) -> bool:
    """Whether the modbus driver reads ``register_type`` (:data:`DRIVER_TYPES`)."""
    return register_type in DRIVER_TYPES
