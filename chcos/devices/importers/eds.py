"""eds - a device map for one CANopen node from its EDS (``chcos import eds FILE --node N``).

The object dictionary is read with canopen's ``import_od`` (``$NODEID`` resolved for node N).
A CiA 402 drive (0x6040, 0x6041, 0x6060, 0x6061 at an axis's offset) becomes one
``profile = "cia402"`` axis device per axis and nothing else, unless asked for: ``objects``
(``--objects``) adds those objects, ``all_objects`` (``--all``) every other one, ``axes=False``
(``--plain``) writes the drive's objects as plain devices. Plain devices, for any other node:

* every object mapped in an enabled TPDO (COB-ID bit 31 clear in 0x1800+n, mapping 0x1A00+n):
  a sensor, delivered by the PDO; ``stale_after`` is five PDO periods (:func:`freshness`: the
  event timer, or n SYNC periods for transmission type n), none for type 0 (sent on change at a
  SYNC); an asynchronous TPDO with event timer 0 is never sent on the node's own: a warning
  names the node and the TPDO with the fix, and ``event_timer`` (``--event-timer``) writes the
  fix into the node's ``config``;
* every object mapped in an enabled RPDO (0x1400+n / 0x1600+n): an actuator, written by the PDO;
* with ``sdo`` (the default), every other numeric or boolean application object (0x2000-0x9FFF,
  sub-index 0 of records and arrays excepted): read-only, constant and read-write objects as
  sensors polled by SDO, write-only and ``rww`` (process output) objects as actuators.

Names come from the EDS's ParameterName (a record's name joined with the entry's; ``short``:
the entry's own, :func:`_name`); limits from LowLimit/HighLimit, clamped to what the object's
data type carries (a warning says so; a DefaultValue outside them is warned about too); units
and scale from canopen's ``unit``/``factor`` where the EDS has them. A refusal names the
section and key, or the line, it is about (:func:`locate_error`).
The bus gets ``nodes = [{id, eds, heartbeat_timeout}]`` (three producer-heartbeat periods, from
0x1017, when it is set). Nothing else is guessed: safe values are left for the user to set,
but a CiA 402 set-point (target position or velocity, profile velocity, mode, quick stop option)
gets ``safe_value = "none"`` with the reason (any value would move the axis).

What will not work on a real bus is said twice, as a warning (:attr:`MapDraft.warnings`, printed
by ``chcos import``) and as a comment in the map:

* synchronous TPDOs (transmission type 0..240) never arrive without SYNC: the bus gets
  ``sync_period`` from the EDS's communication cycle period (0x1006) or, without one,
  :data:`DEFAULT_SYNC_PERIOD` with a warning saying it was chosen; their sensors'
  ``stale_after`` is five PDO periods;
* a node without a heartbeat producer (0x1017 = 0) cannot be supervised: a warning, and the
  configuration to give it (0x1017, then ``heartbeat_timeout``) as a comment;
* an object mapped into two RPDOs is named with both PDOs.

The EDS is read tolerantly (:func:`chcos.devices.eds_file.read_eds`: an empty numeric field is a
warning naming the file, section and key). Objects without a DefaultValue are counted in one
comment line, not one warning each.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Collection
from pathlib import Path
from typing import Any

from chcos.devices.importers.draft import Hex, MapDraft, clamp_limits, limits, unrepr
from chcos.errors import ConfigError

ACCESS_SENSOR = ("ro", "const", "rw", "rwr")
ACCESS_ACTUATOR = ("wo", "rww")


#: SYNC period chosen for synchronous TPDOs when the EDS gives no cycle (0x1006), seconds.
DEFAULT_SYNC_PERIOD = 0.01
#: Objects one PDO maps at most (CiA 301: mapping sub-indices 1..64); a larger count in an
#: EDS is read as this many, so a corrupt count costs no more than a real one.
MAX_MAPPED = 64
#: Producer heartbeat time suggested for a node that has none, milliseconds.
SUGGESTED_HEARTBEAT_MS = 100


def _load(path: str | Path, node: int) -> tuple[Any, tuple[str, ...]]:
    from chcos.devices.eds_file import read_eds

    if not 1 <= node <= 127:
        raise ConfigError(f"--node {node}: expected a CANopen node id 1..127")
    try:
        read = read_eds(path, node)
    except ValueError as exc:
        message = re.sub(r"'([^'\n]{60})[^'\n]+'", r"'\1...'", str(exc))   # a 140 kB value
        raise ConfigError(locate_error(Path(path), str(exc)).replace(str(exc), message)) \
            from exc
    return read.od, read.warnings


_NO_OPTION = re.compile(r"No option '([^']*)' in section: '([^']*)'")


def locate_error(path: Path, message: str) -> str:
    """``message`` (canopen's refusal of the EDS at ``path``) with the section and key, or
    the line, it is about: a missing key as ``[section] key: missing``, a bad value by the
    line that holds it. Unchanged when it already names a section or nothing can be found."""
    if re.search(r"\[[0-9A-Za-z]+\] \w+", message):
        return message
    m = _NO_OPTION.search(message)
    if m:
        return f"{message} ([{m.group(2)}] {m.group(1)}: missing; CiA 306 requires it)"
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        return message
    for quoted in re.findall(r"'([^'\n]+)'?", message):   # Python cuts a long literal
        value = unrepr(quoted)
        section = "?"
        for no, line in enumerate(lines, 1):
            text = line.strip()
            if text.startswith("[") and text.endswith("]"):
                section = text[1:-1]
            elif "=" in text and text.split("=", 1)[1].strip().startswith(value[:80]):
                key = text.split("=", 1)[0].strip()
                return f"{message} (line {no}: [{section[:20]}] {key[:40]})"
    return message


def _every(index: int) -> bool:
    return True


def freshness(trans: int, timer: int, sync_period: float | None) -> tuple[float | None, str]:
    """``stale_after`` (None: none can be known) of a sensor in a TPDO of transmission type
    ``trans`` with event timer ``timer`` ms on a bus with SYNC every ``sync_period`` s, and the
    comment saying why: five PDO periods (a few frames lost in a row are tolerated, a node that
    stopped is seen within five of its periods)."""
    if 1 <= trans <= 240 and sync_period is not None:
        return (round(5 * trans * sync_period, 6),
                f"synchronous (type {trans}): every {'' if trans == 1 else f'{trans}th '}SYNC; "
                "stale after five PDO periods")
    if trans == 0:
        return None, ("acyclic synchronous (type 0): sent at a SYNC only when its data "
                      "changed, so no stale timeout can be known")
    if timer:
        return round(5 * timer / 1000, 6), f"event timer {timer} ms: stale after five periods"
    return None, (f"transmission type {trans}, no event timer: sent only when the node decides "
                  "(on change, if at all): no stale timeout")


def _never_sent(draft: MapDraft, node_table: dict[str, Any], silent: dict[int, list[str]],
                tpdos: dict[int, tuple[int, int, int]], where: str, node: int,
                event_timer: int | None) -> None:
    """Warn about the asynchronous TPDOs without an event timer (the node never sends them on
    its own), with the fix; with ``event_timer`` write it into the node's configuration."""
    pdos = ", ".join(f'{{pdo = "tpdo{n}", event_timer_ms = {event_timer or 100}}}'
                     for n in sorted(silent))
    for n, devices in sorted(silent.items()):
        cob, trans, _timer = tpdos.get(n, (0, 255, 0))
        shown = ", ".join(devices[:6]) + (", ..." if len(devices) > 6 else "")
        if event_timer:
            draft.header.append(f"TPDO{n} of node {node} (0x{0x1800 + n - 1:04X}) had no event "
                                f"timer: the node's config sets {event_timer} ms at boot.")
            continue
        draft.warnings.append(
            f"{where}: node {node} TPDO{n} (0x{0x1800 + n - 1:04X}, COB-ID 0x{cob:03X}): "
            f"transmission type {trans} with event timer 0: the node never sends it on its own, "
            f"so {shown} may never be delivered; fix: an event timer (chcos import eds "
            f"--event-timer MS, or in the node's entry config = {{pdos = [{pdos}]}}) or a "
            f"synchronous transmission type with a SYNC (sync_period)")
    if event_timer:
        node_table["config"] = {"pdos": [{"pdo": f"tpdo{n}", "event_timer_ms": event_timer}
                                         for n in sorted(silent)]}
    else:
        draft.header.append(f"Never sent on its own: TPDO{', TPDO'.join(map(str, sorted(silent)))} "
                            f"of node {node} (no event timer). To have it sent, add to the "
                            f"node's entry: config = {{pdos = [{pdos}]}}")


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
        count = min(od_default(od, mapping + n, 0) or 0, MAX_MAPPED)
        for sub in range(1, count + 1):
            entry = od_default(od, mapping + n, sub)
            if not entry:
                continue
            index, subindex = entry >> 16, (entry >> 8) & 0xFF
            if index < 0x1000:
                continue  # a dummy entry (data-type index) fills a gap
            out.append((n + 1, index, subindex, timer, cob & 0x1FFF_FFFF))
    return out


def pdo_params(od: Any, comm: int) -> list[tuple[int, int, int, int]]:
    """(pdo number, cob id, transmission type, event timer ms) of every enabled PDO of the
    communication range ``comm`` (0x1400 RPDOs, 0x1800 TPDOs); the type is 255 when absent."""
    out = []
    for n in range(512):
        if comm + n not in od:
            continue
        cob = od_default(od, comm + n, 1)
        if cob is None or cob & 0x8000_0000:
            continue
        trans = od_default(od, comm + n, 2)
        out.append((n + 1, cob & 0x1FFF_FFFF, 255 if trans is None else trans,
                    od_default(od, comm + n, 5) or 0))
    return out


def _no_default(od: Any) -> list[str]:
    """``index:sub`` of every numeric object without a DefaultValue (nor ParameterValue)."""
    out: list[str] = []
    for index in sorted(od.indices):
        obj = od[index]
        subs = [obj] if not hasattr(obj, "subindices") else \
            [obj[s] for s in sorted(obj.subindices)]
        out.extend(f"0x{v.index:04X}:{v.subindex:02X}" for v in subs
                   if _numeric(v) and v.default is None and v.value is None)
    return out


def _numeric(var: Any) -> bool:
    from canopen.objectdictionary import BOOLEAN, FLOAT_TYPES, INTEGER_TYPES

    return var.data_type in INTEGER_TYPES or var.data_type in FLOAT_TYPES \
        or var.data_type == BOOLEAN


#: words a short name (``--names short``) leaves out
FILLER = frozenset({"of", "the", "a", "an", "and", "for", "value", "object", "parameter",
                    "number", "actual", "sub", "index", "entry", "manufacturer", "specific"})
#: significant words a short name keeps
SHORT_WORDS = 3


def _name(var: Any, short: bool = False) -> str:
    """A device name's text for ``var``: its record's ParameterName joined with its own
    (``short``: its own alone for a record entry, filler words dropped, at most
    :data:`SHORT_WORDS` words)."""
    parent = getattr(var, "parent", None)
    full = str(var.name)
    if parent is not None and getattr(parent, "name", None) and var.subindex:
        full = f"{parent.name} {var.name}"
    if not short:
        return full
    own = str(var.name) if var.subindex and not re.fullmatch(r"(?i)\s*(sub)?\s*\d+\s*",
                                                           str(var.name)) else full
    words = [w for w in re.split(r"[^0-9A-Za-z]+", own) if w]
    kept = [w for w in words if w.lower() not in FILLER] or words
    return " ".join(kept[:SHORT_WORDS]) or full


def _device(draft: MapDraft, var: Any, direction: str, bus: str, machine: int, prefix: str,
            node: int, short: bool = False) -> dict[str, Any]:
    """The device table of object ``var``: address, scale (canopen's factor), units, and
    limits: LowLimit/HighLimit clamped to what the object's data type carries (a warning
    says so); an actuator's open end is the data type's, so check has nothing to warn about
    and the driver refuses what the object cannot hold before it reaches the bus."""
    from drivers.canopen_od import accepted

    dev: dict[str, Any] = {
        "name": draft.name(_name(var, short), prefix), "direction": direction,
        "machine": machine, "bus": bus,
        "address": {"node": node, "index": Hex(var.index), "subindex": var.subindex}}
    factor = float(getattr(var, "factor", 1) or 1)
    if factor != 1 and math.isfinite(factor):
        dev["scale"] = factor
    else:
        factor = 1.0
    lo, hi = _finite(var.min), _finite(var.max)
    span = accepted(var)
    what = f"node {node} 0x{var.index:04X}:{var.subindex:02X} {_name(var)}"
    if span is not None and (direction == "actuator" or lo is not None or hi is not None):
        lim = clamp_limits(None if lo is None else lo * factor,
                           None if hi is None else hi * factor,
                           (span[0] * factor, span[1] * factor), what, draft.warnings)
    else:
        lim = limits(None if lo is None else lo * factor, None if hi is None else hi * factor)
    if lim is not None:
        dev["limits"] = lim
        default = _finite(var.default) if isinstance(var.default, int | float) else None
        if default is not None and not lim[0] <= default * factor <= lim[1]:
            draft.warnings.append(f"{what}: DefaultValue {var.default} is outside its limits "
                                  f"{lim[0]:g}..{lim[1]:g}")
    if getattr(var, "unit", ""):
        dev["units"] = str(var.unit)[:40]
    return dev


def _finite(v: Any) -> float | None:
    """``v`` as a finite number, else None (an EDS limit of ``nan`` or text)."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        return None
    return float(v) if math.isfinite(v) else None


def import_eds(path: str | Path, node: int, *, bus: str = "canopen", machine: int = 0,
               prefix: str = "", sdo: bool = True, eds_ref: str | None = None,
               interface: str = "socketcan", channel: str = "can0", axes: bool = True,
               objects: Collection[int] | None = None, all_objects: bool = False,
               udp_port: int | None = None, short: bool = False,
               event_timer: int | None = None) -> MapDraft:
    """The device map draft of node ``node`` described by the EDS at ``path`` (see the module
    doc); ``eds_ref`` is how the map names the EDS (default: ``path`` as given).

    A CiA 402 drive (``axes``, and 0x6040/0x6041/0x6060/0x6061 at an axis's offset) becomes one
    ``profile = "cia402"`` axis per axis (:func:`.cia402.axis_device`) plus the objects in
    ``objects`` (indices), or every other object with ``all_objects``. Another node (or
    ``axes=False``) gives every object, or only those in ``objects`` when given. Raises
    ConfigError naming the file if it is not a readable EDS, the node id is out of range, an
    index of ``objects`` is not in the EDS, or ``udp_port`` (the bus's ``port``) is given for an
    interface other than ``udp_multicast``.

    ``short``: short device names (:func:`_name`). ``event_timer`` (ms): the event timer the
    node's configuration gives each asynchronous TPDO that has none (else such a TPDO is only a
    warning and a comment: the node never sends it on its own)."""
    if udp_port is not None and interface != "udp_multicast":
        raise ConfigError(f"--udp-port {udp_port}: only with --interface udp_multicast")
    if event_timer is not None and not 1 <= event_timer <= 65535:
        raise ConfigError(f"--event-timer {event_timer}: expected milliseconds 1..65535 "
                          "(0x1800:05 is UNSIGNED16)")
    od, read_warnings = _load(path, node)
    from chcos.devices.importers.cia402 import (
        HOSTED,
        axis_device,
        detect_axes,
        hostable,
        no_safe_value,
    )

    draft_warnings: list[str] = []

    drives = detect_axes(od, node) if axes else []
    found = [a for a in drives if hostable(a)]
    plain_axes = [a for a in drives if not hostable(a)]
    for axis in plain_axes:
        draft_warnings.append(
            f"{Path(path).name}: node {node} axis {axis.axis} is a CiA 402 drive without "
            + ", ".join(f"0x{r.index + 0x800 * axis.axis:04X}" for r in HOSTED
                        if r not in axis.objects)
            + ": no axis device can confirm its state and mode; its objects are imported "
              "as plain devices")
    for index in objects or ():
        if od.get_variable(index, 0) is None and index not in od:
            raise ConfigError(f"{path}: --objects 0x{index:04X}: no such object in node "
                              f"{node}'s EDS")
    wanted: Callable[[int], bool]
    if all_objects or (objects is None and not drives):
        wanted = _every
    else:
        chosen = frozenset(objects or ()) | {o.index for a in plain_axes
                                             for o in a.objects.values()}
        wanted = chosen.__contains__
    taken = {(o.index, o.subindex) for a in found for o in a.objects.values()}
    draft = MapDraft()
    draft.warnings.extend(read_warnings)
    draft.warnings.extend(draft_warnings)
    info = getattr(od, "device_information", None)
    vendor = getattr(info, "vendor_name", None) or "?"
    product = getattr(info, "product_name", None) or "?"
    draft.header = [f"CANopen node {node}: {product} ({vendor}), imported from {Path(path).name}",
                    "by chcos import eds. Check with chcos check; set safe_value on the actuators.",
                    "Delete interface/channel to take them from python-can's configuration."]
    where = Path(path).name
    node_table: dict[str, Any] = {"id": node, "eds": eds_ref or str(path)}
    hb = od_default(od, 0x1017, 0) if od.get_variable(0x1017, 0) is not None else None
    if hb:
        node_table["heartbeat_timeout"] = round(3 * hb / 1000, 3)
    else:
        draft.warnings.append(
            f"{where}: node {node} has no heartbeat producer (0x1017 "
            f"{'absent' if hb is None else 'default 0'}): chcos cannot notice it disappear; "
            f"configure 0x1017 = {SUGGESTED_HEARTBEAT_MS} ms on the node, then set "
            f"heartbeat_timeout = {3 * SUGGESTED_HEARTBEAT_MS / 1000:g}")
        draft.header.append(
            f"Heartbeat: node {node} produces none (0x1017 = 0). Once the node is configured "
            f"with 0x1017 = {SUGGESTED_HEARTBEAT_MS} ms, add to its nodes entry: "
            f"heartbeat_timeout = {3 * SUGGESTED_HEARTBEAT_MS / 1000:g}")
    if od.get_variable(0x1016, 1) is not None:
        draft.header.append(
            "Controller loss: the node has a heartbeat consumer (0x1016); pointed at the "
            "master's heartbeat it stops the node when the controller dies"
            + (" (with 0x6007, the abort connection option code, saying how)."
               if od.get_variable(0x6007, 0) is not None else "."))
    bus_table: dict[str, Any] = {"name": bus, "kind": "canopen", "interface": interface,
                                 "channel": channel}
    if udp_port is not None:
        bus_table["port"] = udp_port
    tpdos = {n: (cob, trans, timer) for n, cob, trans, timer in pdo_params(od, 0x1800)}
    rpdos = {n: (cob, trans, timer) for n, cob, trans, timer in pdo_params(od, 0x1400)}
    sync_types = {n: trans for n, (_, trans, _) in tpdos.items() if trans <= 240}
    sync_period: float | None = None
    if sync_types:
        shown = ", ".join(f"TPDO{n} (type {t})" for n, t in sorted(sync_types.items())) \
            + (" is" if len(sync_types) == 1 else " are")
        cycle_us = od_default(od, 0x1006, 0) if od.get_variable(0x1006, 0) is not None else None
        if cycle_us:
            sync_period = cycle_us / 1e6
            draft.header.append(f"SYNC: {shown} synchronous; sync_period = "
                                f"{sync_period:g} s from the communication cycle (0x1006).")
        else:
            sync_period = DEFAULT_SYNC_PERIOD
            draft.warnings.append(
                f"{where}: {shown} synchronous: sent on SYNC only, never without it; the EDS "
                f"gives no cycle (0x1006), so sync_period = {sync_period:g} s was chosen: set "
                f"the cycle your drive and bus need")
            draft.header.append(f"SYNC: {shown} synchronous (sent on SYNC only); "
                                f"sync_period = {sync_period:g} s was chosen: set your cycle.")
        bus_table["sync_period"] = sync_period
    bus_table["nodes"] = [node_table]
    draft.buses.append(bus_table)
    for axis in found:
        comments, dev = axis_device(axis, draft, bus=bus, machine=machine, prefix=prefix,
                                    several=len(found) > 1)
        draft.add(comments, dev)
    if found:
        draft.header.append("A CiA 402 drive: "
                           + ("one axis" if len(found) == 1 else f"{len(found)} axes")
                           + (" and every other object (--all)." if all_objects else
                              " and the objects asked for (--objects)." if objects else
                              " with the objects it needs (--objects or --all for more)."))
    rpdos_of: dict[tuple[int, int], list[int]] = {}
    for n, index, sub, _timer, _cob in pdo_mappings(od, 0x1400, 0x1600):
        rpdos_of.setdefault((index, sub), []).append(n)
    done: set[tuple[int, int]] = set(taken)
    silent: dict[int, list[str]] = {}      # TPDO number -> its sensors, when it is never sent
    for kind, comm, mapping, direction in (("TPDO", 0x1800, 0x1A00, "sensor"),
                                           ("RPDO", 0x1400, 0x1600, "actuator")):
        for n, index, sub, timer, cob in pdo_mappings(od, comm, mapping):
            var = od.get_variable(index, sub)
            if var is None or (index, sub) in done or not wanted(index):
                continue
            done.add((index, sub))
            dev = _device(draft, var, direction, bus, machine, prefix, node, short)
            notes = [f"0x{index:04X}:{sub:02X} {_name(var)}: {kind}{n} (COB-ID 0x{cob:03X})"]
            trans = (tpdos if kind == "TPDO" else rpdos).get(n, (0, 255, 0))[1]
            if direction == "sensor":
                if trans > 240 and not timer:
                    silent.setdefault(n, []).append(dev["name"])
                    timer = event_timer or 0
                stale, note = freshness(trans, timer, sync_period)
                if stale is not None:
                    dev["stale_after"] = stale
                notes.append(note)
            if direction == "actuator":
                also = [f"RPDO{m}" for m in rpdos_of.get((index, sub), []) if m != n]
                if also:
                    notes.append(f"also mapped in {', '.join(also)}: every RPDO mapping it "
                                 f"carries the value written")
                reason = no_safe_value(index) if sub == 0 else None
                if reason is not None:
                    dev["safe_value"], dev["safe_reason"] = "none", reason
                else:
                    notes.append("set safe_value: written on e-stop, task failure and "
                                 "shutdown")
            draft.add(notes, dev)
    if silent:
        _never_sent(draft, node_table, silent, tpdos, where, node, event_timer)
    if sdo:
        for index in sorted(i for i in od.indices if 0x2000 <= i <= 0x9FFF):
            obj = od[index]
            subs = [obj] if not hasattr(obj, "subindices") else \
                [obj[s] for s in sorted(obj.subindices) if s != 0]
            for var in subs:
                key = (var.index, var.subindex)
                if key in done or not _numeric(var) or not wanted(var.index):
                    continue
                access = str(var.access_type)
                if access in ACCESS_ACTUATOR:
                    direction = "actuator"
                elif access in ACCESS_SENSOR:
                    direction = "sensor"
                else:
                    continue
                done.add(key)
                dev = _device(draft, var, direction, bus, machine, prefix, node, short)
                notes = [f"0x{var.index:04X}:{var.subindex:02X} {_name(var)}: SDO, access "
                         f"{access}"]
                reason = no_safe_value(var.index) if var.subindex == 0 else None
                if direction == "actuator" and reason is not None:
                    dev["safe_value"], dev["safe_reason"] = "none", reason
                if access in ("rw", "rwr"):
                    notes.append("read-write: make it an actuator to write it")
                draft.add(notes, dev)
    if sdo and objects:
        for index in sorted(objects):   # an object asked for outside 0x2000-0x9FFF
            obj = od[index]
            subs = [obj] if not hasattr(obj, "subindices") else \
                [obj[s] for s in sorted(obj.subindices) if s != 0]
            for var in subs:
                if (var.index, var.subindex) in done or not _numeric(var):
                    continue
                done.add((var.index, var.subindex))
                access = str(var.access_type)
                direction = "actuator" if access in ACCESS_ACTUATOR else "sensor"
                draft.add([f"0x{var.index:04X}:{var.subindex:02X} {_name(var)}: SDO, access "
                           f"{access}, asked for with --objects"],
                          _device(draft, var, direction, bus, machine, prefix, node, short))
    if not draft.devices:
        raise ConfigError(f"{path}: no PDO-mapped or application object in node {node}'s EDS "
                          "(no object mapped by [1600]-[17FF] or [1A00]-[1BFF], no numeric "
                          "object in [2000]-[9FFF])")
    missing = _no_default(od)
    if missing:
        draft.header.append(
            f"{len(missing)} object(s) have no DefaultValue (the node answers what it holds; "
            f"no safe value is derived from them): {', '.join(missing[:8])}"
            + (", ..." if len(missing) > 8 else ""))
    return draft
