"""manager - the communications manager: messages between satellites, over the Zenoh link.

A satellite's message manager hands this layer every message whose destination lives on another
satellite (sensory messages, exception taps, topen/tclose, completion and pre-emption reports,
actuator commands, device status, the emergency stop, world-model queries and their answers).
Each goes out as one :class:`chcos.comm.codec.LinkMessage` carrying its link id and priority, to
the key of the destination machine. Incoming messages arrive on Zenoh's threads and are handed
to the kernel as interrupts (thesis 6.1.2: an incoming message readies TSK0), so the tables are
only ever touched on the kernel thread. Link ids agree across satellites because every satellite
applies the same install log in the same order.

Newest wins across the link as inside one satellite: a sensory message on a newest-wins link
(not queued, not a tap) that is still waiting in its batch when a newer one on the same link is
sent is replaced by it, so a busy producer costs the link no more than its consumer can use.
Sequence numbers count per link, so the receiving satellite sees how many messages were
superseded on the way (a gap) and counts them as sent and overwritten on its copy of the link:
``msgstat`` keeps sent = delivered + overwritten + unread on the destination's satellite.

Keys, under ``chcos/<system>``: ``m/<N>/msg`` (messages to machine N), ``all/msg`` (broadcast:
estop, device status), ``alive/<N>`` (liveliness tokens). Only payloads sealed by the satellite
role are accepted on the message keys (a host cannot set device values, write actuators, forge
statuses or e-stop through them). A malformed or refused message is counted by cause and logged
at most once per cause per interval (:attr:`CommManager.rejected`); actuator values must match
the actuator's type (a number where the safe value or limits are numbers) and be finite.
"""

from __future__ import annotations

import logging
import math
import time
from typing import TYPE_CHECKING, Any

from chcos.comm.codec import LinkMessage, MessageKind, decode_batch, encode, encode_batch
from chcos.comm.secret import Throttle
from chcos.comm.transport import EXPRESS_FROM, Subscription, Transport
from chcos.devices.entry import DeviceStatus
from chcos.errors import LinkError, MessageError
from chcos.kernel.scheduler import Timer
from chcos.tables.messages import TOP_PRIORITY, Link, LinkStatus

if TYPE_CHECKING:
    from chcos.system.embedded import System
    from chcos.tables.tasks import TaskEntry

log = logging.getLogger("chcos.comm.manager")

#: A batch goes out when it holds this many messages, or BATCH_DELAY seconds after its first
#: message; a batch of messages that must arrive (commands, completions, queued links) also as
#: soon as the kernel goes idle. Newest-wins sensory messages wait for the delay on real time, so
#: that newer values on the same link replace them on the way: a busy producer then costs one
#: Zenoh put per BATCH_DELAY instead of one per message (a put that wakes Zenoh's sender costs
#: tens of microseconds, as much as a task step), and the data is at most BATCH_DELAY older.
BATCH_MAX = 64
BATCH_DELAY = 0.001
#: The roles that may send on the message keys.
SATELLITES = frozenset({"satellite"})
_STATUSES = tuple(st.value for st in DeviceStatus)


def check_actuator_value(device: str, safe: Any, limits: tuple[Any, Any], value: Any) -> None:
    """Refuse an actuator command from the link whose type does not fit the actuator: a number
    (int or float, finite; bool only where the safe value is a bool) where the safe value or a
    limit is a number. Raises MessageError naming the device and the value."""
    numeric = any(isinstance(x, int | float) and not isinstance(x, bool)
                  for x in (safe, *limits))
    if isinstance(safe, bool):
        if not isinstance(value, bool):
            raise MessageError(f"actuator {device}: expected true or false, got {value!r:.80}")
    elif numeric:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise MessageError(f"actuator {device}: expected a number, got "
                               f"{type(value).__name__} {value!r:.80}")
        if not math.isfinite(value):
            raise MessageError(f"actuator {device}: expected a finite number, got {value!r}")


def machine_of(token_key: str) -> int | None:
    """The machine number of a satellite's liveliness token key (``.../alive/<N>``), or None
    for a key that does not end in a number."""
    tail = token_key.rsplit("/", 1)[-1]
    return int(tail) if tail.isdigit() else None


