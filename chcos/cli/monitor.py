"""monitor - ``chcos monitor SYSTEM``: commission a live bus without driving anything.

Opens every bus of a system file's device maps listen-only and shows each device live against the
map, flagging mismatches; it never writes:

* ``modbus-tcp``/``modbus-rtu``: the driver polls the sensors and reads the actuators' coils and
  holding registers back (read requests only); nothing is written (every write, the safe values
  at the end included, stops at :class:`chcos.cli.cellsystem.OutputsOff`);
* ``can``: the driver only receives: sensors' frames, and the actuators' frames when another node
  sends them; frames of ids no device uses and frames of the wrong length are counted and flagged;
* ``canopen``: no NMT, no SDO, no SYNC - a passive listener (:class:`PassiveCanopen`) decodes the
  TPDOs and RPDOs the nodes' EDS files map, watches heartbeats, and flags heartbeats of nodes not
  in the map, PDOs whose length does not fit the mapping, and ids that belong to nothing; each
  node's life as the wire shows it gets a line (NMT state of its last heartbeat, boot-ups seen,
  heartbeat losses seen, EMCYs received, last EMCY), and the SYNC cycle of another master one
  (SYNCs seen, period and jitter);
* ``serial``: the port is read (nothing is written); ``memory``/``signal``: in-process.

Mismatches: a sensor with no answer (failed, or nothing within ``--grace`` seconds), a value
outside the device's limits, the bus-level reports above. :func:`run` prints the table once a
second (times since the start) and a summary; exit status 0 when nothing was flagged, 1 when
something was, 2 when the system cannot be opened.
"""

from __future__ import annotations

import argparse
import dataclasses
import signal
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any, TextIO

from chcos.devices.devmap import load
from chcos.devices.entry import DeviceStatus
from chcos.devices.spec import BusSpec, DeviceMap, DeviceSpec
from chcos.errors import BusError, ChcosError
from chcos.helpers import is_number
from chcos.satellites import sysfile
from drivers.canopen_sync import percentile
from drivers.codecs.cia402 import (
    AxisReading,
    StatuswordError,
    decode_command,
    decode_state,
    is_axis_address,
)

_FIXED_IDS = {0x000: "NMT", 0x080: "SYNC", 0x100: "TIME"}
#: the NMT state in a heartbeat (CiA 301), by its code (toggle bit cleared)
NMT_NAMES = {0x00: "BOOT-UP", 0x04: "STOPPED", 0x05: "OPERATIONAL", 0x7F: "PRE-OPERATIONAL"}
#: SYNC intervals the monitor keeps for its period and jitter figures
SYNC_WINDOW = 10_000
READ_BACK = ("modbus-tcp", "modbus-rtu", "can")
"""Bus kinds whose outputs the monitor reads without writing."""


@dataclass
class _Seen:
    value: Any = None
    at: float | None = None
    frames: int = 0


@dataclass
class _Pdo:
    kind: str  # TPDO (node -> master) or RPDO (master -> node)
    node: int
    length: int  # bytes the mapping fills
    #: per mapped object: the devices showing it (an axis's state and statusword share
    #: 0x6041), its variable, its bits
    fields: list[tuple[tuple[str, ...], Any, int]] = field(default_factory=list)


def axis_shown(device: DeviceSpec, value: Any) -> Any:
    """What the monitor shows for a CiA 402 axis device seen on the wire: the controlword and
    the command it gives for the axis's actuator (its limits are the axis's command codes, not
    controlwords, so no limit check applies), the state name for ``<axis>.state``; any other
    device's value unchanged."""
    if not is_axis_address(device.address) or not isinstance(value, int):
        return value
    if device.direction == "actuator":
        command = decode_command(value)
        return f"0x{value:04X} {command.value if command else 'no command'}"
    if device.address.get("reading") == AxisReading.STATE.value:
        try:
            return decode_state(value).name
        except StatuswordError:
            return f"0x{value:04X} no state"
    return value


