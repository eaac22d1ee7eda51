"""canbus - python-can plumbing shared by the ``can`` and ``canopen`` drivers: the bus
configuration, receive filters from a set of ids (:func:`can_filters`), id sets and ranges from a
map (:func:`parse_ids`), the reader thread's receive loop (event-driven where the interface allows
it), the SocketCAN overrun count, a frame's receive time on the kernel clock
(:func:`receive_time`) and rate-limited warnings (:class:`Tally`).
"""

from __future__ import annotations

import contextlib
import functools
import queue
import re
import socket
import struct
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import can
from can.interfaces.socketcan.constants import (
    CAN_EFF_FLAG,
    CAN_ERR_FLAG,
    CAN_RTR_FLAG,
    CANFD_BRS,
    CANFD_ESI,
    CANFD_MTU,
    SO_TIMESTAMPNS,
)
from can.interfaces.socketcan.socketcan import dissect_can_frame
from can.typechecking import CanFilter

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


#: Above this many ids of one frame format, :func:`can_filters` merges ids into id/mask pairs
#: (the kernel takes at most 512 filters per socket, CAN_RAW_FILTER_MAX; single-id filters are
#: looked up by id, masks are tried one by one).
FILTER_LIMIT = 256
SFF_MASK = 0x7FF
EFF_MASK = 0x1FFFFFFF
#: The filter of an empty id set: extended id 0x1FFFFFFF only (python-can takes an empty filter
#: list as "everything"; SocketCAN itself could say "nothing", python-can cannot).
NOTHING: CanFilter = {"can_id": EFF_MASK, "can_mask": EFF_MASK, "extended": True}


def _merge(groups: list[tuple[int, int]], width: int, limit: int) -> list[tuple[int, int]]:
    """``(id, mask)`` groups sorted by id, merged pairwise until at most ``limit`` remain: each
    step merges the two neighbours whose merged mask lets the fewest ids through (the bits
    where their ids differ are cleared from the mask)."""
    groups = list(groups)
    while len(groups) > max(1, limit):
        best, best_free = 0, width.bit_count() + 1
        for k in range(len(groups) - 1):
            (a, ma), (b, mb) = groups[k], groups[k + 1]
            free = (width & ~(ma & mb & ~(a ^ b))).bit_count()
            if free < best_free:
                best, best_free = k, free
        (a, ma), (b, mb) = groups[best], groups[best + 1]
        m = ma & mb & ~(a ^ b) & width
        groups[best:best + 2] = [(a & m, m)]
    return groups


def can_filters(standard: Iterable[int], extended: Iterable[int] = (),
                limit: int = FILTER_LIMIT) -> list[CanFilter]:
    """python-can ``can_filters`` that let through exactly the ``standard`` (11-bit) and
    ``extended`` (29-bit) ids given - on SocketCAN in the kernel, so no other frame reaches user
    space, elsewhere in python-can's ``recv`` - or, where one frame format has more than
    ``limit`` ids, id/mask pairs that let through those ids and as few others as a greedy merge
    of neighbouring ids finds (the driver then meets the others as ids of no device). Each
    filter names its frame format (``extended``). An empty set gives :data:`NOTHING`.

    Raises ValueError for an id outside its format's range. Used by the raw CAN driver (the
    map's ids) and meant for the CANopen driver (its nodes' COB-IDs)."""
    out: list[CanFilter] = []
    for ids, width, ext in ((standard, SFF_MASK, False), (extended, EFF_MASK, True)):
        uniq = sorted(set(ids))
        bad = [i for i in uniq if not 0 <= i <= width]
        if bad:
            raise ValueError(f"CAN id(s) {', '.join(hex(i) for i in bad)} outside "
                             f"0..0x{width:X} ({'extended' if ext else 'standard'})")
        groups = _merge([(i, width) for i in uniq], width, limit)
        out += [{"can_id": i, "can_mask": m, "extended": ext} for i, m in groups]
    return out or [NOTHING]


