"""plant - the arc-welding cell simulator on real field buses: :class:`WeldSim`.

The stand-in for the physical cell of the thesis (sections 5.1, 5.4, appendix 2): it steps the
pure physics model :class:`chcos.apps.weld.model.WeldCell` and presents its devices (the contract of
``chcos/apps/weld/DEVICES.md``) on the buses a real cell uses, as laid down in
``chcos/apps/weld/maps/weld_cell.toml``:

* **CANopen** on python-can channel A: five CiA 402 servo drives (TPDO1 position and velocity
  actual every 10 ms of simulated time while OPERATIONAL, TPDO2 the statusword on change; RPDO2
  controlwords drive each drive's state machine, RPDO1 targets move its joint while it is
  OPERATION ENABLED, see :mod:`chcos.apps.weld.servo`);
* **raw CAN** on channel B: the DBC-coded sensor messages (two channels, so the raw-CAN driver
  never sees CANopen);
* **Modbus TCP** on ``127.0.0.1:port``, unit 1: the power source and the cell I/O, refreshed
  every 10 ms;
* **serial**: the linear light sensor, 50 lines a second to the clients of a TCP server on
  ``127.0.0.1:port`` (the serial driver's ``socket://127.0.0.1:port``).

The slave side of each bus, with its register, object and message layout, is
:mod:`chcos.apps.weld.slaves`; the default channels and ports and the controller's device map
for them are :mod:`chcos.apps.weld.simmap`.

Time. Physics advances in steps of ``tick`` seconds, lazily: whenever the simulator publishes or
takes a command it first steps the model up to the last tick boundary at or before now. Every
publication happens at its own instant, a fraction of a millisecond after the boundary
(:data:`PHASES`: CANopen and Modbus, raw CAN, serial), so that the kernel settles one bus at a
time and no two buses deliver in the same virtual instant (the order of their interrupts would
depend on thread timing), and never on a millisecond grid where driver polls and task timers lie.

:meth:`WeldSim.attach` runs it on a kernel's clock (virtual time in tests and fast runs) through
kernel timers, and registers :meth:`WeldSim.settle`, which takes in every command already sent to
the simulator (RPDO and NMT frames are read synchronously from a second bus handle on the CANopen
channel; Modbus writes are in the register store once the Modbus driver has its answer) and
applies it to the model before virtual time moves on. The kernel settles in registration order
and the drivers must have sent before the simulator looks, so the settler is registered at the
first publication, once the kernel runs: start the drivers that talk to the simulator (boot the
machine) before the kernel runs, whether before or after :meth:`WeldSim.attach` (a driver
started later settles after the simulator, and a command on its bus may then be taken in one
instant late, depending on thread timing).
:meth:`WeldSim.start_realtime` instead runs it from a thread on wall-clock time (``chcos sim
weld``, :func:`main`).

Faults (:mod:`chcos.apps.weld.faults`): a scenario at construction, :meth:`WeldSim.inject` at run
time.
A silent sensor stops being sent: no TPDO of that joint, no frame of its DBC message, no serial
line; its Modbus input register answers exception 11 (gateway target failed to respond), so the
driver fails that device alone. A servo timeout also stops that node's heartbeat. While the coil
``drives_enable`` (the safe-torque-off relay) is 0 every joint is held where it is and RPDO
targets are ignored, whatever state the drives are in; a joint also moves only while its drive is
OPERATION ENABLED (or slows down in a quick stop).

Errors: :class:`chcos.errors.ConfigError` for bad arguments, scenarios or device-map templates;
:class:`chcos.errors.BusError` when a CAN channel cannot be opened or a TCP port bound.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import math
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

from chcos.apps.sim.modbus_server import ModbusSimServer
from chcos.apps.weld.faults import Fault, Scenario, load_scenario, parse_fault
from chcos.apps.weld.lineserver import LineServer
from chcos.apps.weld.model import CellConfig, WeldCell, dbc_signals
from chcos.apps.weld.seam import Seam
from chcos.apps.weld.simmap import (
    DEFAULT_CANOPEN_CHANNEL,
    DEFAULT_MODBUS_PORT,
    DEFAULT_SENSOR_CHANNEL,
    DEFAULT_SERIAL_PORT,
)
from chcos.apps.weld.slaves import (
    CAN_MESSAGES,
    HEARTBEAT_PERIOD,
    NODE_IDS,
    POSITION_SCALE,
    SERVO_PERIOD,
    STATUS_EVERY,
    UNIT,
    WELD_DBC,
    PowerSource,
    SensorFrames,
    ServoDrives,
    TargetWrite,
    format_line,
)
from chcos.errors import BusError, ConfigError, DeviceError
from chcos.helpers import is_int
from chcos.kernel.scheduler import Kernel, Timer
from drivers.codecs.can import load_dbc

LINE_SLOTS = 2
"""Linear light sensor: one line every second slot, 20 ms (50 Hz)."""
PHASES: Mapping[str, float] = {"servo": 0.00025, "can": 0.0005, "line": 0.00075}
"""Offset (s) of each publication after its 10 ms slot boundary (see the module doc); raw CAN
and serial instants exist only in slots where something is due."""


# --- the simulator -----------------------------------------------------------------------------


class WeldSim:
    """The simulated welding cell on CANopen, raw CAN, Modbus TCP and a serial line (see the
    module doc). ``tick`` is the physics step (s, 0 < tick <= 0.01); ``seed`` the noise seed;
    ``scenario`` faults to inject (see :func:`chcos.apps.weld.faults.load_scenario`);
    ``config``/``seam`` the model's.

    Everything is opened at construction: build the simulator before the System whose drivers
    connect to it. Raises :class:`ConfigError` (bad arguments, scenario, EDS or DBC) and
    :class:`BusError` (a channel that cannot be opened, a port that cannot be bound); whatever
    was opened is closed again.
    """

    def __init__(self, *, canopen_channel: str = DEFAULT_CANOPEN_CHANNEL,
                 sensor_channel: str = DEFAULT_SENSOR_CHANNEL,
                 modbus_port: int = DEFAULT_MODBUS_PORT, serial_port: int = DEFAULT_SERIAL_PORT,
                 interface: str = "virtual", scenario: Scenario | str | Path | None = None,
                 seed: int = 0, tick: float = 0.005, config: CellConfig | None = None,
                 seam: Seam | None = None, can_messages: Sequence[str] = CAN_MESSAGES,
                 heartbeat_period: float = HEARTBEAT_PERIOD) -> None:
        if not (isinstance(tick, int | float) and math.isfinite(tick) and 0 < tick <= SERVO_PERIOD):
            raise ConfigError(f"weld simulator tick={tick!r} s: expected 0 < tick <= "
                              f"{SERVO_PERIOD} s")
        if canopen_channel == sensor_channel:
            raise ConfigError(f"weld simulator: canopen_channel and sensor_channel are both "
                              f"{canopen_channel!r}; expected two channels")
        for what, port in (("modbus_port", modbus_port), ("serial_port", serial_port)):
            if not (is_int(port) and 1 <= port <= 65535):
                raise ConfigError(f"weld simulator {what}={port!r}: expected a TCP port 1..65535")
        if not heartbeat_period > 0:
            raise ConfigError(f"weld simulator heartbeat_period={heartbeat_period!r} s: "
                              f"expected > 0")
        self.tick = float(tick)
        self.scenario = load_scenario(scenario)
        self.model = WeldCell(config, seam, self.scenario, seed)
        self.interface = interface
        self.canopen_channel = canopen_channel
        self.sensor_channel = sensor_channel
        self.modbus_port = modbus_port
        self.serial_port = serial_port
        #: Commands the model refused or ignored, counted by kind.
        self.stats: Counter[str] = Counter()
        #: The latest refused commands (text), newest last.
        self.errors: list[str] = []
        self._lock = threading.RLock()
        self._closed = False
        self._steps = 0
        self._origin: float | None = None
        self._clock: Callable[[], float] = time.monotonic
        self._kernel: Kernel | None = None
        self._timers: list[Timer] = []
        self._rt_thread: threading.Thread | None = None
        self._rt_stop = threading.Event()
        self._slot = 0
        self._settler_due = False
        self._later: Callable[[float, Callable[[], None]], None] = lambda _delay, fn: fn()
        self.power = PowerSource()
        self.store = self.power.store
        self.servo: ServoDrives | None = None
        self.sensors: SensorFrames | None = None
        self.modbus: ModbusSimServer | None = None
        self.line: LineServer | None = None
        try:
            self.servo = ServoDrives(interface, canopen_channel, heartbeat_period=heartbeat_period)
            self.sensors = SensorFrames(interface, sensor_channel, load_dbc(str(WELD_DBC)),
                                        messages=can_messages)
            self.modbus = ModbusSimServer(self.store, modbus_port)
            self.modbus.start()
            self.line = LineServer(serial_port)
        except BaseException:
            self.close()
            raise
        self.power.publish(self.model.readings())

    # -- running ------------------------------------------------------------------------------

    def attach(self, kernel: Kernel) -> None:
        """Run on ``kernel``'s clock from now: publications as kernel timers, commands taken in
        by a settler registered at the first publication (see the module doc: boot before the
        kernel runs). Raises ConfigError if already running or closed."""
        with self._lock:
            self._check_idle()
            now = kernel.clock.now()
            self._kernel = kernel
            self._clock = kernel.clock.now
            self._origin = now
            self._timers = [kernel.call_at(now + PHASES["servo"], self._on_servo, SERVO_PERIOD)]

            def later(delay: float, fn: Callable[[], None]) -> None:
                kernel.call_at(kernel.clock.now() + delay, fn)

            self._later = later
            self._settler_due = True  # registered at the first slot, after the drivers' own

    def settle(self, timeout: float) -> bool:
        """Take in every command sent to the simulator so far and apply it to the model (the
        kernel calls this before virtual time moves on). Always True: nothing waits."""
        with self._lock:
            if self._origin is not None and not self._closed:
                self._advance(self._clock())
        return True

    def start_realtime(self) -> None:
        """Run from a thread on wall-clock time (for ``chcos sim weld``). Raises ConfigError if
        already running or closed."""
        with self._lock:
            self._check_idle()
            self._clock = time.monotonic
            self._origin = origin = time.monotonic()
            self._rt_stop.clear()

            def loop() -> None:  # raw CAN and serial go out right after the servo slot
                n = 0
                while not self._rt_stop.wait(
                        max(0.0, origin + PHASES["servo"] + n * SERVO_PERIOD - time.monotonic())):
                    n += 1
                    self._on_servo()

            self._rt_thread = threading.Thread(target=loop, name="weld-sim", daemon=True)
            self._rt_thread.start()

    def continue_realtime(self) -> None:
        """Go on from where the kernel's clock left the simulator, on wall-clock time: at the
        System's shutdown the kernel's timers no longer run, but the joint drives must still
        answer the safe stop (quick stop, then disable voltage) the controller sends them. Does
        nothing unless attached to a kernel and open."""
        with self._lock:
            if self._closed or self._kernel is None or self._rt_thread is not None:
                return
            for timer in self._timers:
                timer.cancel()
            self._timers = []
            self._kernel = None
            self._later = lambda _delay, fn: fn()
            now = time.monotonic()
            self._clock = time.monotonic
            self._origin = now - self._steps * self.tick
            self._rt_stop.clear()

            def loop() -> None:
                n = 0
                while not self._rt_stop.wait(max(0.0, now + (n + 1) * SERVO_PERIOD
                                                 - time.monotonic())):
                    n += 1
                    self._on_servo()

            self._rt_thread = threading.Thread(target=loop, name="weld-sim-shutdown",
                                               daemon=True)
            self._rt_thread.start()

    def _check_idle(self) -> None:
        if self._closed:
            raise ConfigError("weld simulator: closed; create a new one")
        if self._origin is not None:
            raise ConfigError("weld simulator: already running (attach/start_realtime once)")

    def close(self) -> None:
        """Stop the timers or the thread and close every bus and server. Idempotent; never
        raises."""
        with self._lock:
            self._closed = True
            for timer in self._timers:
                timer.cancel()
            self._timers = []
        self._rt_stop.set()
        if self._rt_thread is not None:
            self._rt_thread.join(timeout=5.0)
            self._rt_thread = None
        for part in (self.line, self.servo, self.sensors):
            if part is not None:
                with contextlib.suppress(Exception):
                    part.close()
        if self.modbus is not None:
            with contextlib.suppress(Exception):
                self.modbus.stop()

    def __enter__(self) -> WeldSim:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- faults -------------------------------------------------------------------------------

    def inject(self, fault: Fault | str) -> None:
        """Inject a fault (a :class:`Fault` or one scenario item such as
        ``"sensor-dropout(arc_temperature)"``) at the present simulated time. Raises ConfigError
        for a bad fault string."""
        if isinstance(fault, str):
            fault = parse_fault(fault)
        with self._lock:
            self.model.inject(fault)
            self._sync_heartbeats()

    @property
    def drives_enabled(self) -> bool:
        """The state of the safe-torque-off relay as the simulator applied it last."""
        with self._lock:
            return self.power.drives_enabled

    @property
    def sim_time(self) -> float:
        """Simulated time (s) the model has been stepped to."""
        with self._lock:
            return self._steps * self.tick

    # -- the cycle ----------------------------------------------------------------------------

    def _advance(self, now: float) -> None:
        """Take in commands, then step the drives and the model to the last tick boundary at
        or before ``now`` and apply the commands from there, in arrival order."""
        assert self._origin is not None and self.servo is not None
        commands = self.servo.drain()
        n = math.floor((now - self._origin) / self.tick + 1e-6)
        model = self.model
        servo = self.servo
        while self._steps < n:
            servo.step(self.tick, model, self.power.drives_enabled)
            model.step(self.tick)
            self._steps += 1
        self.power.apply(self.model, self._refused)
        for command in commands:
            taken = servo.apply(command)
            if not isinstance(command, TargetWrite):
                continue
            if not self.power.drives_enabled:
                self.stats["target-ignored-disabled"] += 1
            elif not taken:
                self.stats["target-ignored-drive"] += 1
            else:
                try:
                    model.set_joint_target(command.node, command.counts * POSITION_SCALE)
                except DeviceError as exc:
                    self._refused("target", f"node {command.node} RPDO1 target "
                                            f"{command.counts} counts: {exc}")
        self._sync_heartbeats()

    def _refused(self, kind: str, text: str) -> None:
        self.stats[f"{kind}-refused"] += 1
        self.errors.append(text)
        del self.errors[:-50]

    def _sync_heartbeats(self) -> None:
        if self.servo is not None:
            self.servo.sync_heartbeats(self.model.readings().servo_ok)

    def _on_servo(self) -> None:
        """Every 10 ms slot: TPDO1 of every live, OPERATIONAL drive and the power source's
        registers; then the raw-CAN instant (if a message is due) and the serial instant (every
        second slot) are scheduled."""
        with self._lock:
            if self._closed or self.servo is None:
                return
            if self._settler_due and self._kernel is not None:
                self._settler_due = False
                self._kernel.add_settler(self.settle)
            self._advance(self._clock())
            slot = self._slot
            self._slot += 1
            r = self.model.readings()
            for j, nid in enumerate(NODE_IDS):
                if f"joint{j + 1}" in r.silent or not self.servo.operational[nid]:
                    continue
                self.servo.send_tpdo(nid, round(r.joints[j] / POSITION_SCALE))
                self.servo.send_status(nid, force=slot % STATUS_EVERY == 0)
            self.servo.beat(self._steps * self.tick)
            self.power.publish(r)
            if self.sensors is not None and self.sensors.due(slot, dbc_signals(r, 0)):
                self._later(PHASES["can"] - PHASES["servo"], functools.partial(self._on_can, slot))
            if slot % LINE_SLOTS == 0:
                self._later(PHASES["line"] - PHASES["servo"], self._on_line)

    def _on_can(self, slot: int) -> None:
        """The raw-CAN messages due or changed in ``slot``."""
        with self._lock:
            if self._closed or self.sensors is None:
                return
            self._advance(self._clock())
            self.sensors.publish(slot, dbc_signals(self.model.readings(), 0))

    def _on_line(self) -> None:
        """One line of the linear light sensor."""
        with self._lock:
            if self._closed or self.line is None:
                return
            self._advance(self._clock())
            r = self.model.readings()
            if "linear_sensor" not in r.silent:
                self.line.send_line(format_line(r))


# --- chcos sim weld ----------------------------------------------------------------------------


def main(argv: Sequence[str] | None = None) -> int:
    """``chcos sim weld``: run the simulated cell on wall-clock time until interrupted or
    ``--duration`` elapses, printing a status line every ``--status`` seconds. Returns the exit
    status (0 ok, 2 bad arguments, scenario, channel or port)."""
    p = argparse.ArgumentParser(prog="chcos sim weld",
                                description="The simulated arc-welding cell on CANopen, raw CAN, "
                                            "Modbus TCP and a serial line (busconfig/"
                                            "weld_cell.toml).")
    p.add_argument("--scenario", default="",
                   help='faults, e.g. "tip-stuck@s=120mm,intruder(for=2s)@t=8s", or a .toml file')
    p.add_argument("--seed", type=int, default=0, help="noise seed (0)")
    p.add_argument("--tick", type=float, default=0.005, help="physics step, s (0.005)")
    p.add_argument("--interface", default="virtual", help="python-can interface (virtual)")
    p.add_argument("--canopen-channel", default=DEFAULT_CANOPEN_CHANNEL)
    p.add_argument("--sensor-channel", default=DEFAULT_SENSOR_CHANNEL)
    p.add_argument("--modbus-port", type=int, default=DEFAULT_MODBUS_PORT)
    p.add_argument("--serial-port", type=int, default=DEFAULT_SERIAL_PORT)
    p.add_argument("--duration", type=float, default=None, help="run this long, s")
    p.add_argument("--status", type=float, default=1.0, help="status line period, s (1)")
    args = p.parse_args(list(argv) if argv is not None else None)
    try:
        sim = WeldSim(canopen_channel=args.canopen_channel, sensor_channel=args.sensor_channel,
                      modbus_port=args.modbus_port, serial_port=args.serial_port,
                      interface=args.interface, scenario=args.scenario, seed=args.seed,
                      tick=args.tick)
    except (ConfigError, BusError) as exc:
        print(f"chcos sim weld: {exc}", file=sys.stderr)
        return 2
    with sim:
        sim.start_realtime()
        print(f"weld cell: canopen {args.interface}:{args.canopen_channel} nodes "
              f"{','.join(map(str, NODE_IDS))}, raw CAN {args.interface}:{args.sensor_channel}, "
              f"modbus 127.0.0.1:{args.modbus_port} unit {UNIT}, serial "
              f"socket://127.0.0.1:{args.serial_port}; scenario "
              f"{sim.scenario.describe() or 'none'}", flush=True)
        deadline = None if args.duration is None else time.monotonic() + args.duration
        stop = threading.Event()
        try:
            while deadline is None or time.monotonic() < deadline:
                left = args.status if deadline is None else min(args.status,
                                                                deadline - time.monotonic())
                stop.wait(max(0.0, left))
                print(status_line(sim), flush=True)
        except KeyboardInterrupt:
            pass
    return 0


def status_line(sim: WeldSim) -> str:
    """One line on the simulated cell: time, tip, arc, drives, weld progress."""
    with sim._lock:
        m = sim.model
        x, y, z = m.pose.position
        prog = m.progress()
        return (f"t={sim.sim_time:7.2f}s tip=({x:6.1f},{y:6.1f},{z:6.1f})mm "
                f"s={m.seam_point.s:6.1f}mm V={m.voltage_setpoint:4.1f} "
                f"T={m.temperature:6.0f}C drives={'on' if sim.drives_enabled else 'off'} "
                f"welded={prog.welded:5.1f}/{prog.length:.0f}mm flawed={prog.flawed:.1f}mm")
