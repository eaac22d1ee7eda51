"""dbc_computed - the rolling counters and checksums of a DBC message, found by name and by layout.

A DBC says which bits a counter or a checksum occupies but not that they are one, nor how the
checksum is computed. :func:`computed_signals` finds them: by name (``COUNTER``, ``CNT``,
``ALIVE``, ``ROLLING``, ``SEQ``, VW's ``_BZ``; ``CHECKSUM``, ``CRC``, ``CHKSUM``, ``CHK``...),
and by the common layouts: an 8-bit signal filling the first or last byte, named like a
checksum (``CS``, ``SUM``, ``CKS``), is one; in a message with a checksum, an unsigned 2- or
4-bit signal in the first or last byte, or in or beside the checksum's byte (AUTOSAR E2E
profile 1), is its counter. :func:`likely_algorithm` guesses the checksum's algorithm (a guess
the import report says must be confirmed). The ``can`` driver computes what the map declares
(``[[bus.message]]``: ``counter``, ``checksum = {signal, algorithm}``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

#: the algorithms a map's ``checksum.algorithm`` names (``python``: ``function`` computes it)
ALGORITHMS = ("xor", "sum", "crc8-sae-j1850", "crc8-autosar", "python")

_COUNTER = re.compile(r"(?i)(counter|cntr|(?:^|_)cnt(?:_|$|\d)|cnt$|^cnt|alive|aliv(?:_|$)|"
                      r"rolling|(?:^|_)seq(?:_|$|\d)|sequence|(?:^|_)sqc(?:_|$)|_bz$|msg_?cnt)")
_CHECKSUM = re.compile(r"(?i)(crc|checksum|chksum|chksm|chks|(?:^|_)chk(?:_|$|\d)|chk$|parity)")
#: looser checksum names, taken only for an 8-bit signal filling the first or last byte
_CHECKSUM_LAYOUT = re.compile(r"(?i)((?:^|_)cs(?:_|$|\d)|(?:^|_)sum(?:_|$)|(?:^|_)cks(?:_|$))")


@dataclass(frozen=True)
class Computed:
    """A signal the sending node computes per frame."""

    signal: str
    kind: str       # "counter" or "checksum"
    how: str        # how it was found: "by its name" or the layout


def bits(sig: Any) -> set[int]:
    """The frame bits ``sig`` occupies (bit 0: the least significant bit of byte 0)."""
    if sig.byte_order == "little_endian":
        return set(range(sig.start, sig.start + sig.length))
    out, pos = set(), sig.start        # Motorola: from the MSB, byte by byte
    for _ in range(sig.length):
        out.add(pos)
        pos = pos + 15 if pos % 8 == 0 else pos - 1
    return out


def _edge(sig: Any, length: int, beside: Any = None) -> bool:
    """Whether ``sig`` lies within the first or the last byte of a ``length``-byte frame, or
    (``beside``: a checksum signal) within a byte the checksum occupies or next to one."""
    occupied = {b // 8 for b in bits(sig)}
    allowed = {0, length - 1}
    if beside is not None:
        allowed |= {n + d for n in {b // 8 for b in bits(beside)} for d in (-1, 0, 1)}
    return len(occupied) == 1 and occupied <= allowed


def _plain_unsigned(sig: Any) -> bool:
    return (not sig.is_signed and not sig.is_float and sig.scale == 1 and sig.offset == 0
            and not sig.choices and not sig.is_multiplexer and not sig.multiplexer_ids)


def computed_signals(msg: Any) -> list[Computed]:
    """The counter and the checksum of ``msg`` (at most one each), found as the module doc
    says."""
    found: dict[str, Computed] = {}
    for sig in msg.signals:
        if sig.is_multiplexer or sig.is_float:
            continue
        if "checksum" not in found and _CHECKSUM.search(sig.name):
            found["checksum"] = Computed(sig.name, "checksum", "by its name")
        elif "counter" not in found and _COUNTER.search(sig.name) and not sig.is_signed:
            found["counter"] = Computed(sig.name, "counter", "by its name")
    if "checksum" not in found:
        for sig in msg.signals:
            if sig.length == 8 and _plain_unsigned(sig) and _edge(sig, msg.length) \
                    and _CHECKSUM_LAYOUT.search(sig.name):
                found["checksum"] = Computed(sig.name, "checksum",
                                             "by its name and place (8 bits, first/last byte)")
                break
    if "checksum" in found and "counter" not in found:
        checksum = msg.get_signal_by_name(found["checksum"].signal)
        for sig in msg.signals:
            if sig.name != checksum.name and sig.length in (2, 4) \
                    and _plain_unsigned(sig) and _edge(sig, msg.length, checksum):
                found["counter"] = Computed(sig.name, "counter",
                                            f"by its place: {sig.length}-bit unsigned beside "
                                            "the checksum")
                break
    return [found[k] for k in ("counter", "checksum") if k in found]


def likely_algorithm(msg: Any, signal: str) -> str:
    """The checksum algorithm most often behind ``signal`` of ``msg``: a CRC of 8 bits is
    CRC-8 SAE J1850 (AUTOSAR E2E profile 1, the most common), any other checksum a byte sum.
    A guess: a DBC cannot say."""
    sig = msg.get_signal_by_name(signal)
    return "crc8-sae-j1850" if "crc" in signal.lower() and sig.length == 8 else "sum"
