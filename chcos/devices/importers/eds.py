"""eds - a device map for one CANopen node from its EDS (``chcos import eds FILE --node N``).

The object dictionary is read with canopen's ``import_od`` (``$NODEID`` resolved for node N).
Devices:

* every object mapped in an enabled TPDO (COB-ID bit 31 clear in 0x1800+n, mapping 0x1A00+n):
  a sensor, delivered by the PDO; ``stale_after`` is five event-timer periods when the TPDO has an
  event timer;
* every object mapped in an enabled RPDO (0x1400+n / 0x1600+n): an actuator, written by the PDO;
* with ``sdo`` (the default), every other numeric or boolean application object (0x2000-0x9FFF,
  sub-index 0 of records and arrays excepted): read-only, constant and read-write objects as
  sensors polled by SDO, write-only and ``rww`` (process output) objects as actuators.

Names come from the EDS's ParameterName (a record's name joined with the entry's); limits from
LowLimit/HighLimit; units and scale from canopen's ``unit``/``factor`` where the EDS has them.
The bus gets ``nodes = [{id, eds, heartbeat_timeout}]`` (three producer-heartbeat periods, from
0x1017, when it is set). Nothing else is guessed: safe values are left for the user to set.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from chcos.devices.importers.draft import Hex, MapDraft, limits
from chcos.errors import ConfigError

ACCESS_SENSOR = ("ro", "const", "rw", "rwr")
ACCESS_ACTUATOR = ("wo", "rww")


def _load(path: str | Path, node: int) -> Any:
    import canopen.objectdictionary as od_mod

    if not 1 <= node <= 127:
        raise ConfigError(f"--node {node}: expected a CANopen node id 1..127")
    try:
        return od_mod.import_od(str(path), node)
    except FileNotFoundError as exc:
        raise ConfigError(f"{path}: cannot read the EDS: {exc}") from exc
    except Exception as exc:  # canopen raises several kinds for a malformed file
        raise ConfigError(f"{path}: not a readable EDS: {exc}") from exc


def od_default(od: Any, index: int, sub: int) -> int | None:
    """The EDS default of object ``index:sub`` as an integer (None: no such object or value)."""
    try:
        var = od.get_variable(index, sub)
    except Exception:
        return None
    if var is None or var.default is None:
        return None
    try:
        return int(var.default)
    except (TypeError, ValueError):
        return None


def pdo_mappings(od: Any, comm: int, mapping: int) -> list[tuple[int, int, int, int, int]]:
    """(pdo number, index, subindex, event timer ms, cob id) of every object mapped in an
    enabled PDO of the given communication/mapping ranges."""
    out = []
    for n in range(512):
        if comm + n not in od or mapping + n not in od:
            continue
        cob = od_default(od, comm + n, 1)
        if cob is None or cob & 0x8000_0000:
            continue  # no COB-ID, or the PDO is disabled
        timer = od_default(od, comm + n, 5) or 0
        count = od_default(od, mapping + n, 0) or 0
        for sub in range(1, count + 1):
            entry = od_default(od, mapping + n, sub)
            if not entry:
                continue
            index, subindex = entry >> 16, (entry >> 8) & 0xFF
            if index < 0x1000:
                continue  # a dummy entry (data-type index) fills a gap
            out.append((n + 1, index, subindex, timer, cob & 0x1FFF_FFFF))
    return out


def _numeric(var: Any) -> bool:
    from canopen.objectdictionary import BOOLEAN, FLOAT_TYPES, INTEGER_TYPES

    return var.data_type in INTEGER_TYPES or var.data_type in FLOAT_TYPES \
        or var.data_type == BOOLEAN


def _name(var: Any) -> str:
    parent = getattr(var, "parent", None)
    if parent is not None and getattr(parent, "name", None) and var.subindex:
        return f"{parent.name} {var.name}"
    return str(var.name)


def _device(draft: MapDraft, var: Any, direction: str, bus: str, machine: int, prefix: str,
            node: int) -> dict[str, Any]:
    dev: dict[str, Any] = {
        "name": draft.name(_name(var), prefix), "direction": direction, "machine": machine,
        "bus": bus, "address": {"node": node, "index": Hex(var.index), "subindex": var.subindex}}
    factor = float(getattr(var, "factor", 1) or 1)
    if factor != 1:
        dev["scale"] = factor
    lim = limits(None if var.min is None else var.min * factor,
                 None if var.max is None else var.max * factor)
    if lim is not None:
        dev["limits"] = lim
    if getattr(var, "unit", ""):
        dev["units"] = str(var.unit)
    return dev


def import_eds(path: str | Path, node: int, *, bus: str = "canopen", machine: int = 0,
               prefix: str = "", sdo: bool = True, eds_ref: str | None = None,
               interface: str = "socketcan", channel: str = "can0") -> MapDraft:
    """The device map draft of node ``node`` described by the EDS at ``path`` (see the module
    doc); ``eds_ref`` is how the map names the EDS (default: ``path`` as given). Raises
    ConfigError naming the file if it is not a readable EDS or the node id is out of range."""
    od = _load(path, node)
    draft = MapDraft()
    info = getattr(od, "device_information", None)
    vendor = getattr(info, "vendor_name", None) or "?"
    product = getattr(info, "product_name", None) or "?"
    draft.header = [f"CANopen node {node}: {product} ({vendor}), imported from {Path(path).name}",
                    "by chcos import eds. Check with chcos check; set safe_value on the actuators.",
                    "Delete interface/channel to take them from python-can's configuration."]
    node_table: dict[str, Any] = {"id": node, "eds": eds_ref or str(path)}
    hb = od_default(od, 0x1017, 0)
    if hb:
        node_table["heartbeat_timeout"] = round(3 * hb / 1000, 3)
    draft.buses.append({"name": bus, "kind": "canopen", "interface": interface,
                        "channel": channel, "nodes": [node_table]})
    done: set[tuple[int, int]] = set()
    for kind, comm, mapping, direction in (("TPDO", 0x1800, 0x1A00, "sensor"),
                                           ("RPDO", 0x1400, 0x1600, "actuator")):
        for n, index, sub, timer, cob in pdo_mappings(od, comm, mapping):
            var = od.get_variable(index, sub)
            if var is None or (index, sub) in done:
                continue
            done.add((index, sub))
            dev = _device(draft, var, direction, bus, machine, prefix, node)
            notes = [f"0x{index:04X}:{sub:02X} {_name(var)}: {kind}{n} (COB-ID 0x{cob:03X})"]
            if direction == "sensor" and timer:
                dev["stale_after"] = round(5 * timer / 1000, 3)
                notes.append(f"event timer {timer} ms: stale after five periods")
            if direction == "actuator":
                notes.append("set safe_value: written on e-stop, task failure and shutdown")
            draft.add(notes, dev)
    if sdo:
        for index in sorted(i for i in od.indices if 0x2000 <= i <= 0x9FFF):
            obj = od[index]
            subs = [obj] if not hasattr(obj, "subindices") else \
                [obj[s] for s in sorted(obj.subindices) if s != 0]
            for var in subs:
                key = (var.index, var.subindex)
                if key in done or not _numeric(var):
                    continue
                access = str(var.access_type)
                if access in ACCESS_ACTUATOR:
                    direction = "actuator"
                elif access in ACCESS_SENSOR:
                    direction = "sensor"
                else:
                    continue
                done.add(key)
                dev = _device(draft, var, direction, bus, machine, prefix, node)
                notes = [f"0x{var.index:04X}:{var.subindex:02X} {_name(var)}: SDO, access "
                         f"{access}"]
                if access in ("rw", "rwr"):
                    notes.append("read-write: make it an actuator to write it")
                draft.add(notes, dev)
    if not draft.devices:
        raise ConfigError(f"{path}: no PDO-mapped or application object in node {node}'s EDS")
    return draft
