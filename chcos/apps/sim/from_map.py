"""from_map - simulated slaves for any device map, so a user's own cell runs without its hardware.

:func:`simulate` takes a validated :class:`~chcos.devices.spec.DeviceMap` and starts, per bus, a
peer
that answers the bus's devices on the real protocol:

* ``modbus-tcp``, ``modbus-rtu`` - a slave as strict as a device
  (:class:`chcos.apps.sim.modbus_slave.ModbusSlave`: exception 01/02/03, silence or 0x0B for
  other units, broadcast) holding exactly the mapped registers, coils and inputs; reached
  in-process when ``rewrite`` (the bus's ``direct``), else on a socket
  (:class:`chcos.apps.sim.modbus_server.ModbusSimServer`: Modbus TCP at the bus's loopback
  address, RTU framing over TCP for ``socket://127.0.0.1:PORT``);
* ``can`` - a node on the bus's python-can channel that sends the sensors' messages (coded with
  the bus's DBC, or the raw signal layout, by the driver's own codec with the directions turned
  round) every cycle (the DBC's ``GenMsgCycleTime``, else 0.1 s) and decodes the actuators'
  frames;
* ``canopen`` - per node, :class:`chcos.apps.sim.canopen_slave.CanopenSlave` over the node's EDS
  on the slaves' clock, as strict as a CiA 301 device: boot-up, NMT state machine, SDO server
  (every refusal the device's abort; zero for objects without a default), RPDOs applied (a
  wrong length raises EMCY 0x8210/0x8220), TPDOs on change, event timer and SYNC, EMCY on
  injected faults (:meth:`SimSlaves.canopen_node`), a heartbeat every third of the map's
  ``heartbeat_timeout``;
  a node whose EDS is a CiA 402 drive's is a :class:`chcos.apps.sim.cia402_drive.Cia402Drive`
  (the state machine answers the controlword; 0x605A as the map's axis says, else the EDS);
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
:meth:`~SimSlaves.values` takes ``DEVICE=SCRIPT`` items (``--value``), :meth:`~SimSlaves.add_plant`
attaches a user's plant model (:data:`Plant`, called every :data:`TICK`; :func:`load_plant` loads
one from ``FILE.py:function``), :meth:`~SimSlaves.get` reads what the system last wrote to an
actuator, and
:meth:`~SimSlaves.silence`/:meth:`~SimSlaves.restore` make a bus's peer stop and resume answering.
Time comes from :meth:`~SimSlaves.attach` (a kernel's clock: virtual time stays deterministic) or
:meth:`~SimSlaves.run_realtime`. A serial bus on a device path (not ``socket://``) can be
simulated only with ``rewrite``; a pattern with back-references is refused, naming the bus.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import re
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from chcos.apps.sim.can_peer import CanPeer
from chcos.apps.sim.peers import CanopenPeer, ModbusPeer, Peer
from chcos.apps.sim.scripts import Script, parse_script
from chcos.apps.sim.serial_peer import SerialPeer
from chcos.devices.spec import BusSpec, DeviceMap, DeviceSpec
from chcos.errors import ChcosError, ConfigError, DeviceError
from chcos.helpers import is_number

if TYPE_CHECKING:
    from collections.abc import Callable

    from chcos.apps.sim.canopen_slave import CanopenSlave

IN_PROCESS = ("memory", "signal", "weld-direct")
"""Bus kinds that need no simulated peer."""
SIMULATED = ("modbus-tcp", "modbus-rtu", "can", "canopen", "serial", *IN_PROCESS)
"""Bus kinds :func:`simulate` can stand in for."""
TICK = 0.01
"""Seconds between two updates of scripted values and cyclic frames."""

MODBUS = ("modbus-tcp", "modbus-rtu")
PEERS: dict[str, type[Peer]] = {"modbus-tcp": ModbusPeer, "modbus-rtu": ModbusPeer,
                                "can": CanPeer, "canopen": CanopenPeer, "serial": SerialPeer}


Plant = Callable[[float, "SimSlaves"], None]
"""A user's plant model: called every TICK with the seconds since the start and the slaves; it
reads what the system sent (:meth:`SimSlaves.get` of an actuator) and sets what the sensors
serve (:meth:`SimSlaves.set`)."""


@dataclass
class EmcyFault:
    """A fault scheduled on a simulated CANopen node (:meth:`SimSlaves.schedule_emcy`)."""

    node: CanopenSlave
    code: int
    start: float
    end: float
    report: Callable[[str], None] | None = None
    raised: bool = False

    def apply(self, now: float) -> None:
        """Raise or clear the fault as ``now`` (seconds since the start) says."""
        if self.start <= now < self.end and not self.raised:
            self.node.inject_fault(self.code)
            self.raised = True
            line = f"fault: node {self.node.node_id} EMCY 0x{self.code:04X}"
        elif now >= self.end and self.raised:
            self.node.clear_fault(self.code)
            self.raised = False
            line = f"fault over: node {self.node.node_id} error reset"
        else:
            return
        if self.report is not None:
            self.report(f"t={now:6.1f} s  {line}")


@dataclass
class SimSlaves:
    """The simulated peers of one device map (see the module doc). Close with :meth:`close`."""

    devmap: DeviceMap
    specs: dict[str, DeviceSpec] = dataclasses.field(default_factory=dict)
    peers: dict[str, Peer] = dataclasses.field(default_factory=dict)
    scripts: dict[str, Script] = dataclasses.field(default_factory=dict)
    plants: list[Plant] = dataclasses.field(default_factory=list)
    _timer: Any = None
    _rt: threading.Thread | None = None
    _rt_stop: threading.Event = dataclasses.field(default_factory=threading.Event)
    _closed: bool = False
    _emcy_plan: list[EmcyFault] = dataclasses.field(default_factory=list)
    #: devices :meth:`hold` holds, with what they hold
    held: dict[str, Any] = dataclasses.field(default_factory=dict)

    def simulated(self, device: str) -> bool:
        """True if ``device`` has a simulated peer that :meth:`set`/:meth:`get` reach."""
        return device in self.specs and self.specs[device].bus in self.peers

    def _peer(self, device: str) -> tuple[Peer, DeviceSpec]:
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
        it at its next poll or frame. A device :meth:`hold` holds keeps its held value (the
        call is ignored: a script's or a plant's value does not overwrite a test's). Raises
        DeviceError for an unknown or in-process device and ConfigError if the raw value does
        not fit the register or signal."""
        if device in self.held:
            self._peer(device)
            return
        self._put(device, value)

    def _put(self, device: str, value: Any) -> None:
        peer, spec = self._peer(device)
        raw = value
        if is_number(value):
            raw = (value - spec.offset) / spec.scale
        peer.set(spec, raw)

    def hold(self, device: str, value: Any = None, *, raw: Any = None) -> None:
        """Serve ``value`` (engineering units) for ``device`` - or ``raw``, the value on the
        bus before the device's scale and offset, checked only against what the wire can
        carry (on CAN: the signal's bits, not the DBC's minimum and maximum) - and keep it
        until :meth:`release`: value scripts and plants no longer set it. Raises DeviceError
        for an unknown or in-process device, for a raw value the wire cannot carry, and
        unless exactly one of ``value`` and ``raw`` is given."""
        if (value is None) == (raw is None):
            raise DeviceError(f"{device}: give a value or raw=..., not both or neither")
        peer, spec = self._peer(device)
        if raw is None:
            self._put(device, value)
        else:
            set_raw = getattr(peer, "set_raw", None)
            (set_raw or peer.set)(spec, raw)
        self.held[device] = value if raw is None else ("raw", raw)

    def release(self, device: str) -> None:
        """End :meth:`hold` of ``device``: its value script or plant sets it again from the
        next tick (a device without either keeps the held value). Raises DeviceError if
        ``device`` is not held."""
        if self.held.pop(device, None) is None:
            raise DeviceError(f"{device!r} is not held (held: "
                              f"{', '.join(sorted(self.held)) or 'none'})")

    def bus_fault(self, bus: str, kind: str, duration: float | None = None) -> None:
        """Provoke a fault on the simulated CAN bus ``bus``: ``error-frame``, ``error-passive``,
        ``bus-off`` or ``recover`` (see :meth:`chcos.apps.sim.can_peer.CanPeer.fault`); with a
        ``duration`` (seconds of this handle's clock) it ends by itself. Raises DeviceError for
        a bus without a simulated CAN peer or an unknown fault."""
        peer = self._bus(bus)
        if not isinstance(peer, CanPeer):
            raise DeviceError(f"bus {bus!r} is a {peer.bus.kind!r} bus: bus faults are "
                              f"simulated on can buses")
        peer.fault(kind, duration)

    def get(self, device: str) -> Any:
        """What the peer holds for ``device``, in engineering units (an actuator: the last value
        the system wrote; None if nothing arrived yet on CAN). Raises DeviceError for an unknown
        or in-process device."""
        peer, spec = self._peer(device)
        raw = peer.get(spec)
        if raw is None or isinstance(raw, bool) or not is_number(raw):
            return raw
        return raw * spec.scale + spec.offset

    def script(self, device: str, script: Script | str) -> None:
        """Make sensor ``device`` follow ``script`` (a function of seconds since the start, in
        engineering units, or its text for :func:`parse_script`). Raises DeviceError for an
        unknown or in-process device, or a CiA 402 axis's (the simulated drive owns those)."""
        _peer, spec = self._peer(device)
        if spec.address.get("profile") == "cia402":
            raise DeviceError(f"{device!r} is a CiA 402 axis's: the simulated drive owns its "
                              "value; it cannot follow a script")
        self.scripts[device] = parse_script(script) if isinstance(script, str) else script

    def values(self, items: Sequence[str], base_dir: Path | None = None) -> None:
        """Scripts from ``DEVICE=SCRIPT`` items (``--value``: a number, ``ramp(...)``,
        ``sine(...)``, ``square(...)``, ``csv(FILE[, column])``, files relative to
        ``base_dir``). Raises ConfigError naming the item for a bad item, a device that is not
        a simulated sensor, or a bad script; nothing is applied then."""
        parsed: dict[str, Script] = {}
        for item in items:
            name, eq, spec = item.partition("=")
            name = name.strip()
            if not eq:
                raise ConfigError(f"--value {item!r}: expected DEVICE=SCRIPT")
            if name not in self.specs or self.specs[name].direction != "sensor":
                raise ConfigError(f"--value {item!r}: {name!r} is not a sensor of the maps")
            if not self.simulated(name):
                raise ConfigError(f"--value {item!r}: {name!r} is on an in-process bus with "
                                  "no simulated slave (inject its readings instead)")
            parsed[name] = parse_script(spec, base_dir)
        self.scripts.update(parsed)

    def add_plant(self, plant: Plant) -> None:
        """Call ``plant(seconds since the start, self)`` every TICK, after the scripts: a
        user's model of the machine (what the actuators do to the sensors)."""
        self.plants.append(plant)

    def silence(self, bus: str) -> None:
        """Make the peer of ``bus`` stop answering: a Modbus server closes its port, a CAN node
        stops sending, a CANopen node stops its heartbeat and TPDOs. Raises DeviceError if the
        bus has no simulated peer."""
        self._bus(bus).silence()

    def restore(self, bus: str) -> None:
        """Make the peer of ``bus`` answer again, with the values it held."""
        self._bus(bus).restore()

    def _bus(self, bus: str) -> Peer:
        try:
            return self.peers[bus]
        except KeyError:
            raise DeviceError(f"bus {bus!r} has no simulated peer (simulated: "
                              f"{', '.join(sorted(self.peers)) or 'none'})") from None

    def canopen_node(self, bus: str, node: int) -> CanopenSlave:
        """The simulated CANopen node ``node`` of ``bus``, for fault scripts: its
        ``inject_fault``/``clear_fault`` (0x1001 and EMCY), ``reset``, ``silence``. Raises
        DeviceError naming the bus for a bus without simulated CANopen nodes or another id."""
        peer = self._bus(bus)
        if not isinstance(peer, CanopenPeer):
            raise DeviceError(f"bus {bus!r} is a {peer.bus.kind!r} bus, not canopen")
        try:
            return peer.node(node)  # type: ignore[no-any-return]
        except ConfigError as exc:
            raise DeviceError(str(exc)) from None

    def schedule_emcy(self, items: list[str],
                      report: Callable[[str], None] | None = None) -> None:
        """Faults on simulated CANopen nodes from ``BUS:NODE:CODE@START[-END]`` items
        (``--emcy``): from START seconds the node raises CODE (0x1001 and EMCY), at END it
        clears it (error-reset EMCY), on this handle's clock. ``report`` gets a line for each.
        Raises ConfigError naming the item; nothing is scheduled then."""
        from chcos.apps.sim.canopen_slave import fault_arg

        plan = []
        for item in items:
            where, at, span = item.partition("@")
            parts = where.split(":")
            if len(parts) != 3 or not at:
                raise ConfigError(f"--emcy {item!r}: expected BUS:NODE:CODE@START[-END], e.g. "
                                  "axis:5:0x4210@2-6")
            bus, node_text, code_text = parts
            code, t0, t1 = fault_arg(f"{code_text}@{span}")
            try:
                node = self.canopen_node(bus, int(node_text, 0))
            except (DeviceError, ValueError) as exc:
                raise ConfigError(f"--emcy {item!r}: {exc}") from None
            plan.append(EmcyFault(node, code, t0, t1, report))
        self._emcy_plan.extend(plan)

    def serve(self) -> None:
        """Make every peer answer at its address (see :func:`simulate`'s ``serve``)."""
        for peer in self.peers.values():
            peer.serve()

    def describe(self) -> list[str]:
        """One line per peer: the bus and where it listens."""
        return [f"{name}: {peer.describe()}" for name, peer in self.peers.items()]

    def tick(self, now: float) -> None:
        """Apply the scripts at time ``now`` (seconds since the start) and send what is due."""
        for device, fn in self.scripts.items():
            self.set(device, fn(now))
        for plant in self.plants:
            plant(now, self)
        for peer in self.peers.values():
            peer.tick(now)
        for fault in self._emcy_plan:
            fault.apply(now)

    def settle(self, timeout: float) -> bool:
        """Wait (``timeout`` wall seconds at most for each peer) until every peer has handled
        what the drivers sent it so far; True when all have."""
        return all([peer.settle(timeout) for peer in self.peers.values()])

    def handled(self) -> int:
        """A count that grows whenever a driver sent something to a peer's own threads and
        whenever they are done with it (the kernel's settle activity)."""
        return sum(peer.handled() for peer in self.peers.values())

    def attach(self, kernel: Any) -> None:
        """Run on ``kernel``'s clock from now. Virtual time stays deterministic: the peers are
        the kernel's settlers (virtual time does not move on while a peer still handles what a
        driver sent it, nor while a driver waits for the answer or has not yet taken it in,
        see :meth:`~chcos.kernel.scheduler.Kernel.add_settle_activity`), and each step is
        settled before and after, so that it sees exactly what was sent before it in its
        instant and its frames are taken in before anything else runs in that instant."""
        origin = kernel.clock.now()
        kernel.add_settler(self.settle)
        kernel.add_settle_activity(self.handled)

        def step() -> None:
            kernel.settle()
            self.tick(kernel.clock.now() - origin)
            kernel.settle()

        self.tick(0.0)
        self._timer = kernel.every(TICK, step)

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


