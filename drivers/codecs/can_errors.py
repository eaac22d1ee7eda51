"""can_errors - the CAN controller's state (error-active, error-passive, bus-off) and the error
frames that tell it: Linux SocketCAN's ``CAN_ERR_FLAG`` frames (``<linux/can/error.h>``), decoded
into a :class:`ControllerReport`, and built the same way by the in-process bus
(:mod:`drivers.can_direct`) so that one decoder serves the simulation and the cell.

An error frame's id holds the error classes (``CAN_ERR_*``, python-can's ``arbitration_id`` of a
frame with ``is_error_frame``); its 8 data bytes the details: ``data[1]`` the controller's
problems (``CAN_ERR_CRTL_*``: warning, passive, back to active), ``data[2..3]`` a protocol
violation, ``data[6]``/``data[7]`` the transmit and receive error counters (valid with
``CAN_ERR_CNT``, which newer kernels set whenever they know the counters). Pure: no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

from chcos.devices.status import BusState, ErrorState

# error classes in the id (<linux/can/error.h>)
CAN_ERR_TX_TIMEOUT = 0x001
CAN_ERR_LOSTARB = 0x002
CAN_ERR_CRTL = 0x004
CAN_ERR_PROT = 0x008
CAN_ERR_TRX = 0x010
CAN_ERR_ACK = 0x020
CAN_ERR_BUSOFF = 0x040
CAN_ERR_BUSERROR = 0x080
CAN_ERR_RESTARTED = 0x100
CAN_ERR_CNT = 0x200
# controller problems, data[1]
CAN_ERR_CRTL_RX_OVERFLOW = 0x01
CAN_ERR_CRTL_TX_OVERFLOW = 0x02
CAN_ERR_CRTL_RX_WARNING = 0x04
CAN_ERR_CRTL_TX_WARNING = 0x08
CAN_ERR_CRTL_RX_PASSIVE = 0x10
CAN_ERR_CRTL_TX_PASSIVE = 0x20
CAN_ERR_CRTL_ACTIVE = 0x40
# protocol violations, data[2]
CAN_ERR_PROT_FORM = 0x02
CAN_ERR_PROT_STUFF = 0x04
#: Error counter levels of ISO 11898-1: warning, error-passive, bus-off (transmit only).
WARNING_LEVEL, PASSIVE_LEVEL, BUS_OFF_LEVEL = 96, 128, 256

_CLASSES = ((CAN_ERR_TX_TIMEOUT, "TX timeout"), (CAN_ERR_LOSTARB, "lost arbitration"),
            (CAN_ERR_CRTL, "controller problem"), (CAN_ERR_PROT, "protocol violation"),
            (CAN_ERR_TRX, "transceiver problem"), (CAN_ERR_ACK, "no ACK"),
            (CAN_ERR_BUSOFF, "bus-off"), (CAN_ERR_BUSERROR, "bus error"),
            (CAN_ERR_RESTARTED, "controller restarted"))
_CRTL = ((CAN_ERR_CRTL_RX_OVERFLOW, "RX buffer overflow"),
         (CAN_ERR_CRTL_TX_OVERFLOW, "TX buffer overflow"),
         (CAN_ERR_CRTL_RX_WARNING, "RX warning level"),
         (CAN_ERR_CRTL_TX_WARNING, "TX warning level"),
         (CAN_ERR_CRTL_RX_PASSIVE, "RX error-passive"),
         (CAN_ERR_CRTL_TX_PASSIVE, "TX error-passive"),
         (CAN_ERR_CRTL_ACTIVE, "back to error-active"))


#: A CAN controller's fault confinement state (ISO 11898-1): the device layer's, which chcos
#: reports (error-active, error-warning, error-passive, bus-off).
ControllerState = ErrorState


@dataclass(frozen=True)
class ControllerReport:
    """What one error frame says: the state it puts the controller in (None: it does not say),
    the error counters (None: not given), and its classes and details as text."""

    state: ControllerState | None
    tx_errors: int | None
    rx_errors: int | None
    what: str


def state_of(tx_errors: int, rx_errors: int) -> ControllerState:
    """The state two error counters give (ISO 11898-1's levels)."""
    if tx_errors >= BUS_OFF_LEVEL:
        return ControllerState.BUS_OFF
    top = max(tx_errors, rx_errors)
    if top >= PASSIVE_LEVEL:
        return ControllerState.ERROR_PASSIVE
    if top >= WARNING_LEVEL:
        return ControllerState.ERROR_WARNING
    return ControllerState.ERROR_ACTIVE


def decode_error_frame(can_id: int, data: bytes) -> ControllerReport:
    """Decode an error frame (``can_id``: the error classes, the flag itself masked off or
    not; ``data``: its payload, 8 bytes as the kernel sends; shorter is taken as zeros)."""
    data = bytes(data).ljust(8, b"\0")
    cls = can_id & 0x1FFFFFFF
    names = [text for bit, text in _CLASSES if cls & bit]
    crtl = data[1] if cls & CAN_ERR_CRTL else 0
    names += [text for bit, text in _CRTL if crtl & bit]
    tx = rx = None
    if cls & CAN_ERR_CNT:
        tx, rx = data[6], data[7]
        names.append(f"TX errors {tx}, RX errors {rx}")
    state: ControllerState | None = None
    if cls & CAN_ERR_BUSOFF:
        state = ControllerState.BUS_OFF
    elif cls & CAN_ERR_RESTARTED or crtl & CAN_ERR_CRTL_ACTIVE:
        state = ControllerState.ERROR_ACTIVE
    elif crtl & (CAN_ERR_CRTL_TX_PASSIVE | CAN_ERR_CRTL_RX_PASSIVE):
        state = ControllerState.ERROR_PASSIVE
    elif crtl & (CAN_ERR_CRTL_TX_WARNING | CAN_ERR_CRTL_RX_WARNING):
        state = ControllerState.ERROR_WARNING
    return ControllerReport(state, tx, rx, ", ".join(names) or f"error class 0x{cls:X}")


def error_frame(tx_errors: int, rx_errors: int, old: ControllerState,
                protocol: bool = False) -> tuple[int, bytes]:
    """The error frame (classes, 8 data bytes) a SocketCAN controller driver sends when its
    counters become ``tx_errors``/``rx_errors`` coming from state ``old``: a state change
    (``CAN_ERR_BUSOFF``; ``CAN_ERR_CRTL`` with the warning, passive or active bits;
    ``CAN_ERR_RESTARTED`` out of bus-off), with ``protocol`` a bus error seen on the wire
    (``CAN_ERR_PROT | CAN_ERR_BUSERROR``, a form error), and the counters (``CAN_ERR_CNT``)."""
    new = state_of(tx_errors, rx_errors)
    cls, crtl, prot = CAN_ERR_CNT, 0, 0
    if protocol:
        cls |= CAN_ERR_PROT | CAN_ERR_BUSERROR
        prot = CAN_ERR_PROT_FORM
    if new is ControllerState.BUS_OFF and old is not ControllerState.BUS_OFF:
        cls |= CAN_ERR_BUSOFF
    elif old is ControllerState.BUS_OFF and new is not ControllerState.BUS_OFF:
        cls |= CAN_ERR_RESTARTED
    elif new is not old:
        cls |= CAN_ERR_CRTL
        if new is ControllerState.ERROR_PASSIVE:
            crtl = (CAN_ERR_CRTL_TX_PASSIVE if tx_errors >= PASSIVE_LEVEL
                    else CAN_ERR_CRTL_RX_PASSIVE)
        elif new is ControllerState.ERROR_WARNING:
            crtl = (CAN_ERR_CRTL_TX_WARNING if tx_errors >= WARNING_LEVEL
                    else CAN_ERR_CRTL_RX_WARNING)
        else:
            crtl = CAN_ERR_CRTL_ACTIVE
    data = bytes([0, crtl, prot, 0, 0, 0, min(tx_errors, 255), min(rx_errors, 255)])
    return cls, data


@dataclass
class ControllerStatus:
    """What a driver knows of its controller from the error frames it received: the state,
    the last error counters (None until an error frame gave them), how many error frames and
    how often it went error-passive and bus-off and was restarted."""

    state: ControllerState = ControllerState.ERROR_ACTIVE
    tx_errors: int | None = None
    rx_errors: int | None = None
    error_frames: int = 0
    passive: int = 0
    bus_offs: int = 0
    restarts: int = 0
    last: str = ""

    def take(self, report: ControllerReport) -> ControllerState | None:
        """Account for one error frame; the state it moved the controller to (None: no change
        of state)."""
        self.error_frames += 1
        self.last = report.what
        if report.tx_errors is not None:
            self.tx_errors, self.rx_errors = report.tx_errors, report.rx_errors
        new = report.state
        if new is None or new is self.state:
            return None
        if new is ControllerState.BUS_OFF:
            self.bus_offs += 1
        elif new is ControllerState.ERROR_PASSIVE:
            self.passive += 1
        elif self.state is ControllerState.BUS_OFF:
            self.restarts += 1
        self.state = new
        return new

    def on_bus(self) -> bool:
        """A data frame arrived while the state said bus-off (a restart whose error frame was
        not seen): the controller is on the bus again, counted as a restart. True if that
        changed the state."""
        if self.state is not ControllerState.BUS_OFF:
            return False
        self.state = ControllerState.ERROR_ACTIVE
        self.restarts += 1
        return True

    def as_state(self) -> BusState:
        """As the device layer's :class:`chcos.devices.status.BusState`."""
        return BusState(self.state, self.tx_errors, self.rx_errors, self.bus_offs, self.passive,
                        self.restarts, self.error_frames, self.last)
