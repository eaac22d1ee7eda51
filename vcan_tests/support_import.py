"""support_import - what the importers' tests need: the vendor files, and whether the drivers
take the map keys the importers write that other branches implement.

The importers write ``[[bus.message]]`` tables (counters and checksums, the ``can`` driver) and
the Modbus keys ``scale_factor``, ``unimplemented`` and ``type = "string"`` (SunSpec, the
``modbus`` driver). Until those drivers have them, ``chcos check`` refuses them as unknown keys;
:data:`needs_can_messages` and :data:`needs_modbus_sunspec` skip the tests that check or run
such a map, and only for that reason: any other refusal of the probe map lets the tests run
(and fail), so the skip never hides a broken map.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest

from chcos.devices.devmap import check

HERE = Path(__file__).resolve().parent
VENDOR = HERE / "vendor"
DOCS_VENDOR = HERE.parent / "docs" / "vendor"


def _absent(text: str, key: str) -> bool:
    """True when ``chcos check`` refuses the map ``text`` because ``key`` is unknown."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "probe.toml"
        path.write_text(text, encoding="utf-8")
        _dmap, errors, _ = check([path])
    return any(f".{key}:" in e and ("unknown" in e or "expected one of" in e) for e in errors)


_CAN = f'''
[[bus]]
name = "b"
kind = "can"
interface = "virtual"
channel = "probe"
dbc = "{VENDOR / 'journey' / 'awkward.dbc'}"

[[bus.message]]
name = "Command"
counter = "RollingCounter"
checksum = {{ signal = "CRC8", algorithm = "crc8-sae-j1850" }}

[[device]]
name = "setpoint"
direction = "actuator"
bus = "b"
address = {{ message = "Command", signal = "Setpoint" }}
limits = [0.0, 1000.0]
'''

_MODBUS = '''
[[bus]]
name = "b"
kind = "modbus-tcp"
host = "127.0.0.1"
port = 1502

[[device]]
name = "w"
direction = "sensor"
bus = "b"
[device.address]
unit = 1
table = "holding"
address = 40084
type = "int16"
unimplemented = 0x8000
scale_factor = 40085

[[device]]
name = "w_sf"
direction = "sensor"
bus = "b"
address = { unit = 1, table = "holding", address = 40085, type = "int16" }

[[device]]
name = "mn"
direction = "sensor"
bus = "b"
address = { unit = 1, table = "holding", address = 40004, type = "string", count = 16 }
'''

CAN_MESSAGES = not _absent(_CAN, "message")
MODBUS_SUNSPEC = not any(_absent(_MODBUS, k) for k in ("unimplemented", "scale_factor",
                                                          "type"))

needs_can_messages = pytest.mark.skipif(
    not CAN_MESSAGES, reason="needs the can driver's [[bus.message]] counters and checksums "
                             "(the CAN branch): chcos check refuses the key here")
needs_modbus_sunspec = pytest.mark.skipif(
    not MODBUS_SUNSPEC, reason="needs the modbus driver's scale_factor, unimplemented and "
                               "string type (the Modbus branch): chcos check refuses them here")
