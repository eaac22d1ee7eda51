"""A Modbus address's "not implemented" value, written as a value or as SunSpec's bit pattern."""

from __future__ import annotations

import math

import pytest

from chcos.devices.options import parse
from drivers.codecs.modbus import is_unimplemented, unimplemented_value
from drivers.codecs.modbus_options import ModbusAddress


@pytest.mark.parametrize(("typ", "written", "decoded"), [
    ("int16", 0x8000, -32768), ("int16", -32768, -32768), ("uint16", 0xFFFF, 0xFFFF),
    ("int32", 0x8000_0000, -2**31), ("uint32", 0xFFFF_FFFF, 2**32 - 1),
    ("int64", 0x8000_0000_0000_0000, -2**63)])
def test_a_signed_types_bit_pattern_is_its_negative_value(typ: str, written: int,
                                                          decoded: int) -> None:
    assert unimplemented_value(typ, written) == decoded
    assert is_unimplemented(decoded, unimplemented_value(typ, written))
    assert not is_unimplemented(decoded + 1, unimplemented_value(typ, written))


def test_a_floats_nan_is_matched_as_bits_or_as_nan() -> None:
    for written in (0x7FC0_0000, float("nan")):
        u = unimplemented_value("float32", written)
        assert isinstance(u, float) and math.isnan(u)
        assert is_unimplemented(float("nan"), u) and not is_unimplemented(1.5, u)


def test_the_map_takes_the_bit_pattern_and_nan_and_refuses_what_the_type_cannot_hold() -> None:
    base = {"table": "holding", "address": 5}
    for typ, u in (("int16", 0x8000), ("float32", float("nan")), ("float32", 0x7FC0_0000)):
        cfg, errors = parse(ModbusAddress, {**base, "type": typ, "unimplemented": u}, "a")
        assert errors == [] and cfg is not None
    _, errors = parse(ModbusAddress, {**base, "type": "int16", "unimplemented": 0x10000}, "a")
    assert errors and "unimplemented" in errors[0]
    _, errors = parse(ModbusAddress, {**base, "type": "int16", "unimplemented": float("nan")},
                      "a")
    assert errors and "unimplemented" in errors[0]
