"""mapref - the device-map reference: every key of every bus kind, with type, default and meaning.

A kind whose driver declares its tables as option dataclasses (``Driver.Options``,
``Driver.Address`` / ``Driver.Addresses``, :mod:`chcos.devices.options`) is documented from their
fields (:func:`chcos.devices.options.reference`): the key, its type, its one default and its
meaning are written once, in the field. The driver is found by kind through the registry
(:mod:`chcos.devices.registry`), so this module imports no driver. A kind not converted yet keeps
its hand-written tables in :data:`HAND` (``vcan_tests/test_integrator_reference.py`` probes the
drivers and fails when one accepts a key missing here, or rejects one listed, and when a
hand-written table is shadowed by a typed one). :data:`COMMON` holds the keys of every
``[[bus]]`` and ``[[device]]`` table (``chcos.devices.devmap``'s own lists); :data:`SUMMARY`
and :data:`EXAMPLE` the prose of each kind. :func:`render` writes it all as Markdown:
``python -m chcos.devices.mapref > docs/device-map-reference.md`` (a test checks the committed
file is current).
"""

from __future__ import annotations

import dataclasses
import functools
import sys
from dataclasses import dataclass

from chcos.devices.options import KeyDoc, reference
from chcos.devices.registry import driver_class

#: One key: its name, TOML type, default ("required" or "-" when there is none), meaning, and
#: for which variant of the kind it applies ("" for all).
Key = KeyDoc


@dataclass(frozen=True)
class _Doc:
    """What this module writes of a kind by hand: its summary and example, and its tables where
    the driver declares none (None: generated from the driver's dataclasses)."""

    summary: str
    options: tuple[Key, ...] | None
    address: tuple[Key, ...] | None
    example: str


@dataclass(frozen=True)
class Kind:
    """One bus kind: what it is, its bus options, its device-address keys, an example."""

    summary: str
    options: tuple[Key, ...]
    address: tuple[Key, ...]
    example: str


COMMON_BUS = (
    Key("name", "string", "required", "unique across all files loaded together"),
    Key("kind", "string", "required", "the bus kind (a `chcos.drivers` entry point): the "
        "sections below"),
)
COMMON_DEVICE = (
    Key("name", "string", "required", "unique across all files; letters, digits, `_ . -`, "
        "starting with a letter or `_`"),
    Key("direction", "string", "required", "`sensor` (input) or `actuator` (output)"),
    Key("machine", "integer", "0", "the satellite the device belongs to"),
    Key("bus", "string", "required", "a bus declared in any file of the set"),
    Key("address", "inline table", "{}", "kind-specific: the address keys below"),
    Key("priority", "integer 0..99", "8", "interrupt priority of the device's sensory link"),
    Key("stale_after", "float s", "never", "sensors: seconds without data before the sensor is "
        "stale and its readers get SensorFailure"),
    Key("scale", "float", "1.0", "engineering value = raw x scale + offset (not 0)"),
    Key("offset", "float", "0.0", "see scale"),
    Key("limits", "[lo, hi]", "[-inf, inf]", "engineering units, inclusive: actuator commands "
        "outside are refused (never clamped); a sensor reading outside is not delivered and "
        "fails the sensor (reason `limit: ...`) until one within; `chcos monitor` flags it"),
    Key("safe_value", "float or \"none\"", "none", "actuators: written on e-stop, on abnormal "
        "completion of the commanding task and on shutdown; within limits. `\"none\"` with "
        "`safe_reason`: the actuator has no safe value (a target position), said once instead "
        "of a `chcos check` warning"),
    Key("safe_reason", "string", '""', "why the actuator has no safe value; required with "
        "`safe_value = \"none\"`, refused otherwise"),
    Key("units", "string", '""', "shown with values"),
    Key("round", "bool", "false", "actuators only: round the raw value to an integer for an "
        "integer address (without it a value the address cannot carry exactly is refused)"),
    Key("north_writable", "bool", "false", "actuators only: the north-side facades (Modbus "
        "facade, OPC UA) may command it, within its limits and the owner rules"),
    Key("profile", "string", "none", "`\"cia402\"`: a CiA 402 axis on a `canopen` bus, "
        "without `direction`; keys `address = {node, axis = 0}`, `mode`, `units`, "
        "`counts_per_unit`, `position_limits`, `max_velocity`, `quick_stop_option`, "
        "`safe_stop`, `timeouts`, windows; it becomes the actuator `name` and the sensors "
        "`name.state`, `.statusword`, `.mode`, `.position`, `.velocity`, `.fault` "
        "(docs/cia402.md §5)"),
)
COMMON = {"bus": COMMON_BUS, "device": COMMON_DEVICE}

