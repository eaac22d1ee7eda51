"""canopen_od - the object-dictionary side of the ``canopen`` driver: reading a node's EDS with
the canopen library (once per map load, see :mod:`chcos.devices.parsecache`), the checks of the
bus options and device addresses against it, the raw range of an object and the coercion and
check of a value for its data type. No bus I/O; the driver is :mod:`drivers.canopen_node`.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Mapping, Sequence
from typing import Any

from canopen.objectdictionary import BOOLEAN, FLOAT_TYPES, INTEGER_TYPES
from canopen.objectdictionary.datatypes import REAL32, SIGNED_TYPES

from chcos.devices import parsecache
from chcos.devices.eds_file import read_eds
from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.helpers import is_int, is_number
from drivers import canopen_config
from drivers.base import not_finite
from drivers.canopen_lifecycle import (
    DEFAULT_RESTART_BACKOFF,
    DEFAULT_RESTART_LIMIT,
    MAX_BACKOFF,
    RestartPolicy,
)
from drivers.canopen_sync import MAX_SYNC_PRIORITY
from drivers.codecs.canopen import eds_path

BUS_OPTIONS = ("interface", "channel", "bitrate", "nodes", "sync_period", "sync_priority",
               "poll_period", "sdo_timeout", "poll", "master_heartbeat_ms",
               "master_node_id", "port", "liveness_ms")
NODE_KEYS = ("id", "eds", "heartbeat_timeout", "nmt_start", "identity", "config",
             "store_config", "restart_limit", "restart_backoff")
#: the master heartbeat and SYNC stop when the controller's kernel has completed no scheduling
#: round for this long (the bus's ``liveness_ms``; 0: only while the process lives)
DEFAULT_LIVENESS_MS = 1000
#: the shortest SYNC period and SDO poll period taken (s): a shorter one is no CANopen cycle a
#: bus can carry, and on virtual time a timer storm that never lets the clock move on
MIN_PERIOD = 0.0005
#: the longest SYNC period: 0x1006 (communication cycle period) is an UNSIGNED32 of µs
MAX_SYNC_PERIOD = 4294.967295
#: the longest heartbeat timeout ``chcos run --virtual`` can simulate: its node heartbeats every
#: third of it, and 0x1017 is an UNSIGNED16 of ms
MAX_HEARTBEAT_TIMEOUT = 3 * 65.535
#: the most restarts a recovery policy may send
MAX_RESTART_LIMIT = 1000
#: a consumer time shorter than this many producer periods leaves no room for the producer's
#: jitter (a loaded controller, a busy bus): ``chcos check`` warns
CONSUMER_MARGIN = 1.5
#: the node id of the master's heartbeat (0x700 + id) unless the bus's ``master_node_id`` says
#: otherwise: 127, the highest id, which slave nodes rarely use
DEFAULT_MASTER_ID = 127
ADDRESS_KEYS = ("node", "index", "subindex", "poll_period")
DEFAULT_POLL = 0.1


def load_od(bus: BusSpec, node_id: int, eds: str) -> Any:
    """canopen's object dictionary of node ``node_id`` from ``eds``; raises ``ValueError`` naming
    the file when canopen cannot read it."""
    path = eds_path(bus, eds)
    if not path.is_file():
        raise ValueError(f"EDS file {path} does not exist")
    try:
        return parsecache.cached("eds", path, node_id, lambda: _read_od(path, node_id))
    except Exception as exc:  # canopen raises assorted types for a malformed EDS
        raise ValueError(f"canopen cannot read EDS {path}: {exc}") from exc


def _read_od(path: Any, node_id: int) -> Any:
    """The object dictionary, read tolerantly (:mod:`chcos.devices.eds_file`: an empty numeric
    field is logged as a warning naming the file, section and key, not a rejection)."""
    read = read_eds(path, node_id)
    for warning in read.warnings:
        logging.getLogger("chcos.eds").warning("%s", warning)
    return read.od


def checked_od(bus: BusSpec, node_id: int, eds: str) -> Any:
    """:func:`load_od` for the map checks (``check_device``, ``encodable``): inside a
    :func:`chcos.devices.parsecache.scope` one parse per node and file, however many devices use it.
    The result may be shared: read it, never change it (a running node gets its own).
    Raises ``ValueError`` like :func:`load_od`."""
    return load_od(bus, node_id, eds)


def check_bus(bus: BusSpec) -> list[str]:
    """Errors of the bus options (unknown keys, types, node ids, unreadable EDS files)."""
    errs: list[str] = []
    k = bus.key
    opts = bus.options
    for key in opts:
        if key not in BUS_OPTIONS:
            errs.append(f"{k}.{key}: unknown option for a canopen bus; valid options: "
                        f"{', '.join(BUS_OPTIONS)}")
    for key in ("interface", "channel"):
        if key in opts and (not isinstance(opts[key], str | int) or opts[key] == ""):
            errs.append(f"{k}.{key}: expected a python-can {key} name, got {opts[key]!r}")
    if "bitrate" in opts and not (is_int(opts["bitrate"]) and opts["bitrate"] > 0):
        errs.append(f"{k}.bitrate: expected an integer > 0 (bit/s), got {opts['bitrate']!r}")
    if "poll" in opts and not (is_number(opts["poll"]) and 0.0001 <= opts["poll"] <= 1):
        errs.append(f"{k}.poll: expected seconds in [0.0001, 1], got {opts['poll']!r}")
    if "port" in opts and (opts.get("interface") != "udp_multicast" or not is_int(opts["port"])
                           or not 1 <= opts["port"] <= 65535):
        errs.append(f"{k}.port: the UDP port of interface \"udp_multicast\" (1..65535), got "
                    f"{opts['port']!r} with interface {opts.get('interface')!r}")
    if "sdo_timeout" in opts and not (is_number(opts["sdo_timeout"])
                                      and 0 < opts["sdo_timeout"] <= 3600):
        errs.append(f"{k}.sdo_timeout: expected a number of seconds in (0, 3600], got "
                    f"{opts['sdo_timeout']!r}")
    if "poll_period" in opts and not (is_number(opts["poll_period"])
                                      and MIN_PERIOD <= opts["poll_period"] <= 86400):
        errs.append(f"{k}.poll_period: expected seconds in [{MIN_PERIOD}, 86400], got "
                    f"{opts['poll_period']!r}")
    if "sync_period" in opts and not (is_number(opts["sync_period"])
                                      and MIN_PERIOD <= opts["sync_period"] <= MAX_SYNC_PERIOD):
        errs.append(f"{k}.sync_period: expected seconds in [{MIN_PERIOD}, {MAX_SYNC_PERIOD}] "
                    f"(0x1006 is an UNSIGNED32 of µs), got {opts['sync_period']!r}")
    lv = opts.get("liveness_ms")
    if lv is not None and not (is_int(lv) and (lv == 0 or 10 <= lv <= 65535)):
        errs.append(f"{k}.liveness_ms: expected 10..65535 ms (0: off), got {lv!r}")
    prio = opts.get("sync_priority")
    if prio is not None and not (is_int(prio) and 0 <= prio <= MAX_SYNC_PRIORITY):
        errs.append(f"{k}.sync_priority: expected the SYNC producer's SCHED_FIFO priority "
                    f"1..{MAX_SYNC_PRIORITY}, or 0 for SCHED_OTHER, got {prio!r}")
    elif prio is not None and "sync_period" not in opts and "master_heartbeat_ms" not in opts:
        errs.append(f"{k}.sync_priority: the bus has no sync_period and no "
                    f"master_heartbeat_ms, so no producer process to give it to; set one or "
                    f"remove sync_priority")
    mh = opts.get("master_heartbeat_ms")
    if mh is not None and not (is_int(mh) and 1 <= mh <= 65535):
        errs.append(f"{k}.master_heartbeat_ms: expected 1..65535 ms, got {mh!r}")
    mid = opts.get("master_node_id", DEFAULT_MASTER_ID)
    if not (is_int(mid) and 1 <= mid <= 127):
        errs.append(f"{k}.master_node_id: expected a node id 1..127, got {mid!r}")
    nodes = opts.get("nodes")
    if not isinstance(nodes, list) or not nodes:
        return [*errs, f"{k}.nodes: expected a non-empty array of {{id, eds}} tables, "
                       f"got {nodes!r}"]
    seen: set[int] = set()
    for i, node in enumerate(nodes):
        errs.extend(check_node(bus, f"{k}.nodes[{i}]", node, seen))
    if is_int(mid) and mid in seen and "master_node_id" in opts:
        errs.append(f"{k}.master_node_id: {mid} is also the id of a node of the bus")
    elif is_int(mid) and mid in seen and mh is not None:
        errs.append(f"{k}.master_heartbeat_ms: the master's default id {mid} is the id of a "
                    f"node of the bus; set master_node_id to a free id")
    return errs

def check_node(bus: BusSpec, k: str, node: object, seen: set[int]) -> list[str]:
    """Errors of entry ``k`` of the bus's ``nodes`` (``seen``: the ids so far)."""
    if not isinstance(node, Mapping):
        return [f"{k}: expected a table {{id, eds}}, got {node!r}"]
    errs = [f"{k}.{key}: unknown key; valid keys: {', '.join(NODE_KEYS)}"
            for key in node if key not in NODE_KEYS]
    nid = node.get("id")
    if not (is_int(nid) and 1 <= nid <= 127):
        errs.append(f"{k}.id: expected a CANopen node id 1..127, got {nid!r}")
    elif nid in seen:
        errs.append(f"{k}.id: node id {nid} appears twice on bus {bus.name}")
    else:
        seen.add(nid)
    eds = node.get("eds")
    od = None
    if not isinstance(eds, str) or not eds:
        errs.append(f"{k}.eds: expected the path of the node's EDS file, got {eds!r}")
    elif is_int(nid):
        try:
            od = load_od(bus, nid, eds)
        except ValueError as exc:
            errs.append(f"{k}.eds: expected a readable EDS file; {exc}")
    mh = bus.options.get("master_heartbeat_ms")
    errs.extend(canopen_config.check(k, node, od, mh if is_int(mh) else None,
                                     "sync_period" in bus.options))
    hb = node.get("heartbeat_timeout")
    if hb is not None and not (is_number(hb) and 0.001 <= hb <= MAX_HEARTBEAT_TIMEOUT):
        errs.append(f"{k}.heartbeat_timeout: expected seconds in [0.001, "
                    f"{MAX_HEARTBEAT_TIMEOUT:g}] (a simulated node heartbeats every third of "
                    f"it, in 0x1017's UNSIGNED16 ms), got {hb!r}")
    if "nmt_start" in node and not isinstance(node["nmt_start"], bool):
        errs.append(f"{k}.nmt_start: expected true or false, got {node['nmt_start']!r}")
    rl = node.get("restart_limit")
    if rl is not None and not (is_int(rl) and 0 <= rl <= MAX_RESTART_LIMIT):
        errs.append(f"{k}.restart_limit: expected 0..{MAX_RESTART_LIMIT} restarts (0: never "
                    f"restarted), got {rl!r}")
    rb = node.get("restart_backoff")
    if rb is not None and not (is_number(rb) and 0.05 <= rb <= MAX_BACKOFF):
        errs.append(f"{k}.restart_backoff: expected seconds in [0.05, {MAX_BACKOFF:g}], got "
                    f"{rb!r}")
    return errs


