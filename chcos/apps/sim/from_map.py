"""from_map - simulated slaves for any device map, so a user's own cell runs without its hardware.

:func:`simulate` takes a validated :class:`~chcos.devices.spec.DeviceMap` and starts, per bus, a
peer
that answers the bus's devices on the real protocol:

* ``modbus-tcp`` - a pymodbus server (:class:`chcos.apps.sim.modbus_server.ModbusSimServer`) holding
  every mapped register, coil and input; ``modbus-rtu`` - the same with RTU framing over a TCP
  socket (the bus's ``port`` becomes ``socket://127.0.0.1:PORT``);
* ``can`` - a node on the bus's python-can channel that sends the sensors' messages (coded with
  the bus's DBC, or the raw signal layout, by the driver's own codec with the directions turned
  round) every cycle (the DBC's ``GenMsgCycleTime``, else 0.1 s) and decodes the actuators'
  frames;
* ``canopen`` - per node, :class:`chcos.apps.sim.canopen_slave.CanopenSlave` over the node's EDS
  (canopen's LocalNode: SDO server, NMT, RPDOs applied, TPDOs sent on change and every event
  timer) with a heartbeat every third of the map's ``heartbeat_timeout``;
* ``serial`` - a TCP serial server (the driver reaches it as ``socket://127.0.0.1:PORT``)
  speaking the bus's framing: a line protocol's sensor lines are generated from its ``pattern``
  (the named groups filled with the values; the line is checked against the pattern), binary
  frames are sync + ``struct`` payload + checksum; actuator commands are parsed back from their
  ``format`` or ``struct``;
* ``memory``, ``signal``, ``weld-direct`` - in-process already; kept as they are.

With ``rewrite=True`` (``chcos run --virtual``, the pytest plugin) peers take free loopback ports
and private python-can ``virtual`` channels, and the returned map points at them (the user's
files are untouched); with ``rewrite=False`` (``chcos sim --from MAP``) they serve the addresses
the map names, so ``chcos run`` of the same map finds them (a Modbus host must be a loopback
address).

:class:`SimSlaves` is the handle: :meth:`~SimSlaves.set` puts a sensor's value (engineering units,
the map's scale and offset applied backwards), :meth:`~SimSlaves.script` makes it follow a
function of time (:func:`parse_script`: constant, ramp, sine, square, CSV trace),
:meth:`~SimSlaves.get` reads what the system last wrote to an actuator, and
:meth:`~SimSlaves.silence`/:meth:`~SimSlaves.restore` make a bus's peer stop and resume answering.
Time comes from :meth:`~SimSlaves.attach` (a kernel's clock: virtual time stays deterministic) or
:meth:`~SimSlaves.run_realtime`. A serial bus on a device path (not ``socket://``) can be
simulated only with ``rewrite``; a pattern with back-references is refused, naming the bus.
"""

from __future__ import annotations

import bisect
import contextlib
import csv
import dataclasses
import itertools
import math
import os
import re
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from chcos.apps.sim.modbus_server import ModbusSimServer, RegisterStore
from chcos.devices.spec import BusSpec, DeviceMap, DeviceSpec
from chcos.errors import ConfigError, DeviceError

IN_PROCESS = ("memory", "signal", "weld-direct")
"""Bus kinds that need no simulated peer."""
SIMULATED = ("modbus-tcp", "modbus-rtu", "can", "canopen", "serial", *IN_PROCESS)
"""Bus kinds :func:`simulate` can stand in for."""
LOOPBACK = ("127.0.0.1", "localhost", "::1")
TICK = 0.01
"""Seconds between two updates of scripted values and cyclic frames."""
_channels = itertools.count()

Script = Callable[[float], float]


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


# ---- scripted values --------------------------------------------------------------------------
def _args(text: str, names: tuple[str, ...], spec: str) -> list[float]:
    vals: dict[str, float] = {}
    parts = [p.strip() for p in text.split(",") if p.strip()]
    for i, p in enumerate(parts):
        key, eq, v = p.partition("=")
        name = key.strip() if eq else (names[i] if i < len(names) else "")
        if name not in names:
            raise ConfigError(f"value script {spec!r}: unexpected argument {p!r}; expected "
                              f"{', '.join(names)}")
        try:
            vals[name] = float(v if eq else p)
        except ValueError:
            raise ConfigError(f"value script {spec!r}: {name} {p!r} is not a number") from None
    missing = [n for n in names if n not in vals]
    if missing:
        raise ConfigError(f"value script {spec!r}: missing {', '.join(missing)} (expected "
                          f"{spec.split('(')[0]}({', '.join(names)}))")
    return [vals[n] for n in names]


