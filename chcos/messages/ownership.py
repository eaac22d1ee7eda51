"""ownership - the message manager's command side: who owns a task, pre-emption, queues of
callers, completion and the end of activations (topen, tclose, teotsk, msgstat).

``open`` (topen) makes the caller the owner of a lower task, pre-empting a lower priority owner,
who is told, or queueing the caller; ``close`` (tclose) hands the task to the best waiter or
suspends it; the end of an activation reports normal or abnormal completion (teotsk) to the
owner, and a released or failed task's actuators go to their safe values. Suspension, reset and
wipe of tasks (host, assassin, reload) are here too.
"""

from __future__ import annotations

from typing import Any

from chcos.errors import Busy, MessageError
from chcos.kernel.describe import describe_error
from chcos.kernel.scheduler import End
from chcos.messages.context import MessageContext
from chcos.messages.delivery import log
from chcos.messages.restarts import Restarts
from chcos.tables.messages import Completion, EndpointKind, Link, LinkStatus, LinkType, TapPort
from chcos.tables.tasks import TaskEntry, TaskState

_COMMAND = object()  # what wakes a task waiting (wait_any) for a command message


class Ownership:
    """Command ownership for one satellite (see the module doc): the part of the message
    manager that owns :class:`~chcos.messages.restarts.Restarts`, the restart policies."""

    def __init__(self, ctx: MessageContext) -> None:
        self.ctx = ctx
        self.kernel = ctx.kernel
        self.tsktab = ctx.tsktab
        self.msgtab = ctx.msgtab
        self.devices = ctx.devices
        #: the restart policies of abnormally ended tasks
        self.restarts = Restarts(ctx, self.activate)
        self._qseq = 0  # arrival order in wait queues

    # ---- command messages (topen / tclose / teotsk) -----------------------------------------
    def open(self, link: Link, command: Any, *, wait: bool) -> bool:
        """Invoke ``link.dst`` with ``command`` on behalf of ``link.src`` (topen).

        True if the caller now owns the target (it runs at the link's priority); False if the
        caller was put in the target's wait queue (it must then block until woken). A lower
        priority owner is pre-empted and told. Raises Busy if ``wait`` is False and the target is
        held at an equal or higher priority, MessageError if the link is not a command link to a
        task or is suspended.
        """
        if link.type is not LinkType.COMMAND or link.dst_kind is not EndpointKind.TASK:
            raise MessageError(f"{link.name} is not a command link to a task")
        if link.status is LinkStatus.SUSPENDED:
            raise MessageError(f"link {link.name} is suspended: task {link.dst} is suspended "
                               "(host 'resume' or, after an emergency, 'reset')")
        target = self.tsktab.get(link.dst)
        link.reported = False
        link.result = None
        link.error = ""
        if link.remote:  # the target's satellite decides; the caller waits for its answer
            link.pending = True
            link.sent += 1
            self.ctx.comm.open(link, command, wait)
            return False
        owner = target.owner
        if (owner is link and target.coro is not None and not target.cancelling
                and link.src_kind is not EndpointKind.HOST):
            # Appendix 3: the task already belongs to the caller - no change; the parameters
            # reach the running activation as its newest command. (The host's invoke is the
            # system manager's, not a topen: it starts the command afresh.)
            link.status = LinkStatus.OK
            link.pending = False
            link.sent += 1
            self.give_command(target, command)
            return True
        if owner is link or owner is None or owner.priority < link.priority:
            if owner is not None and owner is not link:
                self.report(owner, LinkStatus.PREEMPTED,
                             error=f"pre-empted by {link.src} at priority {link.priority}")
                self.ctx.event("preempt", f"{link.src} took {target.name} from {owner.src} "
                                      f"(priority {link.priority} > {owner.priority})")
            target.owner = link
            link.status = LinkStatus.OK
            link.pending = False
            link.sent += 1
            self._start(target, command, link)
            return True
        if not wait:
            raise Busy(f"{target.name} is held by {owner.src} at priority {owner.priority} "
                       f">= {link.priority} ({link.name})")
        if not any(e[1] is link for e in target.waitq):
            self._qseq += 1
            target.waitq.append((self._qseq, link, command))
        link.pending = True
        link.status = LinkStatus.OK
        return False

    def close(self, link: Link) -> None:
        """Release ``link.dst`` from the invocation by ``link.src`` (tclose): ownership passes to
        the highest-priority waiter, or the target is suspended. A caller that was only waiting
        leaves the wait queue."""
        target = self.tsktab.get(link.dst)
        link.pending = False
        if link.remote:
            self.ctx.comm.close(link)
            return
        target.waitq[:] = [e for e in target.waitq if e[1] is not link]
        if target.owner is link:
            self.release(target)

    def give_command(self, target: TaskEntry, command: Any) -> None:
        """Hand ``command`` to ``target``'s running activation as its newest command (an older
        one not yet taken is overwritten) and wake it if it waits for commands."""
        target.new_command = (command,)
        if target.wait_commands:
            self.kernel.wake(target, target.base_prio, _COMMAND)

    def _start(self, target: TaskEntry, command: Any, link: Link) -> None:
        """Begin an activation of ``target`` for ``command`` at ``link``'s priority (a running
        activation is cancelled first: the newest command wins)."""
        if target.coro is None:
            self.activate(target, command, link.priority)
        else:
            target.next_command = (command, link.priority, link)
            self.kernel.cancel(target, f"new command from {link.src}")

    def activate(self, target: TaskEntry, command: Any, prio: int) -> None:
        """Begin an activation of ``target`` for ``command`` at ``prio`` (its task function is
        called now; one that fails or is not an ``async def`` ends it abnormally at once)."""
        target.command = command
        target.last_command = command
        target.new_command = None
        target.activations += 1
        try:
            coro = target.func(target.ctx, command)
        except Exception as exc:  # a task function that fails before its first await
            self.activation_ended(target, End.ERROR, exc)
            return
        if not hasattr(coro, "send"):
            self.activation_ended(target, End.ERROR, MessageError(
                f"task {target.name}: {target.code or 'its function'} is not an async def"))
            return
        self.kernel.start(target, coro, prio)  # type: ignore[arg-type]

    def release(self, t: TaskEntry) -> None:
        """``t``'s owner let it go: the best waiter owns it next (and is told), or its
        activation is cancelled and it goes back to its default priority."""
        t.owner = None
        if t.waitq:
            best = max(t.waitq, key=lambda e: (e[1].priority, -e[0]))
            t.waitq.remove(best)
            _, link, command = best
            link.pending = False
            link.status = LinkStatus.OK
            t.owner = link
            caller = self.ctx.caller(link)
            if self.ctx.remote_task(caller):
                self.ctx.comm.granted(link)
            elif caller is not None and caller.wait_link is link:
                self.kernel.wake(caller, caller.base_prio, True)
            self._start(t, command, link)
        elif t.coro is not None:
            self.kernel.cancel(t, "released by its owner")
        if t.owner is None:
            self._back_to_default(t)

    def _back_to_default(self, t: TaskEntry) -> None:
        """A released task goes back to its default priority (resetpri)."""
        if t.prio != t.default_prio:
            self.kernel.set_priority(t, t.default_prio)

    def report(self, link: Link, status: LinkStatus, result: Any = None, error: str = "") -> None:
        """Set ``link``'s status and tell the calling task (wakes it if it waits in ``done``)."""
        link.status = status
        link.result = result
        link.error = error
        link.reported = True
        caller = self.ctx.caller(link)
        if self.ctx.remote_task(caller):
            self.ctx.comm.report(link)
        elif caller is not None and caller.wait_link is link and not link.pending:
            link.reported = False
            self.kernel.wake(caller, max(caller.base_prio, link.priority), link.completion())
        elif caller is not None and caller.multi_wait and link in caller.wait_links:
            self.kernel.wake(caller, max(caller.base_prio, link.priority), link)

    def complete(self, t: TaskEntry, result: Any) -> None:
        """Report normal completion of ``t``'s command to its owner (teotsk) and end the command
        message. A waiter, if any, gets the task next; otherwise the activation may carry on
        unowned (a monitoring loop that has answered its owner)."""
        link = t.owner
        if link is None:
            return
        t.completions += 1
        if self.kernel.hooks.h_event:
            self.ctx.event("complete", f"{t.name} completed for {link.src}")
        self.report(link, LinkStatus.NORMAL, result=result)
        t.owner = None
        if t.waitq:
            self.release(t)
        else:
            self._back_to_default(t)

    def activation_ended(self, t: TaskEntry, how: End, value: Any) -> None:
        """Kernel end handler: ``t``'s activation ended ``how`` with ``value`` (its result, or
        the exception). Reports to the owner, releases what it owned, puts its actuators safe
        after an error or a release, starts the next command or a standing task's own loop."""
        t.coro = None
        t.new_command = None
        self.release_subordinates(t, f"{t.name} ended ({how.value})")
        if how is End.RETURN:
            if t.owner is not None:
                self.complete(t, value)
            elif t.waitq:
                self.release(t)
        elif how is End.ERROR:
            t.abnormal += 1
            text = describe_error(value)
            t.last_error = text
            log.error("task %s ended abnormally: %s", t.name, text)
            self.ctx.event("abnormal", f"{t.name}: {text}")
            link = t.owner
            if link is not None:
                self.report(link, LinkStatus.ABNORMAL, error=text)
            self.devices.safe_values(self._actuators(t))
            t.owner = None
            if t.waitq:
                self.release(t)
        if t.coro is None:
            nxt, t.next_command = t.next_command, None
            if nxt is not None:
                command, prio, link = nxt
                if t.owner is link:
                    self.activate(t, command, prio)
                    return
            t.state = TaskState.SUSPENDED
            if t.owner is None:
                self.kernel.set_priority(t, t.default_prio)
                if how is End.ERROR:
                    self.restarts.plan(t, value)
                elif how is End.PREEMPTED:  # released (tclose): suspended with actuators safe
                    self.devices.safe_values(self._actuators(t))
                    if t.standing and not t.frozen:
                        self.start_standing(t, "re-armed after its owner released it")

    def start_standing(self, t: TaskEntry, why: str = "started") -> None:
        """Start a standing task's own activation (no owner, no command) if it has none and
        nobody owns it; local tasks only."""
        if not self.ctx.is_local(t.machine) or t.coro is not None or t.owner is not None:
            return
        self.ctx.event("standing", f"{t.name} {why}")
        self.activate(t, None, t.default_prio)

    def _actuators(self, t: TaskEntry) -> list[str]:
        """The actuators ``t`` commands."""
        return [lk.dst for lk in t.out_links if lk.dst_kind is EndpointKind.DEVICE]

    # ---- ownership of subordinates, suspension, reset ---------------------------------------
    def release_subordinates(self, t: TaskEntry, why: str) -> int:
        """Release every task ``t`` owns or waits for (tclose on each command link): ownership
        passes to the next waiter, or the task is suspended with its actuators safe (a standing
        task goes back to its own loop). Returns how many were released."""
        n = 0
        links = t.out_links if not t.special_links else [*t.out_links,
                                                          *t.special_links.values()]
        for link in links:
            if link.dst_kind is not EndpointKind.TASK:
                continue
            if link.remote:
                if link.pending or (link.status is LinkStatus.OK and link.sent):
                    link.pending = False
                    self.ctx.comm.close(link)
                continue
            target = self.tsktab.get(link.dst)
            if link.pending:
                link.pending = False
                target.waitq[:] = [e for e in target.waitq if e[1] is not link]
            if target.owner is link:
                n += 1
                self.ctx.event("release", f"{target.name} released: {why}")
                self.release(target)
        return n

    def suspend_task(self, t: TaskEntry, by: str) -> None:
        """Freeze ``t`` (host ``suspend``, the assassin): msgstat shows its command links
        SUSPENDED and it releases its subordinates."""
        self.kernel.suspend(t)
        for link in self.msgtab:
            if (link.dst == t.name and link.type is LinkType.COMMAND
                    and link.status is LinkStatus.OK):
                link.status = LinkStatus.SUSPENDED
        self.release_subordinates(t, f"its owner {t.name} was suspended by {by}")

    def resume_task(self, t: TaskEntry) -> None:
        """Undo :meth:`suspend_task`."""
        for link in self.msgtab:
            if link.dst == t.name and link.status is LinkStatus.SUSPENDED:
                link.status = LinkStatus.OK
        self.kernel.resume(t)

    def reset_task(self, t: TaskEntry) -> bool:
        """Bring a frozen task back to work: its activation is ended (pre-empted), it is
        resumed, unowned, at its default priority; a standing task re-arms itself. True if the
        task was frozen."""
        frozen = t.frozen
        if t.owner is not None:
            link = t.owner
            self.report(link, LinkStatus.PREEMPTED, error=f"{t.name} reset after an emergency")
            t.owner = None
        for _seq, link, _cmd in t.waitq:
            link.pending = False
            self.report(link, LinkStatus.PREEMPTED, error=f"{t.name} reset")
        t.waitq.clear()
        t.next_command = None
        if t.coro is not None:
            self.kernel.cancel(t, "reset")
        self.resume_task(t)
        t.frozen_ready = None
        if t.coro is None:
            self.kernel.set_priority(t, t.default_prio)
        return frozen

    def wipe(self, t: TaskEntry, why: str) -> None:
        """Forget everything ``t`` was doing (a reload from scratch): its owner and waiters are
        told it was pre-empted, its activation is closed at once (its ``finally`` blocks run),
        what it owned is released, its unread messages, newest command, suspension and pending
        restart are dropped; it stays SUSPENDED at its default priority."""
        for link in [e[1] for e in t.waitq] + ([t.owner] if t.owner is not None else []):
            link.pending = False
            self.report(link, LinkStatus.PREEMPTED, error=why)
        t.owner = None
        t.waitq.clear()
        coro, t.coro = t.coro, None
        self.kernel.unhook(t)
        self.kernel.unready(t)  # no ready-queue entry is left behind
        if coro is not None:
            try:
                coro.close()
            except Exception:
                log.exception("task %s: closing its activation failed", t.name)
        self.release_subordinates(t, why)
        t.frozen = False
        t.frozen_ready = None
        t.frozen_state = None
        t.cancelling = False
        t.next_command = t.new_command = None
        t.send_value = t.throw_exc = None
        t.waiting_devices = frozenset()
        if t.restart_timer is not None:
            t.restart_timer.cancel()
            t.restart_timer = None
        for p in t.in_ports:  # unread messages are dropped, and counted so
            p.link.discarded += p.discard()
        if isinstance(t.tap, TapPort):
            t.tap.newest.clear()
            t.tap.order.clear()
        for link in self.msgtab:
            if link.dst == t.name and link.status is LinkStatus.SUSPENDED:
                link.status = LinkStatus.OK
        t.state = TaskState.SUSPENDED
        self.kernel.set_priority(t, t.default_prio)

    def resetpri(self, t: TaskEntry) -> int:
        """resetpri: ``t`` runs again at the priority of its owning link, or at its default
        priority when unowned (a ready task is re-queued). Returns the priority."""
        prio = t.owner.priority if t.owner is not None else t.default_prio
        self.kernel.set_priority(t, prio)
        return prio

    # ---- status (msgstat) and priorities ----------------------------------------------------
    def setpri(self, link: Link, prio: int) -> None:
        """Change ``link``'s priority now; the task it owns runs at the new one (re-queued if
        it is ready: :meth:`Kernel.set_priority`)."""
        link.set_priority(prio)
        if link.dst_kind is EndpointKind.TASK and link.dst in self.tsktab:
            target = self.tsktab.get(link.dst)
            if target.owner is link:
                self.kernel.set_priority(target, prio)

    def done_now(self, link: Link) -> Completion | None:
        """The pending report on ``link`` if there is one (and consume it), else None."""
        if link.reported:
            link.reported = False
            return link.completion()
        return None
