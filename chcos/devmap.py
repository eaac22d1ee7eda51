"""devmap - load and validate device-map files (TOML) into a :class:`chcos.devspec.DeviceMap`.

A device map lists the field buses of a cell and the sensors and actuators on them (the thesis'
device list, section 6.2). Several files may be loaded together (one per cell, per satellite...);
they are validated as a whole, and an invalid set is rejected whole: :func:`load` collects every
error of every file and raises one :class:`chcos.errors.ConfigError` listing them.

Schema (see also ``busconfig/README.md``)::

    [[bus]]
    name = "line1"          # unique across all files loaded together
    kind = "can"            # driver registry key: memory, signal, can, canopen, modbus-tcp, ...
    # ... kind-specific options, checked by the driver's check_bus()

    [[device]]
    name = "S1"             # unique across all files
    direction = "sensor"    # "sensor" | "actuator"
    machine = 0             # satellite the device is attached to; int >= 0, default 0
    bus = "line1"           # a bus declared in any of the files
    address = { message = "Temps", signal = "T1" }   # kind-specific, checked by check_device()
    priority = 8            # interrupt priority 0..99, default 8
    stale_after = 0.5       # seconds; sensors only; > 0; absent: never stale
    scale = 1.0             # engineering = raw * scale + offset; non-zero; default 1.0
    offset = 0.0            # default 0.0
    limits = [-inf, 120.0]  # engineering units, inclusive; TOML's -inf / inf leaves an end open
    safe_value = 0.0        # actuators only; must lie within limits
    units = "degC"          # free text, default ""
    north_writable = false  # actuators only: the Modbus/OPC UA facades may command it

Top-level keys other than ``bus`` and ``device`` are rejected. Option keys that name files
(``dbc``, ``eds``, ``record``, and any key ending in ``_file`` or ``_path``, in bus options and in
device addresses) are resolved against the directory of the file that contains them and stored
absolute.

Error lines look like ``cell.toml:14: device[2].limits: expected lo <= hi, got [5.0, 1.0]``; the
line is the one of the ``[[bus]]``/``[[device]]`` header (or tomllib's syntax-error line) and is
left out where it is not known (inline arrays of tables). ``device[2]`` counts devices from 0
within that file.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
import tomllib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from chcos.devspec import BusSpec, DeviceMap, DeviceSpec, Direction
from chcos.errors import ConfigError, DriverNotAvailable
from drivers.base import Driver
from drivers.registry import driver_class

BUS_KEYS = ("name", "kind")
DEVICE_KEYS = ("name", "direction", "machine", "bus", "address", "priority", "stale_after",
               "scale", "offset", "limits", "safe_value", "units", "north_writable")
TOP_KEYS = ("bus", "device")
PATH_KEYS = frozenset({"dbc", "eds", "record"})
_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")


@dataclass
class _FileErrors:
    """Errors of one file, each prefixed with the file name and (when known) the line."""

    path: str
    bus_lines: list[int] = field(default_factory=list)
    device_lines: list[int] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)

    def add(self, key: str, message: str) -> None:
        """Record ``key: message`` at the line of the table ``key`` starts with."""
        line = self._line(key)
        where = f"{self.path}:{line}" if line else self.path
        self.errors.append(f"{where}: {key}: {message}" if key else f"{where}: {message}")

    def _line(self, key: str) -> int | None:
        m = re.match(r"^(bus|device)\[(\d+)\]", key)
        if not m:
            return None
        lines = self.bus_lines if m.group(1) == "bus" else self.device_lines
        i = int(m.group(2))
        return lines[i] if i < len(lines) else None


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


def _is_number(v: object) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _type_name(v: object) -> str:
    return {bool: "boolean", int: "integer", float: "float", str: "string", list: "array",
            dict: "table"}.get(type(v), type(v).__name__)


def _unknown_keys(fe: _FileErrors, key: str, table: Mapping[str, Any],
                  valid: Sequence[str]) -> None:
    for k in table:
        if k not in valid:
            fe.add(key, f"unknown key {k!r}; valid keys: {', '.join(valid)}")


def _name(fe: _FileErrors, key: str, table: Mapping[str, Any]) -> str | None:
    v = table.get("name")
    if v is None:
        fe.add(f"{key}.name", "missing; expected a name (letters, digits, _ . -)")
        return None
    if not isinstance(v, str) or not _NAME_RE.match(v):
        fe.add(f"{key}.name", f"expected a name of letters, digits, _ . - starting with a letter "
                              f"or _, got {v!r}")
        return None
    return v


def _parse_bus(fe: _FileErrors, i: int, table: Any, base: Path) -> BusSpec | None:
    key = f"bus[{i}]"
    if not isinstance(table, dict):
        fe.add(key, f"expected a table, got {_type_name(table)}")
        return None
    name = _name(fe, key, table)
    kind = table.get("kind")
    if not isinstance(kind, str) or not kind:
        fe.add(f"{key}.kind", f"expected a bus kind string (memory, signal, can, canopen, "
                              f"modbus-tcp, modbus-rtu, serial), got {kind!r}")
        return None
    if name is None:
        return None
    options = _resolve_paths({k: v for k, v in table.items() if k not in BUS_KEYS}, base)
    return BusSpec(name=name, kind=kind, options=options, file=fe.path, key=key)


def _number(fe: _FileErrors, key: str, v: object) -> float | None:
    if not _is_number(v):
        fe.add(key, f"expected a number, got {_type_name(v)} {v!r}")
        return None
    f = float(v)  # type: ignore[arg-type]
    if math.isnan(f):
        fe.add(key, "expected a number, got nan")
        return None
    return f


def _limits(fe: _FileErrors, key: str, v: object) -> tuple[float | None, float | None] | None:
    if not (isinstance(v, list) and len(v) == 2):
        fe.add(key, f"expected [lo, hi] (use -inf / inf for an open end), got {v!r}")
        return None
    lo = _number(fe, f"{key}[0]", v[0])
    hi = _number(fe, f"{key}[1]", v[1])
    if lo is None or hi is None:
        return None
    if lo == math.inf or hi == -math.inf:
        fe.add(key, f"expected lo < inf and hi > -inf, got {v!r}")
        return None
    if lo > hi:
        fe.add(key, f"expected lo <= hi, got {v!r}")
        return None
    return (None if lo == -math.inf else lo, None if hi == math.inf else hi)


def _parse_device(fe: _FileErrors, i: int, table: Any, base: Path) -> DeviceSpec | None:
    key = f"device[{i}]"
    if not isinstance(table, dict):
        fe.add(key, f"expected a table, got {_type_name(table)}")
        return None
    before = len(fe.errors)
    _unknown_keys(fe, key, table, DEVICE_KEYS)
    name = _name(fe, key, table)
    direction = table.get("direction")
    if direction not in ("sensor", "actuator"):
        fe.add(f"{key}.direction", f"expected \"sensor\" or \"actuator\", got {direction!r}")
    machine = table.get("machine", 0)
    if not isinstance(machine, int) or isinstance(machine, bool) or machine < 0:
        fe.add(f"{key}.machine", f"expected an integer >= 0, got {machine!r}")
    bus = table.get("bus")
    if not isinstance(bus, str) or not bus:
        fe.add(f"{key}.bus", f"expected the name of a bus, got {bus!r}")
    address = table.get("address", {})
    if not isinstance(address, dict):
        fe.add(f"{key}.address", f"expected an inline table, got {_type_name(address)}")
    priority = table.get("priority", 8)
    if not isinstance(priority, int) or isinstance(priority, bool) or not 0 <= priority <= 99:
        fe.add(f"{key}.priority", f"expected an integer 0..99, got {priority!r}")
    stale: float | None = None
    if "stale_after" in table:
        stale = _number(fe, f"{key}.stale_after", table["stale_after"])
        if stale is not None and stale <= 0:
            fe.add(f"{key}.stale_after", f"expected seconds > 0, got {stale!r}")
        if direction == "actuator":
            fe.add(f"{key}.stale_after", "applies to sensors only; remove it from an actuator")
    scale = _number(fe, f"{key}.scale", table.get("scale", 1.0))
    if scale == 0.0:
        fe.add(f"{key}.scale", "expected a non-zero number (actuator raw = (value-offset)/scale)")
    offset = _number(fe, f"{key}.offset", table.get("offset", 0.0))
    limits: tuple[float | None, float | None] | None = (None, None)
    if "limits" in table:
        limits = _limits(fe, f"{key}.limits", table["limits"])
    safe: float | None = None
    if "safe_value" in table:
        safe = _number(fe, f"{key}.safe_value", table["safe_value"])
        if direction == "sensor":
            fe.add(f"{key}.safe_value", "applies to actuators only; remove it from a sensor")
        if safe is not None and limits is not None:
            lo, hi = limits
            if (lo is not None and safe < lo) or (hi is not None and safe > hi):
                fe.add(f"{key}.safe_value", f"expected a value within limits "
                                            f"{list(table['limits'])}, got {safe!r}")
    units = table.get("units", "")
    if not isinstance(units, str):
        fe.add(f"{key}.units", f"expected a string, got {_type_name(units)}")
    north = table.get("north_writable", False)
    if not isinstance(north, bool):
        fe.add(f"{key}.north_writable", f"expected true or false, got {north!r}")
    elif north and direction == "sensor":
        fe.add(f"{key}.north_writable", "applies to actuators only; remove it from a sensor")
    if len(fe.errors) != before or name is None or limits is None or not isinstance(bus, str):
        return None
    dir_: Direction = "sensor" if direction == "sensor" else "actuator"
    return DeviceSpec(name=name, direction=dir_, machine=machine, bus=bus, priority=priority,
                      address=_resolve_paths(address, base), stale_after=stale,
                      scale=scale if scale is not None else 1.0,
                      offset=offset if offset is not None else 0.0, limits=limits,
                      safe_value=safe, units=units, file=fe.path, key=key,
                      north_writable=north is True)


def _tables(fe: _FileErrors, doc: Mapping[str, Any], name: str) -> list[Any]:
    tables = doc.get(name, [])
    if not isinstance(tables, list):
        fe.add(name, f"expected an array of tables ([[{name}]]), got {_type_name(tables)}")
        return []
    return tables


def _read_file(path: Path) -> tuple[_FileErrors, list[BusSpec], list[DeviceSpec]]:
    fe = _FileErrors(str(path))
    buses: list[BusSpec] = []
    devices: list[DeviceSpec] = []
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        fe.add("", f"cannot read the file: {exc}")
        return fe, buses, devices
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        m = re.search(r"\(at line (\d+), column \d+\)", str(exc))
        where = f"{fe.path}:{m.group(1)}" if m else fe.path
        fe.errors.append(f"{where}: invalid TOML: {exc}")
        return fe, buses, devices
    fe.bus_lines = _header_lines(text, "bus")
    fe.device_lines = _header_lines(text, "device")
    _unknown_keys(fe, "", doc, TOP_KEYS)
    base = path.parent.resolve()
    for i, t in enumerate(_tables(fe, doc, "bus")):
        bspec = _parse_bus(fe, i, t, base)
        if bspec is not None:
            buses.append(bspec)
    for i, t in enumerate(_tables(fe, doc, "device")):
        dspec = _parse_device(fe, i, t, base)
        if dspec is not None:
            devices.append(dspec)
    return fe, buses, devices


def _driver_checks(fe_by_file: Mapping[str, _FileErrors], buses: Sequence[BusSpec],
                   devices: Sequence[DeviceSpec]) -> None:
    """Run each bus kind's check_bus / check_device; normalise their key paths."""
    classes: dict[str, type[Driver] | None] = {}
    for b in buses:
        fe = fe_by_file[b.file]
        try:
            cls: type[Driver] | None = driver_class(b.kind)
        except DriverNotAvailable as exc:
            fe.add(f"{b.key}.kind", f"bus kind {b.kind!r} has no usable driver: {exc}")
            cls = None
        classes[b.name] = cls
        if cls is not None:
            for msg in cls.check_bus(b):
                fe.add(*_split(msg, b.key, ""))
    by_name = {b.name: b for b in buses}
    for d in devices:
        bus = by_name.get(d.bus)
        cls = classes.get(d.bus)
        if bus is None or cls is None:
            continue
        for msg in cls.check_device(bus, d):
            fe_by_file[d.file].add(*_split(msg, d.key, "address."))