def csv_trace(path: str | Path, column: str | None = None) -> Script:
    """A value following a CSV trace: first column the time in seconds, ``column`` (default the
    second) the value; linear between rows, the last value held after the end. Raises
    ConfigError naming the file and row."""
    path = Path(path)
    try:
        rows = list(csv.reader(path.read_text(encoding="utf-8").splitlines()))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the trace: {exc}") from exc
    if len(rows) < 2:
        raise ConfigError(f"{path}: expected a header row (t, value...) and at least one row")
    header = [h.strip() for h in rows[0]]
    col = 1 if column is None else (header.index(column) if column in header else -1)
    if col < 1 or col >= len(header):
        raise ConfigError(f"{path}: no column {column!r}; columns: {', '.join(header[1:])}")
    ts: list[float] = []
    vs: list[float] = []
    for no, row in enumerate(rows[1:], 2):
        if not row or not "".join(row).strip():
            continue
        try:
            t, v = float(row[0]), float(row[col])
        except (ValueError, IndexError):
            raise ConfigError(f"{path}: row {no}: expected numbers in columns {header[0]} and "
                              f"{header[col]}") from None
        if ts and t < ts[-1]:
            raise ConfigError(f"{path}: row {no}: time {t} goes backwards")
        ts.append(t)
        vs.append(v)

    def at(now: float) -> float:
        i = bisect.bisect_right(ts, now)
        if i == 0:
            return vs[0]
        if i == len(ts):
            return vs[-1]
        t0, t1, v0, v1 = ts[i - 1], ts[i], vs[i - 1], vs[i]
        return v0 if t1 == t0 else v0 + (v1 - v0) * (now - t0) / (t1 - t0)

    return at


def parse_script(spec: str, base_dir: Path | None = None) -> Script:
    """A value script from its text: ``42``, ``ramp(start, end, period)`` (saw-tooth),
    ``sine(center, amplitude, period)``, ``square(low, high, period)``, ``csv(FILE[, column])``;
    arguments also as ``name=value``. Raises ConfigError naming the script and what was
    expected."""
    text = spec.strip()
    try:
        value = float(text)
        return lambda now: value
    except ValueError:
        pass
    m = re.fullmatch(r"(\w+)\((.*)\)", text)
    if not m:
        raise ConfigError(f"value script {spec!r}: expected a number, ramp(start, end, period), "
                          "sine(center, amplitude, period), square(low, high, period) or "
                          "csv(FILE[, column])")
    fn, body = m.group(1), m.group(2)
    if fn == "csv":
        parts = [p.strip() for p in body.split(",")]
        path = Path(parts[0])
        if base_dir is not None and not path.is_absolute():
            path = base_dir / path
        return csv_trace(path, parts[1] if len(parts) > 1 else None)
    if fn == "ramp":
        start, end, period = _args(body, ("start", "end", "period"), spec)
        return lambda now: start + (end - start) * ((now % period) / period)
    if fn == "sine":
        center, amplitude, period = _args(body, ("center", "amplitude", "period"), spec)
        return lambda now: center + amplitude * math.sin(2 * math.pi * now / period)
    if fn == "square":
        low, high, period = _args(body, ("low", "high", "period"), spec)
        return lambda now: low if (now % period) < period / 2 else high
    raise ConfigError(f"value script {spec!r}: unknown function {fn!r}; expected ramp, sine, "
                      "square or csv")


