"""object_store - the values a simulated CANopen node holds in its object dictionary, and the
CiA 301 rules an SDO access to them meets.

The object dictionary is canopen's, read from the EDS (:func:`chcos.devices.eds_file.read_eds`):
what exists, each object's data type, access type and limits. :class:`ObjectStore` holds the
values (bytes, as on the wire) and answers for the rules every object follows alike:

* an index the EDS lacks: abort 0x06020000; a sub-index a record or array lacks, or any
  sub-index but 0 of a plain variable (0x6064:01): 0x06090011 - never the variable's value;
* a read of a write-only object: 0x06010001; a write of a read-only or constant one:
  0x06010002;
* a value of the wrong length for the object's type: 0x06070012 (too long) or 0x06070013
  (too short); strings and domains take any length;
* a number below LowLimit: 0x06090032, above HighLimit: 0x06090031; a BOOLEAN other than
  0 or 1: 0x06090030;
* an object without a DefaultValue reads as the zero of its type (vendors leave measured
  values without one; a device answers them), not as an abort.

What is particular to an object (the error register, the PDO parameters, store and restore)
is the node's (:mod:`chcos.apps.sim.canopen_slave`). canopen's objects are held as ``Any``:
the library is only partly typed.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from canopen.objectdictionary import BOOLEAN, FLOAT_TYPES, INTEGER_TYPES, ODVariable

from chcos.apps.sim.sdo_server import AbortCode, SdoAbort

VISIBLE_STRING, UNICODE_STRING = 0x09, 0x0B


def zero(var: Any) -> Any:
    """The zero value of an object's data type (what an object without a default holds)."""
    if var.data_type == BOOLEAN:
        return False
    if var.data_type in INTEGER_TYPES:
        return 0
    if var.data_type in FLOAT_TYPES:
        return 0.0
    if var.data_type in (VISIBLE_STRING, UNICODE_STRING):
        return ""
    return b""


def fixed_size(var: Any) -> int | None:
    """The size in bytes of a value of ``var``'s type, None for strings and domains."""
    return len(var) // 8 if var.data_type in ODVariable.STRUCT_TYPES else None


class ObjectStore:
    """The values of object dictionary ``od`` (canopen's), keyed by (index, sub-index); an
    object not stored reads as its EDS value (ParameterValue, else DefaultValue, else the
    zero of its type). No method here checks the NMT state or the node's own rules."""

    def __init__(self, od: Any) -> None:
        self.od = od
        self._values: dict[tuple[int, int], bytes] = {}

    # -- what exists ---------------------------------------------------------------------------

    def find(self, index: int, subindex: int) -> Any | None:
        """The variable at ``index:subindex``, None if there is none (a plain variable has
        sub-index 0 only)."""
        obj = self.od.get(index)
        if obj is None:
            return None
        if isinstance(obj, ODVariable):
            return obj if subindex == 0 else None
        return obj.get(subindex)

    def variable(self, index: int, subindex: int) -> Any:
        """The variable at ``index:subindex``; raises :class:`SdoAbort` 0x06020000 (no such
        object) or 0x06090011 (no such sub-index)."""
        if self.od.get(index) is None:
            raise SdoAbort(AbortCode.NO_OBJECT)
        var = self.find(index, subindex)
        if var is None:
            raise SdoAbort(AbortCode.NO_SUBINDEX)
        return var

    def has(self, index: int) -> bool:
        """True if the EDS has object ``index``."""
        return self.od.get(index) is not None

    def subindices(self, index: int) -> list[int]:
        """The sub-indices of a record or array (0 only for a variable, none if absent)."""
        obj = self.od.get(index)
        if obj is None:
            return []
        return [0] if isinstance(obj, ODVariable) else sorted(obj.subindices)

    # -- values --------------------------------------------------------------------------------

    def raw(self, index: int, subindex: int) -> bytes:
        """The bytes the object holds (no access check); raises :class:`SdoAbort` for an
        object or sub-index that does not exist."""
        stored = self._values.get((index, subindex))
        if stored is not None:
            return stored
        var = self.variable(index, subindex)
        default = var.value if var.value is not None else var.default
        return bytes(var.encode_raw(default if default is not None else zero(var)))

    def stored(self, index: int, subindex: int) -> bytes | None:
        """What was put at ``index:subindex`` since the last :meth:`clear` (None: nothing)."""
        return self._values.get((index, subindex))

    def put(self, index: int, subindex: int, data: bytes) -> None:
        """Hold ``data`` at ``index:subindex`` (no check: the caller checked)."""
        self._values[(index, subindex)] = bytes(data)

    def drop(self, index: int, subindex: int) -> None:
        """Forget what was put at ``index:subindex`` (it reads as its EDS value again)."""
        self._values.pop((index, subindex), None)

    def clear(self) -> None:
        """Forget every value put (all objects read as their EDS values again)."""
        self._values.clear()

    def items(self) -> Iterator[tuple[tuple[int, int], bytes]]:
        """Every value put, as ((index, sub-index), bytes)."""
        return iter(list(self._values.items()))

    # -- the SDO rules -------------------------------------------------------------------------

    def readable(self, index: int, subindex: int) -> Any:
        """The variable for an upload; raises :class:`SdoAbort` when it does not exist or is
        write-only."""
        var = self.variable(index, subindex)
        if not var.readable:
            raise SdoAbort(AbortCode.WRITE_ONLY)
        return var

    def writable(self, index: int, subindex: int) -> Any:
        """The variable for a download; raises :class:`SdoAbort` when it does not exist or is
        read-only (``ro`` and ``const``)."""
        var = self.variable(index, subindex)
        if not var.writable:
            raise SdoAbort(AbortCode.READ_ONLY)
        return var

    def check_value(self, var: Any, data: bytes) -> None:
        """Raise :class:`SdoAbort` when ``data`` is not a value ``var`` can take: its length
        (0x06070012/0x06070013), its limits (0x06090031/0x06090032), a BOOLEAN's 0 or 1
        (0x06090030)."""
        size = fixed_size(var)
        if size is None:
            return
        if len(data) != size:
            raise SdoAbort(AbortCode.TOO_LONG if len(data) > size else AbortCode.TOO_SHORT)
        value = var.decode_raw(data)
        if var.data_type == BOOLEAN:
            if data[0] not in (0, 1):
                raise SdoAbort(AbortCode.VALUE)
            return
        if var.min is not None and value < var.min:
            raise SdoAbort(AbortCode.TOO_LOW)
        if var.max is not None and value > var.max:
            raise SdoAbort(AbortCode.TOO_HIGH)