def filters_admit(filters: Iterable[CanFilter], can_id: int, extended: bool) -> bool:
    """Whether a frame with ``can_id`` passes ``filters`` (as SocketCAN and python-can judge)."""
    return any(f.get("extended", extended) == extended
               and can_id & f["can_mask"] == f["can_id"] & f["can_mask"] for f in filters)


_RANGE = re.compile(r"^\s*(0[xX][0-9a-fA-F]+|\d+)\s*(?:-\s*(0[xX][0-9a-fA-F]+|\d+)\s*)?$")


def parse_ids(value: Any, key: str, top: int = EFF_MASK) -> tuple[list[tuple[int, int]], list[str]]:
    """An id set from a map: a list of ids (integers) and ranges (strings ``"0x700-0x77F"``,
    ends included; a string may also be one id, ``"0x80"``). Returns the ranges (``(lo, hi)``)
    and the errors, each naming ``key`` and the item."""
    if not isinstance(value, list):
        return [], [f"{key}: expected a list of CAN ids and ranges such as "
                    f"[\"0x700-0x77F\", 0x80], got {value!r}"]
    ranges: list[tuple[int, int]] = []
    errs: list[str] = []
    for k, item in enumerate(value):
        lo = hi = None
        if isinstance(item, int) and not isinstance(item, bool):
            lo = hi = item
        elif isinstance(item, str) and (m := _RANGE.match(item)):
            lo = int(m.group(1), 0)
            hi = int(m.group(2), 0) if m.group(2) else lo
        if lo is None or hi is None or not 0 <= lo <= hi <= top:
            errs.append(f"{key}[{k}]: expected a CAN id 0..0x{top:X} or a range \"LO-HI\" "
                        f"with LO <= HI, got {item!r}")
            continue
        ranges.append((lo, hi))
    return ranges, errs


def in_ranges(can_id: int, ranges: Iterable[tuple[int, int]]) -> bool:
    """Whether ``can_id`` lies in one of ``ranges`` (``(lo, hi)``, ends included)."""
    return any(lo <= can_id <= hi for lo, hi in ranges)


def receive_time(frame_stamp: float, now: float, virtual: bool) -> float:
    """A frame's receive time on the kernel clock: ``now`` on a virtual clock (the frame's
    stamp is wall time, which a virtual clock does not follow); on the real clock ``now`` less
    the frame's age by the wall clock (``frame_stamp`` is python-can's ``Message.timestamp``:
    on SocketCAN the kernel's receive time stamp, SO_TIMESTAMPNS), never after ``now``."""
    if virtual or frame_stamp <= 0:
        return now
    return now - max(0.0, time.time() - frame_stamp)


class StampClock:
    """A frame's receive time on the host's (real) clock and its age, from the kernel's stamp
    (wall time) with one clock read per frame: the offset between the host's clock and the
    wall clock is measured again at most every ``refresh`` seconds (and whenever the wall
    clock went back), so a step of the wall clock misplaces receive times on the host's clock
    for that long at most; the age itself (wall clock now less the stamp) is exact. On
    SocketCAN under load each clock read is a system call on the reader's path."""

    def __init__(self, now: Callable[[], float], refresh: float = 1.0) -> None:
        self._now = now
        self.refresh = refresh
        self._offset = 0.0
        self._measured = float("-inf")

    def place(self, frame_stamp: float) -> tuple[float, float]:
        """``(at, age)``: when the frame was received on the host's clock (never after now)
        and how old it is now; a frame without a stamp (``frame_stamp`` <= 0) is received
        now, age 0."""
        wall = time.time()
        if not 0 <= wall - self._measured < self.refresh:
            self._offset = self._now() - wall
            self._measured = wall
        age = max(0.0, wall - frame_stamp) if frame_stamp > 0 else 0.0
        return wall + self._offset - age, age