# ---- peers ------------------------------------------------------------------------------------
class _Peer:
    """One bus's simulated peer."""

    bus: BusSpec

    def __init__(self, bus: BusSpec, devices: tuple[DeviceSpec, ...], rewrite: bool) -> None:
        self.bus = bus

    def set(self, device: DeviceSpec, raw: Any) -> None:
        raise NotImplementedError

    def get(self, device: DeviceSpec) -> Any:
        raise NotImplementedError

    def tick(self, now: float) -> None:
        """Clock time ``now`` (seconds since the slaves started): send what is due."""

    def silence(self) -> None:
        raise NotImplementedError

    def restore(self) -> None:
        raise NotImplementedError

    def describe(self) -> str:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class _ModbusPeer(_Peer):
    def __init__(self, bus: BusSpec, devices: tuple[DeviceSpec, ...], rewrite: bool) -> None:
        from drivers.codecs.modbus import point_of

        self.points = {d.name: point_of(d) for d in devices}
        pts = list(self.points.values())
        units = sorted({p.unit for p in pts}) or [1]
        size = max([p.address + p.size for p in pts] + [16])
        self.store = RegisterStore(units, size=size)
        framer: Literal["tcp", "rtu"] = "tcp" if bus.kind == "modbus-tcp" else "rtu"
        options = dict(bus.options)
        if rewrite:
            port = free_port()
            if framer == "tcp":
                options.update(host="127.0.0.1", port=port)
            else:
                options["port"] = f"socket://127.0.0.1:{port}"
            host = "127.0.0.1"
        elif framer == "tcp":
            host, port = str(options["host"]), int(options.get("port", 502))
            if host not in LOOPBACK:
                raise ConfigError(f"{bus.file}: {bus.key} ({bus.name}): host {host!r}: a "
                                  "simulated slave listens on loopback only (expected "
                                  "127.0.0.1)")
        else:
            m = re.fullmatch(r"socket://(127\.0\.0\.1|localhost):(\d+)", str(options["port"]))
            if not m:
                raise ConfigError(f"{bus.file}: {bus.key} ({bus.name}): port "
                                  f"{options['port']!r}: a simulated RTU slave needs "
                                  "socket://127.0.0.1:PORT")
            host, port = "127.0.0.1", int(m.group(2))
        self.bus = dataclasses.replace(bus, options=options)
        self.server = ModbusSimServer(self.store, port, host=host, framer=framer)
        self.server.start()

    def set(self, device: DeviceSpec, raw: Any) -> None:
        p = self.points[device.name]
        if p.type != "bool" and not p.type.startswith("float"):
            raw = round(raw)
        self.store.set_value(p.unit, p.table, p.address, raw, p.type, p.word_order)

    def get(self, device: DeviceSpec) -> Any:
        p = self.points[device.name]
        return self.store.get_value(p.unit, p.table, p.address, p.type, p.word_order)

    def silence(self) -> None:
        self.server.stop()

    def restore(self) -> None:
        self.server.start()

    def describe(self) -> str:
        kind = "Modbus TCP" if self.server.framer == "tcp" else "Modbus RTU over TCP"
        return f"{kind} server on {self.server.host}:{self.server.port}"

    def close(self) -> None:
        self.server.stop()


def _can_args(options: Any, rewrite: bool, tag: str) -> dict[str, Any]:
    if rewrite:
        return {"interface": "virtual",
                "channel": f"chcos-sim-{tag}-{os.getpid()}-{next(_channels)}"}
    args = {k: options[k] for k in ("interface", "channel", "bitrate") if k in options}
    if "interface" not in args or "channel" not in args:
        import can

        cfg = can.util.load_config()
        args.setdefault("interface", cfg.get("interface"))
        args.setdefault("channel", cfg.get("channel"))
    return args


class _CanPeer(_Peer):
    def __init__(self, bus: BusSpec, devices: tuple[DeviceSpec, ...], rewrite: bool) -> None:
        import can

        from drivers.codecs.can import CanCodec

        flipped = [dataclasses.replace(d, direction="actuator" if d.direction == "sensor"
                                       else "sensor") for d in devices]
        self.codec = CanCodec(bus, flipped)
        self.args = _can_args(bus.options, rewrite, bus.name)
        options = dict(bus.options)
        if rewrite:
            options.update(self.args)
        self.bus = dataclasses.replace(bus, options=options)
        self.sensors = [d for d in devices if d.direction == "sensor"]
        self.actuators = {d.name: d for d in devices if d.direction == "actuator"}
        self.values: dict[str, Any] = {}
        self.muted = False
        self.lock = threading.Lock()
        self.received: dict[str, Any] = {}
        self.can: Any = can.Bus(**self.args)
        self.period: dict[str, float] = {}
        dbc_msgs: dict[str, Any] = {}
        for d in self.sensors:
            cycle = None
            if "message" in d.address and "dbc" in bus.options:
                if not dbc_msgs:
                    from drivers.codecs.can import load_dbc

                    dbc_msgs = {m.name: m for m in load_dbc(str(bus.options["dbc"])).messages}
                cycle = dbc_msgs[d.address["message"]].cycle_time
            self.period[d.name] = (cycle or 100) / 1000.0
        self.next_due: dict[str, float] = {d.name: 0.0 for d in self.sensors}

    def set(self, device: DeviceSpec, raw: Any) -> None:
        with self.lock:
            self.values[device.name] = raw
            if not self.muted:
                self._send(device.name)

    def _send(self, name: str) -> None:
        import can

        coded = self.codec.encode(name, self.values.get(name, 0))
        msg = can.Message(arbitration_id=coded.arbitration_id, data=coded.data,
                          is_extended_id=coded.is_extended_id)
        with contextlib.suppress(can.CanError):  # a full queue: the next cycle sends it again
            self.can.send(msg)

    def get(self, device: DeviceSpec) -> Any:
        with self.lock:
            while True:
                frame = self.can.recv(timeout=0)
                if frame is None:
                    break
                status, vals = self.codec.decode(frame)
                if status == "ok" and isinstance(vals, list):
                    for dev, v in vals:
                        self.received[dev] = v
            return self.received.get(device.name)

    def tick(self, now: float) -> None:
        with self.lock:
            if self.muted:
                return
            sent: set[int] = set()
            for d in self.sensors:
                if now + 1e-9 >= self.next_due[d.name]:
                    self.next_due[d.name] = now + self.period[d.name]
                    frame = self.codec.encode(d.name, self.values.get(d.name, 0))
                    if frame.arbitration_id not in sent:  # one frame carries all its signals
                        sent.add(frame.arbitration_id)
                        self._send(d.name)

    def silence(self) -> None:
        with self.lock:
            self.muted = True

    def restore(self) -> None:
        with self.lock:
            self.muted = False

    def describe(self) -> str:
        return f"CAN node on {self.args.get('interface')} channel {self.args.get('channel')}"

    def close(self) -> None:
        self.can.shutdown()


