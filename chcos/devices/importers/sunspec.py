"""sunspec - a device map of a SunSpec device from the official models (``chcos import sunspec``).

The models are SunSpec's own JSON definitions as pysunspec2 ships them, laid out by pysunspec2's
``sunspec2.device.Model`` (point offsets, repeating groups, the legacy 65-register model 1), so
nothing of the layout is typed by hand. The device is given as the model ids in the order the
device holds them (``--models 1,103,160:2``; ``:N`` repeats a model's repeating group N times)
or as a device file in pysunspec2's JSON form (``{"models": [{"ID": 1, "L": 66, ...}, ...]}``,
what ``sunspec2.file.client`` reads: its ``L`` and its repeating-group lists are authoritative).

Addresses (SunSpec Modbus specification, "Device Models"): the map starts at ``base`` (a
protocol address of the holding table; the specification's 40000, or 0 or 50000), whose two
registers hold the marker ``SunS`` (0x53756E53); the first model (model 1) starts at base + 2
with its ID and length registers, its points after them; each next model follows at + 2 + L; an
end model (ID 0xFFFF, L 0) closes the map. Modicon's 40001 is this protocol address 40000.

Each point becomes a device on a ``modbus-tcp`` (or ``modbus-rtu``) bus: read-write points
actuators, the others sensors; types as :data:`.modbus_types.SUNSPEC` maps them, with their "not
implemented" value as ``unimplemented``; a point with a scale-factor point reads it
(``scale_factor`` = the SF register's address: engineering value = raw x 10^SF), a fixed
exponent gives ``scale``; units, labels and symbols from the model. The marker, each model's ID
and length and the end model are sensors whose ``limits`` are the values a device with this
layout must show, so ``chcos monitor`` flags a device laid out otherwise. Points of a type the
driver does not read (``uint64`` where it has none, ``eui48``, ``ipv6addr``) and pads are left
out, said in a warning.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from chcos.devices.importers.draft import Hex, MapDraft, clamp_limits
from chcos.devices.importers.modbus_types import SUNSPEC, capacity, supported
from chcos.errors import ConfigError

#: the marker "SunS" at the base address
MARKER = 0x53756E53
#: the end model's id
END_ID = 0xFFFF
#: models a device file or --models may list
MAX_MODELS = 64
#: repeats of one repeating group
MAX_REPEATS = 255


@dataclass(frozen=True)
class ModelSpec:
    """One model of the device: its id, repeats of its repeating groups (None: as its
    definition or the device file gives), its length as the device reports it (None: from
    the definition), and the device file's values (for the group lists)."""

    model_id: int
    repeats: int | None = None
    length: int | None = None
    data: Mapping[str, Any] | None = None


def parse_models(items: Sequence[str], lengths: Sequence[str] = ()) -> list[ModelSpec]:
    """``--models 1,103,160:2`` and ``--length 1=65`` items as model specs; raises ConfigError
    naming the item."""
    given: dict[int, int] = {}
    for item in lengths:
        mid, eq, length = item.partition("=")
        if not eq or not mid.strip().isdigit() or not length.strip().isdigit() \
                or len(length.strip()) > 5:
            raise ConfigError(f"--length {item!r}: expected MODEL=REGISTERS, e.g. 1=65")
        given[int(mid)] = int(length)
    out: list[ModelSpec] = []
    for item in items:
        for text in filter(None, (t.strip() for t in item.split(","))):
            m = re.fullmatch(r"(\d{1,5})(?::(\d{1,3}))?", text)
            if m is None or not 1 <= int(m.group(1)) < END_ID:
                raise ConfigError(f"--models {text[:40]!r}: expected a model id 1..65534, "
                                  "optionally :N repeats of its repeating group (160:2)")
            repeats = int(m.group(2)) if m.group(2) else None
            if repeats is not None and repeats > MAX_REPEATS:
                raise ConfigError(f"--models {text!r}: at most {MAX_REPEATS} repeats")
            out.append(ModelSpec(int(m.group(1)), repeats, given.get(int(m.group(1)))))
    if not out:
        raise ConfigError("--models: expected at least one model id (e.g. 1,103)")
    if len(out) > MAX_MODELS:
        raise ConfigError(f"--models: {len(out)} models; at most {MAX_MODELS}")
    return out


