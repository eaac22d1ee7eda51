"""cia402_drive - a simulated CiA 402 servo drive for ``chcos sim``, the pytest plugin and the
cells: the power state machine reacting to the controlword (fault reset on the rising edge of bit 7
only), modes of operation confirmed on 0x6061 (some refusable), position and velocity loops,
quick-stop deceleration per 0x605A, a motor that coasts down by friction once its power stage is
off (disable voltage, shutdown: a braked stop and a coasting one differ), following-error (0x8611)
and over-temperature (0x4310) faults with EMCY and 0x603F, a fault that needs a reset.

:class:`DriveModel` is the drive without a bus (pure, stepped on virtual time);
:class:`Cia402Drive` puts it on a CAN bus as a :class:`~chcos.apps.sim.canopen_slave.CanopenSlave`
(the model is its plant, so the node's heartbeat, consumer, SYNC and event timers run as on any
node) with the EDS ``eds/cia402_drive.eds`` (every RPDO carries the controlword, as vendor
drives map them; TPDO1 statusword + modes display + error code, TPDO2 position + velocity) or a
vendor's. ``chcos sim cia402`` is :func:`main`; ``chcos sim --from``, ``run --virtual`` and the
pytest plugin use the class for every node whose EDS is a drive's.

The model is written here from the CiA 402 state diagram, apart from
:mod:`drivers.codecs.cia402` (the master side), so that the one checks the other.
"""

from __future__ import annotations

import argparse
import struct
import sys
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

from chcos import resources
from chcos.apps.sim.canopen_slave import (
    EMCY_HEARTBEAT_LOST,
    CanopenSlave,
    Clock,
    ErrorBits,
    MasterLost,
    NmtCommand,
)
from chcos.errors import BusError, ConfigError

#: The EDS shipped for the simulated CiA 402 drive.
CIA402_EDS = resources.path("chcos.apps.sim", "eds", "cia402_drive.eds")

FOLLOWING_ERROR = 0x8611
OVER_TEMPERATURE = 0x4310
#: Error register (0x1001) bits sent with each fault's EMCY: generic, and temperature.
ERROR_REGISTER = {FOLLOWING_ERROR: 0x01, OVER_TEMPERATURE: 0x09}


class Power(Enum):
    """The drive's power state, with its statusword bits 0-3, 5 and 6."""

    NOT_READY = 0x00
    SWITCH_ON_DISABLED = 0x40
    READY = 0x21
    SWITCHED_ON = 0x23
    ENABLED = 0x27
    QUICK_STOP = 0x07
    FAULT_REACTION = 0x0F
    FAULT = 0x08


#: The device control commands, by controlword bits 0-3 and 7 after masking (bit 7 handled
#: apart as an edge): (mask, value, command name).
COMMANDS: tuple[tuple[int, int, str], ...] = (
    (0x02, 0x00, "disable voltage"),
    (0x06, 0x02, "quick stop"),
    (0x07, 0x06, "shutdown"),
    (0x0F, 0x07, "switch on"),
    (0x0F, 0x0F, "enable operation"),
)

#: (state, command) -> next state. "quick stop" from ENABLED depends on 0x605A (see
#: :meth:`DriveModel.controlword`).
REACTIONS: dict[tuple[Power, str], Power] = {
    (Power.SWITCH_ON_DISABLED, "shutdown"): Power.READY,
    (Power.READY, "switch on"): Power.SWITCHED_ON,
    (Power.READY, "enable operation"): Power.ENABLED,
    (Power.READY, "disable voltage"): Power.SWITCH_ON_DISABLED,
    (Power.READY, "quick stop"): Power.SWITCH_ON_DISABLED,
    (Power.SWITCHED_ON, "enable operation"): Power.ENABLED,
    (Power.SWITCHED_ON, "shutdown"): Power.READY,
    (Power.SWITCHED_ON, "disable voltage"): Power.SWITCH_ON_DISABLED,
    (Power.SWITCHED_ON, "quick stop"): Power.SWITCH_ON_DISABLED,
    (Power.ENABLED, "switch on"): Power.SWITCHED_ON,
    (Power.ENABLED, "shutdown"): Power.READY,
    (Power.ENABLED, "disable voltage"): Power.SWITCH_ON_DISABLED,
    (Power.ENABLED, "quick stop"): Power.QUICK_STOP,
    (Power.QUICK_STOP, "disable voltage"): Power.SWITCH_ON_DISABLED,
}