class PassiveCanopen:
    """Listens to one CANopen bus and never sends: TPDOs/RPDOs decoded from the nodes' EDS
    mappings, heartbeats and EMCYs watched, everything else on the bus accounted for. Raises
    BusError if the CAN channel cannot be opened."""

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec]) -> None:
        import can

        from chcos.devices.importers.eds import pdo_mappings
        from drivers.canopen_od import load_od
        from drivers.codecs.canopen import eds_path

        self.bus = bus
        self.devices = {d.name: d for d in devices}
        self.seen: dict[str, _Seen] = {d.name: _Seen() for d in devices}
        self.in_pdo: set[str] = set()
        self.nodes: dict[int, Any] = {}
        self.heartbeat_timeout: dict[int, float | None] = {}
        self.last_heartbeat: dict[int, float] = {}
        self.nmt_state: dict[int, int] = {}
        self.boots: Counter[int] = Counter()
        #: heartbeat losses seen as a listener: a node silent beyond its heartbeat_timeout,
        #: then heard again, counts one (the wire's receive times, not when this thread ran)
        self.heartbeat_losses: Counter[int] = Counter()
        self.heartbeat_at: dict[int, float] = {}
        self.emcys: Counter[int] = Counter()
        self.last_emcy: dict[int, str] = {}
        #: SYNC frames seen, their intervals (the last :data:`SYNC_WINDOW`), the last one's time
        self.syncs = 0
        self.sync_intervals: deque[float] = deque(maxlen=SYNC_WINDOW)
        self.last_sync: float | None = None
        self.sync_period = (float(bus.options["sync_period"])
                            if "sync_period" in bus.options else None)
        self.pdos: dict[int, _Pdo] = {}
        self.flags: Counter[str] = Counter()
        self.lock = threading.Lock()
        by_obj: dict[tuple[int, int, int], tuple[str, ...]] = {}
        for d in devices:
            obj = (int(d.address["node"]), int(d.address["index"]),
                   int(d.address.get("subindex", 0)))
            by_obj[obj] = (*by_obj.get(obj, ()), d.name)
        for node in bus.options.get("nodes", []):
            nid = int(node["id"])
            od = load_od(bus, nid, str(eds_path(bus, str(node["eds"]))))
            self.nodes[nid] = od
            hb = node.get("heartbeat_timeout")
            self.heartbeat_timeout[nid] = float(hb) if hb else None
            for kind, comm, mapping in (("TPDO", 0x1800, 0x1A00), ("RPDO", 0x1400, 0x1600)):
                for n, index, sub, _timer, cob in pdo_mappings(od, comm, mapping):
                    pdo = self.pdos.setdefault(cob, _Pdo(f"{kind}{n}", nid, 0))
                    var = od.get_variable(index, sub)
                    bits = int(_default_entry(od, mapping + n - 1, index, sub) or 0)
                    pdo.fields.append((by_obj.get((nid, index, sub), ()), var, bits))
                    pdo.length += bits // 8
            self._configured(node, nid, od, by_obj)
        self.in_pdo = {dev for pdo in self.pdos.values() for devs, _var, _bits in pdo.fields
                       for dev in devs}
        args = {k: bus.options[k] for k in ("interface", "channel", "bitrate", "port")
                if k in bus.options}
        try:
            self.can: Any = can.Bus(**args)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise BusError(f"canopen bus {bus.name}: cannot open {args} to listen: {exc}") \
                from exc
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, name=f"monitor-{bus.name}",
                                        daemon=True)
        self._thread.start()

    def _configured(self, node: dict[str, Any], nid: int, od: Any,
                    by_obj: dict[tuple[int, int, int], tuple[str, ...]]) -> None:
        """The PDOs as the node's ``config`` downloads them at boot (COB-ID, enabled,
        mapping) in place of the EDS's: what a master following the map puts on the wire."""
        from drivers import canopen_config

        try:
            cfg = canopen_config.with_bits(canopen_config.parse(node), od)
        except Exception:   # an invalid config: chcos check names it; the EDS's view stays
            return
        for p in cfg.pdos:
            name = f"{p.kind.upper()}{p.number}"
            old = next(((cob, pd) for cob, pd in self.pdos.items()
                        if pd.node == nid and pd.kind == name), None)
            if old is not None:
                del self.pdos[old[0]]
            if not p.enabled:
                continue
            cob = canopen_config.effective_cob_id(p, od, nid)
            if p.mapping is None:
                if old is not None:
                    self.pdos[cob] = old[1]
                continue
            pdo = self.pdos[cob] = _Pdo(name, nid, 0)
            for index, sub, bits in p.mapping:
                pdo.fields.append((by_obj.get((nid, index, sub), ()),
                                   od.get_variable(index, sub), bits))
                pdo.length += bits // 8

    def _flag(self, text: str) -> None:
        self.flags[text] += 1

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                frame = self.can.recv(timeout=0.05)
            except Exception as exc:  # the channel went away: report, keep listening
                with self.lock:
                    self._flag(f"receive error: {exc}")
                self._stop.wait(0.2)
                continue
            if frame is not None and not frame.is_error_frame:
                with self.lock:
                    self._frame(frame)

    def _frame(self, frame: Any) -> None:
        cid, now, data = frame.arbitration_id, time.monotonic(), bytes(frame.data)
        if cid in self.pdos:
            pdo = self.pdos[cid]
            if len(data) != pdo.length:
                self._flag(f"{pdo.kind} of node {pdo.node} (id 0x{cid:03X}) has {len(data)} "
                           f"bytes, the map's EDS mapping fills {pdo.length}")
                return
            bit = 0
            for devices, var, bits in pdo.fields:
                chunk = data[bit // 8:(bit + bits) // 8]
                bit += bits
                if not devices:
                    continue
                try:
                    value = var.decode_raw(chunk)
                except Exception:
                    self._flag(f"{pdo.kind} of node {pdo.node}: cannot decode "
                               f"{', '.join(devices)}")
                    continue
                for device in devices:
                    s = self.seen[device]
                    s.value, s.at, s.frames = value, now, s.frames + 1
            return
        if 0x701 <= cid <= 0x77F:
            nid = cid - 0x700
            if nid not in self.nodes:
                self._flag(f"heartbeat of node {nid}, which is not in the map")
            else:
                self.last_heartbeat[nid] = now
                at = float(frame.timestamp or time.time())    # the interface's receive time
                before = self.heartbeat_at.get(nid)
                timeout = self.heartbeat_timeout.get(nid)
                if before is not None and timeout is not None and at - before > timeout:
                    self.heartbeat_losses[nid] += 1
                self.heartbeat_at[nid] = at
                self.nmt_state[nid] = data[0] if data else -1
                if data and data[0] & 0x7F == 0:
                    self.boots[nid] += 1
            return
        if cid == 0x080:
            at = float(frame.timestamp or time.time())    # the interface's receive time
            if self.last_sync is not None:
                self.sync_intervals.append(at - self.last_sync)
            self.syncs += 1
            self.last_sync = at
            return
        if 0x081 <= cid <= 0x0FF:
            nid = cid - 0x80
            what = "EMCY" if nid in self.nodes else "EMCY of a node not in the map:"
            code = int.from_bytes(data[:2], "little")
            self._flag(f"{what} node {nid} code 0x{code:04X}")
            if nid in self.nodes:
                self.emcys[nid] += 1
                self.last_emcy[nid] = (f"0x{code:04X} register 0x{data[2]:02X}" if len(data) > 2
                                       else f"0x{code:04X}")
            return
        if cid in _FIXED_IDS or (0x581 <= cid <= 0x5FF and cid - 0x580 in self.nodes) \
                or (0x601 <= cid <= 0x67F and cid - 0x600 in self.nodes):
            return  # NMT, SYNC, TIME, SDO traffic of a master already on the bus
        self._flag(f"unknown id 0x{cid:X}: no PDO, heartbeat or EMCY of the map's nodes")

    def problems(self) -> list[str]:
        """Node-level problems now: a heartbeat missing longer than its timeout."""
        out = []
        now = time.monotonic()
        with self.lock:
            for nid, timeout in self.heartbeat_timeout.items():
                last = self.last_heartbeat.get(nid)
                if timeout is not None and (last is None or now - last > timeout):
                    out.append(f"node {nid}: no heartbeat within {timeout} s")
        return out

    def node_lines(self) -> list[str]:
        """One line per node of the map as the wire shows it (the NMT state of its last
        heartbeat and how long ago, boot-ups seen, heartbeat losses seen (silent beyond its
        ``heartbeat_timeout``, then heard again), EMCYs received, last EMCY) and one for the
        SYNC cycle if another master produces one (SYNCs seen, median period, jitter against
        the map's ``sync_period`` p50/p99/max)."""
        now = time.monotonic()
        out = []
        with self.lock:
            for nid in sorted(self.nodes):
                code = self.nmt_state.get(nid)
                last = self.last_heartbeat.get(nid)
                state = ("no heartbeat seen" if code is None or last is None else
                         f"{NMT_NAMES.get(code & 0x7F, f'state 0x{code:02X}')} (heartbeat "
                         f"{now - last:.1f} s ago)")
                out.append(f"node {nid}: {state}, {self.boots[nid]} boot-up(s) seen, "
                           f"{self.heartbeat_losses[nid]} heartbeat loss(es), "
                           f"{self.emcys[nid]} EMCY(s), last EMCY "
                           f"{self.last_emcy.get(nid) or 'none'}")
            if self.syncs:
                iv = sorted(self.sync_intervals)
                text = f"SYNC: {self.syncs} seen"
                if iv:
                    text += f", period {percentile(iv, 0.5) * 1e3:.3f} ms (median)"
                if iv and self.sync_period is not None:
                    jit = sorted(abs(x - self.sync_period) for x in iv)
                    text += (f", jitter against {self.sync_period * 1e3:g} ms p50 "
                             f"{percentile(jit, 0.5) * 1e3:.3f} ms, p99 "
                             f"{percentile(jit, 0.99) * 1e3:.3f} ms, max {jit[-1] * 1e3:.3f} ms")
                out.append(text)
        return [f"bus {self.bus.name}: {line}" for line in out]

    def close(self) -> None:
        """Stop listening and close the channel."""
        self._stop.set()
        self._thread.join(timeout=5)
        self.can.shutdown()


def _default_entry(od: Any, mapping: int, index: int, sub: int) -> int | None:
    """The bit length of object index:sub in mapping object ``mapping``."""
    from chcos.devices.importers.eds import od_default

    count = od_default(od, mapping, 0) or 0
    for s in range(1, count + 1):
        entry = od_default(od, mapping, s)
        if entry and entry >> 16 == index and (entry >> 8) & 0xFF == sub:
            return int(entry & 0xFF)
    return None


class Monitor:
    """Every bus of a system file, listen-only (see the module doc). Close with :meth:`close`."""

    def __init__(self, system_file: str | Path, *, grace: float = 2.0) -> None:
        from chcos.cli.cellsystem import CellSystem, SinceStartClock

        self.sf = sysfile.load(system_file)
        self.grace = grace
        devmap = load(list(self.sf.devmaps))
        self.devmap = devmap
        passive = [b for b in devmap.buses if b.kind == "canopen"]
        # outputs that can be read without writing (Modbus coils and holding registers, CAN
        # frames another node sends) are watched as inputs
        self.read_back = {d.name for d in devmap.devices if d.direction == "actuator"
                          and devmap.bus(d.bus).kind in READ_BACK}
        # raw CAN: no receive filters and every id of no device an error, so they are flagged
        # (ids the map's ignore_ids names stay quiet)
        buses = tuple(b.with_options({"unknown_ids": "fail", **b.options, "filter": False})
                      if b.kind == "can" else b for b in devmap.buses if b.kind != "canopen")
        rest = DeviceMap(buses,
                         tuple(dataclasses.replace(d, direction="sensor", stale_after=None)
                               if d.name in self.read_back else d for d in devmap.devices
                               if devmap.bus(d.bus).kind != "canopen"), devmap.files)
        self.writes_held: list[tuple[str, Any]] = []
        self.system = CellSystem(rest, outputs=False,
                                 on_output=lambda d, v: self.writes_held.append((d, v)),
                                 clock=SinceStartClock(), base_dir=self.sf.base_dir)
        self.passive: list[PassiveCanopen] = []
        self.start = time.monotonic()
        try:
            for m in sorted({d.machine for d in rest.devices}):
                self.system.execute(f"install -m{m} sysfile")
            for b in passive:
                self.passive.append(PassiveCanopen(b, devmap.devices_on(b.name)))
            self.system.start()
        except BaseException:
            self.close()
            raise

    def rows(self) -> list[dict[str, Any]]:
        """One row per device: name, kind, direction, value, age, status, flags."""
        now = time.monotonic()
        out: list[dict[str, Any]] = []
        entries = self.system.call(lambda: {e.name: (e.value, e.updated_at, e.status, e.reason,
                                                     e.readings) for e in self.system.devtab})
        know = self.system.kernel.clock.now()
        for d in self.devmap.devices:
            kind = self.devmap.bus(d.bus).kind
            flags: list[str] = []
            if d.name in entries:
                value, at, status, reason, readings = entries[d.name]
                age = None if at is None else know - at
                state = status.value + (f" ({reason})" if reason else "")
                if d.name in self.read_back:
                    state = "output, read back: " + state
                    if status is DeviceStatus.FAILED:
                        flags.append(f"no answer: {reason}")
                elif d.direction == "actuator":
                    value, age, state = None, None, "output: not read, never written"
                elif status is DeviceStatus.FAILED and not reason.startswith("limit: "):
                    flags.append(f"no answer: {reason}")   # (a limit: flagged below)
                elif status is DeviceStatus.FAILED:
                    pass
                elif readings == 0 and now - self.start > self.grace:
                    flags.append(f"no answer within {self.grace:g} s")
            else:
                mon = next(p for p in self.passive if d.name in p.seen)
                with mon.lock:
                    seen = mon.seen[d.name]
                    value, age = axis_shown(d, seen.value), None if seen.at is None else \
                        now - seen.at
                state = "observed" if seen.at is not None else "not seen"
                if d.name not in mon.in_pdo:
                    state = "SDO object: not read (listen-only)"
                elif seen.at is None and now - self.start > self.grace:
                    if d.direction == "sensor":
                        flags.append(f"no PDO within {self.grace:g} s")
                    else:
                        state = "not seen (no master wrote it)"
            lo, hi = d.limits
            if is_number(value) and \
                    ((lo is not None and value < lo) or (hi is not None and value > hi)):
                flags.append(f"value {value:g} outside limits [{lo}, {hi}]")
            out.append({"name": d.name, "bus": d.bus, "kind": kind, "direction": d.direction,
                        "value": value, "units": d.units, "age": age, "state": state,
                        "flags": flags})
        return out

    def bus_flags(self) -> list[str]:
        """Bus-level mismatches so far: unknown ids, wrong lengths, garbage, heartbeats."""
        out: list[str] = []
        errs = self.system.call(lambda: (dict(self.system.devtab.bus_errors),
                                         dict(self.system.devtab.last_bus_error)))
        counts, last = errs
        for (bus, kind), n in sorted(counts.items()):
            out.append(f"bus {bus}: {kind} x{n} (last: {last.get(bus, '')})")
        for p in self.passive:
            with p.lock:
                out += [f"bus {p.bus.name}: {text} x{n}" for text, n in p.flags.items()]
            out += [f"bus {p.bus.name}: {text}" for text in p.problems()]
        return out

    def node_lines(self) -> list[str]:
        """Each CANopen node's life and the SYNC cycle, as the wire shows them."""
        return [line for p in self.passive for line in p.node_lines()]

    def close(self) -> None:
        """Stop everything; actuator safe values are held back like every other write."""
        for p in self.passive:
            p.close()
        self.passive = []
        self.system.shutdown()


def _show(rows: list[dict[str, Any]], bus: list[str], t: float, out: TextIO,
          nodes: Sequence[str] = ()) -> None:
    print(f"t={t:7.1f} s", file=out)
    width = max([len(r["name"]) for r in rows] + [8])
    for r in rows:
        v = r["value"]
        text = "-" if v is None else (f"{v:.4g}" if isinstance(v, float) else str(v))
        text = f"{text} {r['units']}".strip() if v is not None else text
        age = "" if r["age"] is None else f"{r['age']:.1f} s ago"
        flag = ("  <-- " + "; ".join(r["flags"])) if r["flags"] else ""
        print(f"  {r['direction']:<8} {r['name']:<{width}} {text:>14}  {age:<12} "
              f"{r['state']}{flag}", file=out)
    for b in (*nodes, *bus):
        print(f"  {b}", file=out)
    out.flush()


@dataclass
class MonitorResult:
    """What :func:`run` found."""

    mismatches: list[str]
    rows: list[dict[str, Any]]
    writes_held: list[tuple[str, Any]]


def run(system_file: str | Path, *, duration: float | None = None, grace: float = 2.0,
        out: TextIO | None = None, stop: threading.Event | None = None) -> MonitorResult:
    """Monitor until ``stop`` is set or ``duration`` seconds; print the table once a second
    and a summary. Raises ChcosError if the system cannot be opened."""
    stop = stop or threading.Event()
    out = out or sys.stdout
    mon = Monitor(system_file, grace=grace)
    try:
        print(f"monitoring {mon.sf.name}: {len(mon.devmap.devices)} devices on "
              f"{len(mon.devmap.buses)} buses, listen-only (nothing is written); Ctrl-C stops",
              file=out, flush=True)
        tick = 1
        while not stop.wait(max(0.0, mon.start + tick - time.monotonic())):
            t = time.monotonic() - mon.start
            _show(mon.rows(), mon.bus_flags(), t, out, mon.node_lines())
            tick += 1
            if duration is not None and t >= duration - 1e-6:
                break
        rows, bus, nodes = mon.rows(), mon.bus_flags(), mon.node_lines()
    finally:
        mon.close()
    found = [f"{r['name']}: {f}" for r in rows for f in r["flags"]] + bus
    print("\nsummary", file=out)
    print(f"  {sum(1 for r in rows if r['value'] is not None)} of {len(rows)} devices seen; "
          f"writes held back: {len(mon.writes_held)}", file=out)
    for line in nodes:
        print(f"  {line}", file=out)
    print("  mismatches:" + ("" if found else " none"), file=out)
    for f in found:
        print(f"    {f}", file=out)
    out.flush()
    return MonitorResult(found, rows, mon.writes_held)


def main(argv: Sequence[str] | None = None) -> int:
    """``chcos monitor SYSTEM``: exit status 0 when nothing was flagged, 1 when something was,
    2 when the system cannot be opened."""
    ap = argparse.ArgumentParser(
        prog="chcos monitor",
        description="Commission a live bus: open every bus of the system file's device maps "
                    "listen-only (Modbus reads only, CAN and CANopen passive, serial read "
                    "only), show each device live against the map once a second and flag "
                    "mismatches: no answer, value outside limits, unknown CAN ids, heartbeats "
                    "of nodes not in the map, PDO lengths that do not fit the map. Nothing is "
                    "ever written; no task runs.")
    ap.add_argument("system", metavar="SYSTEM", help="the system file (TOML)")
    ap.add_argument("--duration", type=float, help="stop after this many seconds")
    ap.add_argument("--grace", type=float, default=2.0,
                    help="seconds a device may stay silent before it is flagged (default 2)")
    args = ap.parse_args(argv)
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    old = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        result = run(args.system, duration=args.duration, grace=args.grace, stop=stop)
    except ChcosError as exc:
        print(f"chcos monitor: {exc}", file=sys.stderr)
        return 2
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
    return 1 if result.mismatches else 0
