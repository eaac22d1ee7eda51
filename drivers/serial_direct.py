"""serial_direct - an in-process serial line for virtual time: a null-modem cable whose
``write()`` hands the bytes to the other end's receiver on the caller's thread (the kernel's).

The serial driver (:mod:`drivers.serial_line`) opens ``url = "chcos-direct://NAME"`` as one end
and the simulated instrument (:mod:`chcos.apps.sim.serial_peer`) the other; the bytes are the
ones a real line carries (the framing, the checksums, the end-of-line), only no thread, no
socket and no wall-clock timeout stand between them. An end without a receiver keeps what it
gets for :meth:`LineEnd.read`. Runtime state lives in the line objects; the module keeps the open
lines by name so that both ends find theirs.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

#: The URL scheme of a direct line (``chcos-direct://NAME``).
SCHEME = "chcos-direct://"

Receiver = Callable[[bytes], None]


class LineEnd:
    """One end of a direct line: :meth:`write` to the other end, :meth:`set_receiver` for
    what comes from it."""

    def __init__(self, line: DirectLine) -> None:
        self.line = line
        self._receiver: Receiver | None = None
        self._kept = bytearray()
        self.closed = False
        #: bytes written and received through this end
        self.written = 0
        self.received = 0

    def set_receiver(self, receiver: Receiver | None) -> None:
        """Hand the bytes that arrive from now on to ``receiver`` at once, on the writer's
        thread (None: keep them for :meth:`read`); what was kept goes to it first."""
        self._receiver = receiver
        if receiver is not None and self._kept:
            kept, self._kept = bytes(self._kept), bytearray()
            receiver(kept)

    def write(self, data: bytes) -> None:
        """Put ``data`` on the line: the other end has it when this returns. Raises OSError
        when this end or the other is closed (a cable pulled)."""
        if self.closed:
            raise OSError(f"direct serial line {self.line.name!r}: this end is closed")
        other = self.line.other(self)
        if other is None or other.closed:
            raise OSError(f"direct serial line {self.line.name!r}: nobody at the other end")
        self.written += len(data)
        other._take(bytes(data))

    def _take(self, data: bytes) -> None:
        self.received += len(data)
        receiver = self._receiver
        if receiver is not None:
            receiver(data)
        else:
            self._kept += data

    @property
    def is_open(self) -> bool:
        """As pyserial's ports: False once closed."""
        return not self.closed

    def flush(self) -> None:
        """As pyserial's ports: nothing waits to go out (:meth:`write` delivered it)."""

    def read(self) -> bytes:
        """What arrived and was kept (no receiver), now; b"" if nothing."""
        data, self._kept = bytes(self._kept), bytearray()
        return data

    def close(self) -> None:
        """Leave the line (the line is gone with both ends). Idempotent."""
        self.closed = True
        self.line.leave(self)


class DirectLine:
    """A named line with at most two ends."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.ends: list[LineEnd] = []

    def other(self, end: LineEnd) -> LineEnd | None:
        """The end that is not ``end`` (None if there is none yet)."""
        return next((e for e in self.ends if e is not end), None)

    def leave(self, end: LineEnd) -> None:
        with _lock:
            if end in self.ends:
                self.ends.remove(end)
            if not self.ends and _lines.get(self.name) is self:
                del _lines[self.name]


_lines: dict[str, DirectLine] = {}
_lock = threading.Lock()


def open_end(url_or_name: str) -> LineEnd:
    """A new end of the line ``chcos-direct://NAME`` (or NAME). Raises OSError when the line
    has two ends already."""
    name = url_or_name.removeprefix(SCHEME)
    with _lock:
        line = _lines.setdefault(name, DirectLine(name))
        if len(line.ends) >= 2:
            raise OSError(f"direct serial line {name!r} has two ends already")
        end = LineEnd(line)
        line.ends.append(end)
    return end