class _CanopenPeer(_Peer):
    def __init__(self, bus: BusSpec, devices: tuple[DeviceSpec, ...], rewrite: bool) -> None:
        from chcos.apps.sim.canopen_slave import CanopenSlave
        from drivers.codecs.canopen import eds_path

        self.args = _can_args(bus.options, rewrite, bus.name)
        options = dict(bus.options)
        if rewrite:
            options.update(self.args)
        self.bus = dataclasses.replace(bus, options=options)
        self.slaves: dict[int, Any] = {}
        self.heartbeat: dict[int, float] = {}
        self.muted = False
        self.next_hb: dict[int, float] = {}
        self.next_tpdo: dict[int, float] = {}
        try:
            for node in bus.options.get("nodes", []):
                nid = int(node["id"])
                slave = CanopenSlave(nid, eds_path(bus, str(node["eds"])),
                                     channel=str(self.args["channel"]),
                                     interface=str(self.args["interface"]), heartbeat_period=0.0)
                slave.start()
                self.slaves[nid] = slave
                if node.get("heartbeat_timeout"):
                    self.heartbeat[nid] = float(node["heartbeat_timeout"]) / 3
                    self.next_hb[nid] = 0.0
        except BaseException:
            self.close()
            raise

    def _slave(self, device: DeviceSpec) -> tuple[Any, int, int]:
        a = device.address
        return self.slaves[int(a["node"])], int(a["index"]), int(a.get("subindex", 0))

    def set(self, device: DeviceSpec, raw: Any) -> None:
        slave, index, sub = self._slave(device)
        var = slave._var(index, sub)  # the EDS's type decides how the value is coded
        if getattr(var, "data_type", None) not in _float_types():
            raw = round(raw) if not isinstance(raw, bool) else raw
        if self.muted:
            with slave._lock:
                slave._node.data_store.setdefault(index, {})[sub] = var.encode_raw(raw)
            return
        slave.set(index, sub, raw)

    def get(self, device: DeviceSpec) -> Any:
        slave, index, sub = self._slave(device)
        return slave.get(index, sub)

    def tick(self, now: float) -> None:
        if self.muted:
            return
        for nid, period in self.heartbeat.items():
            if now + 1e-9 >= self.next_hb[nid]:
                self.next_hb[nid] = now + period
                slave = self.slaves[nid]
                state = {"OPERATIONAL": 0x05, "STOPPED": 0x04}.get(slave.nmt_state, 0x7F)
                slave._network.send_message(0x700 + nid, bytes([state]))
        for slave in self.slaves.values():  # TPDO event timers
            period = slave._tpdo_event_period()
            if period is None:
                continue
            if now + 1e-9 >= self.next_tpdo.get(slave.node_id, 0.0):
                self.next_tpdo[slave.node_id] = now + period
                for pdo_map in slave._node.tpdo.map.values():
                    slave._transmit(pdo_map)

    def silence(self) -> None:
        self.muted = True

    def restore(self) -> None:
        self.muted = False

    def describe(self) -> str:
        return (f"CANopen node(s) {', '.join(str(n) for n in self.slaves)} on "
                f"{self.args.get('interface')} channel {self.args.get('channel')}")

    def close(self) -> None:
        for slave in self.slaves.values():
            slave.stop()


def _sre() -> Any:
    """Python's regex parser (``re._parser``): the only way to walk a pattern's structure."""
    import importlib

    return importlib.import_module("re._parser")


