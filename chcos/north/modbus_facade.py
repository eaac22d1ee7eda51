"""modbus_facade - the device table as a Modbus TCP server (pymodbus), for SCADA and HMIs above.

The register map is generated from the device table, in Devtab order (the order of the device
maps), and printed by ``chcos facade modbus --print-map FILE...``:

* **input registers** (FC 4): every device's value as an IEEE-754 float32 in two registers, high
  word first (big-endian, "ABCD"), sensors first, then actuators (their last command);
  NaN when there is no numeric value yet;
* **discrete inputs** (FC 2): one per device in the same order, 1 when the device is healthy
  (status OK), 0 when failed, stale or suspended;
* **holding registers** (FC 3, 6, 16): only the actuators whose device map says
  ``north_writable = true``, two registers each (float32 ABCD); reading gives the last command.

A write goes through the same rules as a task's: on the kernel thread, the device's limits
(refused, never clamped) and status, and the owner rule: an actuator commanded by a task that is
active (not suspended, holding a command) belongs to that task and is refused. Refusals are
Modbus exception codes that say why:

====  ====================  ==========================================================
code  name                  when
====  ====================  ==========================================================
0x01  ILLEGAL_FUNCTION      coils: the facade has none
0x02  ILLEGAL_ADDRESS       no such register, or a write covering half of a float
0x03  ILLEGAL_VALUE         outside the device's limits, or not a finite number
0x04  DEVICE_FAILURE        the actuator is failed or suspended
0x06  DEVICE_BUSY           an active task owns the actuator
====  ====================  ==========================================================

A request whose function code has the exception bit set (0x80 and above: no request is) is
answered ILLEGAL_FUNCTION as pymodbus answers any exception, not passed to the datastore.

The unit id is ignored (one device table). The server binds 127.0.0.1 by default; Modbus has no
authentication, so another address must be asked for explicitly (``allow_remote``).
Connections are bounded (:mod:`chcos.north.guard`): at most :data:`MAX_CONNECTIONS` at once
(a connection beyond is closed as soon as accepted), one silent for
:data:`chcos.north.guard.IDLE_TIMEOUT` seconds is closed; refusals, refused writes and what
pymodbus logs about junk are counted and logged once per period per cause.
"""

from __future__ import annotations

import asyncio
import logging
import math
import struct
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from pymodbus.constants import ExcCodes
from pymodbus.datastore import ModbusServerContext
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.server import ModbusTcpServer

from chcos.comm.config import is_loopback
from chcos.comm.secret import Throttle
from chcos.devices.spec import DeviceMap, DeviceSpec
from chcos.errors import ChcosError, DeviceError
from chcos.north import NorthError
from chcos.north.health import device_health
from chcos.serving.guard import ConnectionGate, connection_cap, throttle_library_logs
from chcos.serving.loopthread import LoopThread
from chcos.tables.tasks import TaskState

if TYPE_CHECKING:
    from chcos.system.embedded import System

log = logging.getLogger("chcos.north.modbus")
INPUT, DISCRETE, HOLDING = "input", "discrete", "holding"
#: Concurrent Modbus connections the facade takes (less if the descriptor limit is low).
MAX_CONNECTIONS = 64


@dataclass(frozen=True)
class Entry:
    """One row of the register map: ``table`` (input, discrete, holding), first ``address``,
    ``count`` of registers or bits, and the device it shows."""

    table: str
    address: int
    count: int
    device: DeviceSpec

    @property
    def access(self) -> str:
        """``read`` or ``read/write``."""
        return "read/write" if self.table == HOLDING else "read"