def simulate(devmap: DeviceMap, *, rewrite: bool = True, direct: bool = True,
             serve: bool = True) -> SimSlaves:
    """Start a simulated peer for every bus of ``devmap`` that has devices; returns the handle,
    whose ``devmap`` is the map the system should load (pointed at the peers when ``rewrite``:
    a Modbus bus reaches its slave in-process, ``direct``, unless ``direct`` is False - then a
    socket server on a free port). Idle actuators hold their safe values; a sensor whose
    limits leave 0 out serves the limit nearest 0 until something sets it (a reading outside
    the limits fails a sensor: a device shows what its map pins). With ``serve`` False
    the peers at the map's own addresses (``rewrite`` False) begin answering only at
    :meth:`SimSlaves.serve`, so that value scripts apply before the first request. Raises
    ConfigError naming the bus and its file for a bus kind without a simulated peer, BusError
    if a peer cannot listen or open its channel."""
    for bus in devmap.buses:
        if bus.kind not in SIMULATED and devmap.devices_on(bus.name):
            raise ConfigError(f"{bus.file}: {bus.key} ({bus.name}): no simulated peer for a "
                              f"{bus.kind!r} bus (simulated kinds: {', '.join(SIMULATED)})")
    slaves = SimSlaves(devmap, {d.name: d for d in devmap.devices})
    buses: list[BusSpec] = []
    try:
        for bus in devmap.buses:
            devs = devmap.devices_on(bus.name)
            if bus.kind in PEERS and devs:
                peer = (ModbusPeer(bus, devs, rewrite, direct) if bus.kind in MODBUS
                        else PEERS[bus.kind](bus, devs, rewrite))
                slaves.peers[bus.name] = peer
                buses.append(peer.bus)
                for d in devs:
                    if d.direction == "actuator" and d.safe_value is not None \
                            and bus.kind.startswith("modbus"):
                        slaves.set(d.name, d.safe_value)  # an idle output holds its safe value
                    elif d.direction == "sensor" and (start := within_limits(d)) is not None:
                        _serve_first(slaves, d, start)
            else:
                buses.append(bus)
        if serve:
            slaves.serve()
    except BaseException:
        slaves.close()
        raise
    slaves.devmap = dataclasses.replace(devmap, buses=tuple(buses))
    return slaves