PP, PV, HM, CSP, CSV = 1, 3, 6, 8, 9
MODES = (PP, PV, HM, CSP, CSV)


@dataclass
class DriveModel:
    """One CiA 402 axis without a bus. Objects it reads (targets, profile, options) are given to
    :meth:`step`; :meth:`controlword` and :meth:`mode` take what the master wrote. ``emcys``
    collects the EMCY codes to send (0: error reset) for the bus side to drain.
    ``coast_deceleration``: counts/s^2 by which the motor slows by friction alone while the
    power stage is off (anything but operation enabled and quick stop active)."""

    refused_modes: tuple[int, ...] = ()
    temperature_limit: float = 80.0
    power: Power = Power.NOT_READY
    mode_display: int = 0
    position: float = 0.0
    velocity: float = 0.0
    demand: float = 0.0
    setpoint: float = 0.0
    error_code: int = 0
    temperature: float = 25.0
    blocked: bool = False
    acked: bool = False
    homing: bool = False
    homed: bool = False
    new_setpoint: bool = False
    last_cw: int = 0
    emcys: list[int] = field(default_factory=list)
    history: list[Power] = field(default_factory=list)
    coast_deceleration: float = 2000.0

    def __post_init__(self) -> None:
        self.history.append(self.power)

    def _enter(self, power: Power) -> None:
        if power is not self.power:
            self.power = power
            self.history.append(power)
            if power is Power.ENABLED:
                self.demand = self.setpoint = self.position
            else:
                self.acked = self.homing = self.new_setpoint = False

    def controlword(self, cw: int, quick_stop_option: int) -> None:
        """React to a controlword written by the master."""
        previous, self.last_cw = self.last_cw, cw
        if self.power is Power.FAULT:
            if cw & 0x80 and not previous & 0x80:
                self._reset()
            return
        if self.power in (Power.NOT_READY, Power.FAULT_REACTION):
            return
        command = next((name for mask, value, name in COMMANDS if cw & mask == value), None)
        if command is None:
            return
        if (self.power, command) == (Power.QUICK_STOP, "enable operation") \
                and 5 <= quick_stop_option <= 8:
            self._enter(Power.ENABLED)                 # transition 16
        nxt = REACTIONS.get((self.power, command))
        if nxt is Power.QUICK_STOP and quick_stop_option == 0:
            nxt = Power.SWITCH_ON_DISABLED             # option 0: disable drive function
        # power removed (from any state): the motor coasts down, see step
        if nxt is not None:
            self._enter(nxt)
        if self.power is Power.ENABLED:
            rising = cw & 0x10 and not previous & 0x10
            if self.mode_display == PP:
                if rising:
                    self.new_setpoint = True           # latched at the next cycle
                elif not cw & 0x10:
                    self.acked = False
            elif self.mode_display == HM and rising:
                self.homing, self.homed = True, False

    def mode(self, value: int) -> None:
        """The master wrote 0x6060: shown on 0x6061 unless refused or unknown."""
        if value in MODES and value not in self.refused_modes:
            self.mode_display = value
            self.demand = self.setpoint = self.position

    def fault(self, code: int, *, emcy: bool = True) -> None:
        """A fault: fault reaction (then FAULT at the next step), 0x603F, an EMCY (``emcy``
        False: the node already sent it)."""
        if self.power in (Power.FAULT, Power.FAULT_REACTION):
            return
        self.error_code = code
        if emcy:
            self.emcys.append(code)
        self._enter(Power.FAULT_REACTION)

    def abort_connection(self, option: int, quick_stop_option: int) -> None:
        """The master fell silent: act on the abort connection option code 0x6007 (0 no
        action, 1 fault 0x8130, 2 disable voltage, 3 quick stop)."""
        if option == 1:
            self.fault(EMCY_HEARTBEAT_LOST, emcy=False)   # the node sent EMCY 0x8130
        elif option == 2 and self.power in (Power.READY, Power.SWITCHED_ON, Power.ENABLED,
                                            Power.QUICK_STOP):
            self._enter(Power.SWITCH_ON_DISABLED)         # power removed: the motor coasts
        elif option == 3 and self.power is Power.ENABLED:
            self._enter(Power.SWITCH_ON_DISABLED if quick_stop_option == 0
                        else Power.QUICK_STOP)
        elif option == 3 and self.power in (Power.READY, Power.SWITCHED_ON):
            self._enter(Power.SWITCH_ON_DISABLED)

    def reboot(self, mode: int = 0) -> None:
        """A reset node: the drive starts again from NOT READY (the self test), stopped, with
        no fault recorded (a cause that persists faults again at the next step), in its
        power-on mode ``mode`` (0x6060's stored value; none if refused or unknown)."""
        self.velocity = 0.0
        self.error_code = 0
        self.last_cw = 0
        self.homed = False
        self.mode_display = 0
        self.mode(mode)
        self._enter(Power.NOT_READY)

    def _reset(self) -> None:
        if self.temperature > self.temperature_limit:
            return                                     # the cause persists: stay in FAULT
        self.error_code = 0
        self.emcys.append(0)
        self._enter(Power.SWITCH_ON_DISABLED)

    def statusword(self, target_velocity: int) -> int:
        """The statusword for the present state."""
        sw = self.power.value | 0x0200
        if self.power in (Power.READY, Power.SWITCHED_ON, Power.ENABLED, Power.QUICK_STOP):
            sw |= 0x0010
        if self.power is Power.ENABLED:
            if self.mode_display == PP:
                at = round(self.position) == round(self.setpoint)
                sw |= (0x0400 if at and not self.new_setpoint else 0) | (0x1000 if self.acked
                                                                         else 0)
            elif self.mode_display == PV:
                sw |= 0x0400 if round(self.velocity) == target_velocity else 0
                sw |= 0x1000 if round(self.velocity) == 0 else 0
            elif self.mode_display == HM and self.homed:
                sw |= 0x1400
            elif self.mode_display in (CSP, CSV):
                sw |= 0x0400
        elif self.power is Power.QUICK_STOP and self.velocity == 0:
            sw |= 0x0400
        return sw

    def step(self, dt: float, *, target_position: int, target_velocity: int,
             profile_velocity: int, quick_stop_deceleration: int, following_window: int,
             quick_stop_option: int) -> None:
        """Advance ``dt`` seconds: automatic transitions, the loops, the fault checks."""
        if self.power is Power.NOT_READY:
            self._enter(Power.SWITCH_ON_DISABLED)      # transition 1: self test done
        elif self.power is Power.FAULT_REACTION:
            self.velocity = 0.0
            self._enter(Power.FAULT)                   # transition 14
        if self.temperature > self.temperature_limit:
            self.fault(OVER_TEMPERATURE)
        if dt <= 0:
            return
        if self.power is Power.QUICK_STOP or (self.power is Power.ENABLED
                                              and self.last_cw & 0x100):
            self._brake(quick_stop_deceleration, dt)
            if (self.power is Power.QUICK_STOP and self.velocity == 0
                    and not 5 <= quick_stop_option <= 8):
                self._enter(Power.SWITCH_ON_DISABLED)  # option 1..4: on to switch on disabled
            return
        if self.power is not Power.ENABLED:
            self._coast(dt)
            return
        if self.mode_display in (PV, CSV):
            self._run(float(target_velocity), dt)
            return
        if self.mode_display == PP and self.new_setpoint:
            self.setpoint, self.acked, self.new_setpoint = float(target_position), True, False
        goal = {PP: self.setpoint, CSP: float(target_position),
                HM: 0.0 if self.homing else self.demand}.get(self.mode_display, self.demand)
        reach = max(0, profile_velocity) * dt
        # within reach up to the rounding of dt (a difference of clock times): the goal itself,
        # so that the profile ends on it, at standstill, instead of a hair short at full speed
        gap = goal - self.demand
        move = gap if abs(gap) <= reach * (1 + 1e-9) else max(-reach, min(reach, gap))
        self.demand += move
        if self.mode_display == CSP:
            self.demand = goal                         # the master interpolates
        if not self.blocked:
            travel = self.demand - self.position
            # arrived at the goal: the motor has stopped (the profile ends at standstill, so a
            # quick stop right after the arrival does not carry the last step's speed on)
            self.velocity = 0.0 if self.demand == goal and self.mode_display != CSP \
                else travel / dt
            self.position = self.demand
        else:
            self.velocity = 0.0
        if self.homing and self.position == 0.0:
            self.homing, self.homed = False, True
        if abs(self.demand - self.position) > following_window:
            self.fault(FOLLOWING_ERROR)

    def _brake(self, deceleration: int, dt: float) -> None:
        speed = max(0.0, abs(self.velocity) - max(0, deceleration) * dt)
        self.velocity = speed if self.velocity >= 0 else -speed
        self.position += self.velocity * dt
        self.demand = self.position

    def _coast(self, dt: float) -> None:
        """The power stage is off: nothing brakes the motor but friction."""
        if self.velocity:
            self._brake(round(self.coast_deceleration), dt)

    def _run(self, velocity: float, dt: float) -> None:
        self.velocity = 0.0 if self.blocked else velocity
        self.position += self.velocity * dt
        self.demand = self.position