_CAN_BUS = (
    Key("interface", "string", "python-can config", "python-can interface (`socketcan`, "
        "`virtual`, `pcan`...); left out: `CAN_INTERFACE` / can.conf"),
    Key("channel", "string", "python-can config", "python-can channel (`can0`, `vcan0`...)"),
    Key("bitrate", "integer", "-", "bit/s, where the interface sets it"),
)
_UDP_PORT = Key("port", "integer 1..65535", "43113", "UDP port of interface `udp_multicast` (a "
               "bus shared by processes on any machine; `channel` is its multicast group): give "
               "each bus its own group and port")
#: The prose of every kind (summary, example) and, for a kind whose driver does not declare its
#: tables as option dataclasses yet, the hand-written tables (None where they are generated: see
#: :func:`kinds`). A bus engineer who converts a kind replaces its tables here by None.
DOCS: dict[str, _Doc] = {
    "memory": _Doc(
        "values from the host (`inject`); actuator writes kept in memory (tests, demos)",
        None, None,
        '[[bus]]\nname = "bench"\nkind = "memory"\n\n[[device]]\nname = "M1"\n'
        'direction = "actuator"\nbus = "bench"\nsafe_value = 0.0'),
    "signal": _Doc(
        "waveform generators on the kernel clock (demos, load); actuators as on `memory`, "
        "without an address",
        None, None,
        '[[device]]\nname = "S1"\ndirection = "sensor"\nbus = "demo"\n'
        'address = { waveform = "sine", rate_hz = 10, amplitude = 50.0, center = 50.0, '
        'period = 4.0 }'),
    "can": _Doc(
        "raw CAN through python-can; signals from a DBC (cantools) or given raw",
        (*_CAN_BUS,
         Key("fd", "boolean", "false", "CAN FD"),
         Key("dbc", "path", "-", "DBC file (relative to the map) for `{message, signal}` "
             "addresses"),
         Key("record", "path", "-", "record every frame (`.log` candump, `.asc`, `.blf`)"),
         Key("poll", "float s", "0.005", "receive timeout on interfaces without a file "
             "descriptor"),
         Key("filter", "boolean", "true", "receive filters (in the kernel on SocketCAN) from the "
             "ids of the sensors' messages: no other frame reaches chcos (docs/can-faults.md)"),
         Key("ignore_ids", "array", "[]", "ids and ranges (`[\"0x700-0x77F\", 0x80]`) another "
             "node owns: never warned about, counted as `ignored-id`"),
         Key("unknown_ids", "string", "`warn`", "a frame of an id of no device that reaches "
             "chcos: `ignore` (counted), `warn` (counted, one warning per 10 s), `fail` (a bus "
             "error: the run is unhealthy)"),
         Key("message", "array of tables", "[]", "`[[bus.message]]`, one per DBC message that "
             "needs more than the DBC says: `name`, `cycle_time` (s; default the DBC's "
             "GenMsgCycleTime, 0: event-driven; chcos repeats its own cyclic commands), "
             "`counter = \"SIGNAL\"` (rolling, +1 per frame, checked on receive), `checksum = "
             "{ signal, algorithm }` (`xor`, `sum`, `crc8-sae-j1850`, `crc8-autosar`, `python` "
             "with `function = \"module:callable\"`); docs/can-faults.md"),
         _UDP_PORT),
        (Key("message", "string", "required (DBC form)", "message name in the DBC", "DBC form"),
         Key("signal", "string", "required (DBC form)", "signal name; the DBC's scale and "
             "offset are applied by the driver", "DBC form"),
         Key("id", "integer", "required (raw form)", "arbitration id", "raw form"),
         Key("start", "integer 0..63", "required (raw form)", "start bit", "raw form"),
         Key("length", "integer 1..64", "required (raw form)", "bit length", "raw form"),
         Key("byte_order", "string", "`little_endian`", "or `big_endian`", "raw form"),
         Key("signed", "boolean", "false", "two's complement", "raw form"),
         Key("dlc", "integer 0..8", "8", "frame length", "raw form"),
         Key("extended", "boolean", "false", "29-bit id", "raw form")),
        '[[bus]]\nname = "cellcan"\nkind = "can"\ndbc = "cell.dbc"\n\n[[device]]\nname = "T1"\n'
        'direction = "sensor"\nbus = "cellcan"\naddress = { message = "Temps", signal = "T1" }'),
    "canopen": _Doc(
        "remote CANopen nodes (canopen): node lifecycle (identity, configuration at boot, one "
        "NMT start, OPERATIONAL confirmed by the heartbeat, a node that leaves OPERATIONAL "
        "restarted by its recovery policy), SDO, PDO (as configured, else from the EDS), master "
        "heartbeat and SYNC while the controller makes progress, EMCY, the host's `nmt` "
        "command; guide: docs/canopen.md",
        (*_CAN_BUS,
         Key("nodes", "array of tables", "required", "`{id, eds, heartbeat_timeout, "
             "nmt_start, identity, config, store_config}` per node"),
         Key("sync_period", "float s 0.0005..4294.967295", "none", "produce SYNC at this "
             "period (while the controller makes progress: liveness_ms)"),
         Key("sync_priority", "integer 0..99", "80", "SCHED_FIFO priority of the producer "
             "processes (SocketCAN: SYNC and the master heartbeat), above the controller's "
             "threads; without root or CAP_SYS_NICE they stay SCHED_OTHER and the bus reports "
             "it once; 0: SCHED_OTHER"),
         Key("poll_period", "float s 0.0005..86400", "0.1", "default SDO polling period"),
         Key("sdo_timeout", "float s (0, 3600]", "0.3", "SDO response timeout"),
         Key("poll", "float s 0.0001..1", "0.005", "receive timeout on interfaces without a "
             "file descriptor"),
         Key("master_heartbeat_ms", "integer 1..65535", "none", "produce the master's "
             "heartbeat (0x700 + master_node_id, state OPERATIONAL) at this period; needed by "
             "every node with master_consumer_ms"),
         Key("liveness_ms", "integer 0 or 10..65535", "1000", "the master heartbeat and SYNC "
             "stop when the controller's kernel completed no scheduling round for this long (a "
             "stuck or stopped controller); 0: only while the process lives"),
         Key("master_node_id", "integer 1..127", "127", "the master's node id (its heartbeat "
             "COB-ID; what the nodes' 0x1016 entry watches)"),
         _UDP_PORT,
         Key("id", "integer 1..127", "required", "node id", "nodes[]"),
         Key("eds", "path", "required", "the node's EDS (relative to the map)", "nodes[]"),
         Key("heartbeat_timeout", "float s 0.001..196.605", "none", "a node silent longer "
             "fails its devices; with it, OPERATIONAL must be confirmed by a heartbeat",
             "nodes[]"),
         Key("restart_limit", "integer 0..1000", "5", "restarts of the recovery policy: a node "
             "that leaves OPERATIONAL by itself gets an NMT start once its cause cleared (0x1001 "
             "reads 0, an error-reset EMCY, its heartbeat back), at most this many times "
             "(counted again after 10 s OPERATIONAL); 0: never", "nodes[]"),
         Key("restart_backoff", "float s 0.05..30", "1.0", "the wait before restart 1, doubled "
             "for each next one (at most 30 s)", "nodes[]"),
         Key("nmt_start", "boolean", "true", "the driver starts the node (once per boot) and "
             "requires OPERATIONAL; false: required state is PRE-OPERATIONAL or OPERATIONAL",
             "nodes[]"),
         Key("identity", "inline table", "none", "`{vendor, product, revision, serial}` "
             "(serial optional): 0x1018 checked at each boot; a mismatch fails the node",
             "nodes[]"),
         Key("config", "table", "none", "downloaded at each boot, every write read back: the "
             "keys below", "nodes[]"),
         Key("store_config", "boolean or integer 1..127", "false", "after the download, "
             "write \"save\" to 0x1010:01 (or this sub-index) unless the node already held "
             "the configuration; for commissioning (flash wear); needs 0x1010 in the EDS",
             "nodes[]"),
         Key("heartbeat_producer_ms", "integer 0..65535", "none", "0x1017", "nodes[].config"),
         Key("master_consumer_ms", "integer 1..65535", "none", "0x1016:01 = master_node_id "
             "<< 16 | ms: the node watches the master heartbeat (needs master_heartbeat_ms, "
             "more than it)", "nodes[].config"),
         Key("error_behaviour", "integer 0..255", "none", "0x1029:01 (0 pre-operational, "
             "1 no change, 2 stopped on a communication error)", "nodes[].config"),
         Key("pdos", "array of tables", "[]", "`{pdo = \"rpdo1\"|\"tpdo1\"..., cob_id, "
             "transmission_type, inhibit_100us, event_timer_ms, enabled, map = [[index, "
             "subindex(, bits)], ...]}`: only the keys given are written (disable, parameters, "
             "mapping, enable); `check` validates each map against the EDS (at most 64 bits, "
             "mappable objects, writable for an RPDO, readable for a TPDO)", "nodes[].config"),
         Key("sdo", "array of tables", "[]", "`{index, subindex = 0, value}`: further SDO "
             "writes (the data type from the EDS), after the PDOs", "nodes[].config")),
        (Key("node", "integer", "required", "a node id of the bus"),
         Key("index", "integer", "required", "object index (write it `0x6064`)"),
         Key("subindex", "integer", "0", "sub-index"),
         Key("poll_period", "float s 0.0005..86400", "the bus's", "SDO polling period "
             "(objects not in a TPDO)")),
        '[[bus]]\nname = "axis"\nkind = "canopen"\nmaster_heartbeat_ms = 100\n\n'
        '[[bus.nodes]]\nid = 5\neds = "drive.eds"\nheartbeat_timeout = 0.3\n'
        'identity = { vendor = 0x1234, product = 0x42, revision = 0x10001 }\n'
        '[bus.nodes.config]\nheartbeat_producer_ms = 50\nmaster_consumer_ms = 300\n'
        'pdos = [{ pdo = "tpdo1", transmission_type = 255, map = [[0x6041, 0], [0x6064, 0]] }]'
        '\nsdo = [{ index = 0x6007, value = 3 }]\n\n'
        '[[device]]\nname = "position"\ndirection = "sensor"\n'
        'bus = "axis"\naddress = { node = 5, index = 0x6064 }'),
    "modbus-tcp": _Doc(
        "Modbus TCP client (an answer matched to its request by transaction id, unit, "
        "function and byte count; pymodbus' PDU codec); under faults: docs/modbus-faults.md",
        None, None,
        '[[bus]]\nname = "plc"\nkind = "modbus-tcp"\nhost = "127.0.0.1"\nport = 5020\n\n'
        '[[device]]\nname = "level"\ndirection = "sensor"\nbus = "plc"\n'
        'address = { table = "input", address = 0 }'),
    "modbus-rtu": _Doc(
        "Modbus RTU client on a serial line (an answer matched by unit, function, byte count "
        "and CRC, the input flushed before each request); under faults: docs/modbus-faults.md",
        None, None,
        '[[bus]]\nname = "rtu"\nkind = "modbus-rtu"\nport = "/dev/ttyUSB0"\nbaudrate = 19200'),
    "serial": _Doc(
        "a serial line (pyserial): a text line protocol (regex) or binary frames (struct); "
        "when the port or a write fails: docs/serial-faults.md",
        (Key("url", "string", "required", "device path or pyserial URL (`socket://`, `loop://`)"),
         Key("baudrate", "integer", "9600", "bit/s"),
         Key("protocol", "string", "required", "`line` or `binary`"),
         Key("poll", "float s", "0.01", "read timeout on ports without a file descriptor"),
         Key("reconnect_min", "float s", "0.05", "first reopen back-off"),
         Key("reconnect_max", "float s", "2.0", "longest back-off"),
         Key("pattern", "string", "required", "regular expression with named groups matching a "
             "whole line", "line"),
         Key("eol", "string", '`"\\n"`', "line end (a trailing `\\r` is stripped)", "line"),
         Key("encoding", "string", "`ascii`", "text encoding", "line"),
         Key("max_line", "integer", "1024", "longest line in bytes", "line"),
         Key("sync", "string", "required", "hex sync bytes, e.g. `AA 55`", "binary"),
         Key("struct", "string", "required", "`struct` format of the payload", "binary"),
         Key("fields", "array of strings", "required", "one name per struct item, `_` to "
             "ignore", "binary"),
         Key("checksum", "string", "`none`", "`none`, `sum8` or `xor8`", "binary")),
        (Key("group", "string", "required", "the pattern's named group", "line sensor"),
         Key("type", "string", "`number`", "`number` or `text`", "line sensor"),
         Key("field", "string", "required", "one of `fields`", "binary sensor"),
         Key("format", "string", "required", "`str.format` with `{value}`, e.g. "
             "`SET {value:.2f}`", "line actuator"),
         Key("struct", "string", "required", "`struct` format of the value", "binary actuator"),
         Key("prefix", "string", '""', "hex bytes before the value", "binary actuator")),
        '[[bus]]\nname = "scale"\nkind = "serial"\nurl = "socket://127.0.0.1:7001"\n'
        'protocol = "line"\npattern = "W=(?P<w>[-0-9.]+)"\n\n[[device]]\nname = "weight"\n'
        'direction = "sensor"\nbus = "scale"\naddress = { group = "w" }'),
    "weld-direct": _Doc(
        "the welding cell's model in-process (chcos' own demo binding)",
        None, None,
        '[[device]]\nname = "arc_temp"\ndirection = "sensor"\nbus = "cell"\n'
        'address = { signal = "arc_temp" }'),
}