def within_limits(device: DeviceSpec) -> float | None:
    """What a simulated sensor serves before anything sets it when 0 is no value its device
    would show: the limit nearest 0 when 0 is outside its limits (a SunSpec marker or model id
    the map pins with equal limits is served as the device shows it), the raw value 1 when its
    address calls 0 "not implemented" (a SunSpec accumulator: the simulated device implements
    what the map reads); None when 0 is such a value (0 is served)."""
    lo, hi = device.limits
    if lo is not None and lo > 0:
        return lo
    if hi is not None and hi < 0:
        return hi
    gap = device.address.get("unimplemented")
    if is_number(gap) and not isinstance(gap, bool) and gap == 0:
        return 1 * device.scale + device.offset
    return None


def _serve_first(slaves: SimSlaves, device: DeviceSpec, value: float) -> None:
    """Serve ``value`` for ``device`` unless its peer cannot (a CiA 402 axis's value, owned by
    the simulated drive, or a value its address cannot carry): then 0 stays, which the limit
    rule reports, as it would of a device that showed it."""
    with contextlib.suppress(ChcosError, ValueError, TypeError, OverflowError):
        slaves.set(device.name, value)


#: ``--fault`` kinds: ``silence`` (the default) and the CAN bus faults of the simulated bus
FAULT_KINDS = ("silence", "error-frame", "error-passive", "bus-off")


