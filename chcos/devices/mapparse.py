"""mapparse - one device-map file read and parsed into bus and device specs, with its errors.

The file-level half of :mod:`chcos.devices.devmap`: TOML syntax, the top-level, bus and device
keys (:data:`BUS_KEYS`, :data:`DEVICE_KEYS`), names, numbers, limits, ranges and nesting depth,
file-naming options resolved against the file's directory. Every error is collected in a
:class:`FileErrors` (``file:line: key: expected ...``); :func:`read_file` never raises for a bad
file. What needs every file at once (unique names, buses declared elsewhere, the drivers' own
checks) is :mod:`chcos.devices.devmap`'s.
"""

from __future__ import annotations

import math
import re
import sys
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from chcos.devices.spec import MAX_MACHINE, BusSpec, DeviceSpec, Direction
from chcos.helpers import NAME_PATTERN, is_int, is_number
from chcos.tables.messages import PRIORITIES, PRIORITY_TEXT

BUS_KEYS = ("name", "kind")
DEVICE_KEYS = ("name", "direction", "machine", "bus", "address", "priority", "stale_after",
               "scale", "offset", "limits", "safe_value", "safe_reason", "units", "round",
               "north_writable", "profile")
#: ``safe_value = "none"``: the actuator has no safe value, for the reason in ``safe_reason``
NO_SAFE_VALUE = "none"
#: the keys of an axis table (``profile = "cia402"``) besides the axis keys of
#: :data:`drivers.codecs.cia402.AXIS_KEYS` (but ``axis``, which is in the address)
AXIS_TABLE_KEYS = ("name", "profile", "machine", "bus", "address", "priority", "units",
                   "mode")
#: the address keys of an axis table
AXIS_ADDRESS_KEYS = ("node", "axis")
TOP_KEYS = ("bus", "device")
PATH_KEYS = frozenset({"dbc", "eds", "record"})
MAX_MESSAGE = 300        # characters of one error's expectation
MAX_NAME = 64            # characters in a bus or device name
MAX_DEPTH = 8            # nesting of tables/arrays inside a bus's options or a device's address
MAX_INT = 2**63 - 1      # any integer in a device map
MAX_MAGNITUDE = 1e15     # limits and safe values (beyond it a float no longer holds every integer)
MAX_SCALE = 1e12         # scale within [1/MAX_SCALE, MAX_SCALE] in magnitude; |offset| too
STALE_RANGE = (1e-4, 3.2e7)    # seconds: stale_after
SECONDS_RANGE = (1e-4, 1e6)    # seconds: any *_period, *timeout, *_delay, *_delay_max, tick option
RATE_RANGE = (1e-6, 1e5)       # per second: any rate_hz option (the satellite bench: 5e4)


@dataclass
class FileErrors:
    """Errors of one file, each prefixed with the file name and (when known) the line."""

    path: str
    bus_lines: list[int] = field(default_factory=list)
    device_lines: list[int] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)

    def add(self, key: str, message: str) -> None:
        """Record ``key: message`` at the line of the table ``key`` starts with."""
        line = self._line(key)
        where = f"{self.path}:{line}" if line else self.path
        message = _clip(message, MAX_MESSAGE)   # a driver quoting a huge value keeps it short
        key = _clip(key, 120)                   # keys are free-form in TOML (quoted keys)
        self.errors.append(f"{where}: {key}: {message}" if key else f"{where}: {message}")

    def _line(self, key: str) -> int | None:
        m = re.match(r"^(bus|device)\[(\d+)\]", key)
        if not m:
            return None
        lines = self.bus_lines if m.group(1) == "bus" else self.device_lines
        i = int(m.group(2))
        return lines[i] if i < len(lines) else None


def _clip(text: str, limit: int) -> str:
    """``text`` on one line (newlines escaped), cut to ``limit`` characters."""
    text = text.replace("\r", "\\r").replace("\n", "\\n")
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _header_lines(text: str, table: str) -> list[int]:
    """1-based line numbers of the ``[[table]]`` headers in ``text``, in order."""
    pat = re.compile(r"^\s*\[\[\s*" + re.escape(table) + r"\s*\]\]")
    return [n for n, line in enumerate(text.splitlines(), 1) if pat.match(line)]


