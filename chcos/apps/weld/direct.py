"""direct - the welding cell's devices bound straight onto a :class:`chcos.apps.weld.WeldCell`.

A protocol-free binding for fast runs and tuning: the cell model lives in this process and is
stepped on the kernel clock (``host.every(tick)``), so it runs on virtual time as fast as the CPU
allows and exactly reproducibly. It offers the device table of ``chcos/apps/weld/DEVICES.md`` with
the
same names, units and meaning as the real-bus simulator (``chcos.apps.weld.plant``) and delivers
sensor
readings at the rates the real buses do (the DBC's cycle times, the servo TPDOs, the serial line,
the Modbus polls):

=====================================================  ========  ================================
devices                                                rate      model sensor (for dropouts)
=====================================================  ========  ================================
``theta1``..``theta5`` (rad)                           100 Hz    ``joint1``..``joint5``
``arc_temp`` (degC)                                    50 Hz     ``arc_temperature``
``start_marker``, ``end_marker`` (0/1)                 20 Hz     ``gap_markers``
``intruder`` (0/1)                                     50 Hz     ``intruder``
``linear`` (64 '0'/'1'), ``range`` (mm, -1 = none)     50 Hz     ``linear_sensor``
``arc_volts``, ``arc_amps``, ``wire_speed``,           20 Hz     ``arc_voltage``, ``arc_current``,
``gas_bottle``, ``gas_flow``                                     ``wire_speed``, ...
=====================================================  ========  ================================

A change of ``intruder``, ``start_marker`` or ``end_marker`` is also sent at once (the raw-CAN
nodes send on change as well as periodically). A dropped-out sensor stops delivering (Devtab then
marks it stale after its ``stale_after``); a servo timeout silences its joint and calls
``host.fail(thetaN)``, and ``host.recover`` when it ends.

Actuators: ``target1``..``target5`` (rad), ``drives_enable`` (0/1, the safe-torque-off relay: 0
holds every joint where it is and target writes are ignored until it is 1 again), ``volts_set``
(V), ``wire_set`` (mm/s), ``gas_valve`` (0/1). A set-point the model refuses is counted as a bus
error (``host.error``), as a real drive would answer with an error code. Every write is
confirmed (``host.written``) once applied.

The joint drives are CiA 402 drives (:class:`chcos.apps.weld.servo.JointDrive`, the same as the
real-bus simulator's): a joint moves only while its drive is OPERATION ENABLED and the relay is
on, and a target is taken only then. An axis table (``profile = "cia402"``, ``address = { node =
N, axis = 0 }`` for joint N) on this bus is an **in-process axis**: the driver hosts the axis
engine (:class:`drivers.canopen_axis.AxisHost`) on that drive, with no protocol between them (a
controlword written is applied at once, the drive's statusword, mode, position and velocity are
read back every tick), and implements the ``AxisDriver`` protocol of :mod:`chcos.user.axes`, so
tasks call ``ctx.axis("jointN")`` on both bindings. The axis's actuator takes the command codes
of :class:`drivers.canopen_axis.AxisCode` (its safe value is the safe stop sequence, confirmed
when the drive confirms it); its sensors are ``jointN.state``, ``.statusword``, ...

Bus options: :class:`WeldDirectOptions` (``scenario``, ``seed``, ``tick``). Device address:
:class:`WeldAddress` (``{ signal = "<name>" }`` where the name is one of :data:`SENSORS` /
:data:`ACTUATORS`; an empty address means the device's own name), or an axis table's.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from chcos.apps.weld import LinearView, Readings, WeldCell, parse_scenario
from chcos.apps.weld.servo import POSITION_SCALE, JointDrive
from chcos.devices.options import option
from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.errors import BusError, ChcosError, ConfigError
from drivers.base import Driver, DriverHost, deliver_all
from drivers.canopen_axis import (
    AxisCall,
    AxisCode,
    AxisHost,
    AxisStatus,
    Done,
    device_write,
)
from drivers.codecs.cia402 import (
    Cia402Error,
    Obj,
    Write,
    config_from_table,
    is_axis_address,
    mode_of,
)

JOINTS = tuple(f"theta{j}" for j in range(1, 6))
TARGETS = tuple(f"target{j}" for j in range(1, 6))


def _linear(r: Readings) -> str:
    return "".join("1" if p else "0" for p in r.linear_pixels)


def _joint(j: int) -> Callable[[Readings], float]:
    def get(r: Readings) -> float:
        return r.joints[j]
    return get


# name -> (period in ticks of 10 ms, model sensor whose dropout silences it, value getter)
SENSORS: dict[str, tuple[int, str, Callable[[Readings], Any]]] = {
    **{f"theta{j + 1}": (1, f"joint{j + 1}", _joint(j)) for j in range(5)},
    "arc_temp": (2, "arc_temperature", lambda r: r.arc_temperature),
    "start_marker": (5, "gap_markers", lambda r: int(r.start_marker)),
    "end_marker": (5, "gap_markers", lambda r: int(r.end_marker)),
    "intruder": (2, "intruder", lambda r: int(r.intruder)),
    "linear": (2, "linear_sensor", _linear),
    "range": (2, "linear_sensor", lambda r: -1.0 if r.range_mm is None else r.range_mm),
    "arc_volts": (5, "arc_voltage", lambda r: r.arc_voltage),
    "arc_amps": (5, "arc_current", lambda r: r.arc_current),
    "wire_speed": (5, "wire_speed", lambda r: r.wire_speed),
    "wire_left": (5, "wire_remaining", lambda r: r.wire_remaining),
    "gas_bottle": (5, "gas_bottle_pressure", lambda r: r.gas_bottle_pressure),
    "gas_flow": (5, "gas_flow", lambda r: r.gas_flow),
}
"""Every sensor this binding offers: its period in 10 ms ticks, the model sensor whose dropout
silences it, and how its value is read from :class:`chcos.apps.weld.Readings`."""

ACTUATORS: tuple[str, ...] = (*TARGETS, "drives_enable", "volts_set", "wire_set", "gas_valve")
"""Every actuator this binding offers."""

AXIS_ADDRESS = ("profile", "node", "axis", "index", "subindex", "mode", "config", "reading")
"""The address keys of an axis table's devices (written by the device-map parser)."""