def _fault(item: str, slaves: SimSlaves) -> tuple[str, str, float, float]:
    """``BUS[:KIND]@START[-END]`` -> (bus, kind, start, end); raises ConfigError naming the
    item (an unknown kind, a bus fault on a bus that is not simulated CAN)."""
    m = re.fullmatch(r"([\w.\-]+)(?::([\w\-]+))?@([0-9.]+)(?:-([0-9.]+))?", item.strip())
    if not m:
        raise ConfigError(f"--fault {item!r}: expected BUS[:KIND]@START[-END] (seconds), e.g. "
                          f"plc@5-8 or can0:bus-off@2-4")
    bus, kind, t0 = m.group(1), m.group(2) or "silence", float(m.group(3))
    t1 = float(m.group(4)) if m.group(4) else math.inf
    if bus not in slaves.peers:
        raise ConfigError(f"--fault {item!r}: bus {bus!r} has no simulated peer (simulated: "
                          f"{', '.join(sorted(slaves.peers)) or 'none'})")
    if kind not in FAULT_KINDS:
        raise ConfigError(f"--fault {item!r}: no fault {kind!r}; expected one of "
                          f"{', '.join(FAULT_KINDS)}")
    if kind != "silence" and not isinstance(slaves.peers[bus], CanPeer):
        raise ConfigError(f"--fault {item!r}: {kind} is a CAN bus fault; {bus!r} is a "
                          f"{slaves.peers[bus].bus.kind!r} bus")
    if t1 <= t0:
        raise ConfigError(f"--fault {item!r}: the end must come after the start")
    return bus, kind, t0, t1


