"""canopen_pdo - the PDOs of a simulated CANopen node as its object dictionary defines them
(CiA 301): reading a PDO's communication and mapping parameters, packing a TPDO and unpacking an
RPDO bit by bit, and the rules a write to the parameters meets (the CiA 301 remapping
procedure). Pure functions over an :class:`~chcos.apps.sim.object_store.ObjectStore`.
"""

from __future__ import annotations

from dataclasses import dataclass

from chcos.apps.sim.object_store import ObjectStore, fixed_size
from chcos.apps.sim.sdo_server import AbortCode, SdoAbort

#: Base indices of the parameters: RPDO communication/mapping, TPDO communication/mapping.
RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP = 0x1400, 0x1600, 0x1800, 0x1A00
#: COB-ID bit 31: the PDO does not exist (is not valid).
INVALID = 0x8000_0000


@dataclass(frozen=True)
class PdoConfig:
    """One PDO as the node's communication and mapping parameters define it. Times are in
    seconds (the parameters hold 100 us units for the inhibit time, ms for the event timer)."""

    number: int
    cob_id: int
    enabled: bool
    trans_type: int
    event_timer_ms: int
    entries: tuple[tuple[int, int, int], ...]   # (index, subindex, bits)
    inhibit_100us: int = 0

    @property
    def synchronous(self) -> bool:
        """Transmission types 0..240 follow SYNC."""
        return self.trans_type <= 240

    @property
    def event_driven(self) -> bool:
        """Transmission types 254/255: on change and on the event timer."""
        return self.trans_type >= 254

    @property
    def inhibit(self) -> float:
        """The inhibit time, seconds (TPDOs of type 254/255 only)."""
        return self.inhibit_100us / 10_000

    @property
    def length(self) -> int:
        """The bytes the mapping fills (a frame shorter than this is a length error)."""
        return (sum(bits for _i, _s, bits in self.entries) + 7) // 8

    def maps(self, index: int, subindex: int) -> bool:
        """True if object ``index:subindex`` is in this PDO."""
        return any(i == index and s == subindex for i, s, _ in self.entries)


def integer(store: ObjectStore, index: int, subindex: int, missing: int = 0) -> int:
    """An integer object's value, ``missing`` when the EDS lacks it."""
    var = store.find(index, subindex)
    if var is None:
        return missing
    try:
        return int(var.decode_raw(store.raw(index, subindex)))
    except (TypeError, ValueError, SdoAbort):
        return missing


def read_pdo(store: ObjectStore, n: int, comm: int, mapping: int) -> PdoConfig | None:
    """PDO ``n`` (0-based) from its parameters at ``comm + n`` and ``mapping + n``; None when
    the EDS has not both."""
    if not (store.has(comm + n) and store.has(mapping + n)):
        return None
    cob = integer(store, comm + n, 1, INVALID)
    entries = []
    for sub in range(1, integer(store, mapping + n, 0) + 1):
        entry = integer(store, mapping + n, sub)
        index, subindex, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
        if index and bits:
            entries.append((index, subindex, bits))
    return PdoConfig(number=n + 1, cob_id=cob & 0x1FFF_FFFF, enabled=not cob & INVALID,
                     trans_type=integer(store, comm + n, 2, 255),
                     event_timer_ms=integer(store, comm + n, 5),
                     inhibit_100us=integer(store, comm + n, 3) if comm == TPDO_COMM else 0,
                     entries=tuple(entries))


def read_all(store: ObjectStore, comm: int, mapping: int) -> list[PdoConfig]:
    """Every PDO of one direction the EDS defines."""
    return [p for n in range(512) if (p := read_pdo(store, n, comm, mapping)) is not None]


def pack(store: ObjectStore, pdo: PdoConfig) -> bytes:
    """A TPDO's data: the mapped objects' values bit by bit, least significant first; a dummy
    entry (a data-type index) or an object the EDS lacks fills its bits with zeros."""
    bits = 0
    offset = 0
    for index, subindex, size in pdo.entries:
        try:
            raw = int.from_bytes(store.raw(index, subindex), "little") \
                if index >= 0x1000 else 0
        except SdoAbort:
            raw = 0
        bits |= (raw & ((1 << size) - 1)) << offset
        offset += size
    return bits.to_bytes((offset + 7) // 8, "little")


def unpack(store: ObjectStore, pdo: PdoConfig,
           data: bytes) -> list[tuple[int, int, bytes]]:
    """What an RPDO of ``data`` (at least :attr:`PdoConfig.length` bytes) writes:
    (index, sub-index, bytes) per mapped object, dummy entries left out."""
    value = int.from_bytes(data, "little")
    offset = 0
    writes = []
    for index, subindex, size in pdo.entries:
        raw = (value >> offset) & ((1 << size) - 1)
        offset += size
        var = store.find(index, subindex) if index >= 0x1000 else None
        if var is None:
            continue
        nbytes = fixed_size(var) or (size + 7) // 8
        writes.append((index, subindex, raw.to_bytes(nbytes, "little")))
    return writes


def check_write(store: ObjectStore, index: int, subindex: int, value: int) -> None:
    """Refuse what a CiA 301 node refuses in a write to PDO parameter ``index:subindex``
    (raises :class:`SdoAbort`): a new COB-ID for a valid PDO (0x06090030); a mapping changed
    while its PDO is valid, or an entry while the entry count is not 0 (0x08000022); a count
    above the entries the EDS has or over 64 bits (0x06040042); an entry naming an object
    missing (0x06020000, 0x06090011) or not mappable in that direction (0x06040041)."""
    is_map = RPDO_MAP <= index < TPDO_COMM or index >= TPDO_MAP
    comm = index - 0x200 if is_map else index
    valid = not integer(store, comm, 1, INVALID) & INVALID
    if not is_map:
        old = integer(store, comm, 1, INVALID)
        if subindex == 1 and valid and not value & INVALID and (old ^ value) & 0x1FFF_FFFF:
            raise SdoAbort(AbortCode.VALUE)
        return
    if valid:
        raise SdoAbort(AbortCode.DEVICE_STATE)
    if subindex == 0:
        if value and store.find(index, value) is None:
            raise SdoAbort(AbortCode.PDO_LENGTH)   # more entries than the EDS has
        if sum(integer(store, index, s) & 0xFF for s in range(1, value + 1)) > 64:
            raise SdoAbort(AbortCode.PDO_LENGTH)
        return
    if integer(store, index, 0):
        raise SdoAbort(AbortCode.DEVICE_STATE)
    obj_index, obj_sub = value >> 16, (value >> 8) & 0xFF
    if obj_index < 0x1000:
        return   # a dummy entry (data-type index) fills a gap
    var = store.variable(obj_index, obj_sub)
    receive = comm < TPDO_COMM
    if not var.pdo_mappable or not (var.writable if receive else var.readable):
        raise SdoAbort(AbortCode.NOT_MAPPABLE)