ON_CHANGE = ("intruder", "start_marker", "end_marker")
BASE_TICK = 0.01


def _scenario(text: str) -> str | None:
    try:
        parse_scenario(text)
    except ConfigError as exc:
        return f"a fault scenario ({exc})"
    return None


def _tick(tick: float) -> str | None:
    return None if 0 < tick <= BASE_TICK else f"seconds, 0 < tick <= {BASE_TICK}"


@dataclass(frozen=True)
class WeldDirectOptions:
    """The options of a ``weld-direct`` bus."""

    scenario: str = option("", doc="fault scenario (`chcos.apps.weld.faults` syntax)",
                           check=_scenario)
    seed: int = option(0, doc="measurement-noise seed")
    tick: float = option(BASE_TICK, unit="s", doc="model step; at most 0.01 so that the joints "
                         "really come at 100 Hz", check=_tick)


@dataclass(frozen=True)
class WeldAddress:
    """The address of a welding-cell device that is no axis."""

    signal: str | None = option(None, default_doc="the device's name", doc="a sensor or "
                                "actuator of the cell model (`chcos/apps/weld/DEVICES.md`), "
                                "as the device's direction")


class _Cell(WeldCell):
    """The cell model with a linear view computed only when a sample of it is due: the view is
    the model's costliest reading and the sensor is sampled at 50 Hz, half the tick rate."""

    view_due = True
    _view: LinearView | None = None

    def linear_view(self) -> LinearView:
        """The linear sensor's view, recomputed when :attr:`view_due` (else the last one)."""
        if self.view_due or self._view is None:
            self._view = super().linear_view()
        return self._view


