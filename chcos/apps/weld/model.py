"""model - the physics of the arc-welding cell, stepped on explicit simulated time.

:class:`WeldCell` is everything a simulator puts behind the field buses (thesis section 5.1): the
5-joint arm with its servos, the welding power source and arc, the shielding-gas bottle and
valve, the wire feeder, the light curtain, the seam on the plate with the linear light sensor and
the start/end-of-gap marker detector, and a record of how much of the gap has been welded and how
well. It never reads a clock: :meth:`WeldCell.step` advances the state by ``dt`` seconds, and
measurement noise comes from a seeded generator, so a run is reproducible given its seed.

Physics, in short (all constants in :class:`CellConfig`):

* servos move the joints towards their targets together (synchronous point-to-point: all
  arrive at once, none faster than its commanded speed, rad/s); a servo timeout freezes the
  joint and silences its position sensor;
* the tip cannot go below the plate; touching it with the power source on (voltage set-point > 0)
  freezes the electrode to the metal: arc voltage reads 0, the arm is held, until the voltage is
  off and the tip is pulled away upwards (tool -z, within 45 degrees of vertical);
* the arc burns while the power source is on, the tip is free and ``0 < stand-off <= V * k``;
  arc voltage is the set-point plus a little per mm of stand-off, open-circuit voltage when out;
  arc current follows the wire feed speed, short-circuit current when stuck;
* arc temperature follows a first-order lag towards ``ambient + gain * (V/Vnom) *
  exp(-(d - dnom)/ds) * exp(-(v - vnom)/vs)`` for voltage V, stand-off d and travel speed v while
  the arc burns (about 1520 degC at 24 V, 10 mm, 5 mm/s), and cools towards ambient otherwise;
* an open gas valve drains the bottle (ideal gas, fixed volume) at the regulated flow, which
  falls off when the bottle pressure drops below the regulator pressure;
* the wire feeder ramps towards its set speed and unwinds the spool.

Why one module of this size (about 820 lines, over the project's ~400): it is one physical
model stepped as a whole - every quantity above is coupled to the others within one
:meth:`WeldCell.step` (the arm's pose sets the stand-off, which sets the arc, which sets the
temperature and the weld record; the gas and wire state feed back into the arc), and the
constants of :class:`CellConfig` are tuned against each other. Cut into files by subsystem, one
step would have to be read across all of them; the seam geometry, the kinematics and the fault
scenarios, which are not coupled that way, already live apart (:mod:`chcos.apps.weld.seam`,
:mod:`chcos.apps.weld.kinematics`, :mod:`chcos.apps.weld.faults`).
"""

from __future__ import annotations

import math
import random
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from enum import IntFlag
from typing import Any, Literal

from chcos.apps.weld.faults import (
    SENSOR_NAMES,
    AtSeam,
    AtTime,
    Fault,
    Immediate,
    Scenario,
)
from chcos.apps.weld.kinematics import Arm, Joints, ToolPose
from chcos.apps.weld.seam import LinearView, Seam, SeamPoint
from chcos.errors import ChcosError, ConfigError, DeviceError

CONTACT_MM = 0.05
"""Stand-off (mm) at or below which the tip touches the plate."""
#: Time constant (s) over which the weld pool averages the travel speed (see WeldCell.step).
POOL_SPEED_TAU = 0.1


class SimulationError(ChcosError):
    """The model was misused: a non-positive or non-finite time step."""


class Flaw(IntFlag):
    """Per-millimetre state of the seam: welded, and what was wrong while it was welded."""

    NONE = 0
    WELDED = 1
    TOO_HOT = 2
    TOO_COLD = 4
    NO_GAS = 8