class Cia402Drive(CanopenSlave):
    """A simulated CiA 402 drive on a CAN bus: :class:`DriveModel` behind the objects of
    ``eds/cia402_drive.eds`` (or another CiA 402 EDS). ``quick_stop_option`` sets 0x605A (None:
    the EDS default); ``refused_modes`` are modes the drive does not accept. Every controlword
    it applied (RPDO or SDO) is kept in :attr:`received`.

    The drive is a :class:`CanopenSlave` with the model as its plant: :meth:`tick` runs the
    model, then the node's own life (heartbeat producer on ``clock=TICK``, heartbeat consumer,
    TPDO event timers); synchronous TPDOs go out on SYNC only, as the node's parameters say.
    When the consumer finds the master silent, the drive applies its abort connection option
    code 0x6007 (1 fault, 2 disable voltage, 3 quick stop). An NMT reset node reboots the
    drive (NOT READY, then SWITCH ON DISABLED; nothing is re-enabled). Raises
    :class:`ConfigError` for an EDS without the CiA 402 objects."""

    def __init__(self, node_id: int, eds: str | Path = CIA402_EDS, *, channel: str,
                 interface: str = "virtual", bitrate: int | None = None,
                 port: int | None = None,
                 heartbeat_period: float = 0.1, tpdo_period: float | None = None,
                 clock: Clock = Clock.REAL, quick_stop_option: int | None = 2,
                 refused_modes: tuple[int, ...] = ()) -> None:
        super().__init__(node_id, eds, channel=channel, interface=interface, bitrate=bitrate,
                         port=port,
                         heartbeat_period=heartbeat_period, tpdo_period=tpdo_period,
                         clock=clock, servo=False)
        for index in (0x6040, 0x6041, 0x6060):
            self.get(index)                            # ConfigError naming the missing object
        #: the objects the model shows that this EDS has (vendor files leave some out)
        self._shown = {i for i in (0x603F, 0x6061, 0x6064, 0x606C)
                       if self._store.find(i, 0) is not None}
        self.model = DriveModel(refused_modes=refused_modes)
        if quick_stop_option is not None:
            # a power-on value: it survives an NMT reset node, as a stored parameter would
            self._factory[(0x605A, 0)] = bytes(self._var(0x605A, 0).encode_raw(
                quick_stop_option))
            self.set(0x605A, 0, quick_stop_option)
        #: every controlword applied, in order
        self.received: list[int] = []
        self._model_fault: int | None = None   # the model's fault raised on the node
        # each RPDO entry and SDO download, in order
        self.add_write_hook(self._on_write)
        self.add_plant(self._step_model)
        self.add_master_lost_hook(self._master_lost)

    def _on_write(self, index: int, subindex: int, data: bytes) -> None:
        if subindex != 0 or index not in (0x6040, 0x6060):
            return
        with self._lock:
            if index == 0x6040:
                (cw,) = struct.unpack("<H", bytes(data[:2]))
                self.received.append(cw)
                self.model.controlword(cw, self._option(0x605A, 2))
            else:
                (mode,) = struct.unpack("<b", bytes(data[:1]))
                self.model.mode(mode)
            self._publish()

    def _option(self, index: int, missing: int) -> int:
        """An optional parameter of the drive (``missing`` when its EDS lacks it)."""
        return self._int(index, 0, missing)

    def _publish(self) -> None:
        """Show the model in the objects (TPDOs go out on change) and raise or clear its
        faults: each fault's EMCY and 0x1001 (with 0x1003) say the same; the fault reset sends
        the error-reset EMCY with the register of what is left."""
        m = self.model
        for code in m.emcys:
            self._show(0x603F, m.error_code)
            now = self._at(None)
            if code:
                self._model_fault = code
                self._raise(code, ErrorBits(ERROR_REGISTER.get(code, 0x01)) | ErrorBits.GENERIC,
                            b"", now)
            elif self._model_fault is not None:
                self._clear(self._model_fault, now)
                self._model_fault = None
            else:   # the reset of a fault the node raised (a lost master): the drive's EMCY
                self._emcy(0, self.error_register, b"", now)
        m.emcys.clear()
        self._show(0x603F, m.error_code)
        self._show(0x6061, m.mode_display)
        self._show(0x6064, round(m.position))
        self._show(0x606C, round(m.velocity))
        self.set(0x6041, 0, m.statusword(self._option(0x60FF, 0)))
        self._changed.notify_all()

    def _show(self, index: int, value: int) -> None:
        if index in self._shown:
            self.set(index, 0, value)

    def _step_model(self, slave: CanopenSlave, dt: float) -> None:
        """The drive's plant, stepped by :meth:`CanopenSlave.tick` under the node's lock."""
        self.model.step(dt, target_position=self._option(0x607A, 0),
                        target_velocity=self._option(0x60FF, 0),
                        profile_velocity=self._option(0x6081, 10000),
                        quick_stop_deceleration=self._option(0x6085, 50000),
                        following_window=self._option(0x6065, 5000),
                        quick_stop_option=self._option(0x605A, 2))
        self._publish()

    def _master_lost(self, slave: CanopenSlave, event: MasterLost) -> None:
        """The heartbeat consumer found the master silent: apply 0x6007."""
        if event.abort_option is not None:
            self.model.abort_connection(event.abort_option, self._option(0x605A, 2))
            self._publish()

    def _boot(self, command: NmtCommand, power_on: bool = False) -> None:
        """As the node's boot; a reset node (not the first power-on) reboots the drive too,
        which ends its fault (a cause that persists faults it again at the next step)."""
        if command is NmtCommand.RESET_NODE and not power_on and self._model_fault is not None:
            self._faults.pop(self._model_fault, None)
            self._model_fault = None
        super()._boot(command, power_on)
        if command is NmtCommand.RESET_NODE:
            if power_on:                               # the first start: the stored mode
                self.model.mode_display = 0
                self.model.mode(self._option(0x6060, 0))
            else:
                self.model.reboot(self._option(0x6060, 0))
            self._publish()

    # -- fault injection and what tests read --------------------------------------------------

    def block(self, blocked: bool = True) -> None:
        """A load that stops the motor: a following error builds up while it moves."""
        with self._lock:
            self.model.blocked = blocked

    def set_temperature(self, celsius: float) -> None:
        """The drive's temperature; above the limit it faults with 0x4310 and refuses resets."""
        with self._lock:
            self.model.temperature = celsius

    def published(self) -> tuple[int, int, int, int, int]:
        """(statusword, modes display, position, velocity, error code) as the objects hold
        (0 for one the EDS lacks)."""
        with self._lock:
            return (self._int(0x6041, 0), self._int(0x6061, 0), self._int(0x6064, 0),
                    self._int(0x606C, 0), self._int(0x603F, 0))

    def value(self, index: int, subindex: int = 0) -> int:
        """An integer object's value as the drive holds it (0 when its EDS lacks it)."""
        with self._lock:
            return self._int(index, subindex, 0)

    def frames(self) -> int:
        """How many controlwords the drive applied."""
        with self._lock:
            return len(self.received)

    def wait(self, predicate: Callable[[], bool], timeout: float = 10.0) -> bool:
        """Block until ``predicate()`` holds (checked on every change of the drive)."""
        with self._changed:
            return self._changed.wait_for(predicate, timeout)

    def step(self, dt: float) -> None:
        """:meth:`tick` (the name test hosts use)."""
        self.tick(dt)