def _apply_faults(slaves: SimSlaves, faults: list[tuple[str, str, float, float]],
                  active: set[int], t: float) -> list[str]:
    """Start and end the ``--fault`` items due at ``t`` seconds (``active``: the indexes of
    those under way, updated); one line for each change. A bus fault with an end ends by
    itself on the peer's clock (the restart)."""
    lines = []
    for i, (bus, kind, t0, t1) in enumerate(faults):
        if i not in active and t0 <= t < t1:
            active.add(i)
            if kind == "silence":
                slaves.silence(bus)
                lines.append(f"fault: {bus} silenced")
            else:
                slaves.bus_fault(bus, kind, None if math.isinf(t1) else t1 - t0)
                lines.append(f"fault: {bus} {kind}")
        elif i in active and t >= t1:
            active.discard(i)
            if kind == "silence":
                slaves.restore(bus)
                lines.append(f"fault over: {bus} answers again")
            else:
                lines.append(f"fault over: {bus} {kind} ended (controllers restarted)")
    return lines


def load_plant(ref: str, base_dir: Path | None = None) -> Plant:
    """The plant model ``ref`` names: ``FILE.py:function`` (relative to ``base_dir``) or
    ``package.module:function``. Raises ConfigError naming ``ref`` if it cannot be loaded or is
    not a callable."""
    import importlib
    import importlib.util

    target, colon, func = ref.rpartition(":")
    if not colon or not target or not func.isidentifier():
        raise ConfigError(f"--plant {ref!r}: expected FILE.py:function or module:function")
    try:
        if target.endswith(".py") or "/" in target:
            path = Path(target)
            if not path.is_absolute() and base_dir is not None:
                path = base_dir / path
            spec = importlib.util.spec_from_file_location(f"chcos_plant_{path.stem}", path)
            if spec is None or spec.loader is None or not path.is_file():
                raise ConfigError(f"--plant {ref!r}: no file {path}")
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
        else:
            module = importlib.import_module(target)
    except ConfigError:
        raise
    except Exception as exc:  # the user's module failed to import: say how
        raise ConfigError(f"--plant {ref!r}: cannot load it: {type(exc).__name__}: "
                          f"{exc}") from exc
    fn = getattr(module, func, None)
    if not callable(fn):
        raise ConfigError(f"--plant {ref!r}: {target} has no function {func}")
    return fn  # type: ignore[no-any-return]