def _is_path_key(key: str) -> bool:
    return key in PATH_KEYS or key.endswith("_file") or key.endswith("_path")


def _resolve_paths(options: Mapping[str, Any], base: Path) -> dict[str, Any]:
    """A copy of ``options`` with file-naming string values made absolute against ``base``."""
    out: dict[str, Any] = {}
    for key, val in options.items():
        if isinstance(val, str) and _is_path_key(key) and val:
            p = Path(val).expanduser()
            out[key] = str(p if p.is_absolute() else (base / p).resolve())
        else:
            out[key] = val
    return out


def _type_name(v: object) -> str:
    return {bool: "boolean", int: "integer", float: "float", str: "string", list: "array",
            dict: "table"}.get(type(v), type(v).__name__)


def _unknown_keys(fe: FileErrors, key: str, table: Mapping[str, Any],
                  valid: Sequence[str]) -> None:
    for k in table:
        if k not in valid:
            fe.add(key, f"unknown key {short(k)}; valid keys: {', '.join(valid)}")


def _name(fe: FileErrors, key: str, table: Mapping[str, Any]) -> str | None:
    v = table.get("name")
    if v is None:
        fe.add(f"{key}.name", "missing; expected a name (letters, digits, _ . -)")
        return None
    if not isinstance(v, str) or not NAME_PATTERN.fullmatch(v) or len(v) > MAX_NAME:
        fe.add(f"{key}.name", f"expected a name of letters, digits, _ . - starting with a letter "
                              f"or _, at most {MAX_NAME} characters, got {short(v)}")
        return None
    return v


def _parse_bus(fe: FileErrors, i: int, table: Any, base: Path) -> BusSpec | None:
    key = f"bus[{i}]"
    if not isinstance(table, dict):
        fe.add(key, f"expected a table, got {_type_name(table)}")
        return None
    name = _name(fe, key, table)
    kind = table.get("kind")
    if not isinstance(kind, str) or not kind:
        fe.add(f"{key}.kind", f"expected a bus kind string (memory, signal, can, canopen, "
                              f"modbus-tcp, modbus-rtu, serial), got {short(kind)}")
        return None
    if name is None:
        return None
    options = _resolve_paths({k: v for k, v in table.items() if k not in BUS_KEYS}, base)
    return BusSpec(name=name, kind=kind, options=options, file=fe.path, key=key)


def _number(fe: FileErrors, key: str, v: object, *, finite: bool = True,
            magnitude: float | None = None) -> float | None:
    """``v`` as a float, or None after recording why not: not a number, nan, an infinity where
    ``finite``, an integer too large for a float, or beyond ``magnitude``."""
    if not is_number(v):
        fe.add(key, f"expected a number, got {_type_name(v)} {short(v)}")
        return None
    try:
        f = float(v)
    except OverflowError:
        fe.add(key, f"expected a number of magnitude <= {magnitude or sys.float_info.max:g}, got "
                    f"an integer of {len(str(abs(v)))} digits")
        return None
    if math.isnan(f):
        fe.add(key, "expected a number, got nan")
        return None
    if finite and math.isinf(f):
        fe.add(key, f"expected a finite number, got {f}")
        return None
    if magnitude is not None and math.isfinite(f) and abs(f) > magnitude:
        fe.add(key, f"expected a number of magnitude <= {magnitude:g}, got {short(v)}")
        return None
    return f


def short(v: object, limit: int = 60) -> str:
    """``repr(v)`` cut to ``limit`` characters (a 400-digit integer or a deep table stays short)."""
    try:
        text = repr(v)
    except (RecursionError, ValueError):
        text = f"<{_type_name(v)}>"
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _limits(fe: FileErrors, key: str, v: object) -> tuple[float | None, float | None] | None:
    if not (isinstance(v, list) and len(v) == 2):
        fe.add(key, f"expected [lo, hi] (use -inf / inf for an open end), got {short(v)}")
        return None
    lo = _number(fe, f"{key}[0]", v[0], finite=False, magnitude=MAX_MAGNITUDE)
    hi = _number(fe, f"{key}[1]", v[1], finite=False, magnitude=MAX_MAGNITUDE)
    if lo is None or hi is None:
        return None
    if lo == math.inf or hi == -math.inf:
        fe.add(key, f"expected lo < inf and hi > -inf, got {v!r}")
        return None
    if lo > hi:
        fe.add(key, f"expected lo <= hi, got {v!r}")
        return None
    return (None if lo == -math.inf else lo, None if hi == math.inf else hi)