def main(argv: Sequence[str] | None = None, stop: threading.Event | None = None) -> int:
    """``chcos sim cia402``: run a simulated CiA 402 drive in real time until interrupted,
    ``--duration`` elapses or ``stop`` is set (an embedding program's or a test's). Returns the
    process exit status (0 ok, 2 bad arguments or bus)."""
    parser = argparse.ArgumentParser(prog="chcos sim cia402",
                                     description="Simulated CiA 402 drive (state machine).")
    parser.add_argument("--node", type=int, default=1, help="node id 1..127 (default 1)")
    parser.add_argument("--eds", default=str(CIA402_EDS), help="EDS file")
    parser.add_argument("--interface", default="virtual", help="python-can interface")
    parser.add_argument("--channel", required=True, help="python-can channel (e.g. vcan0)")
    parser.add_argument("--bitrate", type=int, default=None)
    parser.add_argument("--heartbeat", type=float, default=0.1, help="heartbeat period, s")
    parser.add_argument("--quick-stop-option", type=int, default=2, help="0x605A (default 2)")
    parser.add_argument("--refuse-mode", type=int, action="append", default=[],
                        help="a mode of operation the drive refuses (repeatable)")
    parser.add_argument("--step", type=float, default=0.01, help="physics step, s")
    parser.add_argument("--duration", type=float, default=None, help="run this long, s")
    parser.add_argument("--overheat", metavar="START[-END]", default=None,
                        help="over-temperature from START seconds (to END): fault 0x4310, EMCY, "
                             "fault resets refused until it cools")
    parser.add_argument("--block", metavar="START[-END]", default=None,
                        help="a load stops the motor from START seconds (to END): a following "
                             "error (0x8611) once it moves")
    args = parser.parse_args(list(argv) if argv is not None else None)
    try:
        spans = {name: _span(f"--{name}", text) for name, text in
                 (("overheat", args.overheat), ("block", args.block)) if text is not None}
        drive = Cia402Drive(args.node, args.eds, channel=args.channel,
                            interface=args.interface, bitrate=args.bitrate,
                            heartbeat_period=args.heartbeat,
                            quick_stop_option=args.quick_stop_option,
                            refused_modes=tuple(args.refuse_mode))
        drive.start()
    except (ConfigError, BusError) as exc:
        print(f"chcos sim cia402: {exc}", file=sys.stderr)
        return 2
    for warning in drive.eds_warnings:
        print(f"chcos sim cia402: warning: {warning}", file=sys.stderr)
    drive.run_realtime(args.step)
    print(f"CiA 402 drive node {args.node} on {args.interface}:{args.channel}", flush=True)
    done = stop if stop is not None else threading.Event()
    start = drive.now()
    active: set[str] = set()
    try:
        while not done.wait(0.02):
            t = drive.now() - start
            for name, (t0, t1) in spans.items():
                on = t0 <= t < t1
                if on == (name in active):
                    continue
                active.symmetric_difference_update({name})
                if name == "overheat":
                    drive.set_temperature(95.0 if on else 25.0)
                else:
                    drive.block(on)
                print(f"t={t:6.1f} s  {name} {'on' if on else 'off'}", flush=True)
            if args.duration is not None and t >= args.duration:
                break
    except KeyboardInterrupt:
        pass
    finally:
        drive.stop()
    return 0


def _span(option: str, text: str) -> tuple[float, float]:
    """``START[-END]`` seconds -> (start, end); raises ConfigError naming the option."""
    first, _, last = text.partition("-")
    try:
        start, end = float(first), float(last) if last else float("inf")
    except ValueError:
        raise ConfigError(f"{option} {text!r}: expected START[-END] in seconds, e.g. 2-5") \
            from None
    if start < 0 or end <= start:
        raise ConfigError(f"{option} {text!r}: expected START >= 0 and END after START")
    return start, end
