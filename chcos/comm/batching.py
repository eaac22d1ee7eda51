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

A saturated kernel (one that spent less than :data:`BUSY_IDLE_SHARE` of a whole batch delay
idle) sends its newest-wins batches every :data:`BUSY_BATCH_DELAY` instead, and while it stays
saturated the delay doubles with each batch up to :data:`BUSY_BATCH_DELAY_MAX`, until it idles
longer again. A kernel waiting now and then for a timer due within microseconds (a sensor
sampled faster than it is served) is as saturated as one that never waits. Why: every batch
wakes several threads on both satellites (Zenoh's sender, its receiver, the thread that hands
the batch to the peer's kernel), each of which takes the CPU, and Python's GIL, from a kernel
that has no time to spare; the peer's thread waits for the GIL and forces a switch. At a put
per millisecond a saturated pair of satellites spent half their time on these hand-overs, at
one per 5 ms about a sixth (tools/bench_satellites; the README's performance notes give what
is left). Messages that must arrive keep BATCH_DELAY; messages at EXPRESS_FROM and above are
never batched. On virtual time, where the kernel's idle waits take no time, going idle ends
the saturation.
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
#: the newest-wins batch delay of a kernel found saturated (see the module doc): as long as
#: the interpreter's switch interval (sys.getswitchinterval), the longest a thread waiting for
#: the GIL of a busy process waits anyway
BUSY_BATCH_DELAY = 0.005
#: the longest it grows to while the kernel stays saturated: the oldest a newest-wins value
#: from a saturated satellite gets on the link
BUSY_BATCH_DELAY_MAX = 0.02
#: a kernel idle for less than this share of a batch delay (the wake-up included) is busy; one
#: that has been idle longer than this share of BATCH_DELAY since is not busy any more
BUSY_IDLE_SHARE = 0.25

#: (destination key, droppable, newest wins)
Slot = tuple[str, bool, bool]


class Batches:
    """The waiting batches of one communications manager (kernel thread only). A failed
    publish is logged and handed to ``on_error`` (the manager collects it for ``check()``)."""

    def __init__(self, kernel: Scheduler, transport: LinkTransport,
                 on_error: Callable[[str], None],
                 encode_later: Callable[[Any], bytes | None] | None = None) -> None:
        self.kernel = kernel
        self.transport = transport
        self.on_error = on_error
        self.encode_later = encode_later
        # a batch maps a link id (newest-wins sensory messages: a newer one replaces the
        # waiting one) or a unique negative number (everything else) to the encoded message,
        # or to what ``encode_later`` encodes when the batch leaves (None from it: nothing to
        # send, its caller has said why)
        self._batches: dict[Slot, dict[int, Any]] = {}
        self._prio: dict[Slot, int] = {}
        self._uniq = 0
        self._timer: Timer | None = None
        self._timer_long = False  # the armed timer is a busy kernel's (BUSY_BATCH_DELAY)
        self._armed_at = 0.0      # when the timer was armed, and the kernel's idle time then
        self._armed_idle = 0.0
        self._idle_mark = 0.0     # the kernel's idle time when the last timer fired
        self._busy_delay = BUSY_BATCH_DELAY   # the next long timer's delay
        #: the kernel was saturated during the last batch delay (see the module doc)
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
            if self.busy and (self.kernel.idle_time - self._idle_mark
                              >= BATCH_DELAY * BUSY_IDLE_SHARE):
                self.busy = False  # it has been idle for a while since the last batch left
                self._busy_delay = BUSY_BATCH_DELAY
            self._arm(newest_wins and self.busy)
        elif self._timer_long and not newest_wins:  # must arrive: not after a busy delay
            self._timer.cancel()
            self._arm(False)

    def withdraw(self, key: str, lid: int) -> Any:
        """Take link ``lid``'s waiting newest-wins message out of its batch to ``key`` (what
        :meth:`add` was given; None if there is none)."""
        batch = self._batches.get((key, True, True))
        return None if batch is None else batch.pop(lid, None)

    def _arm(self, long: bool) -> None:
        self._timer_long = long
        self._armed_at = self.kernel.clock.now()
        self._armed_idle = self.kernel.idle_time
        self._timer = self.kernel.call_later(self._busy_delay if long else BATCH_DELAY,
                                             self._on_timer)

    def _on_timer(self) -> None:
        """The batch delay is over: send everything. A kernel that was idle for less than
        BUSY_IDLE_SHARE of it is busy: its next newest-wins batches wait BUSY_BATCH_DELAY, or
        twice the last busy delay (up to BUSY_BATCH_DELAY_MAX) if this one was busy too."""
        self._timer = None
        idle = self._idle_mark = self.kernel.idle_time
        span = self.kernel.clock.now() - self._armed_at
        self.busy = idle - self._armed_idle < span * BUSY_IDLE_SHARE
        if not self.busy:
            self._busy_delay = BUSY_BATCH_DELAY
        elif self._timer_long:
            self._busy_delay = min(self._busy_delay * 2, BUSY_BATCH_DELAY_MAX)
        self.flush()

    def on_idle(self) -> None:
        """Kernel idle hook: send the batches of messages that must arrive now; newest-wins
        sensory batches wait for the batch timer (real time only)."""
        if not self._batches:
            return
        if self.kernel.clock.virtual:
            self.busy = False   # (idle_time counts real time only)
            self._busy_delay = BUSY_BATCH_DELAY
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
        items: list[bytes] = []
        for d in batch.values():
            data = d if type(d) is bytes or later is None else later(d)
            if data is not None:
                items.append(data)
        if not items:
            return
        try:
            self.transport.publish(key, encode_batch(items), priority=prio, kind=kind)
        except LinkError as exc:
            text = f"batch of {len(batch)} message(s) to {key} lost: {exc}"
            log.error("%s", text)
            self.on_error(text)
            return
        self.sent += 1
