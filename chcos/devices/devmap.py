"""devmap - load and validate device-map files (TOML) into a :class:`chcos.devices.spec.DeviceMap`.

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
    round = false           # actuators only: round the raw value to an integer (else refused)
    north_writable = false  # actuators only: the Modbus/OPC UA facades may command it

Top-level keys other than ``bus`` and ``device`` are rejected. Option keys that name files
(``dbc``, ``eds``, ``record``, and any key ending in ``_file`` or ``_path``, in bus options and in
device addresses) are resolved against the directory of the file that contains them and stored
absolute.

Each file is read and parsed by :mod:`chcos.devices.mapparse`; this module checks the files
together (unique names, buses declared in any file, the drivers' own checks and warnings).
Error lines look like ``cell.toml:14: device[2].limits: expected lo <= hi, got [5.0, 1.0]``; the
line is the one of the ``[[bus]]``/``[[device]]`` header (or tomllib's syntax-error line) and is
left out where it is not known (inline arrays of tables). ``device[2]`` counts devices from 0
within that file.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

from chcos.devices import parsecache
from chcos.devices.driver import Driver
from chcos.devices.mapparse import FileErrors, read_file, short
from chcos.devices.registry import driver_class
from chcos.devices.spec import BusSpec, DeviceMap, DeviceSpec
from chcos.errors import ConfigError, DriverNotAvailable

T = TypeVar("T")


def _guarded(fe: FileErrors, key: str, fn: Callable[..., Iterable[T]], *args: Any) -> list[T]:
    """``fn(*args)`` (a driver's check), its failure recorded as an error of ``key`` rather than
    raised: a driver that cannot check a value must not end ``chcos check`` in a traceback."""
    try:
        return list(fn(*args))
    except Exception as exc:  # any driver bug becomes an error naming the key
        fe.add(key, f"could not be checked ({type(exc).__name__}: {exc}); expected a value "
                    f"the {getattr(fn, '__qualname__', 'driver')} check accepts")
        return []


def _parse_into(parse: Callable[..., tuple[Any, list[str]]], into: list[Any],
                *args: Any) -> list[str]:
    """``parse(*args)`` (a driver's ``parse_bus``/``parse_device``): its errors returned, its
    parsed value appended to ``into``."""
    value, errors = parse(*args)
    into.append(value)
    return errors


def _driver_checks(fe_by_file: Mapping[str, FileErrors], buses: Sequence[BusSpec],
                   devices: Sequence[DeviceSpec], configs: dict[int, Any]) -> tuple[
                       dict[str, type[Driver] | None], set[int]]:
    """Run each bus kind's parse_bus / parse_device (its check_bus / check_device), then its
    check_devices over the devices of each bus that passed; normalise their key paths. Returns
    the driver class of each bus (None where the kind has no usable driver or the bus is
    invalid) and the ids of the devices whose address the driver refused; ``configs`` gets the
    typed options and addresses parsed, by the id of their spec."""
    classes: dict[str, type[Driver] | None] = {}
    refused: set[int] = set()
    for b in buses:
        fe = fe_by_file[b.file]
        try:
            cls: type[Driver] | None = driver_class(b.kind)
        except DriverNotAvailable as exc:
            fe.add(f"{b.key}.kind", f"bus kind {short(b.kind)} has no usable driver: {exc}")
            cls = None
        classes[b.name] = cls
        if cls is not None:
            parsed: list[Any] = []
            msgs = _guarded(fe, b.key, _parse_into, cls.parse_bus, parsed, b)
            if parsed and parsed[0] is not None:
                configs[id(b)] = parsed[0]
            for msg in msgs:
                fe.add(*_split(msg, b.key, ""))
            if msgs:
                classes[b.name] = None
    by_name = {b.name: b for b in buses}
    for d in devices:
        bus = by_name.get(d.bus)
        cls = classes.get(d.bus)
        if bus is None or cls is None:
            continue
        fe = fe_by_file[d.file]
        before = len(fe.errors)
        got: list[Any] = []
        for msg in _guarded(fe, f"{d.key}.address", _parse_into, cls.parse_device, got, bus, d):
            fe.add(*_split(msg, d.key, "address."))
        if got and got[0] is not None and len(fe.errors) == before:
            configs[id(d)] = got[0]
        if len(fe.errors) != before:
            refused.add(id(d))
    on_bus: dict[str, list[DeviceSpec]] = {}
    for d in devices:
        if classes.get(d.bus) is not None and id(d) not in refused:
            on_bus.setdefault(d.bus, []).append(d)
    for name, ds in on_bus.items():
        bus, cls = by_name[name], classes[name]
        assert cls is not None
        for d, msg in _guarded(fe_by_file[bus.file], bus.key, cls.check_devices, bus, ds):
            fe_by_file[d.file].add(*_split(msg, d.key, "address."))
            refused.add(id(d))
    return classes, refused


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


def _fmt(x: float) -> str:
    return f"{x:g}"


def _warnings(fe_by_file: Mapping[str, FileErrors], buses: Mapping[str, BusSpec],
              classes: Mapping[str, type[Driver] | None], devices: Sequence[DeviceSpec],
              empty: Sequence[str]) -> list[str]:
    """What is legal but bound to misbehave: a file that declares nothing, ``stale_after``
    shorter than the poll period, an actuator without a safe value, limits the address type
    cannot carry. Each warning names the file, line and key like an error."""
    out: list[str] = [f"{path}: declares no bus and no device; expected [[bus]] and [[device]] "
                      f"tables" for path in empty]
    for d in devices:
        fe = fe_by_file[d.file]
        before = len(fe.errors)
        bus = buses.get(d.bus)
        cls = classes.get(d.bus)
        if d.direction == "actuator" and d.safe_value is None and not d.safe_reason:
            fe.add(f"{d.key}.safe_value", "actuator has no safe value: e-stop, abnormal "
                                          "completion and shutdown leave it at its last command")
        if bus is not None and cls is not None:
            try:
                period = cls.poll_period(bus, d) if d.direction == "sensor" else None
                raw = cls.encodable(bus, d) if d.direction == "actuator" else None
            except Exception as exc:  # a driver bug must not end the check
                fe.add(d.key, f"could not be checked ({type(exc).__name__}: {exc})")
                period = raw = None
            if period is not None and d.stale_after is not None and d.stale_after < period:
                fe.add(f"{d.key}.stale_after", f"{_fmt(d.stale_after)} s is shorter than the "
                                               f"poll period {_fmt(period)} s: the sensor goes "
                                               f"stale between two polls")
            if raw is not None:
                ends = sorted((raw[0] * d.scale + d.offset, raw[1] * d.scale + d.offset))
                lo, hi = d.limits
                if lo is None or hi is None or lo < ends[0] or hi > ends[1]:
                    shown = f"[{'-inf' if lo is None else _fmt(lo)}, " \
                            f"{'inf' if hi is None else _fmt(hi)}]"
                    fe.add(f"{d.key}.limits", f"{shown} reach outside what the address can "
                                              f"carry ([{_fmt(ends[0])}, {_fmt(ends[1])}] after "
                                              f"scale and offset): such writes fail on the bus")
        out.extend(fe.errors[before:])
        del fe.errors[before:]
    for name, bus in buses.items():    # the drivers' own warnings about a bus as a whole
        cls = classes.get(name)
        if cls is None:
            continue
        fe = fe_by_file[bus.file]
        before = len(fe.errors)
        try:
            found = cls.check_warnings(bus, [d for d in devices if d.bus == name])
        except Exception as exc:  # a driver bug must not end the check
            found = [f"could not be checked ({type(exc).__name__}: {exc})"]
        for msg in found:
            fe.add(*_split(msg, bus.key, ""))
        out.extend(fe.errors[before:])
        del fe.errors[before:]
    return out


def check(paths: str | Path | Iterable[str | Path]) -> tuple[DeviceMap | None, list[str],
                                                             list[str]]:
    """Validate device-map file(s) as a whole without opening a bus.

    Returns ``(map or None, errors, warnings)``: every error of every file (general keys and
    the drivers' address checks in one pass), and the warnings of :func:`_warnings` for the
    devices that are valid. The map is None when there is any error. Never raises for a bad
    file: every problem is a line naming the file, line and key."""
    plist = [Path(paths)] if isinstance(paths, str | Path) else [Path(p) for p in paths]
    if not plist:
        return None, ["no device-map files given; expected at least one .toml path"], []
    fe_by_file: dict[str, FileErrors] = {}
    buses: list[BusSpec] = []
    devices: list[DeviceSpec] = []
    checkable: list[DeviceSpec] = []
    empty: list[str] = []
    for p in plist:
        res = read_file(p)
        fe = res.fe
        fe_by_file.setdefault(fe.path, fe)
        if fe_by_file[fe.path] is not fe:
            fe_by_file[fe.path].add("", "file given twice")
            continue
        buses.extend(res.buses)
        devices.extend(res.devices)
        checkable.extend(res.checkable)
        if res.empty and not fe.errors:
            empty.append(fe.path)
    seen_bus: dict[str, BusSpec] = {}
    for b in buses:
        if b.name in seen_bus:
            first = seen_bus[b.name]
            fe_by_file[b.file].add(f"{b.key}.name", f"bus name {b.name!r} is already used by "
                                                    f"{first.file} {first.key}; expected unique")
        else:
            seen_bus[b.name] = b
    seen_dev: dict[str, DeviceSpec] = {}
    for d in checkable:
        if d.name in seen_dev:
            first_d = seen_dev[d.name]
            fe_by_file[d.file].add(f"{d.key}.name", f"device name {d.name!r} is already used by "
                                                    f"{first_d.file} {first_d.key}; expected "
                                                    f"unique")
        else:
            seen_dev[d.name] = d
        if d.bus not in seen_bus:
            fe_by_file[d.file].add(f"{d.key}.bus",
                                   f"no bus named {short(d.bus)}; expected one of: "
                                   f"{', '.join(seen_bus) or 'no buses declared'}")
    configs: dict[int, Any] = {}
    with parsecache.scope():   # each DBC / EDS file parsed once, not once per device
        classes, refused = _driver_checks(fe_by_file, list(seen_bus.values()), checkable,
                                          configs)
        listed = {id(d) for d in devices}
        valid = [d for d in checkable if id(d) in listed and id(d) not in refused]
        if configs:    # the typed options and addresses travel with the specs
            buses, devices, valid = (_typed(buses, configs), _typed(devices, configs),
                                     _typed(valid, configs))
            seen_bus = {name: _typed([b], configs)[0] for name, b in seen_bus.items()}
        warnings = _warnings(fe_by_file, seen_bus, classes, valid, empty)
    errors = [e for fe in fe_by_file.values() for e in fe.errors]
    if errors:
        return None, errors, warnings
    return (DeviceMap(buses=tuple(buses), devices=tuple(devices), files=tuple(fe_by_file),
                      warnings=tuple(warnings)), [], warnings)


S = TypeVar("S", BusSpec, DeviceSpec)


def _typed(specs: Sequence[S], configs: dict[int, Any]) -> list[S]:
    """``specs`` with their parsed options (a bus's ``config``, a device's ``addr``) set."""
    out: list[S] = []
    for spec in specs:
        value = configs.get(id(spec))
        if value is None:
            out.append(spec)
        else:
            field = "config" if isinstance(spec, BusSpec) else "addr"
            out.append(dataclasses.replace(spec, **{field: value}))
    return out


def load(paths: str | Path | Iterable[str | Path]) -> DeviceMap:
    """Load device-map file(s) and validate them as a whole.

    Raises :class:`chcos.errors.ConfigError` listing every error found (unreadable files, TOML
    syntax, unknown keys, wrong types, values out of range, duplicate names, unknown buses,
    unavailable driver kinds, kind-specific errors from the drivers' ``check_bus``/
    ``check_device``). Never opens a bus. The map's ``warnings`` hold what :func:`check` warns
    about."""
    dmap, errors, _ = check(paths)
    if dmap is None:
        files = [str(p) for p in ([paths] if isinstance(paths, str | Path) else paths)]
        raise ConfigError(f"{len(errors)} error(s) in device map {', '.join(files)}:\n"
                          + "\n".join(errors))
    return dmap


def check_main(argv: list[str]) -> int:
    """``chcos check FILE...``: validate device-map files without opening any bus.

    Prints every warning (``warning: file:line: key: ...``) and then ``ok: N buses, M devices``
    and returns 0, or prints every error (and warning) and returns 1."""
    parser = argparse.ArgumentParser(prog="chcos check",
                                     description="validate device-map files (no bus is opened); "
                                                 "warns about maps that are legal but misbehave")
    parser.add_argument("files", nargs="+", help="device-map TOML files, checked together")
    args = parser.parse_args(argv)
    dmap, errors, warnings = check(args.files)
    for w in warnings:
        print(f"warning: {w}", file=sys.stderr)
    if dmap is None:
        print(f"{len(errors)} error(s) in device map {', '.join(args.files)}:\n"
              + "\n".join(errors), file=sys.stderr)
        return 1
    print(f"ok: {len(dmap.buses)} buses, {len(dmap.devices)} devices"
          + (f", {len(warnings)} warning(s)" if warnings else ""))
    return 0
