"""can_direct - an in-process CAN bus for virtual time: ``send()`` hands the frame to every other
endpoint's receiver on the caller's thread (the kernel's), no reader thread, no queue, no copy.

A :class:`DirectChannel` is one simulated wire; each :class:`DirectBus` on it is a python-can
``BusABC`` (python-can ``Message`` objects, filters, ``send``/``recv``/``shutdown``), so a driver or
a simulated node codes exactly the bytes it would put on a real bus. An endpoint either has a
receiver (:meth:`DirectBus.set_receiver`: called synchronously with the frame object the sender
passed, which the receiver must not keep: the sender may reuse it) or, without one, keeps what it
receives for ``recv()`` (a copy: the one place a frame is copied). Opened through python-can as
``can.Bus(interface="chcos-direct", channel=NAME)`` too (entry point ``can.interface``).

Each endpoint has a controller with ISO 11898-1 fault confinement (:class:`Controller`): transmit
and receive error counters and the state they give (error-active, error-warning, error-passive,
bus-off). :meth:`DirectChannel.inject` provokes what a disturbed wire does (:class:`BusFault`): an
error frame seen by every controller (its receive counter +8, as for a receiver that sees the
dominant bits after its own error flag, and for each frame received well -1, or back to 127
from error-passive, as ISO 11898-1's fault confinement says), error-passive, bus-off, and the
restart out of it. Every change of
state reaches the endpoint's receiver as the error frame Linux SocketCAN would deliver
(:func:`drivers.codecs.can_errors.error_frame`), so the driver reads the simulated bus and a real
one with the same decoder. A controller that is bus-off neither sends (``send`` raises
``can.CanOperationError`` with ``ENETDOWN``) nor receives.

Runtime state lives in the channel objects; the module keeps only the names of the open channels
(as python-can's ``virtual`` interface does), so an endpoint opened by name finds its wire.
"""

from __future__ import annotations

import enum
import errno
import threading
from collections import deque
from collections.abc import Callable
from typing import Any

import can

from drivers.codecs.can_errors import (
    BUS_OFF_LEVEL,
    PASSIVE_LEVEL,
    ControllerState,
    error_frame,
    state_of,
)

#: The python-can interface name of the direct bus (the entry point in pyproject.toml).
INTERFACE = "chcos-direct"

Receiver = Callable[[can.Message], None]
#: What an error frame adds to a receiver's error counter, and the counter's top (SocketCAN
#: reports it in a byte).
RX_ERROR_STEP, RX_ERRORS_MAX = 8, 255


class BusFault(enum.StrEnum):
    """What :meth:`DirectChannel.inject` provokes on a wire."""

    ERROR_FRAME = "error-frame"       # one bus error seen by every controller (receive +8)
    ERROR_PASSIVE = "error-passive"   # every controller's transmit counter at 128
    BUS_OFF = "bus-off"               # every controller's transmit counter past 255
    RECOVER = "recover"               # the restart: counters 0, error-active


class Controller:
    """One endpoint's fault confinement: its error counters and their state."""

    def __init__(self) -> None:
        self.tx_errors = 0
        self.rx_errors = 0
        self.state = ControllerState.ERROR_ACTIVE

    def set(self, tx_errors: int, rx_errors: int) -> ControllerState:
        """New counters; returns the state before."""
        old = self.state
        self.tx_errors, self.rx_errors = max(0, tx_errors), max(0, rx_errors)
        self.state = state_of(self.tx_errors, self.rx_errors)
        return old


class DirectChannel:
    """One simulated wire and its endpoints. ``clock`` (seconds, e.g. the kernel's virtual
    clock) stamps the frames sent; without one they keep the sender's stamp."""

    def __init__(self, name: str, clock: Callable[[], float] | None = None) -> None:
        self.name = name
        self.clock = clock
        self.endpoints: list[DirectBus] = []
        #: frames sent on the wire, all endpoints together; error frames delivered
        self.frames = 0
        self.error_frames = 0

    def inject(self, fault: BusFault | str) -> None:
        """Provoke ``fault`` on the wire (see the module doc); every controller whose state it
        changes, or that sees the bus error, is told by an error frame. Raises ValueError for
        an unknown fault."""
        fault = BusFault(fault)
        for ep in list(self.endpoints):
            c = ep.controller
            match fault:
                case BusFault.ERROR_FRAME:
                    if c.state is ControllerState.BUS_OFF:
                        continue
                    old = c.set(c.tx_errors, min(RX_ERRORS_MAX, c.rx_errors + RX_ERROR_STEP))
                    ep._controller_frame(old, protocol=True)
                    continue
                case BusFault.ERROR_PASSIVE:
                    old = c.set(max(c.tx_errors, PASSIVE_LEVEL), c.rx_errors)
                case BusFault.BUS_OFF:
                    old = c.set(BUS_OFF_LEVEL, c.rx_errors)
                case BusFault.RECOVER:
                    old = c.set(0, 0)
            if c.state is not old:
                ep._controller_frame(old)

    def _deliver(self, sender: DirectBus, msg: can.Message) -> None:
        self.frames += 1
        for ep in self.endpoints:
            if (ep is not sender or ep.receive_own) and ep.controller.state is not \
                    ControllerState.BUS_OFF:
                ep._take(msg)


_channels: dict[str, DirectChannel] = {}
_lock = threading.Lock()