@dataclass(frozen=True)
class CellConfig:
    """Constants of the cell. Units: mm, s, rad, rad/s, V, A, degC, bar, L, L/min, mm/s, m.

    Raises :class:`chcos.errors.ConfigError` for a non-finite value, a non-positive constant
    (noise levels may be 0, ambient and home_yaw any sign), or an inverted weld band.
    """

    home_position: tuple[float, float, float] = (500.0, 0.0, 250.0)
    home_yaw: float = 0.0
    joint_max_speed: tuple[float, float, float, float, float] = (1.0, 1.0, 1.2, 2.0, 3.0)
    max_voltage: float = 40.0
    nominal_voltage: float = 24.0
    nominal_standoff: float = 10.0
    arc_length_per_volt: float = 0.75
    arc_voltage_per_mm: float = 0.5
    open_circuit_extra: float = 20.0
    nominal_travel_speed: float = 5.0
    ambient: float = 20.0
    temp_gain: float = 1500.0
    standoff_scale: float = 15.0
    speed_scale: float = 10.0
    temp_max: float = 3000.0
    heat_tau: float = 0.6
    cool_tau: float = 2.5
    weld_band: tuple[float, float] = (1450.0, 1600.0)
    weld_lateral_tolerance: float = 2.0
    bottle_volume: float = 10.0
    bottle_pressure: float = 200.0
    regulator_pressure: float = 2.5
    gas_flow: float = 15.0
    min_shield_flow: float = 8.0
    max_wire_speed: float = 250.0
    wire_accel: float = 1000.0
    wire_spool: float = 2400.0
    amps_per_wire_speed: float = 2.0
    short_circuit_current: float = 450.0
    sensor_pixels: int = 64
    sensor_pitch: float = 0.5
    sensor_look_ahead: float = 5.0
    fault_lateral_tolerance: float = 15.0
    fault_height_tolerance: float = 30.0
    noise_joint: float = 1e-4
    noise_temp: float = 3.0
    noise_voltage: float = 0.1
    noise_current: float = 2.0
    noise_pressure: float = 0.05
    noise_flow: float = 0.1
    noise_wire: float = 0.5

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, float | int):
                continue
            if not math.isfinite(value):
                raise ConfigError(f"cell config {f.name}={value!r}: expected a finite number")
            if f.name in ("ambient", "home_yaw"):
                continue
            if f.name.startswith("noise_"):
                if value < 0.0:
                    raise ConfigError(f"cell config {f.name}={value!r}: expected >= 0")
            elif value <= 0.0:
                raise ConfigError(f"cell config {f.name}={value!r}: expected > 0")
        if len(self.joint_max_speed) != 5 or min(self.joint_max_speed) <= 0.0:
            raise ConfigError(
                f"cell config joint_max_speed={self.joint_max_speed!r}: expected 5 speeds > 0 rad/s"
            )
        if not self.weld_band[0] < self.weld_band[1]:
            raise ConfigError(
                f"cell config weld_band={self.weld_band!r}: expected (low, high) degC, low < high"
            )
        if self.nominal_voltage > self.max_voltage:
            raise ConfigError(
                f"cell config nominal_voltage={self.nominal_voltage} V above "
                f"max_voltage={self.max_voltage} V"
            )


@dataclass(frozen=True)
class Readings:
    """Everything the cell's sensors report at time ``t`` (s). Silent sensors (names in
    ``silent``, see :data:`chcos.apps.weld.faults.SENSOR_NAMES`) hold the value they last reported.

    joints rad; servo_ok per joint; arc_temperature degC; arc_voltage V; arc_current A;
    gas_bottle_pressure and gas_line_pressure bar (gauge); gas_flow L/min; wire_speed mm/s;
    wire_remaining m; start_marker/end_marker flags; linear, the line sensor's view, whose
    pixels (:attr:`linear_pixels`, True = dark) are computed when first read; range_mm to the
    surface (None: beyond 0..100 mm); intruder (light curtain broken).
    """

    t: float
    joints: tuple[float, ...]
    servo_ok: tuple[bool, ...]
    arc_temperature: float
    arc_voltage: float
    arc_current: float
    gas_bottle_pressure: float
    gas_line_pressure: float
    gas_flow: float
    wire_speed: float
    wire_remaining: float
    start_marker: bool
    end_marker: bool
    linear: LinearView
    range_mm: float | None
    intruder: bool
    silent: frozenset[str] = frozenset()

    @property
    def linear_pixels(self) -> tuple[bool, ...]:
        """The line sensor's pixels (True = dark), computed on the first read."""
        return self.linear.pixels


@dataclass(frozen=True)
class WeldProgress:
    """How much of the seam (``length`` mm) has been welded, and the lengths (mm) welded while
    too hot, too cold or without shielding gas."""

    length: float
    welded: float
    too_hot: float
    too_cold: float
    no_gas: float
    flawed: float

    @property
    def fraction(self) -> float:
        """Welded share of the seam, 0..1."""
        return self.welded / self.length

    @property
    def good(self) -> float:
        """Length (mm) welded with no flaw."""
        return self.welded - self.flawed


@dataclass(frozen=True)
class FaultEvent:
    """A fault firing or clearing at time ``t`` (s)."""

    t: float
    fault: Fault
    action: Literal["fired", "cleared", "froze", "averted"]