def read_device(path: Path) -> list[ModelSpec]:
    """The models of a device file in pysunspec2's JSON form (see the module doc); raises
    ConfigError naming the file and the model entry."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the device file: {exc.strerror or exc}") \
            from exc
    except (UnicodeDecodeError, ValueError) as exc:
        raise ConfigError(f"{path}: not a SunSpec device file (JSON): {exc}") from exc
    models = doc.get("models") if isinstance(doc, dict) else None
    if not isinstance(models, list) or not models:
        raise ConfigError(f"{path}: key models: expected a list of models "
                          '({"ID": 1, "L": 66, ...})')
    if len(models) > MAX_MODELS:
        raise ConfigError(f"{path}: models: {len(models)} models; at most {MAX_MODELS}")
    out = []
    for i, model in enumerate(models):
        key = f"{path}: models[{i}]"
        mid = model.get("ID") if isinstance(model, dict) else None
        if isinstance(mid, bool) or not isinstance(mid, int) or not 1 <= mid < END_ID:
            raise ConfigError(f"{key}.ID: expected a model id 1..65534, got {str(mid)[:40]}")
        length = model.get("L")
        if length is not None and (isinstance(length, bool) or not isinstance(length, int)
                                   or not 0 <= length <= 65535):
            raise ConfigError(f"{key}.L: expected the model's length in registers, got "
                              f"{str(length)[:40]}")
        out.append(ModelSpec(mid, None, length or None, model))
    return out


def _definition(spec: ModelSpec, where: str) -> Any:
    """pysunspec2's model definition of ``spec``; raises ConfigError naming ``where``."""
    from sunspec2 import device

    try:
        return device.get_model_def(spec.model_id)
    except Exception as exc:  # pysunspec2 raises its own errors for a missing definition
        raise ConfigError(f"{where}: model {spec.model_id}: no SunSpec model definition in "
                          f"pysunspec2 ({exc})") from exc


