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
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from chcos.comm.codec import MessageKind, encode_batch
from chcos.comm.ports import LinkTransport, Scheduler
from chcos.errors import LinkError
from chcos.kernel.scheduler import Timer

log = logging.getLogger("chcos.comm.manager")

BATCH_MAX = 64
BATCH_DELAY = 0.001

#: (destination key, droppable, newest wins)
Slot = tuple[str, bool, bool]


class Batches:
    """The waiting batches of one communications manager (kernel thread only). A failed
    publish is logged and handed to ``on_error`` (the manager collects it for ``check()``)."""

    def __init__(self, kernel: Scheduler, transport: LinkTransport,
                 on_error: Callable[[str], None]) -> None:
        self.kernel = kernel
        self.transport = transport
        self.on_error = on_error
        # a batch maps a link id (newest-wins sensory messages: a newer one replaces the
        # waiting one) or a unique negative number (everything else) to the encoded message
        self._batches: dict[Slot, dict[int, bytes]] = {}
        self._prio: dict[Slot, int] = {}
        self._uniq = 0
        self._timer: Timer | None = None
        self.sent = 0
        self.coalesced = 0

    def add(self, key: str, drop: bool, newest_wins: bool, lid: int, data: bytes,
            priority: int) -> None:
        """Queue one encoded message for ``key``; sends the batch when it is full."""
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
            self._timer = self.kernel.call_later(BATCH_DELAY, self.flush)

    def on_idle(self) -> None:
        """Kernel idle hook: send the batches of messages that must arrive now; newest-wins
        sensory batches wait for the batch timer (real time only)."""
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
        try:
            self.transport.publish(key, encode_batch(list(batch.values())), priority=prio,
                                   kind=kind)
        except LinkError as exc:
            text = f"batch of {len(batch)} message(s) to {key} lost: {exc}"
            log.error("%s", text)
            self.on_error(text)
            return
        self.sent += 1
