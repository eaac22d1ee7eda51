"""draft - the map being written: :class:`MapDraft` and its TOML rendering, shared by the importers.

Each importer (:mod:`.eds`, :mod:`.dbc`, :mod:`.modbus_csv`, :mod:`.sunspec`) fills a
:class:`MapDraft`; :func:`render` writes it as device-map TOML (a bus's :class:`Table` lists as
``[[bus.KEY]]`` sub-tables with their comments); :func:`limits`, :func:`clamp_limits` and
:class:`Hex` are the value helpers they share; :func:`rename` applies ``--rename OLD=NEW``.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from typing import Any

from chcos.devices.mapparse import MAX_MAGNITUDE, MAX_NAME
from chcos.errors import ConfigError
from chcos.helpers import NAME_PATTERN


@dataclass
class Table:
    """A sub-table of a bus written as ``[[bus.KEY]]`` (a CAN bus's ``message`` tables), with
    the comment lines printed above it."""

    comments: list[str]
    values: dict[str, Any]


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
        """A device name from ``text`` (letters, digits, ``_``), unique in this draft and at
        most :data:`MAX_NAME` characters (a long vendor name is cut, a number added when two
        cut names meet)."""
        snake = re.sub(r"(?<=[a-z0-9])(?=[A-Z])", "_", text[:400])  # OilPressure -> Oil_Pressure
        body = re.sub(r"[^0-9A-Za-z_]+", "_", snake).strip("_").lower() or "device"
        if not prefix and not re.match(r"[A-Za-z_]", body):
            body = f"d_{body}"
        base = (prefix + body)[:MAX_NAME - 4].rstrip("_") or "device"
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
        subs = {k: v for k, v in bus.items() if isinstance(v, list) and v
                and all(isinstance(x, Table) for x in v)}
        out += ["", "[[bus]]"] + [f"{k} = {toml_value(v)}" for k, v in bus.items()
                                  if k not in subs]
        for key, tables in subs.items():
            for table in tables:
                out += ["", *comment(table.comments), f"[[bus.{key}]]"]
                out += [f"{k} = {toml_value(v)}" for k, v in table.values.items()]
    for comments, dev in draft.devices:
        out += ["", *comment(comments), "[[device]]"]
        out += [f"{k} = {toml_value(v)}" for k, v in dev.items()]
    return "\n".join(out) + "\n"


def limits(lo: Any, hi: Any) -> list[float] | None:
    """A ``limits`` value from optional ends (None when both are open)."""
    if lo is None and hi is None:
        return None
    return [-math.inf if lo is None else float(lo), math.inf if hi is None else float(hi)]


def tidy(x: float) -> float:
    """``x`` rounded to 12 significant digits (``3276.7000000000003`` -> ``3276.7``)."""
    return float(f"{x:.12g}")


def clamp_limits(lo: float | None, hi: float | None, capacity: tuple[float, float],
                 what: str, warnings: list[str]) -> list[float] | None:
    """The ``limits`` of a device whose address carries ``capacity`` (engineering units) and
    whose vendor file gives ``lo``..``hi`` (None: open): an end beyond the capacity is clamped
    to it with a warning naming ``what`` (a write beyond it would be refused on the bus, a
    reading never gets there); ends that are not finite numbers, or the wrong way round, give
    the capacity with a warning. Never None when the capacity is finite."""
    cap_lo, cap_hi = (tidy(min(capacity)), tidy(max(capacity)))
    given = [v for v in (lo, hi) if v is not None]
    if any(not math.isfinite(v) for v in given):
        warnings.append(f"{what}: limits {lo}..{hi} are not finite numbers: the signal's "
                        f"capacity {cap_lo:g}..{cap_hi:g} is used")
        lo = hi = None
    elif lo is not None and hi is not None and lo > hi:
        warnings.append(f"{what}: limits {lo:g}..{hi:g} are the wrong way round: the "
                        f"capacity {cap_lo:g}..{cap_hi:g} is used")
        lo = hi = None
    out_lo = cap_lo if lo is None else lo
    out_hi = cap_hi if hi is None else hi
    if out_lo < cap_lo or out_hi > cap_hi:
        warnings.append(f"{what}: limits {out_lo:g}..{out_hi:g} exceed what it can carry "
                        f"({cap_lo:g}..{cap_hi:g}): clamped to {max(out_lo, cap_lo):g}.."
                        f"{min(out_hi, cap_hi):g}")
        out_lo, out_hi = max(out_lo, cap_lo), min(out_hi, cap_hi)
    if out_lo > out_hi:   # both ends beyond the same side: nothing of the vendor's range fits
        warnings.append(f"{what}: no value of its limits fits its capacity: the capacity "
                        f"{cap_lo:g}..{cap_hi:g} is used")
        out_lo, out_hi = cap_lo, cap_hi
    if lo is None and hi is None and not all(map(math.isfinite, (out_lo, out_hi))):
        return None
    return [_open(tidy(out_lo)), _open(tidy(out_hi))]


def _open(x: float) -> float:
    """An end beyond what a map's limits hold (:data:`MAX_MAGNITUDE`: a float holds every
    integer below it) as an open end, ``inf`` (the driver still refuses what the address
    cannot carry)."""
    return x if abs(x) <= MAX_MAGNITUDE else math.copysign(math.inf, x)


def check_name(option: str, value: str, *, prefix: bool = False) -> str:
    """``value`` if it is a valid bus/device name (``prefix``: the start of one, or empty) for
    command-line option ``option``; raises ConfigError naming the option otherwise."""
    if prefix and value == "":
        return value
    limit = 32 if prefix else MAX_NAME
    if not NAME_PATTERN.fullmatch(value) or len(value) > limit:
        raise ConfigError(f"{option} {value[:80]!r}: expected letters, digits, '_', '.' or '-', "
                          f"starting with a letter or '_', at most {limit} characters")
    return value


def rename(draft: MapDraft, pairs: list[str]) -> None:
    """Apply ``--rename OLD=NEW`` items to the devices of ``draft`` (OLD: a name the importer
    chose). Raises ConfigError naming the item for a bad form, an OLD no device has, or a NEW
    that is invalid or already taken; nothing is renamed then."""
    names = [dev["name"] for _c, dev in draft.devices]
    plan: dict[str, str] = {}
    for item in pairs:
        old, eq, new = item.partition("=")
        old, new = old.strip(), new.strip()
        if not eq or not old or not new:
            raise ConfigError(f"--rename {item!r}: expected OLD=NEW")
        if old not in names:
            close = [n for n in names if old.lower() in n][:5]
            raise ConfigError(f"--rename {item!r}: no device {old!r} in the import"
                              + (f" (did you mean {', '.join(close)}?)" if close else ""))
        check_name(f"--rename {old}=", new)
        plan[old] = new
    after = [plan.get(n, n) for n in names]
    for new in set(plan.values()):
        if after.count(new) > 1:
            raise ConfigError(f"--rename: {new!r} would name two devices")
    for _c, dev in draft.devices:
        dev["name"] = plan.get(dev["name"], dev["name"])


def unrepr(text: str) -> str:
    """``text`` as quoted by ``repr`` (``\\x00``, ``\\t``) back to the characters a file holds."""
    try:
        return text.encode("latin-1", "backslashreplace").decode("unicode_escape")
    except UnicodeDecodeError:
        return text