def restart_policy(node: Mapping[str, Any]) -> RestartPolicy:
    """The recovery policy of a node entry that :func:`check_node` accepted."""
    return RestartPolicy(int(node.get("restart_limit", DEFAULT_RESTART_LIMIT)),
                         float(node.get("restart_backoff", DEFAULT_RESTART_BACKOFF)))


def liveness(bus: BusSpec) -> float:
    """The bus's ``liveness_ms`` in seconds (0: off)."""
    return int(bus.options.get("liveness_ms", DEFAULT_LIVENESS_MS)) / 1000.0


#: CiA 402 device type (0x1000, bits 0..15) and the controlword of axis 0 (0x800 per axis)
CIA402_PROFILE = 402
CONTROLWORD = 0x6040


def is_controlword(od: Any, index: int, subindex: int) -> bool:
    """True if ``index``:``subindex`` is a CiA 402 drive's controlword (0x6040 of one of its
    axes) in the node's EDS ``od``: the device type 0x1000 names profile 402, or the EDS names
    the object a controlword."""
    if subindex != 0 or (index - CONTROLWORD) % 0x800 or not 0 <= index - CONTROLWORD < 0x4000:
        return False
    var = od.get_variable(index, 0)
    if var is None:
        return False
    dtype = od.get_variable(0x1000, 0)
    raw = None if dtype is None else (dtype.value if dtype.value is not None else dtype.default)
    return (isinstance(raw, int) and raw & 0xFFFF == CIA402_PROFILE) \
        or "controlword" in str(var.name).replace(" ", "").lower()

