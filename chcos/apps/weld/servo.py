"""servo - one joint's CiA 402 servo drive in the welding cell's simulators: the drive's power
state machine (:class:`chcos.apps.sim.cia402_drive.DriveModel`) composed with the cell's joint
dynamics (:class:`chcos.apps.weld.model.WeldCell` moves the joint).

Both bindings use it: the real-bus simulator (:class:`chcos.apps.weld.slaves.ServoDrives`, the
controlword in RPDO2, the statusword in TPDO2) and the protocol-free one
(:mod:`chcos.apps.weld.direct`, an in-process axis on the same drive). What the drive does:

* the joint moves only while the drive is OPERATION ENABLED *and* the safe-torque-off relay
  (the coil ``drives_enable``) gives it torque; otherwise it is held where it stands (and a
  target taken before the relay dropped is forgotten: the joint stays put until the next one);
* target positions (0x607A, cyclic synchronous position: the controller interpolates) are taken
  only while the drive is OPERATION ENABLED in CSP; one taken before is ignored and counted, and
  on entering OPERATION ENABLED the drive holds where the joint stands until the next target
  (an old target never moves the arm);
* a quick stop (controlword 0x02) decelerates the joint at :data:`QUICK_STOP_DECELERATION`
  from the speed it had; with the quick stop option code (0x605A) 5..8 the drive then stays in
  QUICK STOP ACTIVE until the master disables the voltage, with 1..4 it goes to SWITCH ON
  DISABLED by itself.

Positions are in counts of :data:`POSITION_SCALE` rad (1 microradian), velocities in counts/s.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from chcos.apps.sim.cia402_drive import CSP, DriveModel, Power

POSITION_SCALE = 1e-6
"""rad per count of 0x6064 / 0x607A / 0x606C (per s)."""
QUICK_STOP_OPTION = 6
"""0x605A of ``weld_servo.eds``: slow down on the quick stop ramp and stay in QUICK STOP
ACTIVE (the master disables the voltage once the joint stands)."""
QUICK_STOP_DECELERATION = 20_000_000
"""0x6085 of ``weld_servo.eds``: counts/s^2 (20 rad/s^2)."""
POWER_ON_MODE = CSP
"""0x6060's stored value: the drive starts in cyclic synchronous position."""
NO_FOLLOWING_ERROR = 2**31 - 1
"""The cell's joints never lag their command beyond the drive's window (the plate stops the
torch, not the joint): the following-error check of the model is not used."""


@dataclass
class JointDrive:
    """The drive of joint :attr:`joint` (1..5). :meth:`controlword`, :meth:`mode` and
    :meth:`target` take what the master wrote, in arrival order; :meth:`step` advances it one
    physics step and says where the joint is commanded. :attr:`received` lists every
    controlword applied; ``model.history`` every power state entered."""

    joint: int
    quick_stop_option: int = QUICK_STOP_OPTION
    quick_stop_deceleration: int = QUICK_STOP_DECELERATION
    model: DriveModel = field(default_factory=DriveModel)
    received: list[int] = field(default_factory=list)
    #: targets ignored because the drive was not OPERATION ENABLED in CSP
    ignored_targets: int = 0
    #: the CSP target taken while enabled (None: hold where the joint stands)
    setpoint: int | None = None
    _last: float | None = None

    def __post_init__(self) -> None:
        self.model.mode(POWER_ON_MODE)

    @property
    def power(self) -> Power:
        """The drive's power state."""
        return self.model.power

    @property
    def enabled(self) -> bool:
        """True while OPERATION ENABLED."""
        return self.model.power is Power.ENABLED

    @property
    def statusword(self) -> int:
        """0x6041 for the present state."""
        return self.model.statusword(0)

    @property
    def mode_display(self) -> int:
        """0x6061."""
        return self.model.mode_display

    @property
    def error_code(self) -> int:
        """0x603F."""
        return self.model.error_code

    @property
    def velocity(self) -> int:
        """0x606C: the joint's speed over the last step (counts/s)."""
        return round(self.model.velocity)

    def controlword(self, cw: int) -> None:
        """The master wrote 0x6040."""
        self.received.append(cw)
        was = self.enabled
        self.model.controlword(cw, self.quick_stop_option)
        if self.enabled != was:
            self.setpoint = None

    def mode(self, value: int) -> None:
        """The master wrote 0x6060 (shown on 0x6061 when the model accepts it)."""
        self.model.mode(value)
        self.setpoint = None

    def target(self, counts: int) -> bool:
        """The master wrote 0x607A: True if the drive takes it (OPERATION ENABLED in CSP)."""
        if self.enabled and self.model.mode_display == CSP:
            self.setpoint = int(counts)
            return True
        self.ignored_targets += 1
        return False

    def step(self, dt: float, actual: float, torque: bool) -> float | None:
        """Advance ``dt`` s with the joint at ``actual`` counts and the relay giving torque or
        not; returns where the joint is commanded (counts), or None to hold it where it
        stands."""
        m = self.model
        if not torque:
            self.setpoint = None        # the relay took the torque: the old target is dropped
        measured = 0.0 if self._last is None or dt <= 0 else (actual - self._last) / dt
        self._last = actual
        m.position = m.demand = actual
        m.velocity = measured
        m.step(0.0, target_position=0, target_velocity=0, profile_velocity=0,
               quick_stop_deceleration=self.quick_stop_deceleration,
               following_window=NO_FOLLOWING_ERROR, quick_stop_option=self.quick_stop_option)
        if m.power is Power.QUICK_STOP and dt > 0:
            if not torque:
                m.velocity = 0.0        # no torque: the relay's brake holds the joint
                return None
            m.step(dt, target_position=0, target_velocity=0, profile_velocity=0,
                   quick_stop_deceleration=self.quick_stop_deceleration,
                   following_window=NO_FOLLOWING_ERROR, quick_stop_option=self.quick_stop_option)
            return m.position
        if m.power is Power.ENABLED and torque:
            return None if self.setpoint is None else float(self.setpoint)
        return None

    def reboot(self) -> None:
        """An NMT reset node: the drive starts again (NOT READY, then SWITCH ON DISABLED at the
        next step) in its power-on mode; nothing is enabled again."""
        self.model.reboot(POWER_ON_MODE)
        self.setpoint = None
