"""modbus_server - a simulated Modbus slave: a pymodbus server over a datastore Python code shares.

:class:`RegisterStore` holds, per unit (device id), the four Modbus tables (coils, discrete inputs,
holding and input registers) under one lock; the owner (a test, a simulated cell) reads and writes
it from any thread. :class:`ModbusSimServer` serves that store with pymodbus on its own asyncio
thread - TCP on ``127.0.0.1:port``, or RTU framing over a TCP socket (pymodbus's
``socket://host:port`` serial port) - and can be stopped and restarted on the same port with the
data kept. ``chcos sim modbus`` runs one from the command line.

pymodbus's server keeps its own register image; a per-request ``action`` hook copies the store into
that image before every request and records client writes in the store, so the store is the one
truth and survives restarts.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import sys
import threading
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, Literal

from pymodbus.client.mixin import ModbusClientMixin
from pymodbus.constants import ExcCodes
from pymodbus.framer import FramerType
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from chcos.errors import BusError, ConfigError
from drivers.codecs.modbus import WORD_ORDERS

Table = Literal["coil", "discrete", "holding", "input"]
TABLES: tuple[Table, ...] = ("coil", "discrete", "holding", "input")
BIT_TABLES = ("coil", "discrete")
#: Modbus function code -> the table it addresses (22/23, mask write and read/write multiple, are
#: answered with "illegal function").
FUNCTION_TABLE: dict[int, Table] = {1: "coil", 5: "coil", 15: "coil", 2: "discrete",
                                    3: "holding", 6: "holding", 16: "holding", 4: "input"}
DATATYPES: dict[str, Any] = {
    "int16": ModbusClientMixin.DATATYPE.INT16, "uint16": ModbusClientMixin.DATATYPE.UINT16,
    "int32": ModbusClientMixin.DATATYPE.INT32, "uint32": ModbusClientMixin.DATATYPE.UINT32,
    "float32": ModbusClientMixin.DATATYPE.FLOAT32, "float64": ModbusClientMixin.DATATYPE.FLOAT64,
}


def _pymodbus_order(word_order: str) -> tuple[Literal["big", "little"], bool]:
    """pymodbus' word order for ``word_order`` and whether the bytes of each register are
    swapped on top of it (``BADC``, ``DCBA``)."""
    named = WORD_ORDERS[word_order]
    return ("little" if named in ("CDAB", "DCBA") else "big"), named in ("BADC", "DCBA")


def _swap_bytes(regs: list[int], swap: bool) -> list[int]:
    return [((r & 0xFF) << 8) | (r >> 8) for r in regs] if swap and len(regs) > 1 else regs


Span = tuple[int, int]
"""A run of mapped addresses: (first, count)."""


def merge(spans: Iterable[Span]) -> list[Span]:
    """``spans`` sorted, with overlapping and adjacent runs joined."""
    out: list[Span] = []
    for first, count in sorted(s for s in spans if s[1] > 0):
        if out and first <= out[-1][0] + out[-1][1]:
            last_first, last_count = out[-1]
            out[-1] = (last_first, max(last_count, first + count - last_first))
        else:
            out.append((first, count))
    return out


class RegisterStore:
    """The four tables of each unit. Only mapped addresses exist: by default ``size`` entries
    from 0 in each table; with ``spans`` (table -> runs of (first, count)) only those runs, so a
    device with registers at 0 and 64512 costs a few entries, not 64513. Thread-safe.

    Raises :class:`chcos.errors.ConfigError` for an unknown unit/table or an address that is
    not mapped, or for an address beyond 65535.
    """

    def __init__(self, units: Iterable[int] = (1,), size: int = 1000, *,
                 spans: Mapping[str, Iterable[Span]] | None = None) -> None:
        self.spans: dict[str, list[Span]] = {
            t: merge(spans.get(t, ()) if spans is not None else [(0, size)]) for t in TABLES}
        for table, runs in self.spans.items():
            for first, count in runs:
                if first < 0 or first + count > 0x10000:
                    raise ConfigError(f"modbus store {table}: addresses {first}.."
                                      f"{first + count - 1} outside 0..65535")
        self.size = max([f + c for runs in self.spans.values() for f, c in runs] + [0])
        self._cond = threading.Condition()
        self._units: dict[int, dict[str, dict[int, Any]]] = {
            u: {t: {a: (False if t in BIT_TABLES else 0)
                    for first, count in self.spans[t] for a in range(first, first + count)}
                for t in TABLES} for u in units}
        self.client_writes = 0
        self.requests = 0

    @property
    def units(self) -> list[int]:
        """The unit ids served."""
        return sorted(self._units)

    def _table(self, unit: int, table: str, address: int, count: int) -> dict[int, Any]:
        if unit not in self._units:
            raise ConfigError(f"modbus store: no unit {unit}; units are {self.units}")
        if table not in TABLES:
            raise ConfigError(f"modbus store: table {table!r}; expected one of {TABLES}")
        data = self._units[unit][table]
        if address < 0 or count < 0 or not all(a in data for a in range(address,
                                                                        address + count)):
            mapped = " and ".join(f"{f}..{f + c - 1}" for f, c in self.spans[table])
            raise ConfigError(f"modbus store unit {unit} {table}: addresses {address}.."
                              f"{address + count - 1} outside {mapped or 'nothing mapped'}")
        return data

    def read(self, unit: int, table: str, address: int, count: int = 1) -> list[Any]:
        """``count`` raw entries (bools or 16-bit ints) from ``address``."""
        with self._cond:
            data = self._table(unit, table, address, count)
            return [data[a] for a in range(address, address + count)]

    def write(self, unit: int, table: str, address: int, values: Sequence[Any]) -> None:
        """Store raw entries (bools for bit tables, 0..65535 for registers) from ``address``."""
        with self._cond:
            data = self._table(unit, table, address, len(values))
            bits = table in BIT_TABLES
            for v in values:
                if not bits and not (isinstance(v, int) and 0 <= v <= 0xFFFF):
                    raise ConfigError(f"modbus store unit {unit} {table}: register value {v!r} "
                                      f"is not 0..65535")
            for a, v in enumerate(values, address):
                data[a] = bool(v) if bits else v
            self._cond.notify_all()

    def set_value(self, unit: int, table: str, address: int, value: Any, type: str = "uint16",
                  word_order: str = "ABCD") -> None:
        """Store an engineering value of ``type`` (bool, int16 ... float64) with pymodbus's own
        register conversion, in ``word_order`` (one of the codec's ``WORD_ORDERS``)."""
        if type == "bool":
            self.write(unit, table, address, [bool(value)])
            return
        try:
            words, swap = _pymodbus_order(word_order)
            regs = _swap_bytes(ModbusClientMixin.convert_to_registers(value, DATATYPES[type],
                                                                      words), swap)
        except KeyError as exc:
            raise ConfigError(f"modbus store: type {type!r}; expected bool or one of "
                              f"{', '.join(DATATYPES)}") from exc
        except Exception as exc:  # struct.error and TypeError from pymodbus's packing
            raise ConfigError(f"modbus store: {value!r} is not a valid {type}: {exc}") from exc
        self.write(unit, table, address, regs)

    def get_value(self, unit: int, table: str, address: int, type: str = "uint16",
                  word_order: str = "ABCD") -> Any:
        """The value of ``type`` at ``address`` (see :meth:`set_value`)."""
        if type == "bool":
            return self.read(unit, table, address, 1)[0]
        if type not in DATATYPES:
            raise ConfigError(f"modbus store: type {type!r}; expected bool or one of "
                              f"{', '.join(DATATYPES)}")
        dt = DATATYPES[type]
        regs = self.read(unit, table, address, dt.value[1])
        words, swap = _pymodbus_order(word_order)
        return ModbusClientMixin.convert_from_registers(_swap_bytes(regs, swap), dt, words)

    def wait_for(self, pred: Callable[[RegisterStore], bool], timeout: float) -> bool:
        """Block until ``pred(store)`` holds, re-checked after every write; False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: pred(self), timeout)

    def mirror(self, unit: int, function_code: int, start: int, address: int, count: int,
               image: list[int], values: list[Any] | None) -> ExcCodes | None:
        """The server-side hook: refresh pymodbus's register ``image`` (whose first entry is
        ``start``) for a request, and record the client's written ``values``."""
        table = FUNCTION_TABLE.get(function_code)
        if table is None:
            return ExcCodes.ILLEGAL_FUNCTION
        with self._cond:
            self.requests += 1
            data = self._units.get(unit, self._units.get(0))
            if data is None:
                return ExcCodes.GATEWAY_NO_RESPONSE
            entries = data[table]
            if table in BIT_TABLES:
                first = address // 16
                for i in range(count):
                    word = 0
                    for bit in range(16):
                        word |= int(entries.get((first + i) * 16 + bit, False)) << bit
                    image[first - start + i] = word
            else:
                for a in range(address, address + count):
                    image[a - start] = entries.get(a, 0)
            if values:
                for a, v in enumerate(values, address):
                    if a in entries:   # pymodbus refuses unmapped addresses itself
                        entries[a] = v
                self.client_writes += 1
                self._cond.notify_all()
        return None