def check_device(bus: BusSpec, device: DeviceSpec) -> list[str]:
    """Errors of a device address: keys, node on this bus, object present in the node's EDS,
    readable for a sensor and writable for an actuator."""
    k = f"{device.key}.address"
    a = device.address
    if a.get("profile") == "cia402":
        return check_axis(bus, device)
    errs = [f"{k}.{key}: unknown key; valid keys: {', '.join(ADDRESS_KEYS)}"
            for key in a if key not in ADDRESS_KEYS]
    nodes = {n.get("id"): n for n in bus.options.get("nodes", []) if isinstance(n, Mapping)}
    nid, index, sub = a.get("node"), a.get("index"), a.get("subindex", 0)
    if not is_int(nid) or nid not in nodes:
        errs.append(f"{k}.node: expected the id of a node of bus {bus.name} "
                    f"({', '.join(str(n) for n in nodes) or 'none'}), got {nid!r}")
    if not (is_int(index) and 0 <= index <= 0xFFFF):
        errs.append(f"{k}.index: expected an object index 0..0xFFFF, got {index!r}")
    if not (is_int(sub) and 0 <= sub <= 0xFF):
        errs.append(f"{k}.subindex: expected a subindex 0..255, got {sub!r}")
    pp = a.get("poll_period")
    if pp is not None and not (is_number(pp) and MIN_PERIOD <= pp <= 86400):
        errs.append(f"{k}.poll_period: expected seconds in [{MIN_PERIOD}, 86400], got {pp!r}")
    if errs or not is_int(nid):
        return errs
    eds = nodes[nid].get("eds")
    try:
        od = checked_od(bus, nid, eds) if isinstance(eds, str) else None
    except ValueError:
        return []  # reported by check_bus
    var = od.get_variable(index, sub) if od is not None else None
    if od is not None and var is None:
        errs.append(f"{k}: expected an object of node {nid}'s EDS, no 0x{index:04X}:{sub:02X}")
    elif var is not None and device.direction == "sensor" and not var.readable:
        errs.append(f"{k}: 0x{index:04X}:{sub:02X} is not readable; a sensor needs a readable "
                    f"object")
    elif var is not None and device.direction == "actuator" and not var.writable:
        errs.append(f"{k}: 0x{index:04X}:{sub:02X} is read-only; an actuator needs a writable "
                    f"object")
    return errs