class CommManager:
    """The link between one satellite (machine ``machine``) and all the others."""

    def __init__(self, system: System, transport: Transport, prefix: str, machine: int) -> None:
        self.sys = system
        self.transport = transport
        self.prefix = prefix
        self.machine = machine
        self._seq: dict[int, int] = {}       # outgoing: last sequence number per link id
        self._seen: dict[int, int] = {}      # incoming: last sequence number per link id
        self._uniq = 0
        self._subs: list[Subscription] = []
        self.received = 0
        self.sent = 0
        self.errors: list[str] = []
        self.rejected = Throttle(log)
        self.alive: set[int] = {machine}
        # messages below EXPRESS_FROM wait in a batch per (destination key, droppable,
        # newest-wins) until it is sent (see BATCH_DELAY). A batch maps a link id (newest-wins
        # sensory messages: a newer one replaces the waiting one) or a unique negative number
        # (everything else) to the encoded message.
        self._batches: dict[tuple[str, bool, bool], dict[int, bytes]] = {}
        self._batch_prio: dict[tuple[str, bool, bool], int] = {}
        self._flush_timer: Timer | None = None
        self.batches_sent = 0
        self.coalesced = 0
        self.superseded = 0
        system.msgmgr.comm = self      # the link replaces the one-process NoComm
        system.devtab.remote = self
        system.kernel.add_idle_hook(self._on_idle)

    # ---- keys -------------------------------------------------------------------------------
    def key(self, machine: int) -> str:
        """The message key of ``machine``."""
        return f"{self.prefix}/m/{machine}/msg"

    def start(self) -> None:
        """Subscribe to this machine's messages and the broadcasts and watch the other
        satellites come and go. Raises LinkError if Zenoh refuses."""
        t = self.transport
        self._subs.append(t.subscribe(self.key(self.machine), self._incoming, roles=SATELLITES))
        self._subs.append(t.subscribe(f"{self.prefix}/all/msg", self._incoming,
                                      roles=SATELLITES))
        self._subs.append(t.watch(f"{self.prefix}/alive/*", self._joined, self._left))

    def announce(self) -> None:
        """Declare this satellite alive. Call it last, once everything it serves is declared:
        one session's declarations reach the others in order, so whoever sees the token can
        also reach the servers."""
        self._subs.append(self.transport.announce(f"{self.prefix}/alive/{self.machine}"))

    def stop(self) -> None:
        """Withdraw from the link (the other satellites see this one leave)."""
        for sub in reversed(self._subs):
            sub.close()
        self._subs.clear()

    # ---- outgoing (kernel thread) -----------------------------------------------------------
    def _send(self, machine: int | None, kind: MessageKind, src: str, dst: str, lid: int,
              priority: int, value: Any, queued: bool = False,
              newest_wins: bool = False) -> None:
        seq = self._seq.get(lid, 0) + 1
        self._seq[lid] = seq
        msg = LinkMessage(kind, src, dst, lid, priority, seq, time.time_ns(), value)
        key = f"{self.prefix}/all/msg" if machine is None else self.key(machine)
        drop = kind.droppable and not queued      # a queued link's messages must all arrive
        try:
            data = encode(msg)
            self.sent += 1
            if priority >= EXPRESS_FROM:  # urgent: out at once, on its own
                self.transport.publish(key, data, priority=priority,
                                       kind=MessageKind.SENSORY if drop else MessageKind.COMMAND)
                return
        except LinkError as exc:
            raise MessageError(f"cannot send {kind.name.lower()} {src}->{dst} to machine "
                               f"{machine}: {exc}") from exc
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
        self._batch_prio[slot] = max(priority, self._batch_prio.get(slot, 0))
        if len(batch) >= BATCH_MAX:
            self._flush_slot(slot)
        elif self._flush_timer is None:
            self._flush_timer = self.sys.kernel.call_later(BATCH_DELAY, self.flush)

    def _on_idle(self) -> None:
        """Kernel idle hook: send the batches of messages that must arrive (commands, queued
        links, completions) now; newest-wins sensory batches wait for the batch timer (real
        time only), so that newer values on the same links replace them on the way."""
        if not self._batches:
            return
        if self.sys.kernel.clock.virtual:
            self.flush()
            return
        for slot in [sl for sl in self._batches if not sl[2]]:
            self._flush_slot(slot)

    def flush(self) -> None:
        """Send every waiting batch (kernel thread; BATCH_DELAY after a batch was started, and
        when the kernel goes idle on virtual time)."""
        if self._flush_timer is not None:
            self._flush_timer.cancel()
            self._flush_timer = None
        for slot in list(self._batches):
            self._flush_slot(slot)

    def _flush_slot(self, slot: tuple[str, bool, bool]) -> None:
        batch = self._batches.pop(slot, None)
        prio = self._batch_prio.pop(slot, 0)
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
            self.errors.append(text)
            return
        self.batches_sent += 1

    def sensory(self, link: Link, value: Any) -> None:
        """A sensory message to a task on another satellite."""
        self._send(link.dst_machine, MessageKind.SENSORY, link.src, link.dst, link.lid,
                   link.priority, value, queued=bool(link.queued),
                   newest_wins=not link.queued and not link.tap)

    def tap(self, link: Link, source: str, value: Any) -> None:
        """A tapped sensory message to an exception task on another satellite."""
        self._send(link.dst_machine, MessageKind.SENSORY, source, link.dst, link.lid,
                   link.priority, value)

    def open(self, link: Link, command: Any, wait: bool) -> None:
        """topen of a task on another satellite."""
        self._send(link.dst_machine, MessageKind.COMMAND, link.src, link.dst, link.lid,
                   link.priority, {"op": "open", "command": command, "wait": wait})

    def close(self, link: Link) -> None:
        """tclose of a task on another satellite."""
        self._send(link.dst_machine, MessageKind.COMMAND, link.src, link.dst, link.lid,
                   link.priority, {"op": "close"})

    def report(self, link: Link) -> None:
        """A completion or pre-emption on ``link`` to its caller's satellite."""
        kind = (MessageKind.PREEMPTION if link.status is LinkStatus.PREEMPTED
                else MessageKind.COMPLETION)
        self._send(link.src_machine, kind, link.src, link.dst, link.lid, link.priority,
                   {"status": link.status.value, "result": link.result, "error": link.error})

    def granted(self, link: Link) -> None:
        """The caller of ``link`` (on another satellite) now owns the target."""
        self._send(link.src_machine, MessageKind.REPLY, link.src, link.dst, link.lid,
                   link.priority, {"op": "open", "answer": "owner"})

    def actuator(self, device: str, machine: int, value: Any, source: str) -> None:
        """An actuator command to the device's satellite."""
        self._send(machine, MessageKind.COMMAND, source, device, 0, TOP_PRIORITY - 1,
                   {"op": "actuator", "device": device, "value": value})

    def device_status(self, device: str, status: DeviceStatus, reason: str) -> None:
        """A local device changed status: tell everybody."""
        self._send(None, MessageKind.STATUS, "", device, 0, TOP_PRIORITY - 1,
                   {"device": device, "status": status.value, "reason": reason,
                    "from": self.machine})

    def estop(self, reason: str) -> None:
        """Emergency stop everywhere, at top priority, sent express."""
        self._send(None, MessageKind.COMMAND, "", "", 0, TOP_PRIORITY,
                   {"op": "estop", "reason": reason, "from": self.machine})

    def is_up(self, machine: int) -> bool:
        """Whether satellite ``machine`` is on the link now (its liveliness token is seen)."""
        return machine in self.alive

    def query(self, link: Link, asker: TaskEntry, peer: TaskEntry, qid: int, topic: str,
              args: list[Any]) -> None:
        """A world-model query of ``asker`` to ``peer`` on another satellite, at the priority
        ``asker`` runs at. Raises MessageError if it cannot be encoded."""
        self._send(peer.machine, MessageKind.QUERY, asker.name, peer.name, link.lid, asker.prio,
                   {"qid": qid, "topic": topic, "args": args})

    # ---- incoming (Zenoh thread -> kernel thread) -------------------------------------------
    def _incoming(self, key: str, payload: bytes) -> None:
        try:
            msgs = decode_batch(payload)
        except LinkError as exc:
            self.rejected.note("incoming batch refused (malformed)", f"{key}: {exc}")
            return
        self.sys.kernel.interrupt(self._handle_batch, msgs)

    def _handle_batch(self, msgs: list[LinkMessage]) -> None:
        for msg in msgs:
            self._handle(msg)

    def _link(self, msg: LinkMessage) -> Link:
        links = self.sys.msgtab.links
        if not 0 <= msg.link < len(links):
            raise MessageError(f"message from {msg.src} names link {msg.link}, which this "
                               f"satellite does not have (tables out of step?)")
        return links[msg.link]

    def _handle(self, msg: LinkMessage) -> None:
        """Act on one incoming message (kernel thread)."""
        self.received += 1
        try:
            self._dispatch(msg)
        except Exception as exc:
            text = f"{msg.kind.name} {msg.src}->{msg.dst}: {type(exc).__name__}: {exc}"
            self.rejected.note(f"incoming message refused ({msg.kind.name} "
                               f"{type(exc).__name__})", text)
            self.errors.append(text)
            del self.errors[:-100]

    def _dispatch(self, msg: LinkMessage) -> None:
        s = self.sys
        mm = s.msgmgr
        v = msg.value
        kind = msg.kind
        if kind is MessageKind.STATUS:
            if not (isinstance(v, dict) and isinstance(v.get("device"), str)
                    and v.get("status") in _STATUSES and isinstance(v.get("reason"), str)):
                raise MessageError(f"malformed status message {v!r:.120}")
            if v.get("from") != self.machine:
                s.devtab.set_status(v["device"], DeviceStatus(v["status"]), v["reason"])
            return
        if kind is MessageKind.COMMAND and isinstance(v, dict) and v.get("op") == "estop":
            if v.get("from") != self.machine:
                mm.event("estop", f"from machine {v.get('from')}: {v.get('reason')}")
                s.devtab.estop(str(v.get("reason")))
            return
        if kind is MessageKind.COMMAND and isinstance(v, dict) and v.get("op") == "actuator":
            spec = s.devtab.get(str(v["device"])).spec
            check_actuator_value(spec.name, spec.safe_value, spec.limits, v.get("value"))
            s.devtab.write(v["device"], v["value"], source=msg.src)
            return
        link = self._link(msg)
        if kind is MessageKind.SENSORY:
            if link.tap:
                tap = s.tsktab.get(link.dst).tap
                if tap is None:
                    raise MessageError(f"tapped message for {link.dst}, not an exception task")
                mm.deliver_tap(link, tap, msg.src, v)
            else:
                self._count_superseded(link, msg.seq)
                mm.deliver(link, v)
        elif kind is MessageKind.COMMAND:
            if v["op"] == "open":
                answer = mm.remote_open(link, v["command"], bool(v["wait"]))
                self._send(link.src_machine, MessageKind.REPLY, link.src, link.dst, link.lid,
                           link.priority, {"op": "open", "answer": answer})
            elif v["op"] == "close":
                mm.close(link)
            else:
                raise MessageError(f"unknown command op {v['op']!r}")
        elif kind is MessageKind.QUERY:
            self._answer(msg, link)
        elif kind is MessageKind.REPLY and v.get("op") == "answer":
            mm.ask_answered(int(v["qid"]), v.get("answer"), None)
        elif kind is MessageKind.ERROR:
            mm.ask_answered(int(v["qid"]), None, str(v["error"]))
        elif kind is MessageKind.REPLY:
            mm.open_answer(link, str(v["answer"]))
        elif kind in (MessageKind.COMPLETION, MessageKind.PREEMPTION):
            mm.remote_report(link, LinkStatus(v["status"]), v.get("result"), v.get("error", ""))
        else:
            raise MessageError(f"unexpected message kind {kind.name}")

    def _answer(self, msg: LinkMessage, link: Link) -> None:
        """Answer a world-model query from another satellite with the local task's model, or
        tell the asker why not (an ERROR message, which raises MessageError in the asker)."""
        v = msg.value
        tsktab = self.sys.tsktab
        asker = tsktab.get(msg.src)
        qid = int(v["qid"])
        try:
            answer = self.sys.msgmgr.world_answer(tsktab.get(msg.dst), str(v["topic"]),
                                                  v.get("args") or [])
            self._send(asker.machine, MessageKind.REPLY, msg.dst, msg.src, link.lid,
                       msg.priority, {"op": "answer", "qid": qid, "answer": answer})
        except Exception as exc:
            why = str(exc) if isinstance(exc, MessageError) else f"{type(exc).__name__}: {exc}"
            self._send(asker.machine, MessageKind.ERROR, msg.dst, msg.src, link.lid,
                       msg.priority, {"qid": qid, "error": f"{msg.dst}'s world model: {why}"})

    def _count_superseded(self, link: Link, seq: int) -> None:
        """Count the messages of a newest-wins link that a newer one replaced before they left
        the sender (a gap in its sequence numbers) as sent and overwritten. A sequence number
        that does not move forward (the sender restarted) starts counting afresh."""
        last = self._seen.get(link.lid, 0)
        self._seen[link.lid] = seq
        if not link.queued and seq > last + 1 and last:
            gap = seq - last - 1
            link.sent += gap
            link.overwritten += gap
            self.superseded += gap

    # ---- liveliness -------------------------------------------------------------------------
    def _joined(self, key: str) -> None:
        m = machine_of(key)
        if m is not None and m != self.machine:
            self.sys.kernel.interrupt(self._on_join, m)

    def _left(self, key: str) -> None:
        m = machine_of(key)
        if m is not None and m != self.machine:
            self.sys.kernel.interrupt(self._on_leave, m)

    def _on_join(self, machine: int) -> None:
        self.alive.add(machine)
        self.sys.msgmgr.event("satellite-up", f"machine {machine} joined")
        for e in self.sys.devtab:
            if e.spec.machine == machine and e.status is DeviceStatus.FAILED:
                self.sys.devtab.set_status(e.name, DeviceStatus.OK, "")

    def _on_leave(self, machine: int) -> None:
        self.alive.discard(machine)
        mm = self.sys.msgmgr
        told = mm.satellite_lost(machine)
        mm.event("satellite-down", f"machine {machine} died; {told} owner(s) told")
        for e in self.sys.devtab:
            if e.spec.machine == machine:
                self.sys.devtab.set_status(e.name, DeviceStatus.FAILED,
                                           f"satellite {machine} died")
