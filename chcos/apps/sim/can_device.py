"""can_device - a simulated raw CAN node that speaks the messages of a DBC file.

For tests and demos on a python-can ``virtual`` bus (or ``vcan0``): set signal values from Python,
send a message on demand (:meth:`CanDeviceSim.send`), or let :meth:`CanDeviceSim.tick` send every
periodic message that is due (the owner calls it, so it runs on virtual time), or run it on real
time in a thread (:meth:`CanDeviceSim.start`, used by ``chcos sim can``). Frames it receives are
decoded and kept, so a test can wait for an actuator value (:meth:`CanDeviceSim.wait_for`).
:meth:`CanDeviceSim.send_raw` injects arbitrary frames (unknown ids, wrong lengths).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import can

from chcos.errors import BusError
from drivers.codecs.can import load_dbc


class CanDeviceSim:
    """A CAN node on ``interface``/``channel`` coding the messages of ``dbc``.

    ``periods`` maps message names to their send period in seconds (default: the DBC's cycle
    time, for messages that have one). Raises :class:`BusError` if the DBC or the bus cannot be
    opened, or a message/signal name is unknown.
    """

    def __init__(self, dbc: str | Path, *, interface: str = "virtual", channel: str = "vcan0",
                 periods: Mapping[str, float] | None = None, **bus_kwargs: Any) -> None:
        self.db = load_dbc(str(dbc))
        self._lock = threading.Condition()
        self._values: dict[str, dict[str, float]] = {
            m.name: {s.name: float(s.initial if s.initial is not None else
                                   (s.minimum if s.minimum is not None and s.minimum > 0 else 0))
                     for s in m.signals} for m in self.db.messages}
        self._periods: dict[str, float] = {m.name: m.cycle_time / 1000.0 for m in self.db.messages
                                           if m.cycle_time}
        for name, period in (periods or {}).items():
            self._message(name)
            self._periods[name] = period
        self._due: dict[str, float] = {}
        self.received: dict[str, dict[str, Any]] = {}
        self.frames_in = 0
        self.frames_out = 0
        try:
            self.bus = can.Bus(interface=interface, channel=channel, **bus_kwargs)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise BusError(f"simulated CAN device: cannot open {interface} channel "
                           f"{channel!r}: {exc}") from exc
        self._notifier = can.Notifier(self.bus, [self._on_frame], timeout=0.05)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _message(self, name: str) -> Any:
        try:
            return self.db.get_message_by_name(name)
        except KeyError:
            raise BusError(f"simulated CAN device: no message {name!r} in the DBC; expected one "
                           f"of {', '.join(m.name for m in self.db.messages)}") from None

    def set(self, message: str, **signals: float) -> None:
        """Set signal values of ``message`` (sent with its next frame)."""
        msg = self._message(message)
        names = {s.name for s in msg.signals}
        for sig in signals:
            if sig not in names:
                raise BusError(f"simulated CAN device: no signal {sig!r} in {message}; expected "
                               f"one of {', '.join(sorted(names))}")
        with self._lock:
            self._values[message].update(signals)

    def send(self, message: str) -> can.Message:
        """Encode and send ``message`` now; return the frame. Raises :class:`BusError`."""
        msg = self._message(message)
        with self._lock:
            values = dict(self._values[message])
        try:
            data = msg.encode(values, strict=True)
        except (ValueError, KeyError) as exc:
            raise BusError(f"simulated CAN device: cannot encode {message} {values}: {exc}") \
                from exc
        return self.send_raw(msg.frame_id, data, extended=bool(msg.is_extended_frame))

    def send_raw(self, arbitration_id: int, data: bytes, *, extended: bool = False) -> can.Message:
        """Send any frame (for fault injection); raises :class:`BusError` if the send fails."""
        frame = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=extended)
        try:
            self.bus.send(frame, timeout=1.0)
        except can.CanError as exc:
            raise BusError(f"simulated CAN device: send of 0x{arbitration_id:X} failed: {exc}") \
                from exc
        self.frames_out += 1
        return frame

    def tick(self, now: float) -> int:
        """Send every periodic message due at time ``now`` (any clock); return how many."""
        sent = 0
        for name, period in self._periods.items():
            due = self._due.get(name, now)
            if now >= due:
                self.send(name)
                sent += 1
                self._due[name] = max(due + period, now)
        return sent

    def start(self) -> None:
        """Send the periodic messages on real time from a thread until :meth:`close`."""
        def run() -> None:
            step = min(self._periods.values(), default=0.1) / 4
            while not self._stop.wait(step):
                self.tick(time.monotonic())
        self._thread = threading.Thread(target=run, name="can-device-sim", daemon=True)
        self._thread.start()

    def _on_frame(self, frame: can.Message) -> None:
        try:
            msg = self.db.get_message_by_frame_id(frame.arbitration_id)
            decoded = msg.decode(bytes(frame.data), decode_choices=False)
        except (KeyError, ValueError):
            return          # not ours, or not decodable: a device ignores it
        with self._lock:
            self.frames_in += 1
            self.received.setdefault(msg.name, {}).update(decoded)
            self._lock.notify_all()

    def value(self, message: str, signal: str) -> Any:
        """The last received value of ``message.signal`` (None if never received)."""
        with self._lock:
            return self.received.get(message, {}).get(signal)

    def wait_for(self, message: str, signal: str, pred: Callable[[Any], bool],
                 timeout: float) -> bool:
        """Wait until a received ``message.signal`` satisfies ``pred``; False on timeout."""
        def ok() -> bool:
            v = self.received.get(message, {}).get(signal)
            return v is not None and pred(v)
        with self._lock:
            return self._lock.wait_for(ok, timeout)

    def close(self) -> None:
        """Stop the thread and the notifier, close the bus. Idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._notifier.stop()
        self.bus.shutdown()

    def __enter__(self) -> CanDeviceSim:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