#: the objects an axis cannot work without (statusword, controlword, modes, modes display)
AXIS_REQUIRED = (0x6040, 0x6041, 0x6060, 0x6061)


def check_axis(bus: BusSpec, device: DeviceSpec) -> list[str]:
    """Errors of a device of a CiA 402 axis table (:mod:`drivers.canopen_axis`): its node on
    this bus, and the node's EDS holding 0x6040, 0x6041, 0x6060 and 0x6061 at the axis's offset
    (checked once, on the axis's actuator; its sensors share the address)."""
    k = f"{device.key}.address"
    a = device.address
    nodes = {n.get("id"): n for n in bus.options.get("nodes", []) if isinstance(n, Mapping)}
    nid, axis = a.get("node"), a.get("axis", 0)
    if device.direction == "sensor":
        return []
    if not is_int(nid) or nid not in nodes:
        return [f"{k}.node: expected the id of a node of bus {bus.name} "
                f"({', '.join(str(n) for n in nodes) or 'none'}), got {nid!r}"]
    eds = nodes[nid].get("eds")
    try:
        od = checked_od(bus, nid, eds) if isinstance(eds, str) else None
    except ValueError:
        return []  # reported by check_bus
    if od is None:
        return []
    missing = [f"0x{i + 0x800 * int(axis):04X}" for i in AXIS_REQUIRED
               if od.get_variable(i + 0x800 * int(axis), 0) is None]
    if missing:
        return [f"{k}: node {nid}'s EDS has no {', '.join(missing)}; a CiA 402 axis needs "
                f"controlword, statusword, modes of operation and its display"]
    return []


def encodable(bus: BusSpec, device: DeviceSpec) -> tuple[float, float] | None:
    """The range of the object's data type in the node's EDS: 0..1 for BOOLEAN, the
    INTEGERn/UNSIGNEDn ranges, the largest REAL32; None for REAL64 and other types."""
    a = device.address
    if a.get("profile") == "cia402":
        return None
    nodes = {n.get("id"): n for n in bus.options.get("nodes", []) if isinstance(n, Mapping)}
    var = checked_od(bus, a["node"], str(nodes[a["node"]]["eds"])).get_variable(
        a["index"], a.get("subindex", 0))
    got = accepted(var)
    return None if got is None else (got[0], got[1])


