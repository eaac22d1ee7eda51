"""canbus - python-can plumbing shared by the ``can`` and ``canopen`` drivers: the bus
configuration, the reader thread's receive loop (event-driven where the interface allows it) and
the SocketCAN overrun count.
"""

from __future__ import annotations

import functools
import queue
import socket
import struct
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

import can

from chcos.errors import BusError
from drivers.threaded import ReaderThread


def bus_config(options: Mapping[str, Any]) -> dict[str, Any]:
    """python-can's configuration for this bus: the map's options over ``can.util.load_config``.

    Raises :class:`BusError` if python-can's configuration names no usable interface."""
    given = {k: options[k] for k in ("interface", "channel", "bitrate", "fd", "port")
             if k in options}  # port: udp_multicast's UDP port (one group and port per bus)
    try:
        cfg = dict(can.util.load_config(config=given))
    except (can.CanInterfaceNotImplementedError, ValueError, TypeError) as exc:
        raise BusError(f"python-can configuration: {exc}") from exc
    if cfg.get("channel") is None:
        raise BusError("python-can configuration gives no channel (set channel or CAN_CHANNEL)")
    return cfg


def bus_fileno(bus: can.BusABC) -> int | None:
    """The bus's file descriptor if its interface has one (SocketCAN), else None."""
    try:
        fd = bus.fileno()
    except (NotImplementedError, OSError, AttributeError):
        return None
    return fd if isinstance(fd, int) and fd >= 0 else None


def _readiness(rx: ReaderThread, bus: can.BusABC) -> Callable[[float], bool] | None:
    """How the reader can wait until a frame is there without taking it: ``select`` on the
    bus's file descriptor (SocketCAN), or the receive queue of python-can's ``virtual``
    interface; None for interfaces with neither (then the reader polls)."""
    fd = bus_fileno(bus)
    if fd is not None:
        return functools.partial(rx.wait_readable, fd)
    q = getattr(bus, "queue", None)
    if isinstance(q, queue.Queue):
        items, cond = q.queue, q.not_empty   # the queue's deque and its own condition

        def wait(timeout: float) -> bool:
            if items:
                return True
            with cond:
                if not items:
                    cond.wait(timeout)
                return bool(items)
        return wait
    return None


def _queued(bus: can.BusABC) -> deque[can.Message] | None:
    """The frames python-can's ``virtual`` interface holds for ``bus`` (its receive queue's
    deque: a glance tells whether a receive would find one), or None for other interfaces."""
    q = getattr(bus, "queue", None)
    return q.queue if isinstance(q, queue.Queue) else None


SO_MEMINFO = 55          # Linux <asm-generic/socket.h>: the socket's memory info, u32[9]
SK_MEMINFO_DROPS = 8     # ... whose last entry is sk_drops, the frames the kernel dropped


def socket_drops(sock: Any) -> int | None:
    """How many packets the kernel dropped on ``sock`` because its receive buffer was full (the
    count ``SO_RXQ_OVFL`` reports), or None where the OS does not tell."""
    try:
        raw = sock.getsockopt(socket.SOL_SOCKET, SO_MEMINFO, 4 * (SK_MEMINFO_DROPS + 1))
    except (OSError, AttributeError, TypeError):
        return None
    if not isinstance(raw, bytes) or len(raw) < 4 * (SK_MEMINFO_DROPS + 1):
        return None
    return int(struct.unpack_from(f"={SK_MEMINFO_DROPS + 1}I", raw)[SK_MEMINFO_DROPS])


def read_frames(rx: ReaderThread, bus: can.BusABC, poll: float,
                on_frame: Callable[[can.Message], None], on_error: Callable[[str], None],
                after_drain: Callable[[], None] | None = None,
                end_batch: Callable[[], None] | None = None) -> None:
    """The read loop of a CAN driver's :class:`ReaderThread`: every frame received goes to
    ``on_frame`` (which must not raise), a receive error to ``on_error`` (then a pause of 0.1 s).
    Where it can wait for a frame without taking it (SocketCAN's file descriptor, the
    ``virtual`` interface's queue) it drains without blocking under the reader's lock, and the
    reader's settle drains itself; elsewhere it receives with timeout ``poll`` and reports empty
    receives (see :mod:`drivers.threaded`). ``after_drain`` runs after each batch drained (the
    CAN driver reads the socket's drop count there). ``end_batch`` runs after the frames
    taken together - each drain, the settle's too, or each frame where the loop polls - so that
    ``on_frame`` may collect what it hands on and hand it on there, once per batch."""
    wait = _readiness(rx, bus)
    if wait is None:
        while rx.running:
            try:
                frame = bus.recv(poll)
            except (can.CanError, OSError) as exc:
                on_error(str(exc))
                rx.pause(0.1)
                continue
            if frame is None:
                rx.idle()
            else:
                on_frame(frame)
                if end_batch is not None:
                    end_batch()
        return

    items = _queued(bus)

    def drain(limit: int = 0) -> bool:
        n = 0
        try:
            while limit <= 0 or n < limit:
                if items is not None and not items:   # nothing queued: spare the empty
                    break                             # receive (python-can raises Empty)
                try:
                    frame = bus.recv(0)
                except (can.CanError, OSError) as exc:
                    on_error(str(exc))
                    return False
                if frame is None:
                    break
                n += 1
                on_frame(frame)
            return True
        finally:
            if end_batch is not None and n:
                end_batch()

    rx.set_drain(drain)
    while rx.running:
        if wait(0.05):
            with rx.lock:
                ok = drain(64)
                if after_drain is not None:
                    after_drain()
            if not ok:
                rx.pause(0.1)
