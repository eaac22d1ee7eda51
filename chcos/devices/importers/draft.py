"""draft - the map being written: :class:`MapDraft` and its TOML rendering, shared by the importers.

Each importer (:mod:`.eds`, :mod:`.dbc`, :mod:`.modbus_csv`) fills a :class:`MapDraft`;
:func:`render` writes it as device-map TOML; :func:`limits` and :class:`Hex` are the value
helpers they share.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from typing import Any


@dataclass
class MapDraft:
    """A device map being written: header comment lines, bus tables, device tables (each with
    the comment lines printed above it)."""

    header: list[str] = field(default_factory=list)
    buses: list[dict[str, Any]] = field(default_factory=list)
    devices: list[tuple[list[str], dict[str, Any]]] = field(default_factory=list)
    #: what will not work on a real bus as imported (printed on stderr by ``chcos import``)
    warnings: list[str] = field(default_factory=list)
    _names: set[str] = field(default_factory=set)

    def name(self, text: str, prefix: str = "") -> str:
        """A device name from ``text`` (letters, digits, ``_``), unique in this draft."""
        snake = re.sub(r"(?<=[a-z0-9])(?=[A-Z])", "_", text)  # OilPressure -> Oil_Pressure
        base = prefix + (re.sub(r"[^0-9A-Za-z_]+", "_", snake).strip("_").lower() or "device")
        if not re.match(r"[A-Za-z_]", base):
            base = f"d_{base}"
        name, n = base, 2
        while name in self._names:
            name, n = f"{base}_{n}", n + 1
        self._names.add(name)
        return name

    def add(self, comments: list[str], device: dict[str, Any]) -> None:
        """Add one device table with its comment lines."""
        self.devices.append((comments, device))


class Hex(int):
    """An integer written in hexadecimal (CAN ids, object indices)."""

    __slots__ = ()


def toml_value(v: Any) -> str:
    """``v`` as a TOML value (strings, numbers, booleans, lists and inline tables)."""
    if isinstance(v, Hex):
        return f"0x{int(v):04X}"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"no TOML form for {v!r}")


_CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f]")   # not allowed in a TOML comment


def comment(lines: list[str]) -> list[str]:
    """``lines`` as TOML comment lines: a text of several lines (a vendor file's multi-line
    comment) gives one ``#`` line each, control characters become spaces."""
    return [f"# {_CONTROL.sub(' ', part)}".rstrip()
            for line in lines for part in (str(line).splitlines() or [""])]


def render(draft: MapDraft) -> str:
    """The device-map TOML text of ``draft``."""
    out = comment(draft.header)
    for bus in draft.buses:
        out += ["", "[[bus]]"] + [f"{k} = {toml_value(v)}" for k, v in bus.items()]
    for comments, dev in draft.devices:
        out += ["", *comment(comments), "[[device]]"]
        out += [f"{k} = {toml_value(v)}" for k, v in dev.items()]
    return "\n".join(out) + "\n"


def limits(lo: Any, hi: Any) -> list[float] | None:
    """A ``limits`` value from optional ends (None when both are open)."""
    if lo is None and hi is None:
        return None
    return [-math.inf if lo is None else float(lo), math.inf if hi is None else float(hi)]
