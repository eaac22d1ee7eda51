"""checks - what ``chcos check`` says of a Modbus bus beyond its typed options and addresses
(:mod:`drivers.codecs.modbus_options`): the rules that depend on the device (an actuator's
table, broadcast, text), between the devices of a bus (a one-device TCP server with several
units, a safe value the register type cannot carry), and the warnings of a serial line whose
timing defeats its ``timeout``. Used by both driver kinds' class methods."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from chcos.devices import options as opts
from chcos.devices.spec import BusSpec, DeviceSpec
from drivers.codecs.modbus import (
    READ_REQUEST_BYTES,
    STRING,
    LineTiming,
    answer_bytes,
    plan_reads,
    value_error,
)
from drivers.codecs.modbus_options import (
    ModbusAddress,
    RtuOptions,
    TcpOptions,
    address_of,
    address_rules,
    point_of,
)
from drivers.modbus.config import dead_unit_backoff, sensor_period, try_cost


def parse_device(kind: str, device: DeviceSpec) -> tuple[ModbusAddress | None, list[str]]:
    """``device``'s address parsed, with the rules that depend on the device and the kind;
    ``(address, [])`` or ``(None, errors)``, each error ``"<key path>: <message>"``."""
    path = f"{device.key}.address"
    addr, errors = opts.parse(ModbusAddress, device.address, path)
    if addr is None:
        return None, errors
    found = [f"{path}.{k}: {why}" for k, why in address_rules(addr, device.direction, kind)]
    if device.direction == "actuator" and addr.value_type == STRING:
        found.append(f"{path}.type: a string address is read-only in chcos (a sensor whose "
                     f"value is text); expected a numeric type for an actuator")
    return (None, found) if found else (addr, [])


def device_errors(bus: BusSpec, options: TcpOptions | RtuOptions,
                  devices: Sequence[DeviceSpec]) -> list[tuple[DeviceSpec, str]]:
    """Errors between the devices of a bus: a TCP server declared one device (``server =
    "device"``) whose devices name several units; a safe value the address cannot carry."""
    out: list[tuple[DeviceSpec, str]] = []
    if isinstance(options, TcpOptions) and options.server == "device":
        first = address_of(devices[0]).unit if devices else 0
        for d in devices:
            unit = address_of(d).unit
            if unit != first:
                out.append((d, f"{d.key}.address.unit: expected unit {first} ({bus.key} is "
                               f"one Modbus TCP device: server = \"device\"; a gateway to "
                               f"several units is server = \"gateway\"), got {unit}"))
    for d in devices:
        if d.direction != "actuator" or d.safe_value is None:
            continue
        a = address_of(d)
        if a.scale_factor is not None:
            continue
        raw: Any = (d.safe_value - d.offset) / d.scale
        if d.round:
            raw = round(raw)
        elif isinstance(raw, float) and raw.is_integer():
            raw = int(raw)
        why = value_error(a.value_type, raw, a.count or 0)
        if why is not None:
            out.append((d, f"{d.key}.safe_value: {d.safe_value:g} is raw {raw!r} on the wire "
                           f"(scale and offset): {why}"))
    return out


def line_warnings(options: RtuOptions, devices: Sequence[DeviceSpec]) -> list[str]:
    """A ``timeout`` the line's timing defeats: shorter than the longest exchange (request,
    answer and the silence after each, at the line's baud rate) - that answer never arrives in
    time - or, with several units, a try of the dead ones (``timeout`` x (``retries`` + 1)
    each) longer than the poll period - the live units miss polls at each try."""
    line = LineTiming(options.baudrate, options.bytesize, options.parity, options.stopbits)
    points = [point_of(d) for d in devices]
    reads = plan_reads([p for p, d in zip(points, devices, strict=True)
                        if d.direction == "sensor"])
    longest = max([line.exchange_time(READ_REQUEST_BYTES, answer_bytes(r)) for r in reads]
                  + [line.exchange_time(READ_REQUEST_BYTES + 2 * p.size + 1, 8)
                     for p, d in zip(points, devices, strict=True)
                     if d.direction == "actuator"], default=0.0)
    timeout = options.timeout
    out = []
    if longest > timeout:
        out.append(f"timeout: {timeout:g} s is shorter than the longest exchange on the line "
                   f"({longest * 1e3:.1f} ms at {line.baudrate} baud with the 3.5-character "
                   f"silences): that answer can never arrive in time")
    units = {p.unit for p in points if not p.broadcast}
    cost = try_cost(options)
    periods = [sensor_period(options, d) for d in devices if d.direction == "sensor"]
    period = min(periods, default=options.probe_period())
    if len(units) > 1 and cost * (len(units) - 1) > period:
        out.append(f"timeout: a unit that does not answer holds the line {cost:g} s per try "
                   f"(timeout x (retries + 1), then what is left of line_guard), "
                   f"{len(units) - 1} such unit(s) "
                   f"{cost * (len(units) - 1):g} s, longer than the poll period {period:g} s: "
                   f"while units are dead the live ones miss polls at each try (a dead unit is "
                   f"tried at most every {dead_unit_backoff(options)} poll periods, "
                   f"dead_unit_backoff)")
    return out
