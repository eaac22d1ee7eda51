"""The device-map reference (chcos/devices/mapref.py, docs/device-map-reference.md) against the
drivers
themselves: every key a driver's check accepts is listed, every listed key is accepted, and the
committed page is what the generator writes now. The candidate keys are every identifier-like
string in the drivers' source, so a driver that starts accepting a new key fails here."""

from __future__ import annotations

import ast
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from chcos.devices import mapparse, mapref
from chcos.devices.spec import BusSpec, DeviceSpec
from drivers import canopen_od
from drivers.registry import driver_class

ROOT = Path(__file__).resolve().parent.parent
EDS = ROOT / "chcos" / "apps" / "sim" / "eds" / "servo_drive.eds"
DBC = ROOT / "busconfig" / "examples" / "cell.dbc"


def _candidates() -> set[str]:
    words: set[str] = set()
    for path in (ROOT / "drivers").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) \
                    and re.fullmatch(r"[a-z][a-z0-9_]{0,30}", node.value):
                words.add(node.value)
    for kind in mapref.kinds().values():
        words |= {k.name for k in (*kind.options, *kind.address)}
    return words


CANDIDATES = sorted(_candidates())
# (bus options, device direction, address) contexts that reach each driver's key checks
BUS_CONTEXTS: dict[str, list[dict[str, Any]]] = {
    "memory": [{}], "signal": [{}], "weld-direct": [{}],
    "can": [{"interface": "virtual", "channel": "x"}],
    "canopen": [{"interface": "virtual", "channel": "x", "nodes": [{"id": 1, "eds": str(EDS)}]}],
    "modbus-tcp": [{"host": "127.0.0.1"}], "modbus-rtu": [{"port": "socket://127.0.0.1:1"}],
    "serial": [{"url": "loop://", "protocol": "line", "pattern": "(?P<w>.*)"},
               {"url": "loop://", "protocol": "binary", "sync": "AA", "struct": "<h",
                "fields": ["w"]}],
}
ADDRESS_CONTEXTS: dict[str, list[tuple[int, str, dict[str, Any], dict[str, Any]]]] = {
    "memory": [(0, "sensor", {}, {})], "weld-direct": [(0, "sensor", {}, {"signal": "linear"})],
    "signal": [(0, "sensor", {}, {"waveform": "sine", "rate_hz": 1}),
               (0, "sensor", {}, {"waveform": "echo", "rate_hz": 1, "actuator": "A"})],
    "can": [(0, "sensor", {}, {"id": 1, "start": 0, "length": 8}),
            (0, "sensor", {"dbc": str(DBC)}, {"message": "Temps", "signal": "T1"})],
    "canopen": [(0, "sensor", {}, {"node": 1, "index": 0x6064})],
    "modbus-tcp": [(0, "sensor", {}, {"table": "input", "address": 0})],
    "modbus-rtu": [(0, "sensor", {}, {"table": "input", "address": 0})],
    "serial": [(0, "sensor", {}, {"group": "w"}), (0, "actuator", {}, {"format": "{value}"}),
               (1, "sensor", {}, {"field": "w"}), (1, "actuator", {}, {"struct": "<h"})],
}


def _unknown(errors: list[str], key: str) -> bool:
    return any(re.search(rf"\.{re.escape(key)}: unknown (key|option)", e) for e in errors)


def _accepted_bus_keys(kind: str) -> Iterator[str]:
    cls = driver_class(kind)
    for base in BUS_CONTEXTS[kind]:
        for key in CANDIDATES:
            if key in base:
                yield key
                continue
            errs = cls.check_bus(BusSpec("b", kind, {**base, key: object()}, "f", "bus[0]"))
            if not _unknown(errs, key):
                yield key


