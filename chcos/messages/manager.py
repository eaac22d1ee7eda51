"""manager - the message manager: moves messages on links and keeps command ownership.

It is the layer that readies tasks (thesis 6.1.2): a sensory message readies the receiver at the
link's priority; ``open`` (topen) makes the caller the owner of a lower task, pre-empting a lower
priority owner, who is told, or queueing the caller; ``close`` (tclose) hands the task to the best
waiter or suspends it; the end of an activation reports normal or abnormal completion (teotsk) to
the owner. Devices, files and the host are link ends too.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, TextIO

from chcos.comm.payloads import OpenAnswer, OpenOutcome
from chcos.errors import Busy, DeviceError, MessageError, QueueOverflow
from chcos.kernel.scheduler import Kernel, describe_error
from chcos.tables.messages import (
    Completion,
    EndpointKind,
    InPort,
    Link,
    LinkStatus,
    LinkType,
    Msgtab,
    TapPort,
)
from chcos.tables.tasks import TaskEntry, TaskState, Tsktab

if TYPE_CHECKING:
    from chcos.devices.devtab import Devtab

log = logging.getLogger("chcos.messages.manager")
_LINK_SUSPENDED = LinkStatus.SUSPENDED  # a module constant: read on every delivery

EventSink = Callable[[str, str], None]
_COMMAND = object()  # what wakes a task waiting (wait_any) for a command message


def _healthy(devtab: Devtab, device: str) -> bool:
    """Whether ``device`` delivers (neither failed nor stale)."""
    return devtab.get(device).status.name not in ("FAILED", "STALE")


class Comm(Protocol):
    """What the message manager asks of the communications manager when a link leads to another
    satellite (see :mod:`chcos.comm.manager`). Every call is made on the kernel thread and must not
    block."""

    def sensory(self, link: Link, value: Any) -> None:
        """Carry a sensory message to the destination's satellite."""

    def tap(self, link: Link, source: str, value: Any) -> None:
        """Carry a tapped sensory message to a remote exception task."""

    def open(self, link: Link, command: Any, wait: bool) -> None:
        """Ask the target's satellite to invoke it for ``link``'s caller."""

    def close(self, link: Link) -> None:
        """Ask the target's satellite to release it from ``link``'s caller."""

    def report(self, link: Link) -> None:
        """Send ``link``'s new status (completion, pre-emption) to the caller's satellite."""

    def granted(self, link: Link) -> None:
        """Tell the caller's satellite that ``link``'s caller now owns the target."""

    def actuator(self, device: str, machine: int, value: Any, source: str) -> None:
        """Carry an actuator command to the device's satellite."""

    def device_status(self, device: str, status: str, reason: str) -> None:
        """Tell every satellite that a local device changed status."""

    def estop(self, reason: str) -> None:
        """Emergency stop on every other satellite, at top priority."""

    def is_up(self, machine: int) -> bool:
        """Whether satellite ``machine`` is on the link now."""

    def query(self, link: Link, asker: TaskEntry, peer: TaskEntry, qid: int, topic: str,
              args: list[Any]) -> None:
        """Carry ``asker``'s world-model query ``qid`` to ``peer``'s satellite (on ``link``, a
        link joining the two). Raises MessageError if it cannot be encoded or sent."""


