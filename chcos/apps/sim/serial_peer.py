"""serial_peer - the simulated peer of a ``serial`` bus: in a virtual cell the other end of an
in-process direct line (:mod:`drivers.serial_direct`: its bytes reach the driver inside its tick
on the kernel thread, and the driver's commands reach it inside the driver's write), else
(``chcos sim --from``) a TCP serial server, speaking the bus's framing. Sensor lines are
generated from the line protocol's ``pattern`` (an example string for each named group, built
from the pattern's own parse tree, then checked against the pattern); binary frames are sync +
``struct`` payload + checksum (:mod:`drivers.codecs.serial`); actuator commands are parsed back
from their ``format`` or ``struct``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import os
import re
import socket
import threading
from typing import Any

from chcos.apps.sim.peers import Mutable, Peer
from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.errors import ConfigError
from drivers.serial_direct import SCHEME, LineEnd, open_end

_lines = itertools.count()


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


class SerialPeer(Mutable, Peer):
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
        options = dict(o)
        #: the direct line of a virtual cell (rewrite), else None: a TCP serial server
        self.end: LineEnd | None = None
        port = 0
        if rewrite:
            options["url"] = f"{SCHEME}chcos-sim-{bus.name}-{os.getpid()}-{next(_lines)}"
            self.end = open_end(options["url"])
        elif m:
            port = int(m.group(2))
            options["url"] = f"socket://127.0.0.1:{port}"
        else:
            raise ConfigError(f"{bus.file}: {bus.key} ({bus.name}): url {url!r}: a simulated "
                              "serial peer serves socket://127.0.0.1:PORT only")
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
        self.server: socket.socket | None = None
        if self.end is not None:
            self.end.set_receiver(self._bytes_in)
        else:
            self.server = socket.create_server(("127.0.0.1", port))
            self.server.setblocking(False)

    def _bytes_in(self, data: bytes) -> None:
        """Bytes from the driver on the direct line (inside its write, the kernel thread)."""
        with self.lock:
            self.buf += data
            self._parse()

    def _accept(self) -> None:
        """Take the newest waiting connection, if any (under ``lock``). Accepting here, on the
        thread that ticks or asks, rather than on a thread of its own, makes a virtual-time run
        deterministic: once the driver has connected (the kernel settles the driver before
        virtual time moves), the next tick sends to it."""
        while self.server is not None:
            try:
                conn, _ = self.server.accept()
            except (BlockingIOError, OSError):
                return
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
        if self.muted or not self.sensors:
            return
        if self.end is not None:
            if self.end.line.other(self.end) is not None:   # the driver's end is there
                with contextlib.suppress(OSError):
                    self.end.write(self._line() if self.proto == "line" else self._frame())
            return
        self._accept()
        if self.conn is None:
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
            self._accept()
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

    def describe(self) -> str:
        return f"serial peer ({self.proto}) on {self.bus.options['url']}"

    def close(self) -> None:
        with self.lock:
            if self.conn is not None:
                self.conn.close()
        if self.server is not None:
            self.server.close()
        if self.end is not None:
            self.end.close()