def _example(tree: Any, groups: dict[int, str]) -> str:
    """A string the parsed regex ``tree`` matches, with the text ``groups[n]`` for group n."""
    c = _sre()
    out: list[str] = []
    for op, av in tree:
        if op is c.LITERAL:
            out.append(chr(av))
        elif op is c.NOT_LITERAL:
            out.append("x" if av != ord("x") else "y")
        elif op is c.ANY:
            out.append("x")
        elif op is c.IN:
            out.append(_class_char(av))
        elif op in (c.MAX_REPEAT, c.MIN_REPEAT, getattr(c, "POSSESSIVE_REPEAT", None)):
            lo, _hi, sub = av
            out.append(_example(sub, groups) * lo)
        elif op is c.SUBPATTERN:
            gid, _add, _del, sub = av
            out.append(groups[gid] if gid in groups else _example(sub, groups))
        elif op is c.BRANCH:
            out.append(_example(av[1][0], groups))
        elif op in (c.AT, c.ASSERT, c.ASSERT_NOT):
            continue
        elif op is c.GROUPREF:
            raise ConfigError("back-references are not simulated")
        else:
            raise ConfigError(f"regex construct {op} is not simulated")
    return "".join(out)


def _class_char(items: Any) -> str:
    c = _sre()

    for op, av in items:
        if op is c.NEGATE:
            return "x"
        if op is c.LITERAL:
            return chr(av)
        if op is c.RANGE:
            return chr(av[0])
        if op is c.CATEGORY:
            return {c.CATEGORY_DIGIT: "0", c.CATEGORY_SPACE: " "}.get(av, "a")
    return "a"


class _SerialPeer(_Peer):
    """A TCP serial server (the driver's ``socket://`` URL) speaking the bus's framing: sensor
    lines generated from the ``pattern`` (the named groups filled with the values) or binary
    frames (sync + struct + checksum); actuator commands parsed back."""

    def __init__(self, bus: BusSpec, devices: tuple[DeviceSpec, ...], rewrite: bool) -> None:
        import string
        import struct

        from drivers.codecs.serial import checksum, parse_hex

        o = bus.options
        url = str(o["url"])
        m = re.fullmatch(r"socket://(127\.0\.0\.1|localhost):(\d+)", url)
        if rewrite:
            port = free_port()
        elif m:
            port = int(m.group(2))
        else:
            raise ConfigError(f"{bus.file}: {bus.key} ({bus.name}): url {url!r}: a simulated "
                              "serial peer serves socket://127.0.0.1:PORT only")
        options = dict(o)
        options["url"] = f"socket://127.0.0.1:{port}"
        self.bus = dataclasses.replace(bus, options=options)
        self.proto = str(o["protocol"])
        self.sensors = [d for d in devices if d.direction == "sensor"]
        self.actuators = [d for d in devices if d.direction == "actuator"]
        self.values: dict[str, Any] = {}
        self.received: dict[str, Any] = {}
        self.muted = False
        self.lock = threading.Lock()
        self.next_due = 0.0
        self._checksum, self._struct = checksum, struct
        if self.proto == "line":
            self.encoding = str(o.get("encoding", "ascii"))
            self.eol = str(o.get("eol", "\n"))
            self.pattern = re.compile(str(o["pattern"]))
            self.tree = _sre().parse(str(o["pattern"]))
            self.group_of = {d.name: str(d.address["group"]) for d in self.sensors}
            self.commands = []
            for d in self.actuators:
                rx = ""
                for lit, fld, _spec, _conv in string.Formatter().parse(str(d.address["format"])):
                    rx += re.escape(lit)
                    if fld is not None:
                        rx += r"(?P<value>[-+0-9.eE]+|nan|inf|True|False)"
                self.commands.append((re.compile(rx), d.name))
            self._line(check=True)
        else:
            self.sync = parse_hex(str(o["sync"]))
            self.fmt = str(o["struct"])
            self.fields = [str(f) for f in o["fields"]]
            self.check = str(o.get("checksum", "none"))
            self.field_of = {d.name: str(d.address["field"]) for d in self.sensors}
            self.frames = [(parse_hex(str(d.address.get("prefix", ""))),
                            str(d.address["struct"]), d.name) for d in self.actuators]
        self.buf = b""
        self.conn: socket.socket | None = None
        self.server = socket.create_server(("127.0.0.1", port))
        self.server.settimeout(0.1)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._accept, name=f"sim-serial-{bus.name}",
                                        daemon=True)
        self._thread.start()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.server.accept()
            except (TimeoutError, OSError):
                continue
            with self.lock:
                if self.conn is not None:
                    self.conn.close()
                conn.setblocking(False)
                self.conn = conn

    def _line(self, check: bool = False) -> bytes:
        groups = {}
        index = self.pattern.groupindex
        for d in self.sensors:
            v = self.values.get(d.name, 0)
            text = v if isinstance(v, str) else (f"{v:g}" if isinstance(v, float) else str(v))
            groups[index[self.group_of[d.name]]] = text
        where = f"{self.bus.file}: {self.bus.key} ({self.bus.name})"
        try:
            line = _example(self.tree, groups)
        except ConfigError as exc:
            raise ConfigError(f"{where}: pattern {self.pattern.pattern!r}: {exc}") from exc
        if self.pattern.fullmatch(line) is None:
            raise ConfigError(f"{where}: cannot make a line matching pattern "
                              f"{self.pattern.pattern!r} (tried "
                              f"{line!r})")
        return (line + self.eol).encode(self.encoding)

    def _frame(self) -> bytes:
        by_field = {self.field_of[d.name]: self.values.get(d.name, 0) for d in self.sensors}
        items = []
        for f, code in zip(self.fields, re.findall(r"\d*[a-zA-Z?]", self.fmt.lstrip("<>!=@")),
                           strict=False):
            v = by_field.get(f, 0)
            items.append(round(v) if code[-1] not in "efd" else float(v))
        payload = self._struct.pack(self.fmt, *items)
        return self.sync + payload + self._checksum(self.check, payload)

    def _send(self) -> None:
        if self.conn is None or self.muted or not self.sensors:
            return
        data = self._line() if self.proto == "line" else self._frame()
        with contextlib.suppress(OSError):
            self.conn.sendall(data)

    def set(self, device: DeviceSpec, raw: Any) -> None:
        with self.lock:
            self.values[device.name] = raw
            self._send()

    def get(self, device: DeviceSpec) -> Any:
        with self.lock:
            if self.conn is not None:
                with contextlib.suppress(BlockingIOError, OSError):
                    while chunk := self.conn.recv(4096):
                        self.buf += chunk
            self._parse()
            return self.received.get(device.name)

    def _parse(self) -> None:
        if self.proto == "line":
            eol = self.eol.encode(self.encoding)
            while eol in self.buf:
                raw, self.buf = self.buf.split(eol, 1)
                text = raw.decode(self.encoding, "replace").rstrip("\r")
                for rx, name in self.commands:
                    m = rx.fullmatch(text)
                    if m:
                        v = m.group("value")
                        self.received[name] = float(v) if v not in ("True", "False") else \
                            v == "True"
                        break
            return
        progress = True
        while progress:
            progress = False
            for prefix, fmt, name in self.frames:
                head = self.sync + prefix
                i = self.buf.find(head)
                size = self._struct.calcsize(fmt) + len(self._checksum(self.check, b""))
                if i >= 0 and len(self.buf) >= i + len(head) + size:
                    body = self.buf[i + len(head):i + len(head) + self._struct.calcsize(fmt)]
                    self.received[name] = self._struct.unpack(fmt, body)[0]
                    self.buf = self.buf[i + len(head) + size:]
                    progress = True

    def tick(self, now: float) -> None:
        with self.lock:
            if now + 1e-9 >= self.next_due:
                self.next_due = now + 0.1
                self._send()

    def silence(self) -> None:
        with self.lock:
            self.muted = True

    def restore(self) -> None:
        with self.lock:
            self.muted = False

    def describe(self) -> str:
        return f"serial peer ({self.proto}) on {self.bus.options['url']}"

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        with self.lock:
            if self.conn is not None:
                self.conn.close()
        self.server.close()