def _repeating(gdef: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    return [g for g in gdef.get("groups", []) or [] if g.get("count") is not None]


def _data(spec: ModelSpec, gdef: Mapping[str, Any], where: str) -> dict[str, Any]:
    """What pysunspec2 needs to lay ``spec`` out: the device file's values, else the group
    counts ``spec.repeats`` gives; raises ConfigError when a repeating group has no count."""
    if spec.data is not None:
        return dict(spec.data)
    data: dict[str, Any] = {"ID": spec.model_id}
    for group in _repeating(gdef):
        count = group.get("count")
        fixed = int(str(count)) if str(count).isdigit() else None
        if fixed:   # a fixed count: the definition says it
            continue
        if spec.repeats is None:
            raise ConfigError(f"{where}: model {spec.model_id}: its group {group['name']!r} "
                              f"repeats as the device says: give the count (--models "
                              f"{spec.model_id}:N) or a device file")
        data[group["name"]] = [{} for _ in range(spec.repeats)]
        if fixed is None:
            data[str(count)] = spec.repeats      # the point that holds the count
    return data


def _model(spec: ModelSpec, address: int, where: str) -> Any:
    """pysunspec2's laid-out model of ``spec`` at ``address`` (its ID register)."""
    from sunspec2 import device

    model_def = _definition(spec, where)
    gdef = model_def.get("group", {})
    data = _data(spec, gdef, where)
    try:
        model = device.Model(model_id=spec.model_id, model_addr=address,
                             model_len=spec.length or 0, model_def=model_def, data=data)
    except Exception as exc:  # pysunspec2's ModelError and the errors its data gives
        raise ConfigError(f"{where}: model {spec.model_id}: cannot be laid out: {exc}") from exc
    if model.error_info:
        raise ConfigError(f"{where}: model {spec.model_id}: "
                          f"{model.error_info.strip().splitlines()[0]}")
    return model


def _walk(group: Any, index: str = "") -> Iterator[tuple[Any, Any, str]]:
    """(group, point, instance label) of every point of ``group`` and its groups, in
    address order."""
    for point in group.points.values():
        yield group, point, index
    for name, sub in group.groups.items():
        instances = sub if isinstance(sub, list) else [sub]
        for i, g in enumerate(instances, 1):
            label = f"{index}{name}{i if isinstance(sub, list) else ''}_"
            yield from _walk(g, label)


def import_sunspec(models: Sequence[ModelSpec], *, source: str, base: int = 40000,
                   bus: str = "inverter", host: str | None = None, port: int = 502,
                   unit: int = 1, machine: int = 0, prefix: str = "", short: bool = False,
                   rtu: str | None = None, baudrate: int = 19200,
                   parity: str = "N") -> MapDraft:
    """The device-map draft of a SunSpec device holding ``models`` from ``base`` (see the
    module doc); ``source`` names where the models came from (the device file or the option)
    in errors and the header. Raises ConfigError naming it and the model for an unknown model,
    a repeating group without a count, a layout beyond address 65535 or a bad ``base``/``unit``."""
    from chcos.devices.importers.modbus_csv import _bus

    if not 0 <= base <= 65535 - 4:
        raise ConfigError(f"--base {base}: expected a protocol address 0..65531 of the holding "
                          "table (SunSpec: 40000, 0 or 50000)")
    if not 0 <= unit <= 255 or (rtu is not None and not 1 <= unit <= 247):
        raise ConfigError(f"--unit {unit}: expected 1..247 (0..255 on TCP)")
    draft = MapDraft()
    _bus(draft, Path(source), bus, host, port, rtu, baudrate, parity, "chcos import sunspec")
    laid: list[tuple[ModelSpec, Any, int]] = []
    address = base + 2
    for i, spec in enumerate(models):
        model = _model(spec, address, f"{source}: models[{i}]")
        length = int(model.len) - 2
        laid.append((spec, model, address))
        address += 2 + length
        if address + 2 > 65536:
            raise ConfigError(f"{source}: model {spec.model_id} ends at register {address}: "
                              "beyond 65535, the protocol's last address (a lower --base?)")
    layout = ", ".join(f"{s.model_id} at {a}" for s, _m, a in laid)
    draft.header.insert(1, f"SunSpec map at holding {base} (a protocol address; {base + 1} "
                        f"counted from one): 'SunS' at {base}, models {layout}, end model at "
                        f"{address}; laid out from SunSpec's model definitions (pysunspec2).")
    ident = _Identity(draft, bus, machine, unit, prefix)
    ident.add("sunspec_marker", base, "uint32", MARKER, "the marker 'SunS' (0x53756E53): "
              "a SunSpec map starts here")
    names = _names(laid, short)
    for index, (spec, model, at) in enumerate(laid):
        _model_devices(draft, spec, model, at, index, names, bus=bus, machine=machine,
                       unit=unit, prefix=prefix)
    ident.add("sunspec_end", address, "uint16", END_ID, "the end model (ID 0xFFFF): the map "
              "ends here")
    draft.warnings.append(
        f"{source}: addresses assume the models in this order from holding {base}, each as "
        f"long as its definition (or the device file) says: confirm with the device's "
        f"marker, ID and length registers (chcos monitor flags a device laid out otherwise)")
    return draft


@dataclass
class _Identity:
    """Adds the layout's identity registers (marker, model ids and lengths, end model)."""

    draft: MapDraft
    bus: str
    machine: int
    unit: int
    prefix: str

    def add(self, name: str, address: int, typ: str, value: int, note: str) -> None:
        self.draft.add([f"holding {address}: {note}"], {
            "name": self.draft.name(name, self.prefix), "direction": "sensor",
            "machine": self.machine, "bus": self.bus,
            "address": {"unit": self.unit, "table": "holding", "address": address,
                        "type": typ},
            "limits": [float(value), float(value)]})


def _names(laid: list[tuple[ModelSpec, Any, int]], short: bool) -> dict[tuple[int, str], str]:
    """The name text of each (model position, instance label + point): the model's group name
    and the point's, or with ``short`` the point's alone where no other point has it."""
    full: dict[tuple[int, str], str] = {}
    for i, (_spec, model, _at) in enumerate(laid):
        for _group, point, label in _walk(model):
            full[(i, label + point.pdef["name"])] = f"{model.gname}_{label}{point.pdef['name']}"
    if not short:
        return full
    counts: dict[str, int] = {}
    for _i, key in full:
        counts[key] = counts.get(key, 0) + 1
    return {k: (k[1] if counts[k[1]] == 1 else v) for k, v in full.items()}


def _model_devices(draft: MapDraft, spec: ModelSpec, model: Any, at: int, index: int,
                   names: Mapping[tuple[int, str], str], *, bus: str, machine: int, unit: int,
                   prefix: str) -> None:
    """The devices of the ``index``-th laid-out model, at address ``at`` (its ID register)."""
    skipped: list[str] = []
    for group, point, label in _walk(model):
        pdef = point.pdef
        name = pdef["name"]
        address = at + int(point.offset)
        ptype = SUNSPEC.get(pdef["type"])
        if ptype is None or not ptype.register_type or not supported(ptype.register_type):
            if pdef["type"] != "pad":
                skipped.append(f"{label}{name} ({pdef['type']})")
            continue
        table: dict[str, Any] = {"unit": unit, "table": "holding", "address": address,
                                 "type": ptype.register_type}
        if ptype.register_type == "string":
            table["count"] = int(point.len)
        if (ptype.registers or 1) > 1:
            table["word_order"] = "ABCD"
        if ptype.unimplemented is not None and label + name not in ("ID", "L"):
            table["unimplemented"] = Hex(ptype.unimplemented)
        writable = pdef.get("access") == "RW" and ptype.register_type != "string"
        dev: dict[str, Any] = {"name": draft.name(names[(index, label + name)], prefix),
                               "direction": "actuator" if writable else "sensor",
                               "machine": machine, "bus": bus, "address": table}
        notes = [f"model {spec.model_id} {model.gname} {label}{name} at holding {address}: "
                 f"{pdef.get('label', name)} ({pdef['type']}"
                 + (f", {int(point.len)} registers" if int(point.len) > 1 else "") + ")"]
        if name in ("ID", "L") and not label:
            value = spec.model_id if name == "ID" else int(model.len) - 2
            dev["limits"] = [float(value), float(value)]
            notes.append(f"the device must show {value} here, or the map is laid out wrong")
            table.pop("unimplemented", None)
        _scale(dev, point, group, model, at, notes)
        if pdef.get("units"):
            dev["units"] = str(pdef["units"])[:40]
        if writable and "scale_factor" not in table:
            dev["limits"] = clamp_limits(None, None, capacity(ptype.register_type,
                                                              dev.get("scale", 1.0)),
                                         name, draft.warnings)
        _symbols(pdef, notes)
        if pdef.get("mandatory") != "M":
            notes.append("optional: a device may not implement it (then it reads as not "
                         "implemented)")
        if writable:
            notes.append("set safe_value: written on e-stop, task failure and shutdown")
        draft.add(notes, dev)
    if skipped:
        draft.warnings.append(f"model {spec.model_id}: left out (a type the modbus driver does "
                              f"not read): {', '.join(skipped[:10])}"
                              + (", ..." if len(skipped) > 10 else ""))


def _scale(dev: dict[str, Any], point: Any, group: Any, model: Any, at: int,
           notes: list[str]) -> None:
    """``scale_factor`` (the SF point's address, found in the point's group, then the
    model's top level, as pysunspec2 resolves it) or ``scale`` (a fixed exponent)."""
    if point.sf_value is not None and not point.sf:
        if point.sf_value:
            dev["scale"] = float(10.0 ** int(point.sf_value))
            notes.append(f"scale 10^{point.sf_value} (fixed by the model)")
        return
    if not point.sf:
        return
    sf = group.points.get(point.sf) or model.points.get(point.sf)
    if sf is None:
        notes.append(f"its scale factor {point.sf} is not in the model: read unscaled")
        return
    dev["address"]["scale_factor"] = at + int(sf.offset)
    notes.append(f"scaled by 10^{point.sf} (holding {at + int(sf.offset)})")


def _symbols(pdef: Mapping[str, Any], notes: list[str]) -> None:
    symbols = pdef.get("symbols") or []
    if not symbols:
        return
    kind = "bits" if pdef["type"].startswith("bitfield") else "values"
    text = ", ".join(f"{s.get('value')} {s.get('name')}" for s in symbols)
    notes.append(f"{kind}: {text[:300]}" + ("..." if len(text) > 300 else ""))