class WeldDirectDriver(Driver):
    """Driver for bus kind ``weld-direct``: the cell model in-process (see the module doc).

    :attr:`cell` is the model (for tests and summaries); :attr:`changes` lists
    ``(time, device, value)`` for every change of an on-change device as it was delivered, so the
    reaction latency to an interrupt can be measured; :attr:`writes` counts accepted set-points
    per actuator.
    """

    kind: ClassVar[str] = "weld-direct"
    confirms_writes: ClassVar[bool] = True
    Options: ClassVar[type | None] = WeldDirectOptions
    Address: ClassVar[type | None] = WeldAddress
    settles = False     # the model steps in a kernel timer: nothing is ever in flight

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        config = self.bus_options(bus, WeldDirectOptions)
        self.tick = config.tick
        self.cell: WeldCell = _Cell(scenario=parse_scenario(config.scenario), seed=config.seed)
        #: the joints' CiA 402 drives, joint 1..5 at index 0..4
        self.drives = [JointDrive(j) for j in range(1, 6)]
        self.signal = {name: self.address_of(d, WeldAddress).signal or name
                       for name, d in self.devices.items() if not is_axis_address(d.address)}
        #: the in-process axes by actuator name, and the joint (0..4) each drives
        self.axes: dict[str, AxisHost] = {}
        self.axis_joint: dict[str, int] = {}
        for d in self.devices.values():
            if is_axis_address(d.address) and d.direction == "actuator":
                self._bind_axis(d)
        self.changes: list[tuple[float, str, Any]] = []
        self.writes: dict[str, int] = {}
        self.enabled = True
        self._ticks = 0
        self._failed: set[str] = set()
        self._last: dict[str, Any] = {}

    # ---- checking ---------------------------------------------------------------------------
    @classmethod
    def address_kind(cls, bus: BusSpec, device: DeviceSpec) -> type | None:
        """A :class:`WeldAddress`, or None for an axis table's (checked in
        :meth:`check_device`)."""
        return None if is_axis_address(device.address) else WeldAddress

    @classmethod
    def address_problems(cls, bus: BusSpec, device: DeviceSpec, addr: Any) -> list[str]:
        """``signal`` (the device's name when left out) must name a sensor or an actuator of
        the cell as the device's direction."""
        name = addr.signal or device.name
        known = SENSORS if device.direction == "sensor" else ACTUATORS
        if name in known:
            return []
        return [f"{device.key}.address.signal: {name!r} is not a {device.direction} of the "
                f"welding cell; expected one of {', '.join(known)}"]

    @classmethod
    def check_device(cls, bus: BusSpec, device: DeviceSpec) -> list[str]:
        """An axis table's address (its keys written by the map parser) must name a joint
        drive; any other is a :class:`WeldAddress` (:meth:`address_problems`)."""
        if not is_axis_address(device.address):
            return super().check_device(bus, device)
        key = f"{device.key}.address"
        node = device.address.get("node")
        errs = [f"{key}.{k}: unknown key of an axis" for k in device.address
                if k not in AXIS_ADDRESS]
        if node not in range(1, 6):
            errs.append(f"{key}.node: {node!r} is no joint drive of the welding cell; "
                        f"expected 1..5 (joint1..joint5)")
        if device.address.get("axis", 0) != 0:
            errs.append(f"{key}.axis: the joint drives have one axis each; expected 0")
        return errs

    # ---- running ----------------------------------------------------------------------------
    def start(self) -> None:
        """Register the model step on the kernel clock. Raises BusError if the device list does
        not fit the cell."""
        bad = [n for n, d in self.devices.items() if self.check_device(self.bus, d)]
        if bad:
            raise BusError(f"bus {self.bus.name}: devices {', '.join(bad)} are not devices of the "
                           "welding cell")
        self._running = True
        self.host.every(self.tick, self._step)

    def stop(self) -> None:
        """Stop stepping the model (the host's periodic calls become no-ops)."""
        self._running = False

    def settle(self, timeout: float) -> bool:
        """Always quiet: everything is delivered synchronously on the kernel thread."""
        return True

    def _step(self) -> None:
        if not self._running:
            return
        cell = self.cell
        for j, drive in enumerate(self.drives):
            # a joint moves only while its drive is enabled and the relay gives torque
            goal = drive.step(self.tick, cell.joints[j] / POSITION_SCALE, self.enabled)
            if goal is None:
                cell.targets[j] = cell.joints[j]
            else:
                try:
                    cell.set_joint_target(j + 1, goal * POSITION_SCALE)
                except ChcosError:
                    cell.targets[j] = cell.joints[j]
        cell.step(self.tick)
        self._ticks += 1
        n = round(self._ticks * self.tick / BASE_TICK)
        prev = round((self._ticks - 1) * self.tick / BASE_TICK)
        if isinstance(cell, _Cell):
            cell.view_due = n // 2 != prev // 2
            r = cell.readings()
            cell.view_due = True
        else:
            r = cell.readings()
        now = self.host.now()
        for j, ok in enumerate(r.servo_ok):
            name = JOINTS[j]
            if name not in self.signal:
                continue
            if not ok and name not in self._failed:
                self._failed.add(name)
                self.host.fail(name, f"servo drive of joint {j + 1} timed out (no position)")
            elif ok and name in self._failed:
                self._failed.discard(name)
                self.host.recover(name)
        for dev, sig in self.signal.items():
            spec = SENSORS.get(sig)
            if spec is None:
                continue
            period, model_name, get = spec
            if model_name in r.silent:
                continue
            due = n // period != prev // period
            if not due and sig not in ON_CHANGE:
                continue    # read only what is sent: the linear row is costly
            value = get(r)
            changed = sig in ON_CHANGE and dev in self._last and self._last[dev] != value
            if changed:
                self.changes.append((now, dev, value))
            if due or changed:
                self._last[dev] = value
                self.host.deliver(dev, value)
        self._feed_axes(r.joints, now, r.silent)

    def _feed_axes(self, joints: Sequence[float], now: float,
                   silent: Collection[str] = ()) -> None:
        """Each axis's engine takes its drive's objects (the joint at ``joints``) and runs its
        timers; a drive in ``silent`` (``jointN``: a servo timeout) says nothing."""
        for name, axis in self.axes.items():
            j = self.axis_joint[name]
            if f"joint{j + 1}" in silent:
                continue
            drive = self.drives[j]
            axis.reading({Obj.ERROR_CODE: drive.error_code, Obj.STATUSWORD: drive.statusword,
                          Obj.MODES_DISPLAY: drive.mode_display,
                          Obj.POSITION_ACTUAL: round(joints[j] / POSITION_SCALE),
                          Obj.VELOCITY_ACTUAL: drive.velocity}, now)
            axis.poll(now)

    def _write(self, device: str, value: Any) -> None:
        """Apply a set-point to the model at once and confirm it; a command code of an axis
        starts its command, confirmed when the drive confirmed it. A value the model refuses is
        reported with ``host.error`` (kind ``refused``) and ``host.write_failed``."""
        if device in self.axes:
            self._axis_write(device, value)
            return
        try:
            self._apply(device, value)
        except (ChcosError, ValueError, TypeError) as exc:
            self.host.error(self.bus.name, "refused", f"{device} <- {value!r}: {exc}")
            self.host.write_failed(device, value, str(exc))
            return
        self.writes[device] = self.writes.get(device, 0) + 1
        self.host.written(device, value)

    def _apply(self, device: str, value: Any) -> None:
        sig = self.signal[device]
        cell = self.cell
        if sig in TARGETS:
            j = TARGETS.index(sig)
            if self.drives[j].target(round(float(value) / POSITION_SCALE)) and self.enabled:
                cell.set_joint_target(j + 1, float(value))
        elif sig == "drives_enable":
            on = bool(round(float(value)))
            if on and not self.enabled:
                cell.targets = list(cell.joints)
            self.enabled = on
        elif sig == "volts_set":
            cell.set_voltage(float(value))
        elif sig == "wire_set":
            cell.set_wire_speed(float(value))
        else:
            cell.set_gas_valve(bool(round(float(value))))

    # ---- the in-process axes (the AxisDriver protocol of chcos.user.axes) --------------------
    def _bind_axis(self, spec: DeviceSpec) -> None:
        a = spec.address
        try:
            cfg = config_from_table(spec.name, {"axis": 0, **dict(a.get("config", {}))},
                                    spec.key)
        except Cia402Error as exc:
            raise ConfigError(str(exc)) from exc
        j = int(a["node"]) - 1
        name = spec.name
        self.axis_joint[name] = j
        self.axes[name] = AxisHost(
            name, j + 1, cfg, mode_of(a.get("mode")),
            send=functools.partial(self._axis_send, j),
            read=functools.partial(self._axis_read, j),
            deliver=functools.partial(deliver_all, self.host),
            fail=self.host.fail,
            recover=self.host.recover,
            report=functools.partial(self._axis_report, name))

    def _axis_report(self, device: str, text: str) -> None:
        self.host.error(self.bus.name, "axis", text, device)

    def _axis_send(self, j: int, w: Write) -> None:
        """One write of an axis, applied to joint ``j``'s drive at once. Raises BusError for an
        object the joint drives do not take."""
        drive = self.drives[j]
        match w.obj:
            case Obj.CONTROLWORD:
                drive.controlword(w.value)
            case Obj.MODES:
                drive.mode(w.value)
            case Obj.TARGET_POSITION:
                if drive.target(w.value) and self.enabled:
                    self.cell.set_joint_target(j + 1, w.value * POSITION_SCALE)
            case _:
                raise BusError(f"weld-direct bus {self.bus.name}: joint{j + 1}'s drive has no "
                               f"object 0x{w.index:04X} ({w.obj.name})")

    def _axis_read(self, j: int, obj: Obj, index: int) -> int | None:
        """An axis object of joint ``j``'s drive as it is now (None: not one it shows, or the
        drive is silent, a servo timeout)."""
        drive = self.drives[j]
        if f"joint{j + 1}" in self.cell.readings().silent:
            return None
        values = {Obj.STATUSWORD: drive.statusword, Obj.MODES_DISPLAY: drive.mode_display,
                  Obj.ERROR_CODE: drive.error_code, Obj.VELOCITY_ACTUAL: drive.velocity,
                  Obj.POSITION_ACTUAL: round(self.cell.joints[j] / POSITION_SCALE),
                  Obj.QUICK_STOP_OPTION: drive.quick_stop_option}
        return values.get(obj)

    def axis_call(self, device: str, call: AxisCall, done: Done) -> None:
        """Start ``call`` on axis ``device`` (kernel thread); ``done`` gets the engine's
        :class:`drivers.codecs.cia402.Result`, or the exception that refused it (AxisBusy,
        AxisLimitError, ValueError; BusError when the driver is stopped or has no such
        axis)."""
        axis = self.axes.get(device)
        if axis is None:
            done(BusError(f"weld-direct bus {self.bus.name}: no axis {device!r}"))
            return
        if not self._running:
            done(BusError(f"weld-direct bus {self.bus.name} is not running: {call.op.value} "
                          f"of axis {device} not sent"))
            return
        axis.command(call, done, self.host.now())

    def axis_status(self, device: str) -> AxisStatus:
        """What axis ``device``'s drive last confirmed. Raises KeyError for a device that is
        no axis of this bus."""
        return self.axes[device].status()

    def _axis_write(self, device: str, value: Any) -> None:
        """A Devtab write to an axis's actuator (:func:`drivers.canopen_axis.device_write`)."""
        device_write(self.axes[device], self.host, device, value)

    def check_value(self, device: str, value: Any) -> str | None:
        """For an axis: why ``value`` is not a command code (None if it is)."""
        if device in self.axes and (isinstance(value, bool)
                                    or not isinstance(value, int | float)
                                    or value not in set(AxisCode)):
            return (f"expected a command code of the axis "
                    f"({', '.join(f'{c.value} {c.name.lower()}' for c in AxisCode)}), "
                    f"got {value!r}")
        return None

    def flush(self, timeout: float) -> bool:
        """At shutdown (the kernel's timers no longer run): while an axis runs a command (its
        safe stop), step the cell on this driver's own clock until it ended or ``timeout``
        simulated seconds passed; True if every axis ended its command."""
        if not self._running:
            return not any(a.status().busy is not None for a in self.axes.values())
        steps = 0
        while any(a.status().busy is not None for a in self.axes.values()):
            if steps * self.tick >= timeout:
                return False
            self._shutdown_step(steps)
            steps += 1
        return True

    def _shutdown_step(self, steps: int) -> None:
        """One tick at shutdown: the drives and the cell step, the axes read and poll on a clock
        ``steps`` ticks past the kernel's."""
        cell = self.cell
        now = self.host.now() + (steps + 1) * self.tick
        for j, drive in enumerate(self.drives):
            goal = drive.step(self.tick, cell.joints[j] / POSITION_SCALE, self.enabled)
            cell.targets[j] = cell.joints[j] if goal is None else goal * POSITION_SCALE
        cell.step(self.tick)
        self._feed_axes(cell.joints, now)