class Tally:
    """Rate-limited reports of recurring events (unknown ids on a shared wire): the first
    event of a kind is reported at once, the others counted and reported as one line per kind
    per ``period`` seconds (wall time, or the clock ``now`` gives) with their count and a few
    examples, at the next event after the period or at :meth:`flush`. ``report(kind, count,
    examples)`` does the reporting. Thread-safe."""

    def __init__(self, report: Callable[[str, int, list[str]], None], period: float = 10.0,
                 examples: int = 5, now: Callable[[], float] = time.monotonic) -> None:
        self._report = report
        #: the clock the period is counted on (wall time; a driver on virtual time gives its
        #: host's, so that no report depends on the machine's speed)
        self.now = now
        self.period = period
        self._examples = examples
        self._lock = threading.Lock()
        self._pending: Counter[str] = Counter()
        self._seen: dict[str, list[str]] = {}
        self._last: dict[str, float] = {}
        #: every event counted, per kind (reported or pending)
        self.total: Counter[str] = Counter()

    def add(self, kind: str, example: str, n: int = 1) -> None:
        """Count ``n`` events of ``kind``; report what is pending if the period has passed."""
        with self._lock:
            self.total[kind] += n
            self._pending[kind] += n
            seen = self._seen.setdefault(kind, [])
            if example not in seen:
                seen.append(example)
                del seen[:-self._examples]     # the newest few
            now = self.now()
            last = self._last.get(kind)
            if last is not None and now - last < self.period:
                return
            self._last[kind] = now
            n, ex = self._pending.pop(kind), self._seen.pop(kind, [])
        self._report(kind, n, ex)

    def flush(self) -> None:
        """Report every pending count now (at stop)."""
        with self._lock:
            items = [(k, n, self._seen.pop(k, [])) for k, n in self._pending.items() if n]
            self._pending.clear()
        for kind, n, ex in items:
            self._report(kind, n, ex)


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


SO_RXQ_OVFL = 40          # Linux <asm-generic/socket.h>: the drop count on each frame received
_TIMESTAMPNS = struct.Struct("@ll")
_DROPCOUNT = struct.Struct("=I")
_ANCILLARY = socket.CMSG_SPACE(_TIMESTAMPNS.size) + socket.CMSG_SPACE(_DROPCOUNT.size)


class SocketcanReceive:
    """Frames taken straight off a python-can SocketCAN bus's socket without waiting: one
    ``recvmsg(MSG_DONTWAIT)`` per frame (python-can's ``recv`` selects on the socket before
    each one, and an empty receive costs a second ``select``), the kernel's receive time stamp
    and the socket's drop count (``SO_RXQ_OVFL``) from each frame's ancillary data - so the
    reader learns about overruns without asking the socket after every batch. The frames are
    python-can ``Message`` objects as its own receive makes them. The bus's kernel filters
    apply as before (python-can's SocketCAN bus filters in the kernel only)."""

    def __init__(self, bus: can.BusABC) -> None:
        sock = getattr(bus, "socket", None)
        if not isinstance(sock, socket.socket):
            raise TypeError(f"not a SocketCAN bus: {bus!r}")
        self._sock = sock
        self._channel = str(getattr(bus, "channel", "") or "") or None
        #: the socket's drop count as of the last frame received (None before the first, or
        #: where the kernel does not add it)
        self.drops: int | None = None
        self._counted = False    # the kernel adds the count (only when not 0) to each frame
        with contextlib.suppress(OSError):   # else no drop count on the frames: the reader
            sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)             # asks the socket
            self._counted = True

    @staticmethod
    def usable(bus: can.BusABC) -> bool:
        """Whether ``bus`` is python-can's SocketCAN bus with its socket (raw receive works)."""
        return (type(bus).__name__ == "SocketcanBus"
                and isinstance(getattr(bus, "socket", None), socket.socket))

    def take(self) -> can.Message | None:
        """The next frame the socket holds, or None if it holds none now. Raises
        ``can.CanOperationError`` when the socket fails (the interface went down)."""
        try:
            cf, anc, msg_flags, _ = self._sock.recvmsg(CANFD_MTU, _ANCILLARY,
                                                      socket.MSG_DONTWAIT)
        except (BlockingIOError, InterruptedError):
            return None
        except OSError as exc:
            raise can.CanOperationError(f"Error receiving: {exc.strerror}", exc.errno) from exc
        stamp = 0.0
        if self._counted:
            self.drops = 0
        for level, kind, data in anc:
            if level != socket.SOL_SOCKET:
                continue
            if kind == SO_TIMESTAMPNS and len(data) >= _TIMESTAMPNS.size:
                sec, nsec = _TIMESTAMPNS.unpack_from(data)
                stamp = sec + nsec * 1e-9
            elif kind == SO_RXQ_OVFL and len(data) >= _DROPCOUNT.size:
                self.drops = _DROPCOUNT.unpack_from(data)[0]
        can_id, dlc, flags, payload = dissect_can_frame(cf)
        ext = bool(can_id & CAN_EFF_FLAG)
        fd = len(cf) == CANFD_MTU
        return can.Message(
            timestamp=stamp, channel=self._channel,
            arbitration_id=can_id & (EFF_MASK if ext else SFF_MASK), is_extended_id=ext,
            is_remote_frame=bool(can_id & CAN_RTR_FLAG), is_error_frame=bool(can_id & CAN_ERR_FLAG),
            is_fd=fd, is_rx=not msg_flags & socket.MSG_DONTROUTE,
            bitrate_switch=bool(flags & CANFD_BRS), error_state_indicator=bool(flags & CANFD_ESI),
            dlc=dlc, data=payload)