def _accepted_address_keys(kind: str) -> Iterator[str]:
    cls = driver_class(kind)
    for ctx, direction, extra, base in ADDRESS_CONTEXTS[kind]:
        bus = BusSpec("b", kind, {**BUS_CONTEXTS[kind][ctx], **extra}, "f", "bus[0]")
        for key in CANDIDATES:
            if key in base:
                yield key
                continue
            dev = DeviceSpec("d", direction, 0, "b", {**base, key: object()}, file="f",  # type: ignore[arg-type]
                             key="device[0]")
            if not _unknown(cls.check_device(bus, dev), key):
                yield key


@pytest.mark.parametrize("kind", sorted(mapref.DOCS))
def test_every_key_a_driver_accepts_is_in_the_reference(kind: str) -> None:
    ref = mapref.kinds()[kind]
    bus_keys = set(_accepted_bus_keys(kind))
    listed = {k.name for k in ref.options}
    assert bus_keys - listed == set(), f"{kind}: bus options accepted but not in the reference"
    # the canopen nodes[] keys (and their config table's) are checked by check_bus inside the
    # nodes table
    assert listed - bus_keys <= {k.name for k in ref.options
                                 if k.variant.startswith("nodes[]")}, f"{kind}: listed but refused"
    addr = set(_accepted_address_keys(kind))
    listed_addr = {k.name for k in ref.address}
    assert addr - listed_addr == set(), f"{kind}: address keys accepted but not listed"
    assert listed_addr - addr == set(), f"{kind}: address keys listed but refused"


def test_canopen_node_keys_and_common_keys() -> None:

    listed = {k.name for k in mapref.kinds()["canopen"].options if k.variant == "nodes[]"}
    assert listed == set(canopen_od.NODE_KEYS)
    assert [k.name for k in mapref.COMMON["bus"]] == list(mapparse.BUS_KEYS)
    assert [k.name for k in mapref.COMMON["device"]] == list(mapparse.DEVICE_KEYS)


def test_every_registered_kind_is_documented() -> None:
    from importlib.metadata import entry_points

    kinds = {ep.name for ep in entry_points(group="chcos.drivers")}
    assert kinds == set(mapref.DOCS)


@pytest.mark.parametrize("kind", sorted(mapref.DOCS))
def test_a_typed_table_is_documented_from_its_fields_only(kind: str) -> None:
    """One copy of a key: a kind whose driver declares option dataclasses has no hand-written
    table left in mapref.DOCS (a bus engineer converting a kind sets it to None there)."""
    cls = driver_class(kind)
    doc = mapref.DOCS[kind]
    if cls.Options is not None:
        assert doc.options is None, f"{kind}: delete its hand-written options in mapref.DOCS"
    if cls.Address is not None or cls.Addresses:
        assert doc.address is None, f"{kind}: delete its hand-written address in mapref.DOCS"


def test_the_reference_of_a_typed_kind_is_its_fields() -> None:
    """The rows come from the dataclasses: a field's default, unit and variant, the keys
    shared by the variants once."""
    signal = {(k.name, k.variant): k for k in mapref.kinds()["signal"].address}
    assert ("waveform", "") in signal and ("rate_hz", "") in signal
    assert signal[("value", "waveform")].default == "center"
    assert signal[("value", "echo")].default == "0.0"
    assert signal[("actuator", "echo")].default == "required"
    assert signal[("period", "waveform")].type == "float s"
    weld = {k.name: k for k in mapref.kinds()["weld-direct"].options}
    assert list(weld) == ["scenario", "seed", "tick"] and weld["tick"].default == "0.01"


def test_the_devices_layer_finds_the_drivers_by_kind_without_importing_them() -> None:
    """mapref reaches the drivers through the registry's entry points: no import statement
    of the device layer names a driver module (test_layers checks the whole graph)."""
    import ast

    for path in (ROOT / "chcos" / "devices").glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module and path.name != "mapparse.py":
                assert not node.module.startswith("drivers"), f"{path.name}: {node.module}"


def test_the_committed_page_is_current() -> None:
    page = (ROOT / "docs" / "device-map-reference.md").read_text(encoding="utf-8")
    assert page == mapref.render(), \
        "run: python -m chcos.devices.mapref > docs/device-map-reference.md"