def _address_keys(variants: tuple[type, ...]) -> tuple[Key, ...]:
    """The address keys of a kind whose address takes one of ``variants``: a key the same in
    every variant that has keys is listed once, any other with its variant's ``VARIANT``."""
    docs = [(getattr(v, "VARIANT", ""), reference(v)) for v in variants]
    shaped = [keys for _label, keys in docs if keys]
    out: list[Key] = []
    for label, keys in docs:
        for k in keys:
            if all(k in other for other in shaped):
                if k not in out:
                    out.append(k)
            else:
                out.append(dataclasses.replace(k, variant=k.variant or label))
    return tuple(out)


def kind_reference(kind: str) -> Kind:
    """Bus kind ``kind`` as the reference documents it: its tables from its driver's option
    dataclasses where it declares them, else from :data:`DOCS`. Raises KeyError for a kind
    :data:`DOCS` does not describe, LookupError for one with neither, and
    :class:`chcos.errors.DriverNotAvailable` if its driver cannot be imported."""
    doc = DOCS[kind]
    cls = driver_class(kind)
    variants = cls.Addresses or ((cls.Address,) if cls.Address is not None else ())
    options = reference(cls.Options) if cls.Options is not None else doc.options
    address = _address_keys(variants) if variants else doc.address
    if options is None or address is None:
        raise LookupError(f"bus kind {kind!r}: its driver declares no option dataclass for its "
                          f"{'options' if options is None else 'address'} and mapref.DOCS has "
                          f"no hand-written table")
    return Kind(doc.summary, options, address, doc.example)


