"""can_peer - the simulated ECU of a ``can`` bus: the node on the other end of a map's raw CAN
devices, as strict as a real ECU.

It sends the messages that carry the map's sensors (coded with the bus's DBC, or the raw layout,
by the driver's own codec with the directions turned round) at their cycle - the DBC's
``GenMsgCycleTime``, else the map's ``cycle_time`` (``[[bus.message]]``) - and an event-driven
message (no cycle) once at power-up and then whenever a value is set; a multiplexed message
once per branch its sensors are in; the counter and checksum the map declares for a message
are in every frame. It takes the frames of the map's actuators
as an ECU does:

- a frame whose checksum or counter is wrong is rejected (not applied, counted by cause in
  :attr:`CanPeer.rejected`);
- a command of a cyclic message (a cycle from the DBC, else from the map) that is not repeated
  times out after :data:`TIMEOUT_CYCLES` cycles: the ECU falls back to the signals' substitute
  values, the DBC's initial values (``GenSigStartValue``, else 0), what :meth:`CanPeer.get` then
  shows, until a valid frame comes again (counted in :attr:`CanPeer.timeouts`).

So a map that does not repeat a cyclic command, or leaves a counter or checksum out, fails
against this simulation as it would at the cell. In a virtual cell (``rewrite``) the ECU is an
endpoint of the in-process direct bus (:mod:`drivers.can_direct`): frames reach it on the
kernel thread inside the driver's send, and its own frames reach the driver inside its tick;
:meth:`CanPeer.fault` provokes error frames, error-passive, bus-off and the restart there. On a
real channel (``chcos sim --from`` on vcan or ``udp_multicast``) it drains its python-can bus on
each tick, and a fault is the error frame SocketCAN's controller driver would send.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import os
import threading
from collections import Counter
from typing import Any

import can

from chcos.apps.sim.peers import Mutable, Peer, can_args, on_channel
from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.errors import BusError, DeviceError
from drivers.can_direct import INTERFACE as DIRECT
from drivers.can_direct import BusFault, DirectBus
from drivers.codecs.can import CanCodec, Decoded, FrameFault, Rejected, load_dbc
from drivers.codecs.can_errors import ControllerState, error_frame

#: Cycles without a valid frame after which the ECU takes a cyclic command as timed out.
TIMEOUT_CYCLES = 3
#: Seconds between two error frames of an ``error-frame`` fault with a duration.
ERROR_FRAME_PERIOD = 0.01
_channels = itertools.count()


def direct_args(tag: str) -> dict[str, Any]:
    """python-can arguments of a private direct channel (one process, virtual time)."""
    return {"interface": DIRECT, "channel": f"chcos-sim-{tag}-{os.getpid()}-{next(_channels)}"}


def mux_branch(dbc: Any, device: DeviceSpec) -> tuple[Any, ...]:
    """The multiplexer values that select ``device``'s DBC signal, outermost last (empty for a
    signal outside any multiplexer, or a raw address)."""
    if dbc is None or "message" not in device.address:
        return ()
    msg = dbc.get_message_by_name(device.address["message"])
    by_name = {s.name: s for s in msg.signals}
    sig, out = by_name.get(str(device.address.get("signal"))), []
    while sig is not None and sig.multiplexer_ids and sig.multiplexer_signal is not None:
        out.append((sig.multiplexer_signal, sig.multiplexer_ids[0]))
        sig = by_name.get(sig.multiplexer_signal)
    return tuple(out)


#: One frame the ECU sends: the message's (id, extended) and the multiplexer branch it carries
#: (() for a plain message: a multiplexed one is sent once per branch, each cycle)
OutKey = tuple[int, bool, tuple[Any, ...]]


@dataclasses.dataclass
class _Out:
    """One frame the ECU sends: its period (None: on change), when the next is due."""

    key: OutKey
    device: str
    period: float | None
    due: float = 0.0


@dataclasses.dataclass
class _In:
    """One message the ECU receives: its expected cycle (None: event-driven), its devices,
    when the last valid frame came, whether it has timed out."""

    key: tuple[int, bool]
    devices: list[str]
    cycle: float | None
    last: float | None = None
    timed_out: bool = False


class CanPeer(Mutable, Peer):
    """The simulated ECU of one ``can`` bus (see the module doc)."""

    def __init__(self, bus: BusSpec, devices: tuple[DeviceSpec, ...], rewrite: bool) -> None:
        flipped = [dataclasses.replace(d, direction="actuator" if d.direction == "sensor"
                                       else "sensor") for d in devices]
        self.codec = CanCodec(bus, flipped)
        self.args = direct_args(bus.name) if rewrite else can_args(bus.options, False, bus.name)
        options = on_channel(bus.options, self.args) if rewrite else dict(bus.options)
        self.bus = dataclasses.replace(bus, options=options)
        self.sensors = [d for d in devices if d.direction == "sensor"]
        self.specs = {d.name: d for d in devices}
        self.values: dict[str, Any] = {}
        self.received: dict[str, Any] = {}
        self.muted = False
        self.lock = threading.RLock()  # type: ignore[assignment]  # re-entered by error frames
        self.now = 0.0
        #: frames rejected by cause (``checksum``, ``counter``, ``wrong-length``...), command
        #: timeouts, frames sent and received
        self.rejected: Counter[str] = Counter()
        self.timeouts = 0
        self.frames_out = 0
        self.frames_in = 0
        dbc = load_dbc(str(bus.options["dbc"])) if "dbc" in bus.options else None
        self._out: dict[OutKey, _Out] = {}
        #: each sensor's frame (its message, its multiplexer branch)
        self._out_of: dict[str, OutKey] = {}
        for d in self.sensors:
            mkey = self.codec.key_of(d.name)
            key: OutKey = (*mkey, mux_branch(dbc, d))
            self._out_of[d.name] = key
            if key not in self._out:
                self._out[key] = _Out(key, d.name, self._cycle(dbc, d, mkey))
        self._in: dict[tuple[int, bool], _In] = {}
        for d in devices:
            if d.direction == "actuator":
                ikey = self.codec.key_of(d.name)
                entry = self._in.setdefault(ikey, _In(ikey, [], self._cycle(dbc, d, ikey)))
                entry.devices.append(d.name)
        self._fallback = {d.name: self._initial(dbc, d) for d in devices
                          if d.direction == "actuator"}
        self._fault_until: float | None = None
        self._fault_kind: BusFault | None = None
        self._next_error = 0.0
        #: the payload of each message the ECU sends, as last set
        self._payload = {key: self.codec.held(out.device)[1] for key, out in self._out.items()}
        self._controller = ControllerState.ERROR_ACTIVE   # what a real-channel fault told
        self.can: Any = can.Bus(**self.args)
        self.direct = isinstance(self.can, DirectBus)
        if isinstance(self.can, DirectBus):
            self.can.set_receiver(self._frame)

    def _cycle(self, dbc: Any, device: DeviceSpec, key: tuple[int, bool]) -> float | None:
        """A message's cycle as the ECU has it: the DBC's, else the map's cycle_time."""
        if dbc is not None and "message" in device.address:
            ms = dbc.get_message_by_name(device.address["message"]).cycle_time
            if ms:
                return float(ms) / 1000.0
        return self.codec.cycle(*key)

    @staticmethod
    def _initial(dbc: Any, device: DeviceSpec) -> Any:
        """An actuator's substitute value: its signal's DBC initial value, else 0."""
        if dbc is None or "message" not in device.address:
            return 0
        sig = dbc.get_message_by_name(device.address["message"]).get_signal_by_name(
            device.address["signal"])
        return sig.initial if sig.initial is not None else 0

    # ---- what the ECU sends -----------------------------------------------------------------
    def set(self, device: DeviceSpec, raw: Any) -> None:
        """The value the ECU sends for sensor ``device`` from now on: with the next frame of a
        cyclic message, at once for an event-driven one."""
        self._hold(device, raw, self.codec.encode_raw)

    def _hold(self, device: DeviceSpec, raw: Any, encode: Any) -> None:
        with self.lock:
            key = self._out_of[device.name]
            self._payload[key] = encode(device.name, raw)[1]
            self.values[device.name] = raw
            out = self._out.get(key)
            if out is not None and out.period is None and not self.muted:
                self._send(out)

    def set_raw(self, device: DeviceSpec, raw: Any) -> None:
        """As :meth:`set`, checked only against what the signal's bits carry (not the DBC's
        minimum and maximum): any value the wire can carry. Raises DeviceError naming the
        device if the bits cannot carry it."""
        try:
            self._hold(device, raw, self.codec.encode_unchecked)
        except BusError as exc:
            raise DeviceError(f"{device.name}: raw {raw!r}: {exc}") from None

    def _send(self, out: _Out) -> None:
        """One frame of ``out``'s message with the values held, counter and checksum in."""
        fid, ext, _branch = out.key
        data = self._payload[out.key]
        msg = can.Message(arbitration_id=fid, data=self.codec.stamp(fid, ext, data),
                          is_extended_id=ext)
        try:
            self.can.send(msg, timeout=0)
        except can.CanError:    # bus-off, or a full queue: a lost frame, as on a wire
            return
        self.frames_out += 1

    def tick(self, now: float) -> None:
        """Clock time ``now``: frames due are sent, timed-out commands fall back, a timed
        fault ends."""
        with self.lock:
            self.now = now
            if not self.direct:
                self._drain()
            self._fault_step(now)
            if not self.muted:
                for out in self._out.values():
                    if out.period is None:     # event-driven: once at power-up (once a
                        if out.due <= now and self._heard():   # driver is on the wire), then
                            out.due = math.inf                  # on set
                            self._send(out)
                        continue
                    if now + 1e-9 >= out.due:
                        # drift-free: each frame due one period after the last was due
                        out.due = out.due + out.period if out.due + out.period > now else \
                            now + out.period
                        self._send(out)
            for entry in self._in.values():
                if (entry.cycle is not None and entry.last is not None and not entry.timed_out
                        and now - entry.last > TIMEOUT_CYCLES * entry.cycle + 1e-9):
                    entry.timed_out = True
                    self.timeouts += 1
                    for dev in entry.devices:
                        self.received[dev] = self._fallback[dev]

    def _heard(self) -> bool:
        """Whether a frame sent now reaches anyone: on the direct bus another endpoint is on
        it; on a real channel always (who listens cannot be known)."""
        return not self.direct or len(self.can.wire.endpoints) > 1

    # ---- what the ECU receives --------------------------------------------------------------
    def _frame(self, frame: can.Message) -> None:
        """A frame from the bus (on the sender's thread on the direct bus)."""
        if frame.is_error_frame:
            return
        with self.lock:
            self.frames_in += 1
            result = self.codec.decode(frame)
            key = (frame.arbitration_id, bool(frame.is_extended_id))
            if isinstance(result, Rejected):
                if result.fault not in (FrameFault.UNKNOWN_ID,):
                    self.rejected[result.fault.value] += 1
                return
            if not isinstance(result, Decoded):
                return
            entry = self._in.get(key)
            if entry is not None:
                entry.last = self.now
                entry.timed_out = False
            for dev, v in result.readings:
                self.received[dev] = v

    def _drain(self) -> None:
        while True:
            frame = self.can.recv(timeout=0)
            if frame is None:
                return
            self._frame(frame)

    def get(self, device: DeviceSpec) -> Any:
        """What the ECU holds for ``device``: an actuator's last valid command (its
        substitute value once timed out; None before the first), a sensor's value."""
        with self.lock:
            if not self.direct:
                self._drain()
            if device.direction == "sensor":
                return self.values.get(device.name)
            return self.received.get(device.name)

    # ---- bus faults -------------------------------------------------------------------------
    def fault(self, kind: str, duration: float | None = None) -> None:
        """Provoke ``kind`` (a :class:`drivers.can_direct.BusFault`) on the bus now; with a
        ``duration`` (seconds of the peer's clock) the fault ends by itself: bus-off and
        error-passive with the restart, an ``error-frame`` fault sends one error frame every
        :data:`ERROR_FRAME_PERIOD` until then (a disturbed wire: the receive counters climb to
        error-passive). Raises DeviceError naming the faults for another kind."""
        try:
            fault = BusFault(kind)
        except ValueError:
            raise DeviceError(f"bus {self.bus.name!r}: no bus fault {kind!r}; expected one of "
                              f"{', '.join(f.value for f in BusFault)}") from None
        if duration is not None and not (math.isfinite(duration) and duration > 0):
            raise DeviceError(f"bus fault {kind}: expected a duration > 0 s, got {duration!r}")
        with self.lock:
            self._inject(fault)
            self._fault_kind = fault if duration is not None else None
            self._fault_until = None if duration is None else self.now + duration
            self._next_error = self.now + ERROR_FRAME_PERIOD

    def _fault_step(self, now: float) -> None:
        until, kind = self._fault_until, self._fault_kind
        if until is None or kind is None:
            return
        if now + 1e-9 >= until:
            self._fault_until = self._fault_kind = None
            if kind is not BusFault.ERROR_FRAME:
                self._inject(BusFault.RECOVER)
            return
        if kind is BusFault.ERROR_FRAME:
            while self._next_error <= now + 1e-9:
                self._next_error += ERROR_FRAME_PERIOD
                self._inject(BusFault.ERROR_FRAME)

    def _inject(self, fault: BusFault) -> None:
        """The fault on the direct bus's controllers, or on a real channel the error frame a
        SocketCAN controller driver would send about it."""
        if self.direct:
            self.can.wire.inject(fault)
            return
        old = self._controller
        tx, rx = {BusFault.BUS_OFF: (256, 0), BusFault.ERROR_PASSIVE: (128, 0),
                  BusFault.RECOVER: (0, 0), BusFault.ERROR_FRAME: (0, 1)}[fault]
        cls, data = error_frame(tx, rx, old, protocol=fault is BusFault.ERROR_FRAME)
        self._controller = (ControllerState.BUS_OFF if fault is BusFault.BUS_OFF else
                            ControllerState.ERROR_PASSIVE if fault is BusFault.ERROR_PASSIVE
                            else ControllerState.ERROR_ACTIVE if fault is BusFault.RECOVER
                            else old)
        try:
            self.can.send(can.Message(arbitration_id=cls, is_extended_id=False,
                                      is_error_frame=True, data=data), timeout=1.0)
        except can.CanError as exc:
            raise DeviceError(f"bus {self.bus.name!r}: the error frame of {fault.value} could "
                              f"not be sent: {exc}") from exc

    def describe(self) -> str:
        return f"CAN node on {self.args.get('interface')} channel {self.args.get('channel')}"

    def close(self) -> None:
        self.can.shutdown()