def accepted(od_var: Any) -> tuple[float, float, bool] | None:
    """The values of ``od_var``'s data type as ``(lo, hi, integral)``: 0..1 for BOOLEAN, the
    INTEGERn/UNSIGNEDn ranges (integers only), the largest REAL32; None for REAL64 and other
    types. Each of them :func:`value_error` accepts."""
    dt = od_var.data_type
    if dt == BOOLEAN:
        return 0.0, 1.0, True
    if dt == REAL32:
        return -3.4028234663852886e38, 3.4028234663852886e38, False
    if dt not in INTEGER_TYPES:
        return None
    bits = 8 * od_var.STRUCT_TYPES[dt].size
    if dt in SIGNED_TYPES:
        return float(-(1 << (bits - 1))), float((1 << (bits - 1)) - 1), True
    return 0.0, float((1 << bits) - 1), True


def coerce(od_var: Any, value: Any) -> Any:
    """``value`` as the Python type canopen encodes for ``od_var``'s data type."""
    if od_var.data_type == BOOLEAN:
        return bool(value)
    if od_var.data_type in INTEGER_TYPES:
        if isinstance(value, float):
            if value != value or value in (float("inf"), float("-inf")):
                raise ValueError("not a finite number")
            return round(value)
        return int(value)
    if od_var.data_type in FLOAT_TYPES:
        return float(value)
    return value


def value_error(od_var: Any, index: int, subindex: int, value: Any) -> str | None:
    """Why ``value`` cannot be encoded for object ``od_var`` (``index``:``subindex``), or None
    if it can: not a finite number, a fraction for an integer object, outside the data type's
    range (0 or 1, False or True for a BOOLEAN)."""
    if (why := not_finite(value)) is not None:
        return why
    if isinstance(value, bool):
        value = int(value)
    if od_var.data_type == BOOLEAN:     # canopen would write bool(value): 7 would go as true
        return None if value in (0, 1) else (
            f"expected 0 or 1 for BOOLEAN object 0x{index:04X}:{subindex:02X}, got {value!r}")
    if od_var.data_type in INTEGER_TYPES and isinstance(value, float) and not value.is_integer():
        return f"expected an integer for object 0x{index:04X}:{subindex:02X}, got {value!r}"
    try:
        od_var.encode_raw(coerce(od_var, value))
    except (struct.error, TypeError, ValueError, OverflowError) as exc:
        return (f"expected a value of data type {od_var.data_type:#x} for object "
                f"0x{index:04X}:{subindex:02X}: {exc}")
    return None


# -- chcos check's warnings: the device's timing, and axes without a statusword TPDO ----------

def check_warnings(bus: BusSpec, devices: Sequence[DeviceSpec]) -> list[str]:
    """What a valid bus does wrong at run time, each naming the node entry and the object:
    a synchronous RPDO carrying an actuator without SYNC (the node applies nothing), a TPDO
    carrying a sensor that is never sent (synchronous without SYNC, remote-request only, or
    event-driven with event timer 0), a consumer time shorter than its producer's period plus
    its jitter (:data:`CONSUMER_MARGIN`), a node watched for a heartbeat it is configured not
    to send, and a CiA 402 axis whose statusword 0x6041 is in no enabled TPDO."""
    out: list[str] = []
    k = bus.key
    opts = bus.options
    has_sync = "sync_period" in opts
    mh = opts.get("master_heartbeat_ms")
    for i, node in enumerate(opts.get("nodes", [])):
        nid = node.get("id")
        kn = f"{k}.nodes[{i}]"
        try:
            od = checked_od(bus, nid, str(node["eds"]))
        except (ValueError, KeyError):
            continue                             # reported by check_bus
        cfg = canopen_config.parse(node)
        mine = [d for d in devices if d.address.get("node") == nid]
        out += _pdo_warnings(kn, nid, od, cfg, mine, has_sync)
        out += _heartbeat_warnings(kn, nid, od, node, cfg, mh)
        out += _axis_warnings(kn, nid, cfg, od, mine)
    return out


