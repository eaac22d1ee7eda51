"""remote - the message manager's side of other satellites: topen/tclose answers and reports
coming back over the link, world-model queries (thesis 5.4) asked and answered across
satellites, and what a satellite's death means for the callers and owners here.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from chcos.comm.payloads import OpenAnswer, OpenOutcome
from chcos.errors import Busy, MessageError
from chcos.messages.context import MessageContext
from chcos.messages.ownership import Ownership
from chcos.messages.waits import forget
from chcos.tables.messages import EndpointKind, Link, LinkStatus, LinkType
from chcos.tables.tasks import TaskEntry


class Remote:
    """Answers from and to other satellites (see the module doc): the part of the message
    manager that runs ``ownership``'s topen, tclose and reports for them."""

    def __init__(self, ctx: MessageContext, ownership: Ownership) -> None:
        self.ctx = ctx
        self.kernel = ctx.kernel
        self.ownership = ownership
        self._ask_seq = 0
        self._asks: dict[int, tuple[TaskEntry, int]] = {}  # remote queries: id -> (asker, machine)

    def queries_pending(self) -> int:
        """World-model queries sent to other satellites and not answered yet."""
        return len(self._asks)

    # ---- answers from other satellites (called by the communications manager) ---------------
    def remote_open(self, link: Link, command: Any, wait: bool) -> OpenAnswer:
        """Run an ``open`` that a task on another satellite asked for; returns the answer for
        the caller's satellite: owner, queued, or busy (with the reason)."""
        try:
            owner = self.ownership.open(link, command, wait=wait)
            return OpenAnswer.owner() if owner else OpenAnswer.queued()
        except Busy as exc:
            return OpenAnswer.busy(str(exc))

    def open_answer(self, link: Link, answer: OpenAnswer) -> None:
        """The target's satellite answered this satellite's ``open`` on ``link``."""
        caller = self.ctx.caller(link)
        if answer.outcome is OpenOutcome.QUEUED:
            return
        link.pending = False
        if answer.outcome is OpenOutcome.OWNER:
            link.status = LinkStatus.OK
            if caller is not None and caller.wait_link is link:
                self.kernel.wake(caller, caller.base_prio, True)
        else:
            if caller is not None and caller.wait_link is link:
                self.kernel.wake(caller, caller.base_prio, exc=Busy(answer.reason))

    def remote_report(self, link: Link, status: LinkStatus, result: Any, error: str) -> None:
        """The target's satellite reports a completion or pre-emption on ``link``."""
        link.pending = False
        self.ownership.report(link, status, result, error)

    # ---- world-model queries (thesis 5.4) ---------------------------------------------------
    def world_answer(self, target: TaskEntry, topic: str, args: Sequence[Any]) -> Any:
        """What ``target``'s world model answers about ``topic`` (run as ``target``, so the
        model sees its own task as current). Raises MessageError if the task has no model or
        the model knows nothing about ``topic``; a model's own failure propagates."""
        if target.world is None:
            raise MessageError(f"task {target.name} has no world model")
        k = self.kernel
        caller, k.current = k.current, target
        try:
            return target.world.answer(topic, *args)
        finally:
            k.current = caller

    def ask_remote(self, t: TaskEntry, link: Link, peer: TaskEntry, topic: str,
                   args: Sequence[Any]) -> None:
        """Send ``t``'s query about ``topic`` to ``peer`` on another satellite and mark ``t`` as
        waiting for the answer; its caller then blocks ``t``, which :meth:`ask_answered` (or the
        loss of ``peer``'s satellite) wakes. Raises MessageError if that satellite is not up or
        the query cannot be sent (e.g. ``args`` are not JSON-representable)."""
        comm = self.ctx.comm
        if not comm.is_up(peer.machine):
            raise MessageError(f"cannot ask {peer.name}: satellite {peer.machine} is not up")
        self._ask_seq += 1
        qid = self._ask_seq
        comm.query(link, t, peer, qid, topic, list(args))
        self._asks[qid] = (t, peer.machine)
        t.wait_query = qid
        t.unwait = forget

    def ask_answered(self, qid: int, answer: Any, error: str | None) -> None:
        """The answer (or, with ``error``, the refusal) of remote query ``qid`` arrived: wake
        the asker with it. An answer nobody waits for any more (the asker timed out or was
        pre-empted) is dropped."""
        entry = self._asks.pop(qid, None)
        if entry is None:
            return
        t = entry[0]
        if t.wait_query != qid:
            return
        if error is None:
            self.kernel.wake(t, t.base_prio, answer)
        else:
            self.kernel.wake(t, t.base_prio, exc=MessageError(error))

    def _release_from(self, machine: int) -> int:
        """Local tasks owned by (or queued for) a caller on dead ``machine`` are released."""
        n = 0
        for t in self.ctx.tsktab:
            if not self.ctx.is_local(t.machine):
                continue
            for _seq, link, _cmd in list(t.waitq):
                if link.src_machine == machine and link.src_kind is EndpointKind.TASK:
                    t.waitq[:] = [e for e in t.waitq if e[1] is not link]
                    link.pending = False
            owner = t.owner
            if (owner is not None and owner.src_kind is EndpointKind.TASK
                    and owner.src_machine == machine):
                n += 1
                self.ctx.event("release", f"{t.name} released: its owner {owner.src} died with "
                                      f"satellite {machine}")
                self.ownership.release(t)
        return n

    def satellite_lost(self, machine: int) -> int:
        """Machine ``machine`` died: every local caller of a task there gets an abnormal
        completion, every task waiting for a world-model answer from there a MessageError, and
        every local task owned by a task there is released (tclose). Returns how many links,
        queries and tasks were told."""
        n = self._release_from(machine)
        for qid, (t, m) in list(self._asks.items()):
            if m == machine:
                n += t.wait_query == qid
                self.ask_answered(qid, None,
                                  f"satellite {machine} died before answering {t.name}'s query")
        for link in self.ctx.msgtab:
            if link.type is not LinkType.COMMAND or link.dst_kind is not EndpointKind.TASK:
                continue
            if not link.remote or link.dst_machine != machine:
                continue
            caller = self.ctx.caller(link)
            if caller is None or self.ctx.remote_task(caller):
                continue
            if link.pending or (link.status is LinkStatus.OK and link.sent):
                link.pending = False
                self.ownership.report(link, LinkStatus.ABNORMAL,
                             error=f"satellite {machine} running {link.dst} died")
                n += 1
        return n
