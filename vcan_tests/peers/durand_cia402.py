"""durand_cia402 - an independent CiA 402 servo drive written on durand (not the canopen library,
no code shared with drivers/codecs/cia402.py): its own power state machine written from the CiA 402
state diagram, reacting to the controlword it receives by RPDO or SDO; a position/velocity model
stepped by the test; faults with EMCY and 0x603F; a record of every controlword it received.

The PDOs are those of a typical vendor drive: every RPDO carries the controlword (RPDO1: 0x6040;
RPDO2: 0x6040 + 0x6060; RPDO3: 0x6040 + 0x607A; RPDO4: 0x6040 + 0x60FF), TPDO1 sends 0x6041 +
0x6061 + 0x603F, TPDO2 0x6064 + 0x606C, both on change (transmission type 255).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import can
from durand import CANBusNetwork, MinimalNode, Variable
from durand import DatatypeEnum as DT
from durand.network import NodeListener

# the drive's power states, spelled as the standard's diagram does
NOT_READY = "Not ready to switch on"
SOD = "Switch on disabled"
RTSO = "Ready to switch on"
SWITCHED_ON = "Switched on"
ENABLED = "Operation enabled"
QUICK_STOP = "Quick stop active"
REACTION = "Fault reaction active"
FAULT = "Fault"

#: statusword bits 0-3, 5, 6 shown in each state (bit 5 "quick stop" is 1 when NOT active)
STATE_BITS = {NOT_READY: 0x00, SOD: 0x40, RTSO: 0x21, SWITCHED_ON: 0x23, ENABLED: 0x27,
              QUICK_STOP: 0x07, REACTION: 0x0F, FAULT: 0x08}
REMOTE = 0x0200
VOLTAGE = 0x0010
TARGET_REACHED = 0x0400
BIT12 = 0x1000
BIT13 = 0x2000

PP, PV, HM, CSP, CSV = 1, 3, 6, 8, 9
FOLLOWING_ERROR = 0x8611
OVER_TEMPERATURE = 0x4310


class _Network(CANBusNetwork):  # type: ignore[misc]
    """durand's python-can network with a notifier that stops within 50 ms (durand's waits up
    to a second at every close)."""

    def __init__(self, bus: Any) -> None:
        self._bus = bus
        self._loop = None
        self.lock = threading.Lock()
        self.subscriptions: dict[int, Any] = {}
        self._notifier = can.Notifier(bus, (NodeListener(self),), 0.05)


class DurandCia402Drive:
    """One CiA 402 drive (node ``node_id``) on the python-can virtual channel ``channel``.

    ``refused_modes``: modes of operation it ignores (0x6061 keeps its value).
    ``quick_stop_option``: 0x605A at power-on. Thread-safe: the durand notifier thread applies
    frames, the test calls :meth:`step` and the injections.

    ``axis``/``host``: axis ``axis`` of a multi-axis drive, its objects 0x800 per axis above
    axis 0's, on the node (bus, lock) of ``host`` (its axis 0), with its own state machine; the
    indices this class takes (:meth:`read`) are axis 0's, the offset added. ``pdos``: map the
    single-axis drive's PDOs (a multi-axis drive maps its own, see durand_cia402_multi).
    """

    def __init__(self, channel: str, node_id: int = 5, *, quick_stop_option: int = 2,
                 refused_modes: tuple[int, ...] = (HM,),
                 supported_modes: tuple[int, ...] = (PP, PV, HM, CSP, CSV),
                 profile_velocity: int = 10_000, quick_stop_deceleration: int = 50_000,
                 following_error_window: int = 5_000, axis: int = 0,
                 host: DurandCia402Drive | None = None, pdos: bool = True) -> None:
        self.node_id = node_id
        self.axis = axis
        self.base = 0x800 * axis
        self.owner = host is None
        if host is None:
            self.lock = threading.RLock()
            self.changed = threading.Condition(self.lock)
            self.bus: Any = can.Bus(interface="virtual", channel=channel,
                                    receive_own_messages=False)
            self.network = _Network(self.bus)
            self.node: Any = MinimalNode(self.network, node_id)
        else:
            self.lock, self.changed = host.lock, host.changed
            self.bus, self.network, self.node = host.bus, host.network, host.node
        self.refused_modes = refused_modes
        self.supported_modes = supported_modes
        #: every controlword received (RPDO or SDO), in order
        self.received: list[int] = []
        #: (controlword, state it found, speed at that moment) for each controlword received
        self.log: list[tuple[int, str, float]] = []
        #: every state the drive went through, in order
        self.history: list[str] = [NOT_READY]
        #: every EMCY code sent (0: error reset)
        self.emcys: list[int] = []
        self.state = NOT_READY
        self.position = 0.0
        self.velocity = 0.0
        self.setpoint = 0.0
        self.ack = False
        self.homing = False
        self.homed = False
        self.persistent: int | None = None
        self._last_cw = 0
        od = self.node.object_dictionary
        for index, dtype, access, value, name in (
                (0x6040, DT.UNSIGNED16, "rw", 0, "Controlword"),
                (0x6041, DT.UNSIGNED16, "ro", 0, "Statusword"),
                (0x6060, DT.INTEGER8, "rw", 0, "Modes of operation"),
                (0x6061, DT.INTEGER8, "ro", 0, "Modes of operation display"),
                (0x6064, DT.INTEGER32, "ro", 0, "Position actual value"),
                (0x606C, DT.INTEGER32, "ro", 0, "Velocity actual value"),
                (0x607A, DT.INTEGER32, "rw", 0, "Target position"),
                (0x60FF, DT.INTEGER32, "rw", 0, "Target velocity"),
                (0x603F, DT.UNSIGNED16, "ro", 0, "Error code"),
                (0x605A, DT.INTEGER16, "rw", quick_stop_option, "Quick stop option code"),
                (0x6081, DT.UNSIGNED32, "rw", profile_velocity, "Profile velocity"),
                (0x6085, DT.UNSIGNED32, "rw", quick_stop_deceleration, "Quick stop decel."),
                (0x6065, DT.UNSIGNED32, "rw", following_error_window, "Following error window"),
        ):
            od[index + self.base] = Variable(dtype, access, value, name=name)
        od.download_callbacks[(0x6040 + self.base, 0)].add(self._on_controlword)
        od.download_callbacks[(0x6060 + self.base, 0)].add(self._on_mode)
        if pdos:
            rpdo_maps: tuple[list[tuple[int, int]], ...] = (
                [(0x6040, 0)], [(0x6040, 0), (0x6060, 0)], [(0x6040, 0), (0x607A, 0)],
                [(0x6040, 0), (0x60FF, 0)])
            for n, mapping in enumerate(rpdo_maps):
                self.node.rpdo[n].mapping = mapping
            self.node.tpdo[0].mapping = [(0x6041, 0), (0x6061, 0), (0x603F, 0)]
            self.node.tpdo[1].mapping = [(0x6064, 0), (0x606C, 0)]
        # the drive finishes its power-on self test by itself (transition 1)
        with self.lock:
            self._go(SOD)
            self._publish()

    def close(self) -> None:
        """Stop the notifier and close the bus (the owner of the node: axis 0)."""
        if self.owner:
            self.network.stop()
            self.bus.shutdown()

    # -- the object dictionary, as the drive sees it -----------------------------------------

    def read(self, index: int) -> Any:
        """The value of object ``index`` (sub-index 0; axis 0's index, this axis's offset
        added)."""
        with self.lock:
            return self.node.object_dictionary.read(index + self.base, 0)

    def _write(self, index: int, value: int) -> None:
        od = self.node.object_dictionary
        index += self.base
        if od.read(index, 0) != value:
            od.write(index, 0, value)

    def _publish(self) -> None:
        """Show the state, mode, position and velocity in the objects (TPDOs go on change)."""
        sw = STATE_BITS[self.state] | REMOTE
        if self.state in (RTSO, SWITCHED_ON, ENABLED, QUICK_STOP):
            sw |= VOLTAGE
        mode = self.read(0x6061)
        if self.state == ENABLED:
            if mode == PP:
                sw |= (BIT12 if self.ack else 0)
                sw |= TARGET_REACHED if round(self.position) == round(self.setpoint) else 0
            elif mode == PV:
                target = self.read(0x60FF)
                sw |= TARGET_REACHED if round(self.velocity) == target else 0
                sw |= BIT12 if round(self.velocity) == 0 else 0
            elif mode == HM:
                sw |= (BIT12 | TARGET_REACHED) if self.homed and not self.homing else 0
            elif mode in (CSP, CSV):
                sw |= TARGET_REACHED
        elif self.state == QUICK_STOP and self.velocity == 0:
            sw |= TARGET_REACHED
        self._write(0x6064, round(self.position))
        self._write(0x606C, round(self.velocity))
        self._write(0x6041, sw)
        self.changed.notify_all()

    def _go(self, state: str) -> None:
        if state != self.state:
            self.state = state
            self.history.append(state)
        if state != ENABLED:
            self.ack = False
            self.homing = False

    # -- what the master sends ---------------------------------------------------------------

    def _on_controlword(self, cw: int) -> None:
        with self.lock:
            previous, self._last_cw = self._last_cw, cw
            self.received.append(cw)
            self.log.append((cw, self.state, abs(self.velocity)))
            self._apply(cw, previous)
            self._publish()

    def _apply(self, cw: int, previous: int) -> None:
        state = self.state
        if state == FAULT:
            if cw & 0x80 and not previous & 0x80:      # fault reset: rising edge of bit 7
                self._fault_reset()
            return
        if state in (NOT_READY, REACTION):
            return
        voltage, quick, switch_on, operation = cw & 2, cw & 4, cw & 1, cw & 8
        if not voltage:                                # disable voltage: 7, 9, 10, 12
            if state != SOD:
                self.velocity = 0.0                    # the motor coasts
                self._go(SOD)
            return
        if not quick:                                  # quick stop: 7, 10, 11
            if state in (RTSO, SWITCHED_ON):
                self._go(SOD)
            elif state == ENABLED:
                option = self.read(0x605A)
                if option == 0:
                    self.velocity = 0.0
                    self._go(SOD)
                else:
                    self._go(QUICK_STOP)
            return
        if not switch_on:                              # shutdown: 2, 6, 8
            if state in (SOD, SWITCHED_ON, ENABLED):
                self._go(RTSO)
            return
        if not operation:                              # switch on 3, disable operation 5
            if state in (RTSO, ENABLED):
                self._go(SWITCHED_ON)
            return
        # enable operation: 4, 3+4, 16
        if state in (SWITCHED_ON, RTSO) or (state == QUICK_STOP and 5 <= self.read(0x605A) <= 8):
            self.setpoint = self.position
            self._go(ENABLED)
        if self.state == ENABLED:
            self._operation_bits(cw, previous)

    def _operation_bits(self, cw: int, previous: int) -> None:
        mode = self.read(0x6061)
        rising = cw & 0x10 and not previous & 0x10
        if mode == PP:
            if rising:
                self.setpoint = float(self.read(0x607A))
                self.ack = True
            elif not cw & 0x10:
                self.ack = False
        elif mode == HM and rising:
            self.homing, self.homed = True, False

    def _on_mode(self, mode: int) -> None:
        with self.lock:
            # a mode written again (an RPDO carrying it with a controlword) changes nothing
            if mode in self.supported_modes and mode not in self.refused_modes \
                    and mode != self.read(0x6061):
                self._write(0x6061, mode)
                self.setpoint = self.position
            self._publish()

    # -- faults ------------------------------------------------------------------------------

    def inject_fault(self, code: int, persistent: bool = False) -> None:
        """A drive fault: fault reaction, then FAULT; 0x603F = ``code`` and an EMCY. A
        ``persistent`` fault (over-temperature) refuses resets until :meth:`clear_cause`."""
        with self.lock:
            if persistent:
                self.persistent = code
            self._write(0x603F, code)
            self.node.emcy.set(code, 0x01 | (0x08 if code == OVER_TEMPERATURE else 0x00))
            self.emcys.append(code)
            self._go(REACTION)
            self._publish()

    def clear_cause(self) -> None:
        """The cause of a persistent fault is gone (the drive cooled down)."""
        with self.lock:
            self.persistent = None

    def _fault_reset(self) -> None:
        if self.persistent is not None:
            return                                     # the cause is still there
        self._write(0x603F, 0)
        self.node.emcy.set(0, 0)
        self.emcys.append(0)
        self._go(SOD)

    # -- the model ---------------------------------------------------------------------------

    def step(self, dt: float) -> None:
        """Advance the motion and the automatic transitions by ``dt`` seconds."""
        with self.lock:
            if self.state == REACTION:
                self.velocity = 0.0
                self._go(FAULT)
            elif self.state == QUICK_STOP:
                self._decelerate(float(self.read(0x6085)), dt)
                if self.velocity == 0 and not 5 <= self.read(0x605A) <= 8:
                    self._go(SOD)
            elif self.state == ENABLED:
                self._move(dt)
            self._publish()

    def _decelerate(self, rate: float, dt: float) -> None:
        slower = max(0.0, abs(self.velocity) - rate * dt)
        self.velocity = slower if self.velocity > 0 else -slower
        self.position += self.velocity * dt

    def _move(self, dt: float) -> None:
        mode = self.read(0x6061)
        halt = self._last_cw & 0x100
        if halt:
            self._decelerate(float(self.read(0x6085)), dt)
            return
        if mode in (PP, CSP, HM):
            goal = {PP: self.setpoint, CSP: float(self.read(0x607A)), HM: 0.0}[mode]
            if mode == HM and not self.homing:
                goal = self.position
            speed = float(self.read(0x6081))
            step = max(-speed * dt, min(speed * dt, goal - self.position))
            self.position += step
            self.velocity = step / dt if dt > 0 else 0.0
            if mode == HM and self.homing and self.position == 0.0:
                self.homing, self.homed = False, True
            if mode == CSP and abs(goal - self.position) > self.read(0x6065):
                self.inject_fault(FOLLOWING_ERROR)
        elif mode in (PV, CSV):
            self.velocity = float(self.read(0x60FF))
            self.position += self.velocity * dt

    # -- waiting -----------------------------------------------------------------------------

    def wait(self, predicate: Callable[[], bool], timeout: float = 10.0) -> bool:
        """Block until ``predicate()`` holds (checked under the drive's lock on every change)."""
        with self.changed:
            return self.changed.wait_for(predicate, timeout)

    # -- what a master should see ------------------------------------------------------------

    def published(self) -> tuple[int, int, int, int, int]:
        """(statusword, modes display, position, velocity, error code) as in the TPDOs now."""
        with self.lock:
            return (self.read(0x6041), self.read(0x6061), self.read(0x6064), self.read(0x606C),
                    self.read(0x603F))

    def frames(self) -> int:
        """How many controlwords (RPDOs or SDO writes of 0x6040) the drive has applied."""
        with self.lock:
            return len(self.received)