def _in_range(fe: FileErrors, key: str, v: float | None, rng: tuple[float, float],
              what: str) -> float | None:
    if v is not None and not rng[0] <= v <= rng[1]:
        fe.add(key, f"expected {what} in {rng[0]:g}..{rng[1]:g}, got {v!r}")
        return None
    return v


_SECONDS_RE = re.compile(r"(?:.*_)?(?:period|timeout|delay|delay_max|tick)\Z")


def _check_values(fe: FileErrors, key: str, v: object, depth: int = 0,
                  top: str | None = None) -> bool:
    """Rules every value of a bus's options or a device's address obeys, whatever its kind:
    nesting at most MAX_DEPTH, integers within +-MAX_INT, floats finite, seconds (keys ending in
    period, timeout, delay, delay_max, tick) within SECONDS_RANGE, ``rate_hz`` within RATE_RANGE.
    Records every violation; True if there was none."""
    ok = True
    if depth > MAX_DEPTH:
        fe.add(top or key, f"nested more than {MAX_DEPTH} levels deep; expected a flatter "
                           f"value")
        return False
    if isinstance(v, dict):
        for k, item in v.items():
            sub = f"{key}.{k}" if key else str(k)
            ok = _check_values(fe, sub, item, depth + 1, top or sub) and ok
            if ok and is_number(item):
                last = str(k)
                if _SECONDS_RE.match(last):
                    ok = _in_range(fe, sub, float(item), SECONDS_RANGE, "seconds") is not None
                elif last == "rate_hz":
                    ok = _in_range(fe, sub, float(item), RATE_RANGE, "samples per second") \
                        is not None
        return ok
    if isinstance(v, list):
        for i, item in enumerate(v):
            ok = _check_values(fe, f"{key}[{i}]", item, depth + 1, top or key) and ok
        return ok
    if is_int(v) and abs(v) > MAX_INT:
        fe.add(key, f"expected an integer of magnitude <= {MAX_INT}, got {short(v)}")
        return False
    if isinstance(v, float) and not math.isfinite(v):
        fe.add(key, f"expected a finite number, got {v}")
        return False
    if isinstance(v, str) and len(v) > 4096:
        fe.add(key, f"expected a string of at most 4096 characters, got {len(v)}")
        return False
    return True


@dataclass
class _Parsed:
    """One ``[[device]]`` table: its spec if it is wholly valid, and a spec good enough for the
    drivers' address checks (defaults in place of broken general keys) when it is not."""

    spec: DeviceSpec | None
    checkable: DeviceSpec | None


