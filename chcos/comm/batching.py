"""batching - the outgoing batches of the communications manager (newest wins on the way).

Messages below :data:`chcos.comm.codec.EXPRESS_FROM` wait in a batch per (destination key,
droppable, newest-wins) until it is sent: when it holds :data:`BATCH_MAX` messages,
:data:`BATCH_DELAY` seconds after its first message, and - for messages that must arrive
(commands, completions, queued links) - as soon as the kernel goes idle. Newest-wins sensory
messages wait for the delay on real time, so that a newer value on the same link replaces the
waiting one: a busy producer then costs one Zenoh put per BATCH_DELAY instead of one per
message (a put that wakes Zenoh's sender costs tens of microseconds, as much as a task step),
and the data is at most BATCH_DELAY older. On virtual time everything goes out when the kernel
goes idle.

A saturated kernel (one that did not go idle once during a whole batch delay) sends its
newest-wins batches every :data:`BUSY_BATCH_DELAY` instead, until it goes idle again. Each put
hands Python's GIL to whatever thread waits for it (the link's receiving thread among them)
and costs the kernel a thread wake-up to get it back, on this satellite and, for the batch
received, on the peer's: at a put per millisecond a saturated pair of satellites spent half
their time on these hand-overs (tools/bench_satellites). Messages that must arrive keep
BATCH_DELAY.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from chcos.comm.codec import MessageKind, encode_batch
from chcos.comm.ports import LinkTransport, Scheduler
from chcos.errors import LinkError
from chcos.kernel.scheduler import Timer

log = logging.getLogger("chcos.comm.manager")

BATCH_MAX = 64
BATCH_DELAY = 0.001
#: the newest-wins batch delay of a saturated kernel (see the module doc): as long as the
#: interpreter's switch interval (sys.getswitchinterval), the longest a thread waiting for the
#: GIL of a busy process waits anyway
BUSY_BATCH_DELAY = 0.005

#: (destination key, droppable, newest wins)
Slot = tuple[str, bool, bool]


class Batches:
    """The waiting batches of one communications manager (kernel thread only). A failed
    publish is logged and handed to ``on_error`` (the manager collects it for ``check()``)."""

    def __init__(self, kernel: Scheduler, transport: LinkTransport,
                 on_error: Callable[[str], None],
                 encode_later: Callable[[Any], bytes] | None = None) -> None:
        self.kernel = kernel
        self.transport = transport
        self.on_error = on_error
        self.encode_later = encode_later
        # a batch maps a link id (newest-wins sensory messages: a newer one replaces the
        # waiting one) or a unique negative number (everything else) to the encoded message,
        # or to what ``encode_later`` encodes when the batch leaves
        self._batches: dict[Slot, dict[int, Any]] = {}
        self._prio: dict[Slot, int] = {}
        self._uniq = 0
        self._timer: Timer | None = None
        self._timer_long = False  # the armed timer is a busy kernel's (BUSY_BATCH_DELAY)
        self._idled = True        # the kernel went idle since the timer was armed
        #: the kernel did not go idle during the last batch delay (see the module doc)
        self.busy = False
        self.sent = 0
        self.coalesced = 0

    def add(self, key: str, drop: bool, newest_wins: bool, lid: int, data: Any,
            priority: int) -> None:
        """Queue one message for ``key``: its encoded bytes, or anything else, which
        ``encode_later`` encodes if it is still there when the batch leaves. Sends the batch
        when it is full."""
        slot = (key, drop, newest_wins)
        batch = self._batches.get(slot)
        if batch is None:
            batch = self._batches[slot] = {}
        if newest_wins:
            if batch.pop(lid, None) is not None:
                self.coalesced += 1
            batch[lid] = data
        else:
            self._uniq -= 1
            batch[self._uniq] = data
        self._prio[slot] = max(priority, self._prio.get(slot, 0))
        if len(batch) >= BATCH_MAX:
            self._flush_slot(slot)
        elif self._timer is None:
            self._arm(newest_wins and self.busy)
        elif self._timer_long and not newest_wins:  # must arrive: not after a busy delay
            self._timer.cancel()
            self._arm(False)

    def _arm(self, long: bool) -> None:
        self._timer_long = long
        self._idled = False
        self._timer = self.kernel.call_later(BUSY_BATCH_DELAY if long else BATCH_DELAY,
                                             self._on_timer)

    def _on_timer(self) -> None:
        """The batch delay is over: send everything; a kernel that did not go idle meanwhile
        is busy (its next newest-wins batches wait BUSY_BATCH_DELAY)."""
        self._timer = None
        self.busy = not self._idled
        self.flush()

    def on_idle(self) -> None:
        """Kernel idle hook: send the batches of messages that must arrive now; newest-wins
        sensory batches wait for the batch timer (real time only)."""
        self._idled = True
        self.busy = False
        if not self._batches:
            return
        if self.kernel.clock.virtual:
            self.flush()
            return
        for slot in [sl for sl in self._batches if not sl[2]]:
            self._flush_slot(slot)

    def flush(self) -> None:
        """Send every waiting batch."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        for slot in list(self._batches):
            self._flush_slot(slot)

    def _flush_slot(self, slot: Slot) -> None:
        batch = self._batches.pop(slot, None)
        prio = self._prio.pop(slot, 0)
        if not batch:
            return
        key, drop, _newest = slot
        kind = MessageKind.SENSORY if drop else MessageKind.COMMAND  # congestion: drop or block
        later = self.encode_later
        try:
            items = [d if type(d) is bytes or later is None else later(d)
                     for d in batch.values()]
            self.transport.publish(key, encode_batch(items), priority=prio, kind=kind)
        except LinkError as exc:
            text = f"batch of {len(batch)} message(s) to {key} lost: {exc}"
            log.error("%s", text)
            self.on_error(text)
            return
        self.sent += 1