@functools.cache
def kinds() -> dict[str, Kind]:
    """Every documented bus kind, in the reference's order (see :func:`kind_reference`)."""
    return {name: kind_reference(name) for name in DOCS}


def _table(keys: tuple[Key, ...]) -> list[str]:
    out = ["| key | type | default | meaning |", "|---|---|---|---|"]
    for k in keys:
        where = f" ({k.variant})" if k.variant else ""
        out.append(f"| `{k.name}`{where} | {k.type} | {k.default} | {k.meaning} |")
    return out


def render() -> str:
    """The reference as Markdown."""
    out = ["# Device-map reference", "",
           "Generated by `python -m chcos.devices.mapref` from the bus kinds' option dataclasses "
           "(`Options`/`Address` of each driver, `chcos.devices.options`) and, for kinds not "
           "converted yet, the tables in `chcos/devices/mapref.py`; "
           "`vcan_tests/test_integrator_reference.py` fails when a driver accepts a key this "
           "page does not list. Device maps are TOML files of `[[bus]]` and `[[device]]` tables "
           "(`busconfig/README.md`); `chcos check FILE...` validates them without opening a bus, "
           "and `chcos import eds|dbc|modbus` writes them from vendor files.", "",
           "## Every `[[bus]]`", "", *_table(COMMON_BUS), "",
           "## Every `[[device]]`", "", *_table(COMMON_DEVICE), ""]
    for name, kind in kinds().items():
        out += [f"## `{name}`", "", kind.summary + ".", "", "Bus options:", ""]
        out += _table(kind.options) if kind.options else ["none"]
        out += ["", "Device address:", ""]
        out += _table(kind.address) if kind.address else ["none: `address` is left out"]
        out += ["", "```toml", kind.example, "```", ""]
    return "\n".join(out)


if __name__ == "__main__":
    sys.stdout.write(render())