class ModbusSimServer:
    """Serves a :class:`RegisterStore` on ``host:port`` (``framer`` ``"tcp"`` or ``"rtu"``: RTU
    frames over a TCP socket, what a client reaches as serial port ``socket://host:port``).

    :meth:`start` raises :class:`chcos.errors.BusError` when the port cannot be bound.
    """

    def __init__(self, store: RegisterStore, port: int, *, host: str = "127.0.0.1",
                 framer: Literal["tcp", "rtu"] = "tcp") -> None:
        self.store = store
        self.host = host
        self.port = port
        self.framer = framer
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: Any = None
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    @property
    def running(self) -> bool:
        """True between a successful :meth:`start` and :meth:`stop`."""
        return self._thread is not None

    def start(self) -> None:
        """Listen and serve on a new thread; returns once the port is bound."""
        with self._lock:
            if self._thread is not None:
                return
            ready = threading.Event()
            failure: list[BaseException] = []
            loop = asyncio.new_event_loop()

            def run() -> None:
                asyncio.set_event_loop(loop)
                try:
                    loop.run_until_complete(self._listen())
                except BaseException as exc:  # reported to start() below
                    failure.append(exc)
                    ready.set()
                    loop.close()
                    return
                ready.set()
                loop.run_forever()
                loop.close()

            thread = threading.Thread(target=run, name=f"modbus-sim-{self.port}", daemon=True)
            thread.start()
            ready.wait()
            if failure:
                thread.join()
                exc = failure[0]
                if isinstance(exc, OSError) or "listen" in str(exc).lower():
                    raise BusError(f"modbus sim server: cannot listen on {self.host}:"
                                   f"{self.port}: {exc}") from exc
                # not the port: say what it was (a MemoryError's text is empty)
                raise BusError(f"modbus sim server on {self.host}:{self.port} failed to start: "
                               f"{type(exc).__name__}: {exc}".rstrip(": ")) from exc
            self._loop, self._thread = loop, thread

    async def _listen(self) -> None:
        devices = [SimDevice(u, simdata=self._blocks(), action=self._action(u))
                   for u in self.store.units]
        if self.framer == "tcp":
            self._server = ModbusTcpServer(devices, address=(self.host, self.port))
        else:
            self._server = ModbusSerialServer(devices, framer=FramerType.RTU,
                                              port=f"socket://{self.host}:{self.port}")
        await self._server.serve_forever(background=True)

    def _blocks(self) -> tuple[list[SimData], list[SimData], list[SimData], list[SimData]]:
        """pymodbus's register image: one entry per mapped address (pymodbus's checks grow with
        the square of an entry's count: one entry of 64512 registers asked for gigabytes); an
        address outside them is answered "illegal data address". A table with nothing mapped
        gets address 0, as pymodbus wants a block in every table."""
        def block(table: str, value: Any, datatype: DataType) -> list[SimData]:
            runs = self.store.spans[table] or [(0, 1)]
            return [SimData(a, count=1, values=value, datatype=datatype)
                    for first, count in runs for a in range(first, first + count)]

        return (block("coil", False, DataType.BITS), block("discrete", False, DataType.BITS),
                block("holding", 0, DataType.REGISTERS), block("input", 0, DataType.REGISTERS))

    def _action(self, unit: int) -> Any:
        store = self.store

        async def action(function_code: int, start: int, address: int, count: int,
                         image: list[int], values: list[Any] | None) -> ExcCodes | None:
            return store.mirror(unit, function_code, start, address, count, image, values)

        return action

    def stop(self) -> None:
        """Close the listener and every client connection; the store is kept. Idempotent."""
        with self._lock:
            loop, thread, server = self._loop, self._thread, self._server
            self._loop = self._thread = self._server = None
            if loop is None or thread is None:
                return
            if server is not None:
                fut = asyncio.run_coroutine_threadsafe(self._shutdown(server), loop)
                # A server already torn down raises here; the loop is stopped below anyway.
                with contextlib.suppress(Exception):
                    fut.result(timeout=5.0)
            loop.call_soon_threadsafe(loop.stop)
            thread.join(timeout=5.0)

    @staticmethod
    async def _shutdown(server: Any) -> None:
        """Close the listener and the client connections, and let the loop run the transports'
        close callbacks so every socket is really closed (clients see the connection drop)."""
        await server.shutdown()
        for _ in range(3):
            await asyncio.sleep(0)

    def restart(self) -> None:
        """:meth:`stop` then :meth:`start` on the same port."""
        self.stop()
        self.start()

    def __enter__(self) -> ModbusSimServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def main(argv: Sequence[str] | None = None) -> int:
    """``chcos sim modbus``: serve a fresh store until interrupted or ``--duration`` elapses.
    Returns the exit status (0 ok, 2 when the port cannot be bound)."""
    parser = argparse.ArgumentParser(prog="chcos sim modbus",
                                     description="Simulated Modbus slave (pymodbus server).")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=5020)
    parser.add_argument("--framer", choices=("tcp", "rtu"), default="tcp",
                        help="tcp, or rtu frames over TCP (client port socket://host:port)")
    parser.add_argument("--units", type=int, nargs="+", default=[1], help="unit ids served")
    parser.add_argument("--size", type=int, default=1000, help="entries per table")
    parser.add_argument("--duration", type=float, default=None, help="run this long, s")
    args = parser.parse_args(list(argv) if argv is not None else None)
    server = ModbusSimServer(RegisterStore(args.units, args.size), args.port, host=args.host,
                             framer=args.framer)
    try:
        server.start()
    except BusError as exc:
        print(f"chcos sim modbus: {exc}", file=sys.stderr)
        return 2
    print(f"modbus {args.framer} server on {args.host}:{args.port} units {args.units}", flush=True)
    try:
        threading.Event().wait(args.duration)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
    return 0