def _parse_device(fe: FileErrors, i: int, table: Any, base: Path) -> _Parsed:
    key = f"device[{i}]"
    if not isinstance(table, dict):
        fe.add(key, f"expected a table, got {_type_name(table)}")
        return _Parsed(None, None)
    before = len(fe.errors)
    _unknown_keys(fe, key, table, DEVICE_KEYS)
    name = _name(fe, key, table)
    direction = table.get("direction")
    if direction not in ("sensor", "actuator"):
        fe.add(f"{key}.direction", f"expected \"sensor\" or \"actuator\", got {short(direction)}")
    machine = table.get("machine", 0)
    if not is_int(machine) or not 0 <= machine <= MAX_MACHINE:
        fe.add(f"{key}.machine", f"expected an integer 0..{MAX_MACHINE}, got {short(machine)}")
        machine = 0
    bus = table.get("bus")
    if not isinstance(bus, str) or not bus:
        fe.add(f"{key}.bus", f"expected the name of a bus, got {short(bus)}")
    address = table.get("address", {})
    address_ok = isinstance(address, dict)
    if not address_ok:
        fe.add(f"{key}.address", f"expected an inline table, got {_type_name(address)}")
    else:
        address_ok = _check_values(fe, f"{key}.address", address)
    priority = table.get("priority", 8)
    if not is_int(priority) or priority not in PRIORITIES:
        fe.add(f"{key}.priority", f"expected an integer {PRIORITY_TEXT}, got {short(priority)}")
        priority = 8
    stale: float | None = None
    if "stale_after" in table:
        stale = _number(fe, f"{key}.stale_after", table["stale_after"])
        stale = _in_range(fe, f"{key}.stale_after", stale, STALE_RANGE, "seconds")
        if direction == "actuator":
            fe.add(f"{key}.stale_after", "applies to sensors only; remove it from an actuator")
    scale = _number(fe, f"{key}.scale", table.get("scale", 1.0), magnitude=MAX_SCALE)
    if scale is not None and abs(scale) < 1 / MAX_SCALE:
        fe.add(f"{key}.scale", f"expected a non-zero number of magnitude {1 / MAX_SCALE:g}.."
                               f"{MAX_SCALE:g} (actuator raw = (value-offset)/scale), "
                               f"got {scale!r}")
        scale = None
    offset = _number(fe, f"{key}.offset", table.get("offset", 0.0), magnitude=MAX_SCALE)
    limits: tuple[float | None, float | None] | None = (None, None)
    if "limits" in table:
        limits = _limits(fe, f"{key}.limits", table["limits"])
    safe: float | None = None
    safe_reason = table.get("safe_reason", "")
    if not isinstance(safe_reason, str) or len(safe_reason) > 200:
        fe.add(f"{key}.safe_reason", f"expected a string of at most 200 characters, got "
                                     f"{_type_name(safe_reason)} {short(safe_reason)}")
        safe_reason = ""
    if table.get("safe_value") == NO_SAFE_VALUE:
        if not safe_reason.strip():
            fe.add(f"{key}.safe_reason", f"safe_value = \"{NO_SAFE_VALUE}\" needs the reason "
                                         f"(e.g. \"a target position: 0 would send the axis "
                                         f"home\")")
        if direction == "sensor":
            fe.add(f"{key}.safe_value", "applies to actuators only; remove it from a sensor")
    elif "safe_value" in table:
        if safe_reason:
            fe.add(f"{key}.safe_reason", f"only with safe_value = \"{NO_SAFE_VALUE}\"; remove "
                                         f"it or the safe value")
        safe = _number(fe, f"{key}.safe_value", table["safe_value"], magnitude=MAX_MAGNITUDE)
        if direction == "sensor":
            fe.add(f"{key}.safe_value", "applies to actuators only; remove it from a sensor")
        if safe is not None and limits is not None:
            lo, hi = limits
            if (lo is not None and safe < lo) or (hi is not None and safe > hi):
                fe.add(f"{key}.safe_value", f"expected a value within limits "
                                            f"{list(table['limits'])}, got {safe!r}")
    units = table.get("units", "")
    if not isinstance(units, str) or len(units) > 64:
        fe.add(f"{key}.units", f"expected a string of at most 64 characters, got "
                               f"{_type_name(units)} {short(units)}")
        units = ""
    rounding = table.get("round", False)
    if not isinstance(rounding, bool):
        fe.add(f"{key}.round",
               f"expected true or false, got {_type_name(rounding)} {short(rounding)}")
    elif rounding and direction != "actuator":
        fe.add(f"{key}.round", "applies to actuators only; remove it from a sensor")
    north = table.get("north_writable", False)
    if not isinstance(north, bool):
        fe.add(f"{key}.north_writable",
               f"expected true or false, got {_type_name(north)} {short(north)}")
    elif north and direction == "sensor":
        fe.add(f"{key}.north_writable", "applies to actuators only; remove it from a sensor")
    if name is None or direction not in ("sensor", "actuator") or not isinstance(bus, str) \
            or not bus or not address_ok or not isinstance(address, dict):
        return _Parsed(None, None)
    dir_: Direction = "sensor" if direction == "sensor" else "actuator"
    spec = DeviceSpec(name=name, direction=dir_, machine=machine, bus=bus, priority=priority,
                      address=_resolve_paths(address, base), stale_after=stale,
                      scale=scale if scale is not None else 1.0,
                      offset=offset if offset is not None else 0.0,
                      limits=limits if limits is not None else (None, None),
                      safe_value=safe, units=units, file=fe.path, key=key,
                      round=rounding is True, north_writable=north is True,
                      safe_reason=safe_reason if table.get("safe_value") == NO_SAFE_VALUE
                      else "")
    return _Parsed(spec if len(fe.errors) == before and limits is not None else None, spec)