def open_channel(name: str, clock: Callable[[], float] | None = None) -> DirectChannel:
    """The open channel ``name`` (made, with ``clock``, if none is open); a clock given to an
    open channel replaces its own."""
    with _lock:
        ch = _channels.get(name)
        if ch is None:
            ch = _channels[name] = DirectChannel(name, clock)
        elif clock is not None:
            ch.clock = clock
        return ch


class DirectBus(can.BusABC):
    """One endpoint of a :class:`DirectChannel` (see the module doc). ``channel`` is the
    channel's name; ``receive_own_messages`` as in python-can."""

    def __init__(self, channel: str = "chcos-direct", receive_own_messages: bool = False,
                 can_filters: Any = None, clock: Callable[[], float] | None = None,
                 **kwargs: Any) -> None:
        self.channel_info = f"chcos direct channel {channel!r}"
        self.receive_own = bool(receive_own_messages)
        self.controller = Controller()
        self._receiver: Receiver | None = None
        self._kept: deque[can.Message] = deque()
        self._cond = threading.Condition()
        self._closed = False
        super().__init__(channel=channel, can_filters=can_filters, **kwargs)
        self.wire = open_channel(str(channel), clock)
        with _lock:
            self.wire.endpoints.append(self)

    def set_receiver(self, receiver: Receiver | None) -> None:
        """Hand every frame received from now on to ``receiver`` at once, on the sender's
        thread (None: keep them for ``recv()`` again)."""
        self._receiver = receiver

    @property
    def state(self) -> can.BusState:
        """python-can's view of the controller: ACTIVE, PASSIVE or ERROR (bus-off); the
        state follows the controller's counters (set by :meth:`DirectChannel.inject`)."""
        s = self.controller.state
        if s is ControllerState.BUS_OFF:
            return can.BusState.ERROR
        return can.BusState.PASSIVE if s is ControllerState.ERROR_PASSIVE else can.BusState.ACTIVE

    @state.setter
    def state(self, new_state: can.BusState) -> None:
        raise NotImplementedError("a direct bus's state follows its controller's counters: "
                                  "inject a fault on its channel instead")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Put ``msg`` on the wire: every other endpoint's receiver has it when this returns.
        Raises ``can.CanOperationError`` (``ENETDOWN``) when the controller is bus-off or the
        endpoint is shut down."""
        if self._closed:
            raise can.CanOperationError(f"{self.channel_info} is shut down", errno.ENETDOWN)
        if self.controller.state is ControllerState.BUS_OFF:
            raise can.CanOperationError(f"{self.channel_info}: the controller is bus-off",
                                        errno.ENETDOWN)
        clock = self.wire.clock
        if clock is not None:
            msg.timestamp = clock()
        self.wire._deliver(self, msg)

    def _take(self, msg: can.Message) -> None:
        """A frame from the wire (the sender's thread): a receive well done counts the receive
        counter down; then the filters, then the receiver or the kept frames."""
        c = self.controller
        if c.rx_errors and not msg.is_error_frame:
            old = c.set(c.tx_errors, PASSIVE_LEVEL - 1 if c.rx_errors >= PASSIVE_LEVEL
                        else c.rx_errors - 1)
            if c.state is not old:
                self._controller_frame(old)
        if not self._matches_filters(msg):
            return
        receiver = self._receiver
        if receiver is not None:
            receiver(msg)
            return
        copy = can.Message(timestamp=msg.timestamp, arbitration_id=msg.arbitration_id,
                           is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                           is_error_frame=msg.is_error_frame, dlc=msg.dlc,
                           data=bytes(msg.data), channel=self.wire.name, is_rx=True)
        with self._cond:
            self._kept.append(copy)
            self._cond.notify()

    def _controller_frame(self, old: ControllerState, protocol: bool = False) -> None:
        """Tell this endpoint's owner its controller's counters as SocketCAN would: an error
        frame, past the filters (SocketCAN filters error frames by class, not by id)."""
        c = self.controller
        cls, data = error_frame(c.tx_errors, c.rx_errors, old, protocol)
        self.wire.error_frames += 1
        clock = self.wire.clock
        frame = can.Message(timestamp=clock() if clock is not None else 0.0,
                            arbitration_id=cls, is_extended_id=False, is_error_frame=True,
                            dlc=8, data=data, channel=self.wire.name, is_rx=True)
        receiver = self._receiver
        if receiver is not None:
            receiver(frame)
            return
        with self._cond:
            self._kept.append(frame)
            self._cond.notify()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        with self._cond:
            if not self._kept and timeout != 0:
                self._cond.wait_for(lambda: bool(self._kept) or self._closed, timeout)
            if not self._kept:
                return None, True
            msg = self._kept.popleft()
        return msg, msg.is_error_frame     # error frames pass python-can's id filters

    def _apply_filters(self, filters: Any) -> None:
        """Filters are applied in :meth:`_take` (python-can's own check)."""

    def fileno(self) -> int:
        """No file descriptor: the direct bus has nothing to wait on."""
        raise NotImplementedError("the direct bus has no file descriptor")

    def shutdown(self) -> None:
        """Leave the wire (the channel closes with its last endpoint). Idempotent."""
        if self._closed:
            return
        self._closed = True
        with self._cond:
            self._cond.notify_all()
        with _lock:
            if self in self.wire.endpoints:
                self.wire.endpoints.remove(self)
            if not self.wire.endpoints and _channels.get(self.wire.name) is self.wire:
                del _channels[self.wire.name]
        super().shutdown()