def _joint_sensor(j: int) -> str:
    return f"joint{j + 1}"


class WeldCell:
    """The simulated welding cell (see the module docstring).

    Actuator set-points out of range raise :class:`chcos.errors.DeviceError`; a bad ``dt``
    raises :class:`SimulationError`; a home position the arm cannot reach raises
    :class:`chcos.apps.weld.kinematics.UnreachableError`.
    """

    def __init__(
        self,
        config: CellConfig | None = None,
        seam: Seam | None = None,
        scenario: Scenario | None = None,
        seed: int = 0,
        arm: Arm | None = None,
    ) -> None:
        self.config = cfg = config if config is not None else CellConfig()
        self.arm = arm if arm is not None else Arm()
        self.seam = seam if seam is not None else Seam()
        self._rng = random.Random(seed)
        self.t = 0.0
        home = self.arm.inverse_down(cfg.home_position, cfg.home_yaw)
        self.joints: list[float] = list(home)
        self.targets: list[float] = list(home)
        self.speeds: list[float] = list(cfg.joint_max_speed)
        self.voltage_setpoint = 0.0
        self.gas_valve = False
        self.wire_setpoint = 0.0
        self.wire_speed = 0.0
        self.wire_remaining = cfg.wire_spool
        self.bottle_pressure = cfg.bottle_pressure
        self.temperature = cfg.ambient
        self.tip_stuck = False
        self.stubbing: tuple[Fault, float, float] | None = None
        """A tip-stuck precursor in progress: (fault, progress 0..1, wire set-point at onset)."""
        self.intruder_input = False
        self._pose = self.arm.tool_pose(self.joints)
        self._tip = self.seam.nearest(self._pose.position[0], self._pose.position[1])
        self._travel_speed = 0.0
        self._pool_speed = 0.0
        self._bins = [0] * math.ceil(self.seam.length)
        self._weld_s: float | None = None
        self._pending: list[Fault] = []
        self._dropouts: dict[str, tuple[float, Fault]] = {}
        self._frozen: dict[str, Readings] = {}
        self._servo_timeouts: dict[int, tuple[float, Fault]] = {}
        self._intruder_fault: tuple[float, Fault] | None = None
        self.events: list[FaultEvent] = []
        self._noise: dict[str, float] = {}
        self._draw_noise()
        self._cache: tuple[int, Readings] | None = None
        self._steps = 0
        for fault in scenario.faults if scenario is not None else ():
            if fault.kind in ("gap-wide", "gap-narrow") and isinstance(fault.trigger, AtSeam):
                self._fire(fault)
            else:
                self.inject(fault)

    # --- actuators ---------------------------------------------------------------------------

    def set_joint_targets(self, targets: Sequence[float]) -> None:
        """Command all 5 joints to move to ``targets`` (rad). DeviceError outside joint limits."""
        if len(targets) != 5:
            raise DeviceError(f"joint targets {tuple(targets)!r}: expected 5 angles (rad)")
        for j, value in enumerate(targets):
            self._check_target(j, value)
        self.targets = [float(v) for v in targets]

    def set_joint_target(self, joint: int, angle: float) -> None:
        """Command joint ``joint`` (1..5) to ``angle`` (rad). DeviceError outside its limits."""
        j = self._joint_index(joint)
        self._check_target(j, angle)
        self.targets[j] = float(angle)

    def set_joint_speed(self, joint: int, speed: float) -> None:
        """Set the speed (rad/s) joint ``joint`` (1..5) moves at; DeviceError unless
        ``0 <= speed <= joint_max_speed``."""
        j = self._joint_index(joint)
        top = self.config.joint_max_speed[j]
        if not 0.0 <= speed <= top:
            raise DeviceError(f"joint{joint} speed {speed!r} rad/s, expected 0..{top} rad/s")
        self.speeds[j] = float(speed)

    def move_tip(self, position: Sequence[float], yaw: float) -> Joints:
        """Command the joints to put the tip at ``position`` (mm) pointing down with tool yaw
        ``yaw`` (rad); returns the joint targets. Raises UnreachableError if it cannot."""
        q = self.arm.inverse_down(position, yaw)
        self.set_joint_targets(q)
        return q

    def _joint_index(self, joint: int) -> int:
        if joint not in (1, 2, 3, 4, 5):
            raise DeviceError(f"joint {joint!r}: expected a joint number 1..5")
        return joint - 1

    def _check_target(self, j: int, angle: float) -> None:
        link = self.arm.links[j]
        if not (math.isfinite(angle) and link.lower <= angle <= link.upper):
            raise DeviceError(
                f"joint{j + 1} target {angle!r} rad, "
                f"expected {link.lower:.4f}..{link.upper:.4f} rad"
            )

    def set_voltage(self, volts: float) -> None:
        """Set the power source voltage (V, 0 = off). DeviceError outside 0..max_voltage."""
        if not 0.0 <= volts <= self.config.max_voltage:
            raise DeviceError(
                f"arc voltage set-point {volts!r} V, expected 0..{self.config.max_voltage} V"
            )
        self.voltage_setpoint = float(volts)

    def set_gas_valve(self, open_: bool) -> None:
        """Energise (True) or release (False) the gas valve coil."""
        self.gas_valve = bool(open_)

    def set_wire_speed(self, speed: float) -> None:
        """Set the wire feed speed (mm/s). DeviceError outside 0..max_wire_speed."""
        if not 0.0 <= speed <= self.config.max_wire_speed:
            raise DeviceError(
                f"wire speed set-point {speed!r} mm/s, expected 0..{self.config.max_wire_speed}"
            )
        self.wire_setpoint = float(speed)

    def set_intruder(self, present: bool) -> None:
        """Someone breaks (True) or leaves (False) the light curtain; False also ends an
        ``intruder`` fault."""
        self.intruder_input = bool(present)
        if not present and self._intruder_fault is not None:
            self.events.append(FaultEvent(self.t, self._intruder_fault[1], "cleared"))
            self._intruder_fault = None

    # --- faults ------------------------------------------------------------------------------

    def inject(self, fault: Fault) -> None:
        """Inject ``fault``: fire it now if its trigger is Immediate (or a time already passed),
        otherwise keep it until its trigger is reached during :meth:`step`."""
        if isinstance(fault.trigger, Immediate) or (
            isinstance(fault.trigger, AtTime) and fault.trigger.t <= self.t
        ):
            self._fire(fault)
        else:
            self._pending.append(fault)

    @property
    def pending(self) -> tuple[Fault, ...]:
        """Faults waiting for their trigger."""
        return tuple(self._pending)

    def _fire(self, fault: Fault) -> None:
        until = math.inf if fault.duration is None else self.t + fault.duration
        if fault.kind in ("gap-wide", "gap-narrow"):
            if isinstance(fault.trigger, AtSeam):
                s0 = fault.trigger.s
            else:
                s0 = min(max(self._tip.s, 0.0), self.seam.length)
            width = fault.width if fault.width is not None else 0.0
            self.seam = self.seam.with_width_override(s0, s0 + fault.length, width)
            self._cache = None
        elif fault.kind == "tip-stuck":
            if fault.precursor > 0.0:
                self.stubbing = (fault, 0.0, self.wire_setpoint)
            else:
                self.tip_stuck = True
            self._cache = None
        elif fault.kind == "gas-empty":
            self.bottle_pressure = 0.0
        elif fault.kind == "wire-empty":
            self.wire_remaining = 0.0
            self.wire_speed = 0.0
        elif fault.kind == "sensor-dropout":
            assert fault.sensor is not None
            self._silence(fault.sensor, until, fault)
        elif fault.kind == "servo-timeout":
            assert fault.joint is not None
            self._servo_timeouts[fault.joint - 1] = (until, fault)
            self._silence(_joint_sensor(fault.joint - 1), until, fault)
        else:  # intruder
            self.intruder_input = True
            self._intruder_fault = (until, fault)
        self._cache = None
        self.events.append(FaultEvent(self.t, fault, "fired"))

    def _silence(self, sensor: str, until: float, fault: Fault) -> None:
        if sensor not in self._dropouts:
            self._frozen[sensor] = self.readings()
        elif self._dropouts[sensor][0] > until:
            return
        self._dropouts[sensor] = (until, fault)
        self._cache = None

    def _expire(self) -> None:
        for sensor, (until, fault) in list(self._dropouts.items()):
            if self.t >= until - 1e-9:
                del self._dropouts[sensor]
                del self._frozen[sensor]
                if fault.kind == "sensor-dropout":
                    self.events.append(FaultEvent(self.t, fault, "cleared"))
        for j, (until, fault) in list(self._servo_timeouts.items()):
            if self.t >= until - 1e-9:
                del self._servo_timeouts[j]
                self.events.append(FaultEvent(self.t, fault, "cleared"))
        if self._intruder_fault is not None and self.t >= self._intruder_fault[0] - 1e-9:
            self.events.append(FaultEvent(self.t, self._intruder_fault[1], "cleared"))
            self._intruder_fault = None
            self.intruder_input = False

    def _trigger_due(self) -> None:
        still: list[Fault] = []
        tip = self._tip
        cfg = self.config
        near = (
            abs(tip.lateral) <= cfg.fault_lateral_tolerance
            and self.standoff <= cfg.fault_height_tolerance
        )
        for fault in self._pending:
            trig = fault.trigger
            if (isinstance(trig, AtTime) and self.t >= trig.t - 1e-9) or (
                isinstance(trig, AtSeam) and near and tip.s >= trig.s
            ):
                self._fire(fault)
            else:
                still.append(fault)
        self._pending = still

    # --- the physics -------------------------------------------------------------------------

    @property
    def pose(self) -> ToolPose:
        """The torch pose now (tip position mm, yaw/tilt rad)."""
        return self._pose

    def move_surface(self, dz: float) -> None:
        """Raise (``dz`` > 0) or lower the plate surface by ``dz`` mm (a warped or re-clamped
        workpiece): the range sensor, the stand-off and the arc see it at once."""
        self.seam.plate_z += float(dz)
        self._cache = None

    @property
    def standoff(self) -> float:
        """Height (mm) of the tip above the plate."""
        return self._pose.position[2] - self.seam.plate_z

    @property
    def seam_point(self) -> SeamPoint:
        """The seam point nearest the tip (s and lateral offset in mm)."""
        return self._tip

    @property
    def travel_speed(self) -> float:
        """Speed (mm/s) of the tip in the plate plane over the last step."""
        return self._travel_speed

    @property
    def touching(self) -> bool:
        """True when the tip touches the plate (stand-off within :data:`CONTACT_MM`)."""
        return self.standoff <= CONTACT_MM

    def _stub(self, dt: float) -> None:
        """Advance a tip-stuck precursor: the wire stubs into the pool (progress grows over the
        fault's ``precursor`` s) unless its feed is below half the onset speed (then the arc
        burns it back twice as fast); at 1 the tip freezes, at 0 the fault is averted."""
        if self.stubbing is None:
            return
        fault, progress, wire0 = self.stubbing
        if self.tip_stuck or self.voltage_setpoint <= 0.0:
            self.stubbing = None
            return
        if self.wire_setpoint < 0.5 * wire0:
            progress -= 2.0 * dt / fault.precursor
        else:
            progress += dt / fault.precursor
        self._cache = None
        if progress >= 1.0:
            self.stubbing = None
            self.tip_stuck = True
            self.events.append(FaultEvent(self.t, fault, "froze"))
        elif progress <= 0.0:
            self.stubbing = None
            self.events.append(FaultEvent(self.t, fault, "averted"))
        else:
            self.stubbing = (fault, progress, wire0)

    @property
    def arc_length(self) -> float:
        """The arc's length (mm): the stand-off, shortened while the wire stubs into the pool."""
        if self.stubbing is None:
            return self.standoff
        return self.standoff * (1.0 - self.stubbing[1])

    @property
    def arc_burning(self) -> bool:
        """True while the arc burns: power on, tip free, ``contact < stand-off <= V * k``."""
        v = self.voltage_setpoint
        return (
            v > 0.0
            and not self.tip_stuck
            and CONTACT_MM < self.standoff <= v * self.config.arc_length_per_volt
        )

    @property
    def gas_flow(self) -> float:
        """Shielding gas flow (L/min) through the valve now."""
        cfg = self.config
        if not self.gas_valve or self.bottle_pressure <= 0.0:
            return 0.0
        return cfg.gas_flow * min(1.0, self.bottle_pressure / cfg.regulator_pressure)

    def _temperature_target(self) -> float:
        cfg = self.config
        if not self.arc_burning:
            return cfg.ambient
        heat = (
            cfg.temp_gain
            * (self.voltage_setpoint / cfg.nominal_voltage)
            * math.exp(-(self.standoff - cfg.nominal_standoff) / cfg.standoff_scale)
            * math.exp(-(self._pool_speed - cfg.nominal_travel_speed) / cfg.speed_scale)
        )
        return min(cfg.temp_max, cfg.ambient + heat)

    def step(self, dt: float) -> None:
        """Advance the cell by ``dt`` seconds. Raises SimulationError unless ``0 < dt <= 1``."""
        if not (math.isfinite(dt) and 0.0 < dt <= 1.0):
            raise SimulationError(f"step dt={dt!r} s, expected 0 < dt <= 1 s")
        cfg = self.config
        self._move_arm(dt)
        # the weld pool feels the travel speed averaged over a fraction of a second, not the
        # servo's millisecond steps: low-pass it, so a stepwise trajectory heats like a smooth one
        self._pool_speed += (self._travel_speed - self._pool_speed) * (
            1.0 - math.exp(-dt / POOL_SPEED_TAU))
        if self.voltage_setpoint > 0.0 and self.touching:
            self.tip_stuck = True  # power switched on while touching
        self._stub(dt)
        # gas
        flow = self.gas_flow
        self.bottle_pressure = max(0.0, self.bottle_pressure - flow / 60.0 * dt / cfg.bottle_volume)
        # wire
        dv = self.wire_setpoint - self.wire_speed
        self.wire_speed += max(-cfg.wire_accel * dt, min(cfg.wire_accel * dt, dv))
        self.wire_remaining = max(0.0, self.wire_remaining - self.wire_speed * dt / 1000.0)
        if self.wire_remaining <= 0.0:
            self.wire_speed = 0.0
        # arc temperature: first-order lag
        target = self._temperature_target()
        tau = cfg.heat_tau if target > self.temperature else cfg.cool_tau
        self.temperature = target + (self.temperature - target) * math.exp(-dt / tau)
        self._record_weld(flow)
        self.t += dt
        self._steps += 1
        self._expire()
        self._trigger_due()
        self._draw_noise()
        self._cache = None

    def _move_arm(self, dt: float) -> None:
        old = self._pose
        candidate = list(self.joints)
        live = [j for j in range(5) if j not in self._servo_timeouts and self.speeds[j] > 0.0]
        # synchronous point-to-point: every joint arrives together, none beyond its speed
        needed = max(
            (abs(self.targets[j] - self.joints[j]) / self.speeds[j] for j in live), default=0.0
        )
        share = 1.0 if needed <= dt else dt / needed
        for j in live:
            candidate[j] += (self.targets[j] - self.joints[j]) * share
        pose = self.arm.tool_pose(candidate)
        dx = pose.position[0] - old.position[0]
        dy = pose.position[1] - old.position[1]
        dz = pose.position[2] - old.position[2]
        if self.tip_stuck:
            freed = self.voltage_setpoint == 0.0 and dz > 0.0 and math.hypot(dx, dy) <= dz
            if not freed:
                self._travel_speed = 0.0
                return
            self.tip_stuck = False
        if pose.position[2] < self.seam.plate_z:
            # the plate stops the torch: move only as far as the contact point (bisection)
            lo, hi = 0.0, 1.0
            for _ in range(40):
                mid = (lo + hi) / 2.0
                q = [a + mid * (b - a) for a, b in zip(self.joints, candidate, strict=True)]
                if self.arm.tool_pose(q).position[2] >= self.seam.plate_z:
                    lo = mid
                else:
                    hi = mid
            candidate = [a + lo * (b - a) for a, b in zip(self.joints, candidate, strict=True)]
            pose = self.arm.tool_pose(candidate)
            dx = pose.position[0] - old.position[0]
            dy = pose.position[1] - old.position[1]
        self.joints = candidate
        self._pose = pose
        self._travel_speed = math.hypot(dx, dy) / dt
        if self.voltage_setpoint > 0.0 and self.touching:
            self.tip_stuck = True  # a live electrode touching the metal freezes to it
        guess = self.seam.project(pose.position[0], pose.position[1], self._tip.s)
        if abs(guess.lateral) > 50.0 or abs(guess.s - self._tip.s) > 50.0:
            guess = self.seam.nearest(pose.position[0], pose.position[1])
        self._tip = guess

    def _record_weld(self, flow: float) -> None:
        tip = self._tip
        cfg = self.config
        if not self.arc_burning or (
            abs(tip.lateral) > self.seam.width(tip.s) / 2.0 + cfg.weld_lateral_tolerance
        ):
            self._weld_s = None
            return
        flags = Flaw.WELDED
        if self.temperature > cfg.weld_band[1]:
            flags |= Flaw.TOO_HOT
        if self.temperature < cfg.weld_band[0]:
            flags |= Flaw.TOO_COLD
        if flow < cfg.min_shield_flow:
            flags |= Flaw.NO_GAS
        s_from = min(tip.s, self._weld_s) if self._weld_s is not None else tip.s
        s_to = max(tip.s, self._weld_s) if self._weld_s is not None else tip.s
        if s_to - s_from > 5.0:
            s_from = s_to = tip.s
        lo = max(0, math.floor(s_from))
        hi = min(len(self._bins) - 1, math.floor(s_to))
        for k in range(lo, hi + 1):
            self._bins[k] |= int(flags)
        self._weld_s = tip.s

    def weld_bins(self) -> tuple[Flaw, ...]:
        """The seam's state per millimetre of arc length (index = floor(s))."""
        return tuple(Flaw(b) for b in self._bins)

    def progress(self) -> WeldProgress:
        """How much of the seam is welded (mm) and with which flaws."""
        welded = [b for b in self._bins if b & Flaw.WELDED]
        n = len(self._bins)
        scale = self.seam.length / n

        def count(flag: Flaw) -> float:
            return sum(1 for b in welded if b & flag) * scale

        flawed = sum(1 for b in welded if b & ~Flaw.WELDED) * scale
        return WeldProgress(
            self.seam.length,
            len(welded) * scale,
            count(Flaw.TOO_HOT),
            count(Flaw.TOO_COLD),
            count(Flaw.NO_GAS),
            flawed,
        )

    # --- sensors -----------------------------------------------------------------------------

    def _draw_noise(self) -> None:
        cfg = self.config
        g = self._rng.gauss
        self._noise = {
            "arc_temperature": g(0.0, cfg.noise_temp),
            "arc_voltage": g(0.0, cfg.noise_voltage),
            "arc_current": g(0.0, cfg.noise_current),
            "gas_bottle_pressure": g(0.0, cfg.noise_pressure),
            "gas_line_pressure": g(0.0, cfg.noise_pressure / 5.0),
            "gas_flow": g(0.0, cfg.noise_flow),
            "wire_speed": g(0.0, cfg.noise_wire),
        }
        for j in range(5):
            self._noise[_joint_sensor(j)] = g(0.0, cfg.noise_joint)

    def linear_view(self) -> LinearView:
        """What the linear light sensor (``sensor_look_ahead`` mm ahead of the tip along the tool
        x axis, pixels along tool y) sees now, without dropout."""
        cfg = self.config
        pose = self._pose
        xa = pose.x_axis
        norm = math.hypot(xa[0], xa[1])
        ux, uy = (xa[0] / norm, xa[1] / norm) if norm > 1e-9 else (1.0, 0.0)
        x = pose.position[0] + cfg.sensor_look_ahead * ux
        y = pose.position[1] + cfg.sensor_look_ahead * uy
        height = pose.position[2] - self.seam.plate_z
        axis = math.atan2(uy, ux) + math.pi / 2.0
        return self.seam.sense(
            x, y, height, axis, cfg.sensor_pixels, cfg.sensor_pitch, s_guess=self._tip.s
        )

    def readings(self) -> Readings:
        """Everything the sensors report now (noisy, with dropouts applied)."""
        if self._cache is not None and self._cache[0] == self._steps:
            return self._cache[1]
        cfg = self.config
        n = self._noise
        v = self.voltage_setpoint
        if v <= 0.0:
            volts, amps = 0.0, 0.0
        elif self.tip_stuck or self.touching:
            volts, amps = 0.0, cfg.short_circuit_current
        elif self.arc_burning:
            volts = max(0.0, v + cfg.arc_voltage_per_mm * (self.arc_length
                                                            - cfg.nominal_standoff))
            amps = cfg.amps_per_wire_speed * self.wire_speed
        else:
            volts, amps = v + cfg.open_circuit_extra, 0.0
        flow = self.gas_flow
        line = min(self.bottle_pressure, cfg.regulator_pressure) if flow > 0.0 else 0.0
        view = self.linear_view()

        def noisy(name: str, value: float, floor: float = 0.0) -> float:
            return value if value == 0.0 else max(floor, value + n[name])

        r = Readings(
            t=self.t,
            joints=tuple(q + n[_joint_sensor(j)] for j, q in enumerate(self.joints)),
            servo_ok=tuple(j not in self._servo_timeouts for j in range(5)),
            arc_temperature=self.temperature + n["arc_temperature"],
            arc_voltage=noisy("arc_voltage", volts),
            arc_current=noisy("arc_current", amps),
            gas_bottle_pressure=noisy("gas_bottle_pressure", self.bottle_pressure),
            gas_line_pressure=noisy("gas_line_pressure", line),
            gas_flow=noisy("gas_flow", flow),
            wire_speed=noisy("wire_speed", self.wire_speed),
            wire_remaining=self.wire_remaining,
            start_marker=view.start_marker,
            end_marker=view.end_marker,
            linear=view,
            range_mm=view.range_mm,
            intruder=self.intruder_input,
            silent=frozenset(self._dropouts),
        )
        r = self._apply_silence(r)
        self._cache = (self._steps, r)
        return r

    def _apply_silence(self, r: Readings) -> Readings:
        if not self._dropouts:
            return r
        joints = list(r.joints)
        changes: dict[str, Any] = {}
        for sensor in self._dropouts:
            frozen = self._frozen[sensor]
            if sensor.startswith("joint"):
                j = int(sensor[5:]) - 1
                joints[j] = frozen.joints[j]
            else:
                for name in _FIELDS[sensor]:
                    changes[name] = getattr(frozen, name)
        return replace(r, joints=tuple(joints), **changes)


