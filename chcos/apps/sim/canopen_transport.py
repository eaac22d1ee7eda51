"""canopen_transport - a simulated CANopen node on a python-can bus: the only module of the
simulated node that touches python-can or starts a thread.

:class:`BusTransport` opens the bus, hands every received frame to the node (a function that
returns the frames to answer with) on a receiving thread of its own and sends what the node
gives it. On python-can's ``virtual`` interface the thread takes frames straight from the bus's
queue and marks each done (``task_done``), so that :meth:`BusTransport.settle` can wait until
every frame sent to the node so far has been handled and answered: the kernel settles a
simulated node so before virtual time moves on (:meth:`chcos.kernel.scheduler.Kernel.settle`);
there the thread blocks on the queue with no timeout and is woken to stop by a marker frame.
:meth:`BusTransport.periodic` sends a real-time node's heartbeat with python-can's periodic send
(on SocketCAN the kernel's broadcast manager: timed by the kernel, on due times, unaffected by
the load of the process); a node on virtual time has none (its own timers, advanced by its
owner, send it).
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable
from typing import Any

import can

from chcos.errors import BusError
from drivers.codecs.can import CanFrame

log = logging.getLogger("chcos.apps.sim.canopen_transport")

#: A node's receive side: one received frame in, the frames to send back out.
Handler = Callable[[can.Message], list[CanFrame]]

#: Seconds a receiving thread on a real interface waits for a frame before it looks whether it
#: must stop (real time only: on ``virtual`` the thread is woken by a marker frame).
POLL = 0.05


class BusTransport:
    """A node's python-can bus and its receiving thread (see the module doc). ``bus_args`` are
    python-can's (``interface``, ``channel``, ...). Raises :class:`BusError` naming the bus if
    it cannot be opened."""

    def __init__(self, bus_args: dict[str, Any], handler: Handler, name: str) -> None:
        try:
            self._bus: Any = can.Bus(**bus_args)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise BusError(f"{name}: cannot open CAN bus {bus_args}: {exc}") from exc
        self._handler = handler
        self._queue: Any = getattr(self._bus, "queue", None)  # python-can's virtual bus
        self._stop_marker = can.Message(arbitration_id=0x7FF, is_remote_frame=True)
        self._running = True
        self._send_lock = threading.Lock()
        self._periodic: Any = None
        self._thread = threading.Thread(target=self._loop, name=f"{name}-rx", daemon=True)
        #: frames handled so far (error and remote frames included, as ignored)
        self.handled = 0
        self._thread.start()

    def send(self, frame: CanFrame) -> None:
        """Put ``frame`` on the bus. A send error (a full queue at shutdown) is not fatal: the
        node sends again on its next change or timer."""
        msg = can.Message(arbitration_id=frame.arbitration_id, data=frame.data,
                          is_extended_id=frame.is_extended_id)
        with self._send_lock, contextlib.suppress(can.CanError, OSError, ValueError):
            self._bus.send(msg)

    def periodic(self, frame: CanFrame, period: float) -> None:
        """Send ``frame`` every ``period`` seconds from now on (the first at once), replacing
        the periodic frame there was; a period of 0 or less stops it. A bus that refuses is not
        fatal (a stopped node sends nothing anyway)."""
        self.stop_periodic()
        if period <= 0:
            return
        msg = can.Message(arbitration_id=frame.arbitration_id, data=frame.data,
                          is_extended_id=frame.is_extended_id)
        with contextlib.suppress(can.CanError, OSError, ValueError):
            self._periodic = self._bus.send_periodic(msg, period, store_task=False)

    def modify_periodic(self, frame: CanFrame) -> None:
        """New data for the periodic frame, its timing kept (nothing if none runs)."""
        task = self._periodic
        if task is not None:
            msg = can.Message(arbitration_id=frame.arbitration_id, data=frame.data,
                              is_extended_id=frame.is_extended_id)
            with contextlib.suppress(can.CanError, OSError, ValueError):
                task.modify_data(msg)

    def stop_periodic(self) -> None:
        """Stop the periodic frame, if one runs."""
        task, self._periodic = self._periodic, None
        if task is not None:
            with contextlib.suppress(Exception):
                task.stop()

    def close(self) -> None:
        """End the thread, wait for it (not from the thread itself) and shut the bus down.
        Idempotent; never raises."""
        self.stop_periodic()
        self._running = False
        if self._queue is not None:
            self._queue.put(self._stop_marker)
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        with contextlib.suppress(Exception):  # the bus is going away anyway
            self._bus.shutdown()

    def settle(self, timeout: float) -> bool:
        """True once every frame put on the node's queue so far has been handled (``virtual``
        only; True at once elsewhere); False if ``timeout`` wall seconds passed first or the
        thread has ended with frames left."""
        if self._queue is None:
            return True
        done = self._queue.all_tasks_done
        with done:
            return bool(done.wait_for(lambda: self._queue.unfinished_tasks == 0
                                      or not self._thread.is_alive(), timeout)) \
                and self._queue.unfinished_tasks == 0

    def activity(self) -> int:
        """Frames put on the node's queue so far plus frames handled so far (0 off
        ``virtual``): it grows when something is sent to the node and when the node is done."""
        if self._queue is None:
            return 0
        queued: int = self._queue.unfinished_tasks
        return 2 * self.handled + queued   # (queued + handled) + handled

    def _next(self) -> can.Message | None:
        msg: can.Message | None = self._queue.get() if self._queue is not None \
            else self._bus.recv(POLL)      # on virtual: woken to stop by the marker frame
        return msg

    def _loop(self) -> None:
        while self._running:
            try:
                msg = self._next()
            except (can.CanError, OSError, ValueError):
                return   # the bus was shut down under it
            if msg is None:
                continue
            try:
                if msg is not self._stop_marker and not (msg.is_error_frame
                                                         or msg.is_remote_frame):
                    for frame in self._handler(msg):
                        self.send(frame)
            except Exception:   # as canopen's listener: a failing handler drops one frame
                log.exception("simulated CANopen node: handling frame 0x%X failed",
                              msg.arbitration_id)
            finally:
                self.handled += 1
                if self._queue is not None:
                    self._queue.task_done()