def process_local(devmap: DeviceMap) -> list[BusSpec]:
    """The CAN and CANopen buses of ``devmap`` (with devices) on python-can's ``virtual``
    interface (named in the map or by python-can's own configuration): a channel that exists
    only inside one process, so a peer in another process never reaches it."""
    from chcos.apps.sim.peers import can_args

    found = []
    for bus in devmap.buses:
        if bus.kind in ("can", "canopen") and devmap.devices_on(bus.name):
            try:
                interface = can_args(bus.options, False, bus.name).get("interface")
            except (ValueError, NotImplementedError):  # checked again where the bus opens
                continue
            if interface == "virtual":
                found.append(bus)
    return found


def changes(slaves: SimSlaves, last: dict[str, str]) -> list[str]:
    """One ``name=value units`` line per simulated device whose value changed since ``last``
    (updated; the first call shows every device), in the map's order."""
    lines = []
    for d in slaves.devmap.devices:
        if not slaves.simulated(d.name):
            continue
        v = slaves.get(d.name)
        text = f"{v:.4g}" if isinstance(v, float) else str(v)
        shown = f"{d.name}={text} {d.units}".rstrip()
        if last.get(d.name) != shown:
            last[d.name] = shown
            lines.append(f"{d.direction:<8} {shown}")
    return lines