_FIELDS: dict[str, tuple[str, ...]] = {
    name: (name,) for name in SENSOR_NAMES if not name.startswith("joint")
}
_FIELDS["gap_markers"] = ("start_marker", "end_marker")
_FIELDS["linear_sensor"] = ("linear", "range_mm")


DBC_MESSAGE_SENSORS: dict[str, tuple[str, ...]] = {
    "LightCurtain": ("intruder",),
    "ArcTemperature": ("arc_temperature",),
    "GapMarkers": ("gap_markers",),
    "GasSupply": ("gas_bottle_pressure", "gas_line_pressure", "gas_flow"),
    "WireFeed": ("wire_speed", "wire_remaining"),
}
"""Which sensors (:data:`chcos.apps.weld.faults.SENSOR_NAMES`) each raw-CAN message of
``chcos/apps/weld/maps/weld_cell.dbc`` carries."""

ARC_TEMP_RANGE = (0.0, 3000.0)
"""The pyrometer's measuring range (degC), as in the DBC's ``ArcTemp`` signal."""


def dbc_signals(readings: Readings, counter: int) -> dict[str, dict[str, float | int | str]]:
    """The physical signal values of the raw-CAN messages of ``chcos/apps/weld/maps/weld_cell.dbc``
    for
    ``readings``, by message name, ready for ``cantools`` ``Message.encode``. ``counter`` is the
    alive counter (taken modulo 16). A message whose sensors are silent (dropped out) is left out:
    its device stops sending. Values are clamped to each signal's range; an arc temperature
    outside the pyrometer's range is reported at the range limit with an over/under-range status.
    """
    alive = counter % 16
    lo, hi = ARC_TEMP_RANGE
    temp = readings.arc_temperature
    status = "over_range" if temp > hi else "under_range" if temp < lo else "ok"

    def clamp(value: float, top: float) -> float:
        return min(top, max(0.0, value))

    out: dict[str, dict[str, float | int | str]] = {
        "LightCurtain": {"Intruder": int(readings.intruder), "CurtainOk": 1, "AliveCounter": alive},
        "ArcTemperature": {
            "ArcTemp": round(min(hi, max(lo, temp)), 1),
            "ArcTempStatus": status,
            "AliveCounter": alive,
        },
        "GapMarkers": {
            "StartOfGap": int(readings.start_marker),
            "EndOfGap": int(readings.end_marker),
            "MarkerSensorOk": 1,
            "AliveCounter": alive,
        },
        "GasSupply": {
            "BottlePressure": round(clamp(readings.gas_bottle_pressure, 300.0), 2),
            "LinePressure": round(clamp(readings.gas_line_pressure, 10.0), 3),
            "GasFlow": round(clamp(readings.gas_flow, 50.0), 2),
            "AliveCounter": alive,
        },
        "WireFeed": {
            "WireSpeed": round(clamp(readings.wire_speed, 250.0), 2),
            "WireRemaining": round(clamp(readings.wire_remaining, 5000.0), 3),
            "WireOk": int(readings.wire_remaining > 0.0),
            "AliveCounter": alive,
        },
    }
    for message, sensors in DBC_MESSAGE_SENSORS.items():
        if any(s in readings.silent for s in sensors):
            del out[message]
    return out