def _tables(fe: FileErrors, doc: Mapping[str, Any], name: str) -> list[Any]:
    tables = doc.get(name, [])
    if not isinstance(tables, list):
        fe.add(name, f"expected an array of tables ([[{name}]]), got {_type_name(tables)}")
        return []
    return tables


@dataclass
class FileResult:
    """What one file gave: its errors, its valid buses and devices, the devices the drivers can
    still check, and whether it declared anything at all."""

    fe: FileErrors
    buses: list[BusSpec] = field(default_factory=list)
    devices: list[DeviceSpec] = field(default_factory=list)
    checkable: list[DeviceSpec] = field(default_factory=list)
    empty: bool = False


def read_file(path: Path) -> FileResult:
    res = FileResult(FileErrors(str(path)))
    fe = res.fe
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        fe.add("", f"cannot read the file: {exc}")
        return res
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        m = re.search(r"\(at line (\d+), column \d+\)", str(exc))
        where = f"{fe.path}:{m.group(1)}" if m else fe.path
        fe.errors.append(f"{where}: invalid TOML: {exc}")
        return res
    except RecursionError:
        fe.add("", f"tables or arrays nested too deeply for TOML's parser; expected at most "
                   f"{MAX_DEPTH} levels")
        return res
    fe.bus_lines = _header_lines(text, "bus")
    fe.device_lines = _header_lines(text, "device")
    _unknown_keys(fe, "", doc, TOP_KEYS)
    base = path.parent.resolve()
    bus_tables = _tables(fe, doc, "bus")
    device_tables = _tables(fe, doc, "device")
    res.empty = not bus_tables and not device_tables
    for i, t in enumerate(bus_tables):
        if isinstance(t, dict):
            opts = {k: v for k, v in t.items() if k not in BUS_KEYS}
            if not _check_values(fe, f"bus[{i}]", opts):
                _name(fe, f"bus[{i}]", t)
                continue
        bspec = _parse_bus(fe, i, t, base)
        if bspec is not None:
            res.buses.append(bspec)
    for i, t in enumerate(device_tables):
        if isinstance(t, dict) and "profile" in t:
            specs = _parse_axis(fe, i, t)
            res.devices.extend(specs)
            res.checkable.extend(specs)
            continue
        parsed = _parse_device(fe, i, t, base)
        if parsed.spec is not None:
            res.devices.append(parsed.spec)
        if parsed.checkable is not None:
            res.checkable.append(parsed.checkable)
    return res


