"""canopen - the pure part of the ``canopen`` bus: where a node's EDS file is, which EMCY codes
are fatal, and what a received COB-ID says (heartbeat or EMCY of which node). No I/O and no
canopen library: used by the CANopen driver (:mod:`drivers.canopen_node`), ``chcos monitor``
and the simulated CANopen slaves.
"""

from __future__ import annotations

from pathlib import Path

from chcos.devices.spec import BusSpec

#: EMCY error-code classes (value, mask) that fail a node's devices until an error reset:
#: current (2xxx), voltage (3xxx), temperature (4xxx), device hardware (50xx), monitoring (8xxx).
FATAL_EMCY_MASKS = ((0x2000, 0xF000), (0x3000, 0xF000), (0x4000, 0xF000), (0x5000, 0xFF00),
                    (0x8000, 0xF000))
HEARTBEAT_BASE = 0x700   # NMT error control (heartbeat, boot-up): COB-ID 0x700 + node id
EMCY_BASE = 0x80         # EMCY: COB-ID 0x80 + node id


def is_fatal_emcy(code: int) -> bool:
    """True for EMCY codes that fail the node's devices (see :data:`FATAL_EMCY_MASKS`)."""
    return any(code & mask == value for value, mask in FATAL_EMCY_MASKS)


def is_error_reset(code: int) -> bool:
    """True for the EMCY that says the node's errors are reset (code 00xx)."""
    return code & 0xFF00 == 0


def heartbeat_node(cob_id: int) -> int | None:
    """The node id of a heartbeat/boot-up COB-ID (0x701..0x77F), else None."""
    return cob_id - HEARTBEAT_BASE if 0x701 <= cob_id <= 0x77F else None


def emcy_node(cob_id: int) -> int | None:
    """The node id of an EMCY COB-ID (0x81..0xFF), else None."""
    return cob_id - EMCY_BASE if 0x81 <= cob_id <= 0xFF else None


def eds_path(bus: BusSpec, eds: str) -> Path:
    """The EDS path ``eds`` of ``bus``: absolute as given, else relative to the bus's file."""
    p = Path(eds).expanduser()
    if p.is_absolute() or bus.file.startswith("<"):
        return p
    return Path(bus.file).resolve().parent / p