class RegisterMap:
    """The facade's register map of a device map (see the module doc)."""

    def __init__(self, devmap: DeviceMap) -> None:
        devs = [d for d in devmap.devices if d.direction == "sensor"] + \
            [d for d in devmap.devices if d.direction == "actuator"]
        self.inputs = [Entry(INPUT, 2 * i, 2, d) for i, d in enumerate(devs)]
        self.discretes = [Entry(DISCRETE, i, 1, d) for i, d in enumerate(devs)]
        self.holdings = [Entry(HOLDING, 2 * i, 2, d) for i, d in
                         enumerate(d for d in devs if d.north_writable)]

    def entries(self) -> list[Entry]:
        """Every row, table by table."""
        return [*self.inputs, *self.discretes, *self.holdings]

    def render(self) -> str:
        """The map as a text table (what ``--print-map`` prints)."""
        rows = [("table", "address", "count", "type", "device", "kind", "units", "limits",
                 "access")]
        for e in self.entries():
            lo, hi = e.device.limits
            limits = "" if lo is None and hi is None else \
                f"[{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]"
            rows.append((e.table, str(e.address), str(e.count),
                         "bool (1 = healthy)" if e.table == DISCRETE else "float32 ABCD",
                         e.device.name, e.device.direction, e.device.units,
                         limits if e.table != DISCRETE else "", e.access))
        widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
        lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip()
                 for r in rows]
        lines.insert(1, "  ".join("-" * w for w in widths))
        return "\n".join(lines)


def encode(value: Any) -> list[int]:
    """A value as two registers (float32, high word first); NaN if it is not a number."""
    f = float(value) if isinstance(value, int | float) else math.nan
    hi, lo = struct.unpack(">HH", struct.pack(">f", f))
    return [hi, lo]


def decode(regs: Sequence[int]) -> float:
    """Two registers (float32, high word first) as a float."""
    return float(struct.unpack(">f", struct.pack(">HH", regs[0], regs[1]))[0])


class Refused(Exception):
    """A north-side write refused: the Modbus exception code and the reason."""

    def __init__(self, code: ExcCodes, reason: str) -> None:
        super().__init__(reason)
        self.code = code


def owner_of(system: System, device: str) -> str | None:
    """The active task that commands actuator ``device`` (holds a command, not suspended), or
    None if no task holds it now."""
    for lk in list(system.msgtab):
        if lk.dst == device and lk.src in system.tsktab:
            t = system.tsktab.get(lk.src)
            if t.state is not TaskState.SUSPENDED and not t.frozen and t.owner is not None:
                return t.name
    return None


def north_write(system: System, device: str, value: float, source: str) -> None:
    """Command actuator ``device`` from the north (call it on the kernel thread, through
    ``System.call``). Raises :class:`Refused` with the exception code and the reason."""
    e = system.devtab.get(device)
    spec = e.spec
    if e.is_sensor or not spec.north_writable:
        raise Refused(ExcCodes.ILLEGAL_ADDRESS, f"{device} is not writable from the north")
    if not math.isfinite(value):
        raise Refused(ExcCodes.ILLEGAL_VALUE, f"{device}: {value} is not a finite number")
    lo, hi = spec.limits
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        e.rejected += 1
        raise Refused(ExcCodes.ILLEGAL_VALUE,
                      f"{device}: {value} {spec.units} is outside its limits "
                      f"[{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]")
    h = device_health(e)
    if h.status in ("failed", "suspended"):
        raise Refused(ExcCodes.DEVICE_FAILURE, f"{device} is {h.status}: {h.cause}")
    owner = owner_of(system, device)
    if owner is not None:
        raise Refused(ExcCodes.DEVICE_BUSY, f"{device} is commanded by task {owner} (active)")
    try:
        system.devtab.write(device, value, source=source)
    except DeviceError as exc:
        raise Refused(ExcCodes.DEVICE_FAILURE, str(exc)) from exc


