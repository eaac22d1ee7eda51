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
estop, device status, hellos), ``alive/<N>`` (liveliness tokens: a satellite is up once its
token is seen and a sealed hello from it arrived, see :meth:`CommManager.is_up`). Only payloads
sealed by the satellite role are accepted on the message keys (a host cannot set device values,
write actuators, forge statuses or e-stop through them). A malformed or refused message is
counted by cause and logged at most once per cause per interval (:attr:`CommManager.rejected`);
actuator values must match the actuator's type (a number where the safe value or limits are
numbers) and be finite.

Payloads are typed (:mod:`chcos.comm.payloads`), encoded and checked only at this boundary.
The collaborators (kernel, tables, message manager, device table) are given at construction
as the narrow protocols of :mod:`chcos.comm.ports`. What goes wrong on the link (a batch that
could not be published, an incoming message refused) is collected in :attr:`CommManager.errors`
and raised by :meth:`CommManager.check` (like canopen's ``Network.check()``).
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any

from chcos.comm.batching import Batches
from chcos.comm.codec import EXPRESS_FROM, LinkMessage, MessageKind, decode_batch, encode
from chcos.comm.payloads import (
    KIND_OF,
    ActuatorCommand,
    AxisReply,
    AxisRequest,
    CloseRequest,
    EmergencyStop,
    Hello,
    OpenAnswer,
    OpenReply,
    OpenRequest,
    Payload,
    Query,
    QueryAnswer,
    QueryFailed,
    Report,
    StatusChange,
    check_actuator_value,
    from_wire,
    to_wire,
)
from chcos.comm.ports import Closable, Devices, Links, LinkTransport, Messages, Scheduler, Tasks
from chcos.comm.secret import Throttle
from chcos.devices.entry import DeviceStatus
from chcos.errors import LinkError, MessageError
from chcos.tables.messages import TOP_PRIORITY, Link, LinkStatus
from chcos.tables.tasks import TaskEntry
from drivers.canopen_axis import AxisCall, Done
from drivers.codecs.cia402 import Op, Result, is_axis_address, result_doc, result_from_doc

log = logging.getLogger("chcos.comm.manager")

#: The roles that may send on the message keys.
SATELLITES = frozenset({"satellite"})
#: How many collected errors are kept (the oldest are dropped; :attr:`error_count` counts all).
ERRORS_KEPT = 100

__all__ = ["CommManager", "check_actuator_value", "machine_of"]


class OutSlot:
    """A remote newest-wins link's message waiting in an outgoing batch. A newer message
    replaces it; the batch takes ``value`` when it leaves."""

    __slots__ = ("fresh", "replaced", "value")

    def __init__(self) -> None:
        self.value: Any = None
        #: a message waits (the link's batch holds this slot)
        self.fresh = False
        #: how many waiting messages newer ones replaced since the batch took this slot
        self.replaced = 0


def machine_of(token_key: str) -> int | None:
    """The machine number of a satellite's liveliness token key (``.../alive/<N>``), or None
    for a key that does not end in a number."""
    tail = token_key.rsplit("/", 1)[-1]
    return int(tail) if tail.isdigit() else None


class CommManager:
    """The link between one satellite (machine ``machine``) and all the others, on
    ``transport``, under the key ``prefix``. The message manager learns of it from the
    composition root (``msgmgr.comm``); the manager registers its idle hook with ``kernel``."""

    def __init__(self, *, kernel: Scheduler, tsktab: Tasks, msgtab: Links, msgmgr: Messages,
                 devtab: Devices, transport: LinkTransport, prefix: str, machine: int) -> None:
        self.kernel = kernel
        self.tsktab = tsktab
        self.msgtab = msgtab
        self.msgmgr = msgmgr
        self.devtab = devtab
        self.transport = transport
        self.prefix = prefix
        self.machine = machine
        self._seq: dict[int, int] = {}       # outgoing: last sequence number per link id
        self._seen: dict[int, int] = {}      # incoming: last sequence number per link id
        self._subs: list[Closable] = []
        self.received = 0
        #: messages handed to the link that were sent or replaced on the way (not those that
        #: could not be encoded)
        self.sent = 0
        #: what went wrong on the link, newest last (at most ERRORS_KEPT); see :meth:`check`
        self.errors: list[str] = []
        self.error_count = 0
        self.rejected = Throttle(log)
        self.alive: set[int] = {machine}
        self._tokens: set[int] = set()   # machines whose liveliness token is seen now
        self._greeted: set[int] = set()  # machines whose sealed hello came since that token
        self.batches = Batches(kernel, transport, self._collect, self._leave)
        # the newest-wins links' messages waiting in batches, by link (see sensory)
        self._waiting: dict[Link, OutSlot] = {}
        self._keys: dict[int | None, str] = {}   # destination machine -> its message key
        self.superseded = 0
        #: axis commands sent to other satellites and not answered yet: request id -> (who
        #: gets the result, the machine hosting the axis, the axis, the command)
        self._axis_waits: dict[int, tuple[Done, int, str, str]] = {}
        self._axis_seq = 0
        #: the last result each remote axis's satellite confirmed, by axis
        self.axis_results: dict[str, Result] = {}
        kernel.add_idle_hook(self.batches.on_idle)

    # ---- collected errors -------------------------------------------------------------------
    def _collect(self, text: str) -> None:
        self.errors.append(text)
        del self.errors[:-ERRORS_KEPT]
        self.error_count += 1

    def check(self) -> None:
        """Raise LinkError if this satellite collected link errors (batches that could not be
        published, incoming messages refused): how many, and the last few. The errors stay
        collected (the map shows them) until :meth:`clear_errors`."""
        if not self.errors:
            return
        last = "\n  - ".join(self.errors[-5:])
        raise LinkError(f"machine {self.machine}: {self.error_count} link error(s) collected; "
                        f"the last:\n  - {last}")

    def clear_errors(self) -> list[str]:
        """Acknowledge the collected errors: returns them and forgets them."""
        out, self.errors = self.errors, []
        self.error_count = 0
        return out

    @property
    def coalesced(self) -> int:
        """Newest-wins messages replaced by a newer one before they left this satellite."""
        return self.batches.coalesced

    @property
    def batches_sent(self) -> int:
        """How many batches were published."""
        return self.batches.sent

    def flush(self) -> None:
        """Send every waiting batch now (kernel thread)."""
        self.batches.flush()

    # ---- keys -------------------------------------------------------------------------------
    def key(self, machine: int) -> str:
        """The message key of ``machine``."""
        return f"{self.prefix}/m/{machine}/msg"

    def _key_of(self, machine: int | None) -> str:
        """The key a message to ``machine`` goes to (None: the broadcast key), kept in
        ``_keys`` for the next message."""
        key = self._keys[machine] = (f"{self.prefix}/all/msg" if machine is None
                                     else self.key(machine))
        return key

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
    def _send(self, machine: int | None, src: str, dst: str, lid: int, priority: int,
              payload: Payload, *, queued: bool = False) -> None:
        self._put(machine, KIND_OF[type(payload)], src, dst, lid, priority, to_wire(payload),
                  queued=queued)

    def _put(self, machine: int | None, kind: MessageKind, src: str, dst: str, lid: int,
             priority: int, value: Any, queued: bool = False, newest_wins: bool = False) -> None:
        seq = self._seq.get(lid, 0) + 1
        msg = LinkMessage(kind, src, dst, lid, priority, seq, time.time_ns(), value)
        key = self._keys.get(machine) or self._key_of(machine)
        drop = kind.droppable and not queued      # a queued link's messages must all arrive
        try:
            data = encode(msg)
            self._seq[lid] = seq   # a message that cannot be encoded takes no number: the
            self.sent += 1         # receiver would count it as sent and overwritten
            if priority >= EXPRESS_FROM:  # urgent: out at once, on its own
                self.transport.publish(key, data, priority=priority,
                                       kind=MessageKind.SENSORY if drop else MessageKind.COMMAND)
                return
        except LinkError as exc:
            raise MessageError(f"cannot send {kind.name.lower()} {src}->{dst} to machine "
                               f"{machine}: {exc}") from exc
        self.batches.add(key, drop, newest_wins, lid, data, priority)

    def sensory(self, link: Link, value: Any) -> bool:
        """A sensory message to a task on another satellite. True if it replaced one of the
        link's that was still waiting to leave (the message layer counts that one as
        overwritten on this satellite's copy of the link).

        On a newest-wins link below EXPRESS_FROM (the common case, and the one that comes in
        floods) the message waits in its batch, unencoded, in the link's :class:`OutSlot`;
        a newer message replaces it there, and only the one that leaves is encoded
        (:meth:`_leave`). What is not a number is encoded here, so that what cannot be sent
        fails in the sender's put (a number cannot fail: a float must be finite). Raises
        MessageError for a message that cannot be encoded."""
        if link.queued or link.tap or link.priority >= EXPRESS_FROM:
            slot = self._waiting.get(link)
            if slot is not None and slot.fresh:  # an express priority came while one waited:
                self._withdraw(link, slot)       # this newer message replaces it
            self._put(link.dst_machine, MessageKind.SENSORY, link.src, link.dst, link.lid,
                      link.priority, value, queued=bool(link.queued),
                      newest_wins=not link.queued and not link.tap)
            return False
        t = type(value)
        if not (t is int or t is bool or (t is float and math.isfinite(value))):
            try:
                encode(LinkMessage(MessageKind.SENSORY, link.src, link.dst, link.lid,
                                   link.priority, 0, 0, value))
            except LinkError as exc:
                raise MessageError(f"cannot send sensory {link.src}->{link.dst} to machine "
                                   f"{link.dst_machine}: {exc}") from exc
        slot = self._waiting.get(link)
        if slot is None:
            slot = self._waiting[link] = OutSlot()
        replaced = slot.fresh
        if replaced:
            slot.replaced += 1
        else:
            slot.fresh = True
            slot.replaced = 0
            machine = link.dst_machine
            self.batches.add(self._keys.get(machine) or self._key_of(machine), True, True,
                             link.lid, link, link.priority)
        slot.value = value
        return replaced

    @staticmethod
    def _taken(slot: OutSlot) -> int:
        """Empty a link's waiting slot: how many messages it took (the one waiting and those
        it replaced)."""
        n = 1 + slot.replaced
        slot.fresh = False
        slot.value = None
        return n

    def _withdraw(self, link: Link, slot: OutSlot) -> None:
        """Take a waiting message out of its batch: a newer one on the same link goes express.
        Its sequence numbers are used up, so that the receiver counts it as overwritten."""
        self.batches.withdraw(self._keys.get(link.dst_machine) or self._key_of(link.dst_machine),
                              link.lid)
        n = self._taken(slot)
        self.sent += n
        self.batches.coalesced += n
        self._seq[link.lid] = self._seq.get(link.lid, 0) + n

    def _leave(self, link: Link) -> bytes | None:
        """The wire bytes of the message waiting in ``link``'s slot as its batch leaves, with
        the sequence number of the newest message it replaced (the receiver counts the gap as
        overwritten) and the time it leaves; None if it cannot be encoded (a value stored on
        the hot path: logged and collected, the messages dropped without a number)."""
        slot = self._waiting.get(link)
        if slot is None or not slot.fresh:
            return None
        value = slot.value
        n = self._taken(slot)
        lid = link.lid
        seq = self._seq.get(lid, 0) + n
        try:
            data = encode(LinkMessage(MessageKind.SENSORY, link.src, link.dst, lid,
                                      link.priority, seq, time.time_ns(), value))
        except LinkError as exc:
            text = (f"sensory {link.src}->{link.dst} to machine {link.dst_machine}: {n} "
                    f"message(s) not sent: {exc}")
            log.error("%s", text)
            self._collect(text)
            return None
        self._seq[lid] = seq
        self.sent += n
        self.batches.coalesced += n - 1
        return data

    def tap(self, link: Link, source: str, value: Any) -> None:
        """A tapped sensory message to an exception task on another satellite."""
        self._put(link.dst_machine, MessageKind.SENSORY, source, link.dst, link.lid,
                  link.priority, value)

    def open(self, link: Link, command: Any, wait: bool) -> None:
        """topen of a task on another satellite."""
        self._send(link.dst_machine, link.src, link.dst, link.lid, link.priority,
                   OpenRequest(command, wait))

    def close(self, link: Link) -> None:
        """tclose of a task on another satellite."""
        self._send(link.dst_machine, link.src, link.dst, link.lid, link.priority, CloseRequest())

    def report(self, link: Link) -> None:
        """A completion or pre-emption on ``link`` to its caller's satellite."""
        kind = (MessageKind.PREEMPTION if link.status is LinkStatus.PREEMPTED
                else MessageKind.COMPLETION)
        self._put(link.src_machine, kind, link.src, link.dst, link.lid, link.priority,
                  to_wire(Report(link.status, link.result, link.error)))

    def granted(self, link: Link) -> None:
        """The caller of ``link`` (on another satellite) now owns the target."""
        self._send(link.src_machine, link.src, link.dst, link.lid, link.priority,
                   OpenReply(OpenAnswer.owner()))

    def actuator(self, device: str, machine: int, value: Any, source: str) -> None:
        """An actuator command to the device's satellite."""
        self._send(machine, source, device, 0, TOP_PRIORITY - 1, ActuatorCommand(device, value))

    def device_status(self, device: str, status: DeviceStatus, reason: str) -> None:
        """A local device changed status: tell everybody."""
        self._send(None, "", device, 0, TOP_PRIORITY - 1,
                   StatusChange(device, status.value, reason, self.machine))

    def estop(self, reason: str) -> None:
        """Emergency stop everywhere, at top priority, sent express."""
        self._send(None, "", "", 0, TOP_PRIORITY, EmergencyStop(reason, self.machine))

    def axis_call(self, device: str, machine: int, source: str, call: AxisCall,
                  done: Done) -> None:
        """Send task ``source``'s command ``call`` of axis ``device`` to satellite ``machine``,
        which hosts it; ``done`` gets the drive's :class:`Result` (or a MessageError: refused
        there, or that satellite died first) on the kernel thread. Raises MessageError, sending
        nothing, when that satellite is not up or the request cannot be sent."""
        if not self.is_up(machine):
            raise MessageError(f"axis {device} is on satellite {machine}, which is not up: "
                               f"{call.op.value} not sent")
        self._axis_seq += 1
        rid = self._axis_seq
        self._send(machine, source, device, 0, TOP_PRIORITY - 1,
                   AxisRequest(rid, device, call.op.value, call.arg, self.machine))
        self._axis_waits[rid] = (done, machine, device, call.op.value)

    def _serve_axis(self, msg: LinkMessage, p: AxisRequest) -> None:
        """Run another satellite's command of a local axis; its result (or why it was
        refused) goes back to the asker as an AxisReply. Only a task with an output link to
        the axis may command it (the tables are the same on every satellite)."""
        def reply(result: Result | None, error: str) -> None:    # kernel thread
            try:
                self._send(p.origin, p.device, msg.src, 0, TOP_PRIORITY - 1,
                           AxisReply(p.rid, None if result is None else result_doc(result),
                                     error))
            except MessageError as exc:     # the asker's satellite is gone: nobody waits
                self._collect(f"axis {p.device}: reply to {msg.src} not sent: {exc}")

        def done(outcome: Result | Exception) -> None:          # the driver's thread
            if isinstance(outcome, Result):
                self.kernel.interrupt(reply, outcome, "")
            else:
                self.kernel.interrupt(reply, None, f"axis {p.device}: {outcome}")

        try:
            entry = self.devtab.get(p.device)
            driver = entry.driver
            if not is_axis_address(entry.spec.address) or entry.spec.direction != "actuator" \
                    or driver is None or not hasattr(driver, "axis_call"):
                raise MessageError(f"{p.device} is not a CiA 402 axis driven by satellite "
                                   f"{self.machine}")
            if not any(lk.src == msg.src and lk.dst == p.device for lk in self.msgtab.links):
                raise MessageError(f"task {msg.src} has no output port to axis {p.device}")
            driver.axis_call(p.device, AxisCall(Op(p.call), p.arg), done)
        except Exception as exc:
            reply(None, str(exc) if isinstance(exc, MessageError)
                  else f"axis {p.device}: {type(exc).__name__}: {exc}")

    def _axis_answered(self, p: AxisReply) -> None:
        """The hosting satellite answered axis request ``p.rid``: its waiter gets the result
        (or a MessageError with the refusal). An answer nobody waits for is dropped."""
        waiting = self._axis_waits.pop(p.rid, None)
        if waiting is None:
            return
        done, machine, device, _op = waiting
        if p.result is None:
            done(MessageError(p.error or f"axis {device}: refused by satellite {machine}"))
            return
        try:
            result = result_from_doc(p.result)
        except Exception as exc:
            done(MessageError(f"axis {device}: satellite {machine} answered {exc}"))
            return
        self.axis_results[device] = result
        done(result)

    def is_up(self, machine: int) -> bool:
        """Whether satellite ``machine`` is on the link now (its liveliness token is seen and
        a sealed hello from it arrived)."""
        return machine in self.alive

    def query(self, link: Link, asker: TaskEntry, peer: TaskEntry, qid: int, topic: str,
              args: list[Any]) -> None:
        """A world-model query of ``asker`` to ``peer`` on another satellite, at the priority
        ``asker`` runs at. Raises MessageError if it cannot be encoded."""
        self._send(peer.machine, asker.name, peer.name, link.lid, asker.prio,
                   Query(qid, topic, args))

    # ---- incoming (Zenoh thread -> kernel thread) -------------------------------------------
    def _incoming(self, key: str, payload: bytes) -> None:
        try:
            msgs = decode_batch(payload)
        except LinkError as exc:
            self.rejected.note("incoming batch refused (malformed)", f"{key}: {exc}")
            return
        self.kernel.interrupt(self._handle_batch, msgs)

    def _handle_batch(self, msgs: list[LinkMessage]) -> None:
        for msg in msgs:
            self._handle(msg)

    def _link(self, msg: LinkMessage) -> Link:
        links = self.msgtab.links
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
            self._collect(text)

    def _dispatch(self, msg: LinkMessage) -> None:
        mm = self.msgmgr
        if msg.kind is MessageKind.SENSORY:
            link = self._link(msg)
            if link.tap:
                tap = self.tsktab.get(link.dst).tap
                if tap is None:
                    raise MessageError(f"task {link.dst} has no exception tap")
                mm.deliver_tap(link, tap, msg.src, msg.value)
            else:
                self._count_superseded(link, msg.seq)
                mm.deliver(link, msg.value)
            return
        p = from_wire(msg.kind, msg.value)
        if isinstance(p, Hello):
            self._on_hello(p)
        elif isinstance(p, StatusChange):
            if p.origin != self.machine:
                self.devtab.set_status(p.device, DeviceStatus(p.status), p.reason)
        elif isinstance(p, EmergencyStop):
            if p.origin != self.machine:
                mm.event("estop", f"from machine {p.origin}: {p.reason}")
                self.devtab.estop(p.reason)
        elif isinstance(p, ActuatorCommand):
            spec = self.devtab.get(p.device).spec
            check_actuator_value(spec.name, spec.safe_value, spec.limits, p.value)
            self.devtab.write(p.device, p.value, source=msg.src)
        elif isinstance(p, AxisRequest):
            self._serve_axis(msg, p)
        elif isinstance(p, AxisReply):
            self._axis_answered(p)
        elif isinstance(p, OpenRequest):
            link = self._link(msg)
            self._send(link.src_machine, link.src, link.dst, link.lid, link.priority,
                       OpenReply(mm.remote_open(link, p.command, p.wait)))
        elif isinstance(p, CloseRequest):
            mm.close(self._link(msg))
        elif isinstance(p, Query):
            self._answer(msg, self._link(msg), p)
        elif isinstance(p, QueryAnswer):
            self._link(msg)
            mm.ask_answered(p.qid, p.answer, None)
        elif isinstance(p, QueryFailed):
            self._link(msg)
            mm.ask_answered(p.qid, None, p.error)
        elif isinstance(p, OpenReply):
            mm.open_answer(self._link(msg), p.answer)
        else:  # Report
            mm.remote_report(self._link(msg), p.status, p.result, p.error)

    def _answer(self, msg: LinkMessage, link: Link, q: Query) -> None:
        """Answer a world-model query from another satellite with the local task's model, or
        tell the asker why not (an ERROR message, which raises MessageError in the asker)."""
        asker = self.tsktab.get(msg.src)
        try:
            answer = self.msgmgr.world_answer(self.tsktab.get(msg.dst), q.topic, q.args)
            self._send(asker.machine, msg.dst, msg.src, link.lid, msg.priority,
                       QueryAnswer(q.qid, answer))
        except Exception as exc:
            why = str(exc) if isinstance(exc, MessageError) else f"{type(exc).__name__}: {exc}"
            self._send(asker.machine, msg.dst, msg.src, link.lid, msg.priority,
                       QueryFailed(q.qid, f"{msg.dst}'s world model: {why}"))

    def _count_superseded(self, link: Link, seq: int) -> None:
        """Count the messages of a newest-wins link that a newer one replaced before they left
        the sender (a gap in its sequence numbers) as sent and overwritten. A sequence number
        that does not move forward (the sender restarted) starts counting afresh."""
        last = self._seen.get(link.lid, 0)
        self._seen[link.lid] = seq
        if not link.queued and seq > last + 1 and last:
            gap = seq - last - 1
            self.msgmgr.superseded(link, gap)
            self.superseded += gap

    # ---- liveliness -------------------------------------------------------------------------
    # A liveliness token carries no seal: any session that may open could declare one. A
    # satellite is up here only once its token is seen *and* a sealed hello from it arrived
    # (it answers the hello this satellite asks with when the token appears), so a forged
    # token for a satellite that is down changes nothing. A token vanishing still means down.
    def _joined(self, key: str) -> None:
        m = machine_of(key)
        if m is not None and m != self.machine:
            self.kernel.interrupt(self._on_token, m)

    def _left(self, key: str) -> None:
        m = machine_of(key)
        if m is not None and m != self.machine:
            self.kernel.interrupt(self._on_token_gone, m)

    def _on_token(self, machine: int) -> None:
        self._tokens.add(machine)
        if machine in self._greeted:
            self._confirm(machine)
        else:
            self._hello(ask=True)

    def _on_token_gone(self, machine: int) -> None:
        self._tokens.discard(machine)
        self._greeted.discard(machine)
        if machine in self.alive:
            self._on_leave(machine)

    def _hello(self, ask: bool) -> None:
        try:
            self._send(None, "", "", 0, TOP_PRIORITY - 1, Hello(self.machine, ask))
        except MessageError as exc:  # the link is down: the next token seen asks again
            log.warning("machine %d: hello not sent: %s", self.machine, exc)

    def _on_hello(self, hello: Hello) -> None:
        if hello.origin == self.machine:
            return
        self._greeted.add(hello.origin)
        if hello.ask:
            self._hello(ask=False)
        self._confirm(hello.origin)

    def _confirm(self, machine: int) -> None:
        if machine in self._tokens and machine not in self.alive:
            self._on_join(machine)

    def _on_join(self, machine: int) -> None:
        self.alive.add(machine)
        self.msgmgr.event("satellite-up", f"machine {machine} joined")
        for e in self.devtab:
            if e.spec.machine == machine and e.status is DeviceStatus.FAILED:
                self.devtab.set_status(e.name, DeviceStatus.OK, "")

    def _on_leave(self, machine: int) -> None:
        self.alive.discard(machine)
        for rid, (done, m, device, op) in list(self._axis_waits.items()):
            if m == machine:
                del self._axis_waits[rid]
                done(MessageError(f"axis {device}: satellite {machine} died before confirming "
                                  f"{op}"))
        told = self.msgmgr.satellite_lost(machine)
        self.msgmgr.event("satellite-down", f"machine {machine} died; {told} owner(s) told")
        for e in self.devtab:
            if e.spec.machine == machine:
                self.devtab.set_status(e.name, DeviceStatus.FAILED,
                                       f"satellite {machine} died")