def _float_types() -> tuple[int, ...]:
    from canopen.objectdictionary import FLOAT_TYPES

    return tuple(FLOAT_TYPES)


_PEERS: dict[str, type[_Peer]] = {"modbus-tcp": _ModbusPeer, "modbus-rtu": _ModbusPeer,
                                  "can": _CanPeer, "canopen": _CanopenPeer,
                                  "serial": _SerialPeer}


@dataclass
class SimSlaves:
    """The simulated peers of one device map (see the module doc). Close with :meth:`close`."""

    devmap: DeviceMap
    specs: dict[str, DeviceSpec] = dataclasses.field(default_factory=dict)
    peers: dict[str, _Peer] = dataclasses.field(default_factory=dict)
    scripts: dict[str, Script] = dataclasses.field(default_factory=dict)
    _timer: Any = None
    _rt: threading.Thread | None = None
    _rt_stop: threading.Event = dataclasses.field(default_factory=threading.Event)
    _closed: bool = False

    def simulated(self, device: str) -> bool:
        """True if ``device`` has a simulated peer that :meth:`set`/:meth:`get` reach."""
        return device in self.specs and self.specs[device].bus in self.peers

    def _peer(self, device: str) -> tuple[_Peer, DeviceSpec]:
        spec = self.specs.get(device)
        if spec is None:
            raise DeviceError(f"no device named {device!r} in the device map")
        peer = self.peers.get(spec.bus)
        if peer is None:
            raise DeviceError(f"device {device!r} is on a {self.devmap.bus(spec.bus).kind} bus, "
                              "which is in-process: use inject instead")
        return peer, spec

    def set(self, device: str, value: Any) -> None:
        """Put ``value`` (engineering units) where the peer serves ``device``; the system reads
        it at its next poll or frame. Raises DeviceError for an unknown or in-process device and
        ConfigError if the raw value does not fit the register or signal."""
        peer, spec = self._peer(device)
        raw = value
        if isinstance(value, int | float) and not isinstance(value, bool):
            raw = (value - spec.offset) / spec.scale
        peer.set(spec, raw)

    def get(self, device: str) -> Any:
        """What the peer holds for ``device``, in engineering units (an actuator: the last value
        the system wrote; None if nothing arrived yet on CAN). Raises DeviceError for an unknown
        or in-process device."""
        peer, spec = self._peer(device)
        raw = peer.get(spec)
        if raw is None or isinstance(raw, bool):
            return raw
        return raw * spec.scale + spec.offset

    def script(self, device: str, script: Script | str) -> None:
        """Make sensor ``device`` follow ``script`` (a function of seconds since the start, in
        engineering units, or its text for :func:`parse_script`)."""
        self._peer(device)
        self.scripts[device] = parse_script(script) if isinstance(script, str) else script

    def silence(self, bus: str) -> None:
        """Make the peer of ``bus`` stop answering: a Modbus server closes its port, a CAN node
        stops sending, a CANopen node stops its heartbeat and TPDOs. Raises DeviceError if the
        bus has no simulated peer."""
        self._bus(bus).silence()

    def restore(self, bus: str) -> None:
        """Make the peer of ``bus`` answer again, with the values it held."""
        self._bus(bus).restore()

    def _bus(self, bus: str) -> _Peer:
        try:
            return self.peers[bus]
        except KeyError:
            raise DeviceError(f"bus {bus!r} has no simulated peer (simulated: "
                              f"{', '.join(sorted(self.peers)) or 'none'})") from None

    def describe(self) -> list[str]:
        """One line per peer: the bus and where it listens."""
        return [f"{name}: {peer.describe()}" for name, peer in self.peers.items()]

    def tick(self, now: float) -> None:
        """Apply the scripts at time ``now`` (seconds since the start) and send what is due."""
        for device, fn in self.scripts.items():
            self.set(device, fn(now))
        for peer in self.peers.values():
            peer.tick(now)

    def attach(self, kernel: Any) -> None:
        """Run on ``kernel``'s clock from now (virtual time stays deterministic)."""
        origin = kernel.clock.now()
        self.tick(0.0)
        self._timer = kernel.every(TICK, lambda: self.tick(kernel.clock.now() - origin))

    def run_realtime(self) -> None:
        """Run on wall-clock time on a thread of its own until :meth:`close`."""
        origin = time.monotonic()

        def loop() -> None:
            while not self._rt_stop.wait(TICK):
                self.tick(time.monotonic() - origin)

        self.tick(0.0)
        self._rt = threading.Thread(target=loop, name="chcos-sim-from-map", daemon=True)
        self._rt.start()

    def close(self) -> None:
        """Stop every peer. Idempotent."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._rt_stop.set()
        if self._rt is not None:
            self._rt.join(timeout=5)
            self._rt = None
        if self._closed:
            return
        self._closed = True
        for peer in self.peers.values():  # kept: get() still reads what the peers last held
            peer.close()


def simulate(devmap: DeviceMap, *, rewrite: bool = True) -> SimSlaves:
    """Start a simulated peer for every bus of ``devmap`` that has devices; returns the handle,
    whose ``devmap`` is the map the system should load (pointed at the peers when ``rewrite``).
    Idle actuators hold their safe values. Raises ConfigError naming the bus and its file for a
    bus kind without a simulated peer, BusError if a peer cannot listen or open its channel."""
    for bus in devmap.buses:
        if bus.kind not in SIMULATED and devmap.devices_on(bus.name):
            raise ConfigError(f"{bus.file}: {bus.key} ({bus.name}): no simulated peer for a "
                              f"{bus.kind!r} bus (simulated kinds: {', '.join(SIMULATED)})")
    slaves = SimSlaves(devmap, {d.name: d for d in devmap.devices})
    buses: list[BusSpec] = []
    try:
        for bus in devmap.buses:
            devs = devmap.devices_on(bus.name)
            if bus.kind in _PEERS and devs:
                peer = _PEERS[bus.kind](bus, devs, rewrite)
                slaves.peers[bus.name] = peer
                buses.append(peer.bus)
                for d in devs:
                    if d.direction == "actuator" and d.safe_value is not None \
                            and bus.kind.startswith("modbus"):
                        slaves.set(d.name, d.safe_value)  # an idle output holds its safe value
            else:
                buses.append(bus)
    except BaseException:
        slaves.close()
        raise
    slaves.devmap = dataclasses.replace(devmap, buses=tuple(buses))
    return slaves


def _fault(item: str, slaves: SimSlaves) -> tuple[str, float, float]:
    """``BUS@START[-END]`` -> (bus, start, end); raises ConfigError naming the item."""
    m = re.fullmatch(r"([\w.\-]+)@([0-9.]+)(?:-([0-9.]+))?", item.strip())
    if not m:
        raise ConfigError(f"--fault {item!r}: expected BUS@START[-END] (seconds), e.g. plc@5-8")
    bus, t0 = m.group(1), float(m.group(2))
    t1 = float(m.group(3)) if m.group(3) else math.inf
    if bus not in slaves.peers:
        raise ConfigError(f"--fault {item!r}: bus {bus!r} has no simulated peer (simulated: "
                          f"{', '.join(sorted(slaves.peers)) or 'none'})")
    if t1 <= t0:
        raise ConfigError(f"--fault {item!r}: the end must come after the start")
    return bus, t0, t1


def main(argv: list[str]) -> int:
    """``chcos sim --from MAP...``: serve simulated slaves at the addresses the maps name until
    Ctrl-C, SIGTERM or ``--duration``; prints what each actuator was sent once a second.
    Returns 0, or 2 when a map or script is invalid or a peer cannot listen."""
    import argparse
    import signal
    import sys

    from chcos.devices.devmap import load
    from chcos.errors import ChcosError

    ap = argparse.ArgumentParser(
        prog="chcos sim --from",
        description="Simulated slaves for every bus of the device maps, at the addresses the "
                    "maps name (Modbus servers on loopback, CAN and CANopen nodes on the maps' "
                    "channels), so that 'chcos run' of the same system finds them. Sensor values "
                    "are constant (0 unless --value) or scripted.")
    ap.add_argument("--from", dest="maps", metavar="MAP", action="append", required=True,
                    help="a device-map file (repeat for several)")
    ap.add_argument("--value", action="append", default=[], metavar="DEVICE=SCRIPT",
                    help="a sensor's value: a number, ramp(start, end, period), sine(center, "
                         "amplitude, period), square(low, high, period) or csv(FILE[, column])")
    ap.add_argument("--fault", action="append", default=[], metavar="BUS@START[-END]",
                    help="silence the peer of BUS from START seconds (to END), e.g. plc@5-8: "
                         "a Modbus server closes its port, CAN and CANopen nodes stop sending")
    ap.add_argument("--duration", type=float, help="stop after this many seconds")
    args = ap.parse_args(argv)
    stop = threading.Event()
    old = {sig: signal.signal(sig, lambda *_: stop.set())
           for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        devmap = load(args.maps)
        slaves = simulate(devmap, rewrite=False)
        try:
            for item in args.value:
                name, eq, spec = item.partition("=")
                if not eq:
                    raise ConfigError(f"--value {item!r}: expected DEVICE=SCRIPT")
                if name not in slaves.specs or slaves.specs[name].direction != "sensor":
                    raise ConfigError(f"--value {item!r}: {name!r} is not a sensor of the maps")
                slaves.script(name, parse_script(spec, Path.cwd()))
            faults = [_fault(item, slaves) for item in args.fault]
            for line in slaves.describe():
                print(f"simulating {line}", flush=True)
            slaves.run_realtime()
            start = time.monotonic()
            shown_at = 0.0
            silenced: set[str] = set()
            while not stop.wait(0.1):
                t = time.monotonic() - start
                for bus, t0, t1 in faults:
                    want = t0 <= t < t1
                    if want and bus not in silenced:
                        slaves.silence(bus)
                        silenced.add(bus)
                        print(f"t={t:6.1f} s  fault: {bus} silenced", flush=True)
                    elif not want and bus in silenced and t >= t1:
                        slaves.restore(bus)
                        silenced.discard(bus)
                        print(f"t={t:6.1f} s  fault over: {bus} answers again", flush=True)
                if t + 1e-9 < shown_at + 1.0:
                    continue
                shown_at = t
                shown = []
                for d in devmap.devices:
                    if slaves.simulated(d.name):
                        v = slaves.get(d.name)
                        text = f"{v:.4g}" if isinstance(v, float) else str(v)
                        shown.append(f"{d.name}={text}")
                print(f"t={t:6.1f} s  " + "  ".join(shown), flush=True)
                if args.duration is not None and t >= args.duration:
                    break
        finally:
            slaves.close()
    except ChcosError as exc:
        print(f"chcos sim --from: {exc}", file=sys.stderr)
        return 2
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
    return 0