class _Context(ModbusServerContext):
    """The datastore pymodbus calls: reads from Devtab, writes through :func:`north_write`."""

    def __init__(self, facade: ModbusFacade) -> None:  # no super(): no simulated devices
        self.facade = facade
        self.simdevices = []
        self.old_simulator = True
        self._devices = {}

    def device_ids(self) -> list[int]:
        """One device table, whatever the unit id."""
        return [0]

    async def async_getValues(self, device_id: int, func_code: int, address: int,
                              count: int = 1) -> list[int] | list[bool] | ExcCodes:
        """Registers or bits from the device table (read as they are now)."""
        f = self.facade
        devtab = f.system.devtab
        if func_code == 2:
            if address + count > len(f.map.discretes):
                return ExcCodes.ILLEGAL_ADDRESS
            return [device_health(devtab.get(e.device.name)).healthy
                    for e in f.map.discretes[address:address + count]]
        if func_code == 4:
            table = f.map.inputs
        elif func_code in (3, 6, 16, 22, 23):
            table = f.map.holdings
        else:
            return ExcCodes.ILLEGAL_FUNCTION
        if address + count > 2 * len(table):
            return ExcCodes.ILLEGAL_ADDRESS
        regs: list[int] = []
        for e in table[address // 2:(address + count + 1) // 2]:
            regs.extend(encode(devtab.get(e.device.name).value))
        start = address % 2
        return regs[start:start + count]

    async def async_setValues(self, device_id: int, func_code: int, address: int,
                              values: Sequence[int] | Sequence[bool]) -> ExcCodes | None:
        """Writes to holding registers: whole floats only, each through north_write."""
        f = self.facade
        if func_code not in (6, 16, 23):
            return ExcCodes.ILLEGAL_FUNCTION
        count = len(values)
        if address % 2 or count % 2 or address + count > 2 * len(f.map.holdings):
            f.refusals.append((ExcCodes.ILLEGAL_ADDRESS, f"holding {address}+{count}: writes "
                               "must cover whole float32 pairs of a writable actuator"))
            return ExcCodes.ILLEGAL_ADDRESS
        loop = asyncio.get_running_loop()
        for i in range(0, count, 2):
            e = f.map.holdings[(address + i) // 2]
            value = decode([int(values[i]), int(values[i + 1])])
            try:
                await loop.run_in_executor(None, f.system.call, north_write, f.system,
                                           e.device.name, value, "modbus-facade")
            except Refused as exc:
                f.rejected.note(f"modbus facade: write refused ({exc.code.name})", str(exc))
                f.refusals.append((exc.code, str(exc)))
                return exc.code
            except ChcosError as exc:
                f.refusals.append((ExcCodes.DEVICE_FAILURE, str(exc)))
                return ExcCodes.DEVICE_FAILURE
        return None


class _NotARequest(ExceptionResponse):
    """A received frame whose function code has the exception bit set: no request is. Answered
    ILLEGAL_FUNCTION in pymodbus' own exception form, never passed to the datastore."""

    async def datastore_update(self, context: Any, device_id: int) -> ModbusPDU:
        return ExceptionResponse(self.function_code & 0x7F, ExcCodes.ILLEGAL_FUNCTION)


def _requests_only(sending: bool, pdu: ModbusPDU) -> ModbusPDU:
    """pymodbus' trace hook: a received exception frame becomes :class:`_NotARequest`."""
    if not sending and isinstance(pdu, ExceptionResponse):
        return _NotARequest(pdu.function_code & 0x7F, device_id=pdu.dev_id,
                            transaction=pdu.transaction_id)
    return pdu


class _GatedServer(ModbusTcpServer):
    """pymodbus' TCP server with its connections through a :class:`ConnectionGate`."""

    def __init__(self, gate: ConnectionGate, context: ModbusServerContext,
                 address: tuple[str, int]) -> None:
        self._gate = gate
        super().__init__(context, address=address, trace_pdu=_requests_only)

    def handle_new_connection(self) -> Any:
        return self._gate.factory(super().handle_new_connection)()


class ModbusFacade:
    """The facade of ``system`` served on ``host:port`` (port 0: a free one) from a background
    thread. ``refusals`` lists (code, reason) of the last 100 refused writes, newest last."""

    def __init__(self, system: System, host: str = "127.0.0.1", port: int = 0, *,
                 allow_remote: bool = False) -> None:
        if not is_loopback(host) and not allow_remote:
            raise NorthError(f"modbus facade on {host}: Modbus has no authentication; bind a "
                             "loopback address or ask for a remote one explicitly")
        self.system = system
        self.host = host
        self.port = port
        self.map = RegisterMap(system.devmap)
        self.refusals: deque[tuple[int, str]] = deque(maxlen=100)
        #: refused writes by cause, logged once per period
        self.rejected = Throttle(log)
        #: the cap, idle timeout and counts of the facade's connections
        self.gate = ConnectionGate("modbus facade", connection_cap(MAX_CONNECTIONS),
                                   stream=True)
        self._server: ModbusTcpServer | None = None
        self._service = LoopThread("chcos-modbus-facade")

    def start(self) -> ModbusFacade:
        """Start serving; returns self. Raises NorthError if the address cannot be bound."""
        try:
            self._service.start(self._serve)
        except Exception as exc:
            raise NorthError(f"modbus facade: cannot serve on {self.host}:{self.port}: "
                             f"{exc}") from exc
        return self

    async def _serve(self, service: LoopThread) -> None:
        """The server's life on its loop: bind, serve until stopped, shut down."""
        throttle_library_logs()
        server = _GatedServer(self.gate, _Context(self), (self.host, self.port))
        await server.serve_forever(background=True)
        self._server = server
        try:
            assert server.transport is not None
            self.port = int(server.transport.sockets[0].getsockname()[1])  # type: ignore[attr-defined]
            service.ready()
            await service.stopped()
        finally:
            await server.shutdown()  # type: ignore[no-untyped-call]

    def stop(self) -> None:
        """Stop serving and join the thread (no error if not running)."""
        self._service.stop(timeout=10)

    def __enter__(self) -> ModbusFacade:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def load_devmap(paths: Sequence[str]) -> DeviceMap:
    """The device map of a system given as device-map TOML files, a system file (TOML with a
    ``[system]`` table) or a sysfile.map (JSON). Raises ConfigError naming the file."""
    from chcos.devices.devmap import load
    from chcos.satellites import sysfile
    from chcos.system import sysmap

    files: list[str] = []
    for p in paths:
        if p.endswith(".map"):
            files.extend(sysmap.read(p).get("devmaps", []))
            continue
        try:
            with open(p, "rb") as fh:
                head = fh.read(4096)
        except OSError as exc:
            from chcos.errors import ConfigError

            raise ConfigError(f"{p}: cannot read: {exc}") from exc
        if b"[system]" in head:
            files.extend(str(m) for m in sysfile.load(p).devmaps)
        else:
            files.append(p)
    return load(files)


def facade_main(argv: Sequence[str]) -> int:
    """``chcos facade modbus --print-map FILE...``: print the register map; returns the exit
    status (1 with a message on stderr for a bad file)."""
    import argparse
    import sys

    ap = argparse.ArgumentParser(prog="chcos facade", description="North-side facades.")
    sub = ap.add_subparsers(dest="kind", required=True)
    mb = sub.add_parser("modbus", help="the Modbus TCP facade")
    mb.add_argument("--print-map", nargs="+", metavar="FILE", required=True,
                    help="device maps, a system file or a sysfile.map")
    args = ap.parse_args(list(argv))
    try:
        devmap = load_devmap(args.print_map)
    except ChcosError as exc:
        print(f"chcos facade modbus: {exc}", file=sys.stderr)
        return 1
    print(RegisterMap(devmap).render())
    return 0


__all__ = [
    "Entry",
    "ModbusFacade",
    "Refused",
    "RegisterMap",
    "decode",
    "encode",
    "facade_main",
    "load_devmap",
    "north_write",
    "owner_of",
]