def _parse_axis(fe: FileErrors, i: int, table: dict[str, Any]) -> list[DeviceSpec]:
    """An axis table (``profile = "cia402"``): its keys checked (the axis keys by
    :func:`drivers.codecs.cia402.config_from_table`), and the devices it becomes: the actuator
    ``name`` (safe value: the safe stop sequence) and the sensors ``name.state``, ...
    (:mod:`drivers.canopen_axis`). Nothing if any key is wrong."""
    from drivers.canopen_axis import AxisCode
    from drivers.codecs.cia402 import (
        AXIS_KEYS,
        PROFILE,
        READING_OBJECTS,
        AxisReading,
        Cia402Error,
        axis_names,
        config_from_table,
        mode_of,
    )

    key = f"device[{i}]"
    before = len(fe.errors)
    profile = table.get("profile")
    if profile != PROFILE:
        fe.add(f"{key}.profile", f"expected \"{PROFILE}\" (a CiA 402 axis), got {short(profile)}")
        return []
    axis_keys = tuple(k for k in AXIS_KEYS if k != "axis")
    _unknown_keys(fe, key, table, AXIS_TABLE_KEYS + axis_keys)
    name = _name(fe, key, table)
    if name is not None and len(name) + len(".statusword") > MAX_NAME:
        fe.add(f"{key}.name", f"an axis name has at most {MAX_NAME - len('.statusword')} "
                              f"characters (its sensors are name.statusword...), got {len(name)}")
    machine = table.get("machine", 0)
    if not is_int(machine) or not 0 <= machine <= MAX_MACHINE:
        fe.add(f"{key}.machine", f"expected an integer 0..{MAX_MACHINE}, got {short(machine)}")
    bus = table.get("bus")
    if not isinstance(bus, str) or not bus:
        fe.add(f"{key}.bus", f"expected the name of a canopen bus, got {short(bus)}")
    priority = table.get("priority", 8)
    if not is_int(priority) or priority not in PRIORITIES:
        fe.add(f"{key}.priority", f"expected an integer {PRIORITY_TEXT}, got {short(priority)}")
    units = table.get("units", "")
    if not isinstance(units, str) or len(units) > 64:
        fe.add(f"{key}.units", f"expected a string of at most 64 characters, got {short(units)}")
    address = table.get("address")
    node, axis = None, 0
    if not isinstance(address, dict):
        fe.add(f"{key}.address", f"expected {{node = 1..127, axis = 0..7}}, got "
                                 f"{short(address)}")
    else:
        _unknown_keys(fe, f"{key}.address", address, AXIS_ADDRESS_KEYS)
        node = address.get("node")
        if not is_int(node) or not 1 <= node <= 127:
            fe.add(f"{key}.address.node", f"expected a node id 1..127, got {short(node)}")
        axis = address.get("axis", 0)
        if not is_int(axis) or not 0 <= axis <= 7:
            fe.add(f"{key}.address.axis", f"expected an axis number 0..7 (0x800 per axis), "
                                          f"got {short(axis)}")
    mode = None
    if "mode" in table:
        mode = mode_of(table["mode"])
        if mode is None:
            fe.add(f"{key}.mode", f"expected a mode of operation (PP, PV, HM, CSP, CSV... or "
                                  f"its number), got {short(table['mode'])}")
    cfg_table = {k: v for k, v in table.items() if k in axis_keys}
    if _check_values(fe, key, cfg_table):
        try:
            config_from_table(name or "axis", {"axis": axis if is_int(axis) else 0,
                                               **cfg_table}, key)
        except Cia402Error as exc:
            where, _, what = str(exc).partition(": ")
            fe.add(where, what)
    if len(fe.errors) != before or name is None or not isinstance(bus, str):
        return []
    common: dict[str, Any] = {"machine": machine, "bus": bus, "priority": priority,
                              "file": fe.path, "key": key}
    # each device also names the object it shows (index/subindex, as any CANopen device), so
    # what reads CANopen addresses without knowing axes (chcos monitor, chcos sim --from)
    # works on them: the actuator the controlword, each sensor its object
    offset = 0x800 * int(axis)
    actuator = DeviceSpec(name=name, direction="actuator", units="",
                          limits=(float(min(AxisCode)), float(max(AxisCode))),
                          safe_value=float(AxisCode.SAFE_STOP),
                          address={"profile": PROFILE, "node": node, "axis": axis,
                                   "index": 0x6040 + offset, "subindex": 0,
                                   "mode": None if mode is None else int(mode),
                                   "config": cfg_table}, **common)
    sensor_units = {AxisReading.POSITION: units, AxisReading.VELOCITY: f"{units}/s" if units
                    else ""}
    sensors = [DeviceSpec(name=dev, direction="sensor", units=sensor_units.get(r, ""),
                          address={"profile": PROFILE, "node": node, "axis": axis,
                                   "index": READING_OBJECTS[r] + offset, "subindex": 0,
                                   "reading": r.value}, **common)
               for r, dev in axis_names(name).items()]
    return [actuator, *sensors]
