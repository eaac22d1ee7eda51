"""recording - record CAN traffic to python-can log files and replay a log onto a bus.

A session at the cell is recorded (``record = "session.log"`` in a ``can`` bus's options makes the
can driver record every frame it receives and sends) and replayed on a laptop onto a virtual bus.
The format follows the file suffix, as python-can's :class:`can.Logger` and :class:`can.LogReader`
choose it: ``.log`` (candump/canutils), ``.asc`` (Vector ASCII), ``.blf`` (Vector binary),
``.csv``, ``.trc``. Direction (received/sent) is kept by ``.log``, ``.asc`` and ``.blf``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can

from chcos.errors import BusError

LOG_SUFFIXES = (".log", ".asc", ".blf", ".csv", ".trc")


class Recorder:
    """A thread-safe sink of CAN frames into one log file (a :class:`can.Listener`).

    Both the driver's reader thread (received frames) and writer thread (sent frames) call
    :meth:`on_message_received`. Raises :class:`BusError` if the file cannot be created or its
    suffix has no python-can writer.
    """

    def __init__(self, path: str | Path, channel: str = "can0") -> None:
        self.path = Path(path)
        if self.path.suffix.lower() not in LOG_SUFFIXES:
            raise BusError(f"record file {self.path}: expected a suffix in "
                           f"{', '.join(LOG_SUFFIXES)}")
        self._lock = threading.Lock()
        self._channel = channel
        self.count = 0
        try:
            self._logger: Any = can.Logger(str(self.path))
        except (OSError, ValueError) as exc:
            raise BusError(f"record file {self.path}: cannot open for writing: {exc}") from exc
        self._closed = False

    def on_message_received(self, msg: can.Message) -> None:
        """Append ``msg`` (its timestamp is set to now if it has none); ignored after stop."""
        if msg.timestamp == 0.0:
            msg.timestamp = time.time()
        if msg.channel is None:
            msg.channel = self._channel
        with self._lock:
            if not self._closed:
                self._logger.on_message_received(msg)
                self.count += 1

    def stop(self) -> None:
        """Flush and close the file. Idempotent."""
        with self._lock:
            if not self._closed:
                self._closed = True
                self._logger.stop()


class BusRecording:
    """Records every frame a python-can bus receives into a log file, from a Notifier thread,
    until :meth:`stop` (for buses no driver owns, e.g. a bench tap). Raises :class:`BusError`
    like :class:`Recorder`."""

    def __init__(self, bus: can.BusABC, path: str | Path) -> None:
        self.recorder = Recorder(path)
        self._bus = bus
        self._notifier = can.Notifier(bus, [self.recorder.on_message_received], timeout=0.05)

    def stop(self) -> int:
        """Stop listening, record what is still queued on the bus, close the file; return how
        many frames were recorded. Idempotent."""
        self._notifier.stop()
        try:
            while (msg := self._bus.recv(0)) is not None:
                self.recorder.on_message_received(msg)
        except (can.CanError, OSError):
            pass                                   # a closed bus: nothing left to record
        self.recorder.stop()
        return self.recorder.count

    def __enter__(self) -> BusRecording:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def read_log(path: str | Path) -> Iterator[can.Message]:
    """The frames of a log file, in order. Raises :class:`BusError` if it cannot be read."""
    p = Path(path)
    if p.suffix.lower() not in LOG_SUFFIXES:
        raise BusError(f"log file {p}: expected a suffix in {', '.join(LOG_SUFFIXES)}")
    try:
        reader = can.LogReader(str(p))
    except (OSError, ValueError) as exc:
        raise BusError(f"log file {p}: cannot open for reading: {exc}") from exc
    try:
        yield from reader
    except (ValueError, IndexError) as exc:
        raise BusError(f"log file {p}: malformed content: {exc}") from exc


def replay(path: str | Path, bus: can.BusABC, *, realtime: bool = False,
           rx_only: bool = False, stop: threading.Event | None = None) -> int:
    """Send the frames of log ``path`` onto ``bus``; return how many were sent.

    ``realtime`` keeps the recorded gaps (via :class:`can.MessageSync`, long pauses cut to 60 s);
    otherwise frames go out back to back. ``rx_only`` sends only frames recorded as received
    (leaving out what the recording node itself sent, e.g. its actuator commands). ``stop`` ends
    the replay early. Raises :class:`BusError` on unreadable logs or a failed send.
    """
    frames: Any = read_log(path)
    if realtime:
        frames = can.MessageSync(frames, timestamps=True)
    sent = 0
    for msg in frames:
        if stop is not None and stop.is_set():
            break
        if msg.is_error_frame or (rx_only and not msg.is_rx):
            continue
        out = can.Message(arbitration_id=msg.arbitration_id, data=msg.data, dlc=msg.dlc,
                          is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                          is_fd=msg.is_fd, bitrate_switch=msg.bitrate_switch)
        try:
            bus.send(out, timeout=1.0)
        except can.CanError as exc:
            raise BusError(f"replay of {path}: send of frame {sent} "
                           f"(id 0x{msg.arbitration_id:X}) failed: {exc}") from exc
        sent += 1
    return sent