class MessageManager:
    """Message transfer and ownership for one satellite's tables."""

    def __init__(self, kernel: Kernel, tsktab: Tsktab, msgtab: Msgtab) -> None:
        self.kernel = kernel
        self.tsktab = tsktab
        self.msgtab = msgtab
        self.devtab: Devtab | None = None
        self.taps: list[tuple[TaskEntry, TapPort, dict[str, Link]]] = []
        self._files: dict[str, TextIO] = {}
        self.base_dir = Path.cwd()
        #: where run state lives beside the map (learned world-model data): set by the System
        self.state_dir = Path.cwd()
        self.comm: Comm | None = None
        self.local: set[int] | None = None  # machines hosted here (None: every machine)
        self._qseq = 0
        self._ask_seq = 0
        self._asks: dict[int, tuple[TaskEntry, int]] = {}  # remote queries: id -> (asker, machine)
        kernel.set_end_handler(self._activation_ended)

    def is_local(self, machine: int) -> bool:
        """True if ``machine`` runs in this process."""
        return self.local is None or machine in self.local

    def _remote_task(self, t: TaskEntry | None) -> bool:
        return t is not None and self.local is not None and t.machine not in self.local

    # ---- events -----------------------------------------------------------------------------
    def event(self, kind: str, detail: str) -> None:
        """Report a system event to the instruments and the log."""
        log.info("%s: %s", kind, detail)
        for i in self.kernel.h_event:
            i.event(kind, detail)

    # ---- sensory messages (tputc) -----------------------------------------------------------
    def put(self, t: TaskEntry, value: Any) -> int:
        """Send ``value`` from ``t`` up every sensory link leaving it (and into exception taps).

        Never blocks. Returns how many links took it. Raises QueueOverflow (after delivering to
        every other link) if a queued link was full.
        """
        n = 0
        overflow: QueueOverflow | None = None
        for link in t.up_links:
            try:
                if self.deliver(link, value):
                    n += 1
            except QueueOverflow as exc:
                overflow = exc
        if self.taps:
            self._tap(t, value)
        if overflow is not None:
            raise overflow
        return n

    def deliver(self, link: Link, value: Any) -> bool:
        """Put ``value`` into ``link``'s destination port and ready a receiver waiting on it.

        False if the link is suspended. Raises QueueOverflow for a full queued link.
        """
        if link.status is _LINK_SUSPENDED:
            link.refused += 1
            return False
        if link.remote:
            assert self.comm is not None
            link.sent += 1
            self.comm.sensory(link, value)
            return True
        port = link.port
        if not isinstance(port, InPort):
            raise MessageError(f"sensory link {link.name} has no input port")
        kernel = self.kernel
        if port.fifo is None and not kernel.h_delivered:  # the hot path: newest wins
            if port.fresh:
                link.overwritten += 1
                if kernel.h_overwritten:
                    for i in kernel.h_overwritten:
                        i.message_overwritten(link)
            port.value = value
            port.fresh = True
        elif port.store(value, kernel.clock.now()):
            link.overwritten += 1
            for i in kernel.h_overwritten:
                i.message_overwritten(link)
        link.sent += 1
        if kernel.h_sent:
            for i in kernel.h_sent:
                i.message_sent(link)
        w = port.waiter
        if w is not None and (w.wake_filter is None or self._wanted(w, link.src, value)):
            base = w.base_prio
            kernel.wake(w, base if base > link.priority else link.priority, port)
        return True

    @staticmethod
    def _wanted(w: TaskEntry, source: str, value: Any) -> bool:
        """Whether ``w``'s ``wait_any(when=...)`` filter lets this message wake it (a filter
        that raises lets it through: a failure is never masked)."""
        f = w.wake_filter
        try:
            return f is None or bool(f(source, value))
        except Exception:
            log.exception("wake filter of %s failed on a message from %s", w.name, source)
            return True

    def _tap(self, t: TaskEntry, value: Any) -> None:
        for _exc_task, tap, links in self.taps:
            link = links.get(t.name)
            if link is None or link.status is LinkStatus.SUSPENDED:
                continue
            if link.remote:
                assert self.comm is not None
                link.sent += 1
                self.comm.tap(link, t.name, value)
                continue
            self.deliver_tap(link, tap, t.name, value)

    def deliver_tap(self, link: Link, tap: TapPort, source: str, value: Any) -> None:
        """Put ``source``'s message into an exception task's tap and ready the task."""
        kernel = self.kernel
        if tap.store_from(source, value, kernel.clock.now()):
            link.overwritten += 1
        link.sent += 1
        w = tap.waiter
        if w is not None and (w.wake_filter is None or self._wanted(w, source, value)):
            tap.waiter = None
            kernel.wake(w, max(w.base_prio, link.priority), tap)

    def taken(self, link: Link, sent_at: float) -> None:
        """Count a delivery on ``link`` (the receiver read it) and feed latency instruments."""
        link.delivered += 1
        hooks = self.kernel.h_delivered
        if hooks:
            lat = self.kernel.clock.now() - sent_at
            for i in hooks:
                i.message_delivered(link, lat)

    # ---- command output to actuators and files (putc) ---------------------------------------
    def write(self, t: TaskEntry, link: Link, value: Any) -> None:
        """Send ``value`` down command link ``link`` to an actuator or a file, without blocking.

        Raises MessageError if the link leads to a task (use open), DeviceError if the actuator
        refuses the value (outside its limits, failed device).
        """
        if link.status is LinkStatus.SUSPENDED:
            link.refused += 1
            raise MessageError(f"link {link.name} is suspended")
        if link.dst_kind is EndpointKind.DEVICE:
            if self.devtab is None:
                raise DeviceError(f"no device table: cannot write {link.dst}")
            self.devtab.write(link.dst, value, source=t.name)
        elif link.dst_kind is EndpointKind.FILE:
            self.write_file(link.dst, value)
        else:
            raise MessageError(
                f"{link.name} is a command link to task {link.dst}: invoke it, do not write to it")
        link.sent += 1
        link.delivered += 1

    def resolve_path(self, name: str) -> Path:
        """A file endpoint's path: relative names are relative to the system's base directory."""
        p = Path(name)
        return p if p.is_absolute() else self.base_dir / p

    def write_file(self, path: str, value: Any) -> None:
        """Append ``value`` as one line to the file at ``path`` (kept open, line-buffered)."""
        fh = self._files.get(path)
        if fh is None:
            try:
                fh = open(self.resolve_path(path), "a", buffering=1,  # noqa: SIM115 - kept open
                          encoding="utf-8")
            except OSError as exc:
                raise MessageError(f"cannot open output file {path}: {exc}") from exc
            self._files[path] = fh
        fh.write(f"{value}\n")

    def close_files(self) -> None:
        """Close every output file."""
        for fh in self._files.values():
            fh.close()
        self._files.clear()

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
            assert self.comm is not None
            link.pending = True
            link.sent += 1
            self.comm.open(link, command, wait)
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
                self._report(owner, LinkStatus.PREEMPTED,
                             error=f"pre-empted by {link.src} at priority {link.priority}")
                self.event("preempt", f"{link.src} took {target.name} from {owner.src} "
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
            assert self.comm is not None
            self.comm.close(link)
            return
        target.waitq[:] = [e for e in target.waitq if e[1] is not link]
        if target.owner is link:
            self._release(target)

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
            self._activate(target, command, link.priority)
        else:
            target.next_command = (command, link.priority, link)
            self.kernel.cancel(target, f"new command from {link.src}")

    def _activate(self, target: TaskEntry, command: Any, prio: int) -> None:
        target.command = command
        target.last_command = command
        target.new_command = None
        target.activations += 1
        try:
            coro = target.func(target.ctx, command)
        except Exception as exc:  # a task function that fails before its first await
            self._activation_ended(target, "error", exc)
            return
        if not hasattr(coro, "send"):
            self._activation_ended(target, "error", MessageError(
                f"task {target.name}: {target.code or 'its function'} is not an async def"))
            return
        target.coro = coro  # type: ignore[assignment]
        self.kernel.ready(target, prio)

    def _release(self, t: TaskEntry) -> None:
        t.owner = None
        if t.waitq:
            best = max(t.waitq, key=lambda e: (e[1].priority, -e[0]))
            t.waitq.remove(best)
            _, link, command = best
            link.pending = False
            link.status = LinkStatus.OK
            t.owner = link
            caller = self._caller(link)
            if self._remote_task(caller):
                assert self.comm is not None
                self.comm.granted(link)
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
            if t.state is TaskState.READY and not t.frozen:
                self.kernel.ready(t, t.default_prio)
            else:
                t.prio = t.default_prio

    def _caller(self, link: Link) -> TaskEntry | None:
        if link.src_kind is EndpointKind.TASK and link.src in self.tsktab:
            return self.tsktab.get(link.src)
        return None

    def _report(self, link: Link, status: LinkStatus, result: Any = None, error: str = "") -> None:
        """Set ``link``'s status and tell the calling task (wakes it if it waits in ``done``)."""
        link.status = status
        link.result = result
        link.error = error
        link.reported = True
        caller = self._caller(link)
        if self._remote_task(caller):
            assert self.comm is not None
            self.comm.report(link)
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
        if self.kernel.h_event:
            self.event("complete", f"{t.name} completed for {link.src}")
        self._report(link, LinkStatus.NORMAL, result=result)
        t.owner = None
        if t.waitq:
            self._release(t)
        else:
            self._back_to_default(t)

    def _activation_ended(self, t: TaskEntry, how: str, value: Any) -> None:
        t.coro = None
        t.new_command = None
        self.release_subordinates(t, f"{t.name} ended ({how})")
        if how == "return":
            if t.owner is not None:
                self.complete(t, value)
            elif t.waitq:
                self._release(t)
        elif how == "error":
            t.abnormal += 1
            text = describe_error(value)
            t.last_error = text
            log.error("task %s ended abnormally: %s", t.name, text)
            self.event("abnormal", f"{t.name}: {text}")
            link = t.owner
            if link is not None:
                self._report(link, LinkStatus.ABNORMAL, error=text)
            if self.devtab is not None:
                self.devtab.safe_outputs(t)
            t.owner = None
            if t.waitq:
                self._release(t)
        if t.coro is None:
            nxt, t.next_command = t.next_command, None
            if nxt is not None:
                command, prio, link = nxt
                if t.owner is link:
                    self._activate(t, command, prio)
                    return
            t.state = TaskState.SUSPENDED
            if t.owner is None:
                t.prio = t.default_prio
                if how == "error":
                    self._plan_restart(t, value)
                elif how == "preempted":  # released (tclose): suspended with actuators safe
                    if self.devtab is not None:
                        self.devtab.safe_outputs(t)
                    if t.standing and not t.frozen:
                        self.start_standing(t, "re-armed after its owner released it")

    # ---- standing tasks and restart policies ------------------------------------------------
    def start_standing(self, t: TaskEntry, why: str = "started") -> None:
        """Start a standing task's own activation (no owner, no command) if it has none and
        nobody owns it; local tasks only."""
        if not self.is_local(t.machine) or t.coro is not None or t.owner is not None:
            return
        self.event("standing", f"{t.name} {why}")
        self._activate(t, None, t.default_prio)

    def _plan_restart(self, t: TaskEntry, err: Any) -> None:
        """After an abnormal end with nobody to take the task over: apply its restart policy."""
        if t.restart == "never" or not self.is_local(t.machine):
            return
        if t.restart == "always":
            self._restart_later(t, f"restart=always after {type(err).__name__}")
            return
        bad = self._unhealthy_devices(t)
        if not bad:  # on-recovery: it did not end because a device failed
            self.event("restart-skipped", f"{t.name}: ended abnormally with its devices healthy "
                                          "(restart=on-recovery restarts only after a device "
                                          "failure)")
            return
        t.waiting_devices = frozenset(bad)
        self.event("restart-waiting", f"{t.name}: waiting for {', '.join(sorted(bad))} to be "
                                      "healthy again")

    def _unhealthy_devices(self, t: TaskEntry) -> set[str]:
        devtab = self.devtab
        if devtab is None:
            return set()
        names = {p.link.src for p in t.in_ports if p.link.src_kind is EndpointKind.DEVICE}
        names |= {lk.dst for lk in t.out_links if lk.dst_kind is EndpointKind.DEVICE}
        return {n for n in names if not _healthy(devtab, n)}

    def _restart_later(self, t: TaskEntry, why: str) -> None:
        if t.restart_timer is not None:
            return

        def fire() -> None:
            t.restart_timer = None
            if t.coro is not None or t.owner is not None or t.frozen:
                return  # somebody took it over meanwhile: the owner decides
            t.restarts += 1
            self.event("restart", f"{t.name} restarted ({why}) with its last command "
                                  f"{t.last_command!r}")
            self._activate(t, t.last_command, t.default_prio)

        t.restart_timer = self.kernel.call_later(t.backoff, fire)

    def device_health(self, device: str, healthy: bool, cause: str) -> None:
        """Devtab health listener: restart the on-recovery tasks waiting for ``device``."""
        if not healthy:
            return
        devtab = self.devtab
        for t in self.tsktab:
            if device in t.waiting_devices:
                if devtab is not None and any(not _healthy(devtab, n)
                                              for n in t.waiting_devices):
                    continue
                t.waiting_devices = frozenset()
                self._restart_later(t, f"restart=on-recovery: {device} healthy again")

    # ---- ownership of subordinates ------------------------------------------------------------
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
                    assert self.comm is not None
                    link.pending = False
                    self.comm.close(link)
                continue
            target = self.tsktab.get(link.dst)
            if link.pending:
                link.pending = False
                target.waitq[:] = [e for e in target.waitq if e[1] is not link]
            if target.owner is link:
                n += 1
                self.event("release", f"{target.name} released: {why}")
                self._release(target)
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
            self._report(link, LinkStatus.PREEMPTED, error=f"{t.name} reset after an emergency")
            t.owner = None
        for _seq, link, _cmd in t.waitq:
            link.pending = False
            self._report(link, LinkStatus.PREEMPTED, error=f"{t.name} reset")
        t.waitq.clear()
        t.next_command = None
        if t.coro is not None:
            self.kernel.cancel(t, "reset")
        self.resume_task(t)
        t.frozen_ready = None
        if t.coro is None:
            t.prio = t.default_prio
        return frozen

    def wipe(self, t: TaskEntry, why: str) -> None:
        """Forget everything ``t`` was doing (a reload from scratch): its owner and waiters are
        told it was pre-empted, its activation is closed at once (its ``finally`` blocks run),
        what it owned is released, its unread messages, newest command, suspension and pending
        restart are dropped; it stays SUSPENDED at its default priority."""
        for link in [e[1] for e in t.waitq] + ([t.owner] if t.owner is not None else []):
            link.pending = False
            self._report(link, LinkStatus.PREEMPTED, error=why)
        t.owner = None
        t.waitq.clear()
        coro, t.coro = t.coro, None
        self.kernel.unhook(t)
        t.stamp = -1  # drop any ready-heap entry
        if coro is not None:
            try:
                coro.close()
            except Exception:
                log.exception("task %s: closing its activation failed", t.name)
        self.release_subordinates(t, why)
        t.frozen = False
        t.frozen_ready = None
        t.cancelling = False
        t.next_command = t.new_command = None
        t.send_value = t.throw_exc = None
        t.waiting_devices = frozenset()
        if t.restart_timer is not None:
            t.restart_timer.cancel()
            t.restart_timer = None
        for p in t.in_ports:
            p.fresh = False
            p.value = None
            if p.fifo is not None:
                p.fifo.clear()
        if isinstance(t.tap, TapPort):
            t.tap.newest.clear()
            t.tap.order.clear()
        for link in self.msgtab:
            if link.dst == t.name and link.status is LinkStatus.SUSPENDED:
                link.status = LinkStatus.OK
        t.prio = t.default_prio
        t.state = TaskState.SUSPENDED

    def resetpri(self, t: TaskEntry) -> int:
        """resetpri: ``t`` runs again at the priority of its owning link, or at its default
        priority when unowned (a ready task is re-queued). Returns the priority."""
        prio = t.owner.priority if t.owner is not None else t.default_prio
        if t.state is TaskState.READY:
            self.kernel.ready(t, prio)
        else:
            t.prio = prio
        return prio

    # ---- answers from other satellites (called by the communications manager) ---------------
    def remote_open(self, link: Link, command: Any, wait: bool) -> OpenAnswer:
        """Run an ``open`` that a task on another satellite asked for; returns the answer for
        the caller's satellite: owner, queued, or busy (with the reason)."""
        try:
            owner = self.open(link, command, wait=wait)
            return OpenAnswer.owner() if owner else OpenAnswer.queued()
        except Busy as exc:
            return OpenAnswer.busy(str(exc))

    def open_answer(self, link: Link, answer: OpenAnswer) -> None:
        """The target's satellite answered this satellite's ``open`` on ``link``."""
        caller = self._caller(link)
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
        self._report(link, status, result, error)

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
        comm = self.comm
        if comm is None or not comm.is_up(peer.machine):
            raise MessageError(f"cannot ask {peer.name}: satellite {peer.machine} is not up")
        self._ask_seq += 1
        qid = self._ask_seq
        comm.query(link, t, peer, qid, topic, list(args))
        self._asks[qid] = (t, peer.machine)
        t.wait_query = qid

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
        for t in self.tsktab:
            if not self.is_local(t.machine):
                continue
            for _seq, link, _cmd in list(t.waitq):
                if link.src_machine == machine and link.src_kind is EndpointKind.TASK:
                    t.waitq[:] = [e for e in t.waitq if e[1] is not link]
                    link.pending = False
            owner = t.owner
            if (owner is not None and owner.src_kind is EndpointKind.TASK
                    and owner.src_machine == machine):
                n += 1
                self.event("release", f"{t.name} released: its owner {owner.src} died with "
                                      f"satellite {machine}")
                self._release(t)
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
        for link in self.msgtab:
            if link.type is not LinkType.COMMAND or link.dst_kind is not EndpointKind.TASK:
                continue
            if not link.remote or link.dst_machine != machine:
                continue
            caller = self._caller(link)
            if caller is None or self._remote_task(caller):
                continue
            if link.pending or (link.status is LinkStatus.OK and link.sent):
                link.pending = False
                self._report(link, LinkStatus.ABNORMAL,
                             error=f"satellite {machine} running {link.dst} died")
                n += 1
        return n

    # ---- status (msgstat) and priorities ----------------------------------------------------
    def setpri(self, link: Link, prio: int) -> None:
        """Change ``link``'s priority now; a ready task it owns is re-queued at the new one."""
        link.priority = prio
        if link.dst_kind is EndpointKind.TASK and link.dst in self.tsktab:
            target = self.tsktab.get(link.dst)
            if target.owner is link and target.state is TaskState.READY:
                self.kernel.ready(target, prio)

    def done_now(self, link: Link) -> Completion | None:
        """The pending report on ``link`` if there is one (and consume it), else None."""
        if link.reported:
            link.reported = False
            return link.completion()
        return None
