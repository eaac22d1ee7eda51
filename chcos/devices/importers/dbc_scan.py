"""dbc_scan - a DBC's messages and signals read line by line before cantools builds anything.

cantools allocates per bit of a signal and per byte of a message: a DBC declaring a
4,294,967,296-bit signal took 78 s and 9 GB before cantools refused it. :func:`prescan` reads
the ``BO_`` and ``SG_`` lines with a regular expression (linear in the file), refuses sizes no
CAN frame can have (more than 64 bytes, a signal longer than 64 bits or beyond the frame) naming
the file, line and name, and returns where each message and signal is declared, so that an error
cantools raises later can name the line too (:func:`locate`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from chcos.devices.importers.draft import unrepr
from chcos.errors import ConfigError

#: bytes of the largest CAN (FD) frame
MAX_FRAME = 64
#: bits of the longest signal cantools codes (an integer or a double)
MAX_SIGNAL = 64
#: bytes of a DBC read by the importer (a vendor's whole vehicle DBC is a few megabytes)
MAX_FILE = 64 * 1024 * 1024

# linear on any line: no two adjacent repeats can match the same characters
_BO = re.compile(r"^\s*BO_\s+(-?\d+)\s+(\w+)\s*:\s*(\d+)")
_SG = re.compile(r"^\s*SG_\s+(\w+)(?:\s+\w+)?\s*:\s*(\d+)\s*\|\s*(\d+)\s*@")


@dataclass
class DbcLines:
    """Where each message and signal of a DBC is declared (1-based line numbers)."""

    messages: dict[str, int] = field(default_factory=dict)
    signals: dict[tuple[str, str], int] = field(default_factory=dict)


def _too_long(text: str) -> bool:
    return len(text) > 12     # no DBC number needs more digits (ids and sizes are 32-bit)


def prescan(path: Path, text: str) -> DbcLines:
    """The declarations of ``text`` (the DBC at ``path``); raises ConfigError naming the file,
    line and message or signal for a frame longer than :data:`MAX_FRAME` bytes, a signal longer
    than :data:`MAX_SIGNAL` bits, or one that starts beyond its frame."""
    if len(text) > MAX_FILE:
        raise ConfigError(f"{path}: {len(text)} characters: more than a DBC importer reads "
                          f"({MAX_FILE // 2**20} MB)")
    lines = DbcLines()
    message, size = "", MAX_FRAME
    for no, line in enumerate(text.splitlines(), 1):
        if "BO_" in line and (m := _BO.match(line)):
            message, size_text = m.group(2), m.group(3)
            if _too_long(m.group(1)) or _too_long(size_text) or int(size_text) > MAX_FRAME:
                raise ConfigError(f"{path}: line {no}: BO_ {message}: {size_text[:20]} bytes: a "
                                  f"CAN frame carries at most {MAX_FRAME}")
            size = int(size_text)
            lines.messages.setdefault(message, no)
        elif "SG_" in line and (m := _SG.match(line)):
            signal, start_text, length_text = m.group(1), m.group(2), m.group(3)
            where = f"{path}: line {no}: SG_ {signal} (in {message or 'no message'})"
            if _too_long(length_text) or int(length_text) > MAX_SIGNAL \
                    or int(length_text) == 0:
                raise ConfigError(f"{where}: {length_text[:20]} bits: expected a signal of "
                                  f"1..{MAX_SIGNAL} bits")
            if _too_long(start_text) or int(start_text) >= 8 * max(size, 1):
                raise ConfigError(f"{where}: start bit {start_text[:20]}: beyond the "
                                  f"{size}-byte frame (bits 0..{8 * max(size, 1) - 1})")
            lines.signals.setdefault((message, signal), no)
    return lines


def locate(lines: DbcLines, text: str, source: str = "") -> str | None:
    """``line N`` of the first message or signal that ``text`` (an error message) names, else
    of the first line of ``source`` (the DBC) holding a word ``text`` quotes; None when
    nothing is found."""
    for (message, signal), no in lines.signals.items():
        if re.search(rf"\b{re.escape(signal)}\b", text) and (
                message in text or f"'{signal}'" in text or f'"{signal}"' in text):
            return f"line {no} (SG_ {signal} of {message})"
    for message, no in lines.messages.items():
        if re.search(rf"\b{re.escape(message)}\b", text):
            return f"line {no} (BO_ {message})"
    for (message, signal), no in lines.signals.items():
        if re.search(rf"\b{re.escape(signal)}\b", text):
            return f"line {no} (SG_ {signal} of {message})"
    for statement in re.findall(r"\b([A-Z_]{2,}_ -?\d+ \w+)", text):   # "VAL_ 385 State"
        for no, line in enumerate(source.splitlines(), 1):
            if " ".join(line.split()).startswith(statement):
                return f"line {no}"
    for quoted in re.findall(r"'([^']{3,})'", text):
        needle = unrepr(quoted)[:60]
        for no, line in enumerate(source.splitlines(), 1):
            if needle in line:
                return f"line {no}"
    return None