def _pdo_warnings(kn: str, nid: int, od: Any, cfg: canopen_config.NodeConfig,
                  devices: Sequence[DeviceSpec], has_sync: bool) -> list[str]:
    """The PDOs carrying the map's devices that the node never sends or never applies."""
    out: list[str] = []
    by_object: dict[tuple[int, int], list[str]] = {}
    for d in devices:
        if "index" in d.address:
            key = (int(d.address["index"]), int(d.address.get("subindex", 0)))
            by_object.setdefault(key, []).append(d.name)
    for p in canopen_config.effective_pdos(od, cfg):
        if not p.enabled:
            continue
        carried = [f"0x{i:04X}:{s:02X} ({', '.join(by_object[(i, s)])})" for i, s in p.objects
                   if (i, s) in by_object]
        if not carried:
            continue
        what = f"{kn} (node {nid}): {p.name} (transmission type {p.transmission_type}"
        if p.kind == "rpdo" and p.synchronous and not has_sync:
            out.append(f"{what}, synchronous) is applied by the node only at a SYNC, and the "
                       f"bus has no sync_period: every write of {', '.join(carried)} is lost; "
                       f"set the bus's sync_period or configure the RPDO with type 255")
        if p.kind != "tpdo":
            continue
        tt = p.transmission_type
        if p.synchronous and not has_sync:
            out.append(f"{what}, synchronous) is sent only after a SYNC, and the bus has no "
                       f"sync_period: {', '.join(carried)} never arrive; set sync_period or "
                       f"use type 254/255 with event_timer_ms")
        elif tt in (252, 253):
            out.append(f"{what}) is sent only on a remote request, which chcos never sends: "
                       f"{', '.join(carried)} never arrive; use type 254/255 with "
                       f"event_timer_ms, or a synchronous type with sync_period")
        elif tt in (254, 255) and not p.event_timer_ms:
            out.append(f"{what}, event timer 0) is sent only when the node itself decides "
                       f"(a change of value, if it detects one): {', '.join(carried)} may "
                       f"never arrive; set event_timer_ms (e.g. 100) in the node's config")
    return out


def _heartbeat_warnings(kn: str, nid: int, od: Any, node: Mapping[str, Any],
                        cfg: canopen_config.NodeConfig, master_ms: object) -> list[str]:
    """Consumer times against their producers' periods, both ways."""
    out: list[str] = []
    hb = node.get("heartbeat_timeout")
    producer = cfg.heartbeat_producer_ms
    if producer is None:
        var = od.get_variable(0x1017, 0)
        raw = None if var is None else (var.value if var.value is not None else var.default)
        producer = raw if isinstance(raw, int) and raw > 0 else None
    if is_number(hb) and producer == 0:
        out.append(f"{kn}.heartbeat_timeout: the node is configured to send no heartbeat "
                   f"(config.heartbeat_producer_ms = 0): it is declared lost "
                   f"{hb} s after every boot")
    elif is_number(hb) and producer and hb * 1000 < CONSUMER_MARGIN * producer:
        out.append(f"{kn}.heartbeat_timeout: {hb} s is shorter than the node's heartbeat "
                   f"period {producer} ms plus its jitter (at least {CONSUMER_MARGIN:g} "
                   f"times it): a late heartbeat fails the node; use 2 to 3 times the period")
    mc = cfg.master_consumer_ms
    if is_int(master_ms) and mc is not None and master_ms < mc < CONSUMER_MARGIN * master_ms:
        out.append(f"{kn}.config.master_consumer_ms: {mc} ms is shorter than the master "
                   f"heartbeat's period {master_ms} ms plus its jitter (at least "
                   f"{CONSUMER_MARGIN:g} times it): a late master heartbeat makes the node "
                   f"leave OPERATIONAL; use 2 to 3 times master_heartbeat_ms")
    return out


def _axis_warnings(kn: str, nid: int, cfg: canopen_config.NodeConfig, od: Any,
                   devices: Sequence[DeviceSpec]) -> list[str]:
    """CiA 402 axes whose statusword no enabled TPDO carries."""
    out: list[str] = []
    tpdo_objects = {o for p in canopen_config.effective_pdos(od, cfg)
                    if p.kind == "tpdo" and p.enabled for o in p.objects}
    for d in devices:
        if d.address.get("profile") != "cia402" or d.direction != "actuator":
            continue
        sw = 0x6041 + 0x800 * int(d.address.get("axis", 0))
        if (sw, 0) not in tpdo_objects:
            out.append(f"{kn} (node {nid}): axis {d.name}'s statusword 0x{sw:04X} is in no "
                       f"enabled TPDO: the axis reads it by SDO (at each command, each EMCY "
                       f"and each change of the node's NMT state), so a fault between "
                       f"commands is seen only if the drive sends its EMCY; map 0x{sw:04X} "
                       f"into a TPDO")
    return out