def main(argv: list[str]) -> int:
    """``chcos sim --from MAP...``: serve simulated slaves at the addresses the maps name until
    Ctrl-C, SIGTERM or ``--duration``; prints each device's value on a line of its own when it
    changed, at most every ``--every`` seconds. Returns 0, or 2 when a map or script is invalid,
    a bus is on a process-local channel (see :func:`process_local`) or a peer cannot listen."""
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
    ap.add_argument("--emcy", action="append", default=[], metavar="BUS:NODE:CODE@START[-END]",
                    help="raise fault CODE on CANopen node NODE of BUS from START seconds (to "
                         "END): 0x1001 set, an EMCY sent, an error-reset EMCY when it ends, "
                         "e.g. axis:5:0x4210@2-6")
    ap.add_argument("--fault", action="append", default=[], metavar="BUS[:KIND]@START[-END]",
                    help="from START seconds (to END) a fault on BUS: silence (the default: "
                         "a Modbus server closes its port, CAN and CANopen nodes stop "
                         "sending), or on a CAN bus error-frame (one every 10 ms), "
                         "error-passive or bus-off (the controllers restart at END), e.g. "
                         "plc@5-8, can0:bus-off@2-4")
    ap.add_argument("--plant", action="append", default=[], metavar="FILE.py:FUNCTION",
                    help="a plant model called every 10 ms as FUNCTION(seconds, slaves): it reads "
                         "actuators (slaves.get) and sets sensors (slaves.set)")
    ap.add_argument("--duration", type=float, help="stop after this many seconds")
    ap.add_argument("--every", type=float, default=1.0, metavar="S",
                    help="print a device's value at most every S seconds, one line per device, "
                         "and only when it changed (default 1)")
    args = ap.parse_args(argv)
    if not (math.isfinite(args.every) and args.every > 0):
        ap.error(f"--every {args.every}: expected seconds > 0")
    stop = threading.Event()
    old = {sig: signal.signal(sig, lambda *_: stop.set())
           for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        devmap = load(args.maps)
        for local in process_local(devmap):
            raise ConfigError(f"{local.file}: {local.key} ({local.name}): python-can's 'virtual' "
                              "interface lives inside one process: a 'chcos run' in another "
                              "process would never hear this simulator. Use interface = "
                              "\"udp_multicast\" (any machine, loopback) or a SocketCAN vcan "
                              "channel; or 'chcos run SYSTEM --virtual', which simulates in its "
                              "own process")
        slaves = simulate(devmap, rewrite=False, serve=False)
        try:
            slaves.values(args.value, Path.cwd())
            for ref in args.plant:
                slaves.add_plant(load_plant(ref, Path.cwd()))
            faults = [_fault(item, slaves) for item in args.fault]
            slaves.schedule_emcy(args.emcy, report=lambda line: print(line, flush=True))
            slaves.run_realtime()      # the scripts' values at t = 0, before the first request
            slaves.serve()
            for line in slaves.describe():
                print(f"simulating {line}", flush=True)
            start = time.monotonic()
            shown_at = -math.inf
            last_shown: dict[str, str] = {}
            active: set[int] = set()
            while not stop.wait(0.1):
                t = time.monotonic() - start
                for line in _apply_faults(slaves, faults, active, t):
                    print(f"t={t:6.1f} s  {line}", flush=True)
                if t + 1e-9 < shown_at + args.every:
                    continue
                shown_at = t
                for line in changes(slaves, last_shown):
                    print(f"t={t:6.1f} s  {line}", flush=True)
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