def _split(msg: str, prefix: str, relative: str) -> tuple[str, str]:
    """Split a driver's ``"<key path>: <expectation>"`` into (full key path, expectation).

    Drivers may give the full path (``device[3].address.signal``), a path from the device
    (``address.signal``) or one relative to the options/address (``signal``)."""
    key, sep, rest = msg.partition(": ")
    if not sep:
        return prefix, msg
    if key.startswith(prefix + ".") or key == prefix:
        return key, rest
    if relative and key.startswith(relative.rstrip(".")):
        return f"{prefix}.{key}", rest
    return f"{prefix}.{relative}{key}", rest


def load(paths: str | Path | Iterable[str | Path]) -> DeviceMap:
    """Load device-map file(s) and validate them as a whole.

    Raises :class:`chcos.errors.ConfigError` listing every error found (unreadable files, TOML
    syntax, unknown keys, wrong types, duplicate names, unknown buses, unavailable driver kinds,
    kind-specific errors from the drivers' ``check_bus``/``check_device``). Never opens a bus.
    """
    plist = [Path(paths)] if isinstance(paths, str | Path) else [Path(p) for p in paths]
    if not plist:
        raise ConfigError("no device-map files given; expected at least one .toml path")
    fe_by_file: dict[str, _FileErrors] = {}
    buses: list[BusSpec] = []
    devices: list[DeviceSpec] = []
    for p in plist:
        fe, file_buses, file_devices = _read_file(p)
        fe_by_file.setdefault(fe.path, fe)
        if fe_by_file[fe.path] is not fe:
            fe_by_file[fe.path].add("", "file given twice")
            continue
        buses.extend(file_buses)
        devices.extend(file_devices)
    seen_bus: dict[str, BusSpec] = {}
    for b in buses:
        if b.name in seen_bus:
            first = seen_bus[b.name]
            fe_by_file[b.file].add(f"{b.key}.name", f"bus name {b.name!r} is already used by "
                                                    f"{first.file} {first.key}; expected unique")
        else:
            seen_bus[b.name] = b
    seen_dev: dict[str, DeviceSpec] = {}
    for d in devices:
        if d.name in seen_dev:
            first_d = seen_dev[d.name]
            fe_by_file[d.file].add(f"{d.key}.name", f"device name {d.name!r} is already used by "
                                                    f"{first_d.file} {first_d.key}; expected "
                                                    f"unique")
        else:
            seen_dev[d.name] = d
        if d.bus not in seen_bus:
            fe_by_file[d.file].add(f"{d.key}.bus", f"no bus named {d.bus!r}; expected one of: "
                                                   f"{', '.join(seen_bus) or 'no buses declared'}")
    _driver_checks(fe_by_file, list(seen_bus.values()),
                   [d for d in devices if seen_dev.get(d.name) is d])
    errors = [e for fe in fe_by_file.values() for e in fe.errors]
    if errors:
        raise ConfigError(f"{len(errors)} error(s) in device map "
                          f"{', '.join(fe_by_file)}:\n" + "\n".join(errors))
    return DeviceMap(buses=tuple(buses), devices=tuple(devices), files=tuple(fe_by_file))


def check_main(argv: list[str]) -> int:
    """``chcos check FILE...``: validate device-map files without opening any bus.

    Prints ``ok: N buses, M devices`` and returns 0, or prints every error and returns 1."""
    parser = argparse.ArgumentParser(prog="chcos check",
                                     description="validate device-map files (no bus is opened)")
    parser.add_argument("files", nargs="+", help="device-map TOML files, checked together")
    args = parser.parse_args(argv)
    try:
        dmap = load(args.files)
    except ConfigError as exc:
        print(str(exc), file=sys.stderr)
        return 1
    print(f"ok: {len(dmap.buses)} buses, {len(dmap.devices)} devices")
    return 0