def read_frames(rx: ReaderThread, bus: can.BusABC, poll: float,
                on_frame: Callable[[can.Message], None], on_error: Callable[[str], None],
                after_drain: Callable[[], None] | None = None,
                end_batch: Callable[[], None] | None = None,
                receiver: SocketcanReceive | None = None) -> None:
    """The read loop of a CAN driver's :class:`ReaderThread`: every frame received goes to
    ``on_frame`` (which must not raise), a receive error to ``on_error`` (then a pause of 0.1 s).
    Where it can wait for a frame without taking it (SocketCAN's file descriptor, the
    ``virtual`` interface's queue) it drains without blocking under the reader's lock, and the
    reader's settle drains itself; elsewhere it receives with timeout ``poll`` and reports empty
    receives (see :mod:`drivers.threaded`). ``after_drain`` runs after each batch drained (the
    CAN driver reads the socket's drop count there). ``end_batch`` runs after the frames
    taken together - each drain, the settle's too, or each frame where the loop polls - so that
    ``on_frame`` may collect what it hands on and hand it on there, once per batch. With a
    ``receiver`` (SocketCAN) the drain takes the frames off the socket itself
    (:class:`SocketcanReceive`) instead of through python-can's ``recv``, and ``end_batch``
    also runs right after the first frame of each drain: a frame that came alone is handed on
    before the receive that finds the socket empty (the rest of a burst goes as one batch)."""
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
    take: Callable[[], can.Message | None] = functools.partial(bus.recv, 0)
    if receiver is not None:
        take = receiver.take
    early = end_batch if receiver is not None else None

    def drain(limit: int = 0) -> bool:
        n = tries = 0
        try:
            while limit <= 0 or tries < limit:
                if items is not None and not items:   # nothing queued: spare the empty
                    break                             # receive (python-can raises Empty)
                tries += 1
                try:
                    frame = take()
                except (can.CanError, OSError) as exc:
                    on_error(str(exc))
                    return False
                if frame is None:
                    if items:      # a frame python-can's own filters took out: go on
                        continue
                    break
                n += 1
                on_frame(frame)
                if n == 1 and early is not None:
                    early()         # the first frame goes at once: it may be alone, and
            return True             # finding out costs another receive
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
