"""context - the user API: what a task's code calls (the thesis' Usrmgr.h / sysfile.h).

Every task function is ``async def task(ctx: TaskContext, command) -> result``; it runs once per
command (invocation) and its return is the normal completion (teotsk) reported to the owner.
``ctx`` is the task's Usrtab: eight input ports (sensory sources) and eight output ports (command
destinations), addressed by index or by the peer's name. Calls that can wait are awaited; sending
upward and writing to actuators never block.

Thesis name → chcos name: tgetc → :meth:`TaskContext.read` / :meth:`~TaskContext.read_any` /
:meth:`~TaskContext.poll`; tputc → :meth:`~TaskContext.put`; putc (actuator) →
:meth:`~TaskContext.write`; topen → :meth:`~TaskContext.invoke`;
tclose → :meth:`~TaskContext.close`;
teotsk → return, or :meth:`~TaskContext.complete`; msgstat → :meth:`~TaskContext.status`;
sleep → :meth:`~TaskContext.sleep`; gettid → :attr:`~TaskContext.tid`.
"""

from __future__ import annotations

import logging
import types
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from chcos.errors import MessageError, ReadTimeout, SensorFailure
from chcos.kernel.scheduler import BLOCK, YIELD, Kernel
from chcos.messages.manager import MessageManager
from chcos.messages.waits import forget
from chcos.tables.messages import (
    PRIORITIES,
    Completion,
    EndpointKind,
    InPort,
    Link,
    LinkStatus,
    LinkType,
    TapPort,
)
from chcos.tables.tasks import TaskEntry, TaskState
from chcos.user.worldmodel import WorldModel

Port = int | str
log = logging.getLogger("chcos.user.context")
_WAITING = TaskState.WAITING  # a module constant: read on every blocking read


@dataclass(frozen=True)
class Event:
    """What :meth:`TaskContext.wait_any` returns: what happened first.

    ``kind`` is ``"command"`` (a newer command from this task's owner; ``value`` is the
    command, ``source`` the owner), ``"completion"`` (a subordinate completed or was
    pre-empted; ``value`` is the :class:`Completion`, ``port`` the output port), ``"exception"``
    (a tapped sensory message of a lower task; ``source`` is that task), ``"message"`` (a message
    on input ``port`` from ``source``) or ``"failure"`` (the sensor on input ``port`` failed or
    went stale while waiting; ``value`` is the reason)."""

    kind: str
    source: str
    value: Any = None
    port: int = -1


class TaskContext:
    """The handle a task's code uses for every system call. One per task, made at install."""

    def __init__(self, task: TaskEntry, kernel: Kernel, msgmgr: MessageManager) -> None:
        self._t = task
        self._k = kernel
        self._mm = msgmgr

    # ---- identity ---------------------------------------------------------------------------
    @property
    def tid(self) -> int:
        """This task's id (gettid)."""
        return self._t.tid

    @property
    def name(self) -> str:
        """This task's name."""
        return self._t.name

    @property
    def machine(self) -> int:
        """The machine (satellite) number the task runs on."""
        return self._t.machine

    @property
    def level(self) -> int:
        """The task's level in the hierarchy (1 = just above the devices)."""
        return self._t.level

    @property
    def params(self) -> dict[str, Any]:
        """Install-time parameters (``install --param key=value``)."""
        return self._t.params

    @property
    def command(self) -> Any:
        """The command (parameters) of the current activation; after :meth:`take_command`, the
        newest one taken."""
        return self._t.command

    @property
    def has_command(self) -> bool:
        """True when the owner sent a newer command to this running activation (a repeated
        topen from the owner, Appendix 3) that :meth:`take_command` has not taken yet."""
        return self._t.new_command is not None

    def take_command(self) -> Any:
        """The owner's newest command to this running activation (it becomes :attr:`command`).
        Raises MessageError if there is none (see :attr:`has_command`)."""
        t = self._t
        if t.new_command is None:
            raise MessageError(f"task {t.name}: no new command from its owner")
        (cmd,), t.new_command = t.new_command, None
        t.command = t.last_command = cmd
        return cmd

    @property
    def world(self) -> WorldModel:
        """This task's world model."""
        wm = self._t.world
        if not isinstance(wm, WorldModel):
            raise MessageError(f"task {self._t.name} has no world model")
        return wm

    @property
    def now(self) -> float:
        """The kernel clock's time in seconds."""
        return self._k.clock.now()

    @property
    def priority(self) -> int:
        """The priority the task runs at now."""
        return self._t.prio

    @property
    def inputs(self) -> list[str]:
        """Names of the sources on input ports 0..n-1."""
        return [p.link.src for p in self._t.in_ports]

    @property
    def outputs(self) -> list[str]:
        """Names of the destinations on output ports 0..n-1."""
        return [lk.dst for lk in self._t.out_links]

    # ---- port lookup ------------------------------------------------------------------------
    def _in(self, port: Port) -> InPort:
        ports = self._t.in_ports
        if isinstance(port, int):
            if 0 <= port < len(ports):
                return ports[port]
            raise MessageError(f"task {self._t.name} has no input port {port} "
                               f"(it has {len(ports)}: {', '.join(self.inputs) or 'none'})")
        for p in ports:
            if p.link.src == port:
                return p
        raise MessageError(f"task {self._t.name} has no input from {port!r} "
                           f"(inputs: {', '.join(self.inputs) or 'none'})")

    def _out(self, port: Port) -> Link:
        links = self._t.out_links
        if isinstance(port, int):
            if 0 <= port < len(links):
                return links[port]
            raise MessageError(f"task {self._t.name} has no output port {port} "
                               f"(it has {len(links)}: {', '.join(self.outputs) or 'none'})")
        for lk in links:
            if lk.dst == port:
                return lk
        special = self._t.special_links.get(port)
        if special is not None:
            return special
        raise MessageError(f"task {self._t.name} has no output to {port!r} "
                           f"(outputs: {', '.join(self.outputs) or 'none'})")

    def input_file(self, port: Port = 0) -> str:
        """The path of the file on input ``port`` (relative names resolved against the system's
        base directory); raises MessageError if it is not a file."""
        link = self._in(port).link
        if link.src_kind is not EndpointKind.FILE:
            raise MessageError(f"input {link.src} of task {self._t.name} is not a file")
        return str(self._mm.resolve_path(link.src))

    # ---- sensory input (tgetc) --------------------------------------------------------------
    def _check_source(self, p: InPort) -> None:
        link = p.link
        if link.src_kind is EndpointKind.DEVICE:
            self._mm.devices.check_readable(link.src)

    def _take(self, p: InPort) -> Any:
        value, at = p.take()
        self._mm.taken(p.link, at)
        return value

    def _arm_timeout(self, timeout: float | None, what: str) -> None:
        if timeout is None:
            return
        t, k = self._t, self._k

        def expire() -> None:
            t.timer = None
            k.wake(t, t.base_prio, exc=ReadTimeout(
                f"task {t.name}: no message on {what} within {timeout} s"))

        t.timer = k.call_later(timeout, expire)

    @types.coroutine
    def read(self, port: Port = 0, *, timeout: float | None = None) -> Generator[Any, Any, Any]:
        """The newest message on input ``port``, waiting for one if there is none.

        Raises MessageError for a bad port, SensorFailure if the source is a failed or stale
        sensor (also while waiting), ReadTimeout after ``timeout`` seconds without a message.
        """
        ports = self._t.in_ports
        p = ports[port] if port.__class__ is int and 0 <= port < len(ports) else self._in(port)
        if not p.fresh:
            if p.device:
                self._check_source(p)
            t = self._t
            p.waiter = t
            t.wait_ports = p.single
            t.unwait = forget
            t.state = _WAITING
            if self._k.h_blocked:
                self._k.block(t, _WAITING)
            if timeout is not None:
                self._arm_timeout(timeout, p.link.name)
            yield BLOCK
        if p.fifo is None and not self._k.h_delivered:  # the hot path
            value = p.value
            p.value = None
            p.fresh = False
            p.link.delivered += 1
            return value
        return self._take(p)

    @types.coroutine
    def read_any(self, ports: Sequence[Port] | None = None, *,
                 timeout: float | None = None) -> Generator[Any, Any, tuple[int, Any]]:
        """(port index, message) from whichever of ``ports`` (default: all inputs) has one; if
        several do, the highest-priority link first, then the lowest port. Waits if none has.
        Raises as :meth:`read`."""
        chosen = [self._in(p) for p in ports] if ports is not None else list(self._t.in_ports)
        if not chosen:
            raise MessageError(f"task {self._t.name} has no input ports to read")
        fresh = [p for p in chosen if p.fresh]
        if fresh:
            best = max(fresh, key=lambda p: (p.link.priority, -p.index))
            return best.index, self._take(best)
        for p in chosen:
            self._check_source(p)
        t = self._t
        for p in chosen:
            p.waiter = t
        t.wait_ports = tuple(chosen)
        t.unwait = forget
        self._k.block(t, TaskState.WAITING)
        self._arm_timeout(timeout, ", ".join(p.link.name for p in chosen))
        got: InPort = yield BLOCK
        return got.index, self._take(got)

    def poll(self, port: Port = 0, default: Any = None) -> Any:
        """The newest message on ``port`` if there is one, else ``default`` (never waits).
        Raises SensorFailure if there is none because the source sensor failed or is stale."""
        p = self._in(port)
        if p.fresh:
            return self._take(p)
        self._check_source(p)
        return default

    @types.coroutine
    def wait_any(self, ports: Sequence[Port] = (), *, exceptions: bool = False,
                 completions: Sequence[Port] = (), commands: bool = False,
                 when: Callable[[str, Any], bool] | None = None,
                 timeout: float | None = None) -> Generator[Any, Any, Event]:
        """Wait for whichever happens first and return it as an :class:`Event`: a message on one
        of the input ``ports``, a tapped message (``exceptions``, exception task only), the
        completion or pre-emption of a command sent on one of the output ports in
        ``completions``, a newer command from this task's owner (``commands``). What is already
        there is returned at once, in that order of importance: command, completion, tapped
        message, port message (highest link priority first). The returned message, completion or
        command is consumed.

        ``when(source, message)``, if given, decides which port and tap messages are worth
        waking for; it runs at delivery time in the sender's step, so it must be cheap and must
        not block. Messages it turns down stay unread (a newer one overwrites them).
        A sensor that fails while waited on gives a ``"failure"`` event (an already failed sensor
        is not reported again: wait for its next reading). Raises MessageError for a bad port or
        ``exceptions`` in a task that is not the exception task, ReadTimeout after ``timeout``
        seconds with nothing."""
        t = self._t
        ins = tuple(self._in(p) for p in ports)
        links = tuple(self._task_link(p) for p in completions)
        tap = t.tap if exceptions else None
        if exceptions and not isinstance(tap, TapPort):
            raise MessageError(f"task {t.name} is not an exception task: it has no tap to wait on")
        if not (ins or links or exceptions or commands):
            raise MessageError(f"task {t.name}: wait_any with nothing to wait for")
        deadline = None if timeout is None else self._k.clock.now() + timeout
        while True:
            ev = self._happened(ins, links, tap, commands, when)
            if ev is not None:
                if t.timer is not None:
                    t.timer.cancel()
                    t.timer = None
                return ev
            for p in ins:
                p.waiter = t
            t.wait_ports = ins
            if tap is not None:
                tap.waiter = t
                t.wait_tap = True
            t.wait_links = links
            t.wait_commands = commands
            t.wake_filter = when
            t.multi_wait = True
            t.unwait = forget
            self._k.block(t, TaskState.WAITING)
            if deadline is not None:
                self._arm_timeout(max(0.0, deadline - self._k.clock.now()), "wait_any")
            try:
                yield BLOCK
            except SensorFailure as exc:
                self._k.unhook(t)
                index = next((p.index for p in ins if p.link.src == exc.device), -1)
                return Event("failure", exc.device, exc.reason, index)
            finally:
                if t.multi_wait:  # woken by a message, the timer (the deadline) stays
                    t.unwait = None
                    forget(t)

    def _happened(self, ins: tuple[InPort, ...], links: tuple[Link, ...], tap: Any,
                  commands: bool, when: Callable[[str, Any], bool] | None) -> Event | None:
        t = self._t
        if commands and t.new_command is not None:
            src = t.owner.src if t.owner is not None else ""
            return Event("command", src, self.take_command())
        for link in links:
            report = self._mm.done_now(link)
            if report is not None:
                return Event("completion", link.dst, report, link.src_port)
        if tap is not None and tap.order:
            for src in tap.order:
                value = tap.newest[src][0]
                if when is None or _accepts(when, src, value):
                    _s, value, _at = tap.take_from(src)
                    return Event("exception", src, value)
        best: InPort | None = None
        for p in ins:
            if (p.fresh and (best is None or p.link.priority > best.link.priority)
                    and (when is None or _accepts(when, p.link.src, _head(p)))):
                best = p
        if best is not None:
            return Event("message", best.link.src, self._take(best), best.index)
        return None

    def feed(self, port: Port, value: Any) -> None:
        """Deliver ``value`` on input ``port`` as if its source had sent it. Thread-safe: for
        system drivers whose own thread reads a terminal or a file (the delivery happens on
        the kernel thread, between task steps). Raises MessageError for a bad port."""
        link = self._in(port).link
        mm = self._mm

        def deliver() -> None:
            mm.deliver(link, value)

        self._k.interrupt(deliver)

    def watch_events(self, fn: Callable[[str, str], None]) -> Callable[[], None]:
        """Call ``fn(kind, detail)`` on every system event (installs, setpri, invokes,
        completions, abnormal completions, pre-emptions, restarts, suspends, e-stops, device
        failures...) until the returned function is called. ``fn`` runs on the kernel thread in
        whatever step caused the event: it must not block (a system driver's log, e.g.)."""
        from chcos.kernel.instrument import Instrument

        class _Watch(Instrument):
            def event(self, kind: str, detail: str) -> None:
                fn(kind, detail)

        watch = _Watch()
        self._k.add_instrument(watch)
        return lambda: self._k.remove_instrument(watch)

    def pending(self, port: Port = 0) -> bool:
        """True if a message waits on ``port``."""
        return self._in(port).fresh

    # ---- sensory output (tputc) and actuator output (putc) ----------------------------------
    def put(self, value: Any) -> int:
        """Send ``value`` upward to every task that reads this one; never blocks. Returns how
        many links took it. Raises QueueOverflow if a queued link was full."""
        return self._mm.put(self._t, value)

    def write(self, port: Port, value: Any) -> None:
        """Command actuator (or output file) on ``port`` with ``value``; never blocks.
        Raises DeviceError if the actuator refuses it (outside limits, failed), MessageError if
        the port leads to a task."""
        self._mm.write(self._t, self._out(port), value)

    # ---- command messages (topen, tclose, teotsk, msgstat) ----------------------------------
    def _task_link(self, port: Port) -> Link:
        link = self._out(port)
        if link.dst_kind is not EndpointKind.TASK:
            raise MessageError(f"{link.name} leads to {link.dst_kind.value} {link.dst}, "
                               "not to a task: write() to it")
        return link

    @types.coroutine
    def invoke(self, port: Port, command: Any = None, *, wait: bool = True,
               priority: int | None = None) -> Generator[Any, Any, None]:
        """Invoke the lower task on ``port`` with ``command`` (topen). Returns once this task
        owns it (the target then runs at the link's priority). If a higher or equal priority owner
        holds it, waits in its queue, or with ``wait=False`` raises Busy at once.

        ``priority`` raises the link's priority for this and later commands (until setpri or
        resetpri), up to the priority this task runs at now: a task that a high-priority command
        made urgent may pass that urgency down (thesis 6.1.5: C1's priority-9 command makes B1
        take every A-level task). Raises MessageError for a priority above that or outside
        0..99 (:data:`chcos.tables.messages.PRIORITIES`)."""
        link = self._task_link(port)
        if priority is not None:
            cap = max(self._t.prio, self._t.base_prio)
            if priority not in PRIORITIES or priority > cap:
                raise MessageError(f"task {self._t.name} runs at priority {cap}: it cannot "
                                   f"invoke {link.dst} at priority {priority}")
            link.priority = max(link.priority, priority)
        if self._mm.open(link, command, wait=wait):
            return
        t = self._t
        t.wait_link = link
        t.unwait = forget
        self._k.block(t, TaskState.WAITING)
        try:
            yield BLOCK
        except BaseException:
            if link.pending:
                self._mm.close(link)
            raise

    @types.coroutine
    def done(self, port: Port) -> Generator[Any, Any, Completion]:
        """Wait until the command sent on ``port`` completes or is pre-empted, and return how.
        Returns at once if that has already happened. Raises MessageError if no command is
        outstanding on the link."""
        link = self._task_link(port)
        report = self._mm.done_now(link)
        if report is not None:
            return report
        target = self._mm.tsktab.get(link.dst)
        t = self._t
        while link.pending:  # still queued for the target: first become its owner
            t.wait_link = link
            t.unwait = forget
            self._k.block(t, TaskState.WAITING)
            yield BLOCK
        report = self._mm.done_now(link)
        if report is not None:
            return report
        outstanding = (link.sent > 0 and link.status is LinkStatus.OK if link.remote
                       else target.owner is link)  # a remote target's owner is known there
        if not outstanding:
            raise MessageError(f"no command outstanding on {link.name} (status "
                               f"{link.status.value})")
        t.wait_link = link
        t.unwait = forget
        self._k.block(t, TaskState.WAITING)
        result: Completion = yield BLOCK
        return result

    async def call(self, port: Port, command: Any = None) -> Completion:
        """Invoke the task on ``port`` and wait for its completion: topen + wait for eotsk."""
        await self.invoke(port, command)
        return await self.done(port)

    def close(self, port: Port) -> None:
        """Release the task on ``port`` (tclose): it passes to its best waiter or is suspended."""
        self._mm.close(self._task_link(port))

    def complete(self, result: Any = None) -> None:
        """Report normal completion to the owner now (teotsk) and end its command message; the
        activation may go on unowned. Returning from the task function does the same."""
        self._mm.complete(self._t, result)

    def status(self, port: Port) -> LinkStatus:
        """The status of the link on output ``port`` (msgstat): SUSPENDED while the task on it
        is suspended."""
        return self._out(port).status

    def resetpri(self, port: Port | None = None) -> int:
        """resetpri (Appendix 3): this task (or the task on output ``port``) runs again at the
        priority of the command message that owns it, or at its default priority when unowned.
        Returns that priority. Raises MessageError for a bad port."""
        t = self._t if port is None else self._mm.tsktab.get(self._task_link(port).dst)
        return self._mm.resetpri(t)

    def input_status(self, port: Port) -> LinkStatus:
        """The status of the link on input ``port``."""
        return self._in(port).link.status

    # ---- task management --------------------------------------------------------------------
    @types.coroutine
    def sleep(self, seconds: float) -> Generator[Any, Any, None]:
        """Sleep ``seconds`` of kernel-clock time (ASLEEP). Raises ValueError if negative."""
        if seconds < 0:
            raise ValueError(f"cannot sleep a negative time ({seconds})")
        t, k = self._t, self._k
        t.sleep_until = k.clock.now() + seconds

        def wake() -> None:
            t.timer = None
            k.wake(t, t.base_prio)

        t.timer = k.call_at(t.sleep_until, wake)
        k.block(t, TaskState.ASLEEP)
        yield BLOCK

    @types.coroutine
    def checkpoint(self) -> Generator[Any, Any, None]:
        """Give the processor to any ready task of higher or equal priority, then go on."""
        yield YIELD

    @property
    def commander(self) -> str | None:
        """The name of the task that owns (commands) this one now; None if idle or owned by the
        host (world-model context, ``chcos.user.worldmodel.context``)."""
        owner = self._t.owner
        if owner is None or owner.src not in self._mm.tsktab:
            return None
        return owner.src

    @property
    def state_dir(self) -> Path:
        """Where this system keeps run state beside its map (learned world-model data goes to
        ``state_dir/learned``): the directory of its sysfile.map (the satellite's state
        directory, ``chcos run``'s work directory), else its base directory."""
        return Path(self._mm.state_dir)

    # ---- world model queries ----------------------------------------------------------------
    @types.coroutine
    def ask(self, peer: str, topic: str, *args: Any,
            timeout: float | None = None) -> Generator[Any, Any, Any]:
        """Ask task ``peer``'s world model about ``topic`` (a request on a link joining the two
        tasks, answered by the peer's model, never by reading its memory). A peer on another
        satellite is asked over the link: this task waits for the answer, at most ``timeout``
        seconds if given. Raises MessageError if no link joins the tasks, the peer has no model,
        the model has no answer, or the peer's satellite is down or dies before answering;
        ReadTimeout if no answer came within ``timeout``."""
        me = self._t.name
        mm = self._mm
        mt = mm.msgtab
        joining = next((lk for a, b in ((me, peer), (peer, me)) for ty in LinkType
                        if (lk := mt.get(a, b, ty)) is not None), None)
        if joining is None:
            raise MessageError(f"task {me} has no link to {peer}: it may not query its world model")
        target = mm.tsktab.get(peer)
        if mm.is_local(target.machine):
            answer = mm.world_answer(target, topic, args)
            yield YIELD
            return answer
        t = self._t
        mm.ask_remote(t, joining, target, topic, args)
        self._k.block(t, TaskState.WAITING)
        self._arm_timeout(timeout, f"the answer of {peer} about {topic!r}")
        return (yield BLOCK)

    # ---- exception task and assassin --------------------------------------------------------
    @types.coroutine
    def read_exception(self, *, timeout: float | None = None) -> Generator[Any, Any,
                                                                            tuple[str, Any]]:
        """(source task, message): the next sensory message any lower task sent, newest per
        source. Only for a task installed as the exception task; raises MessageError otherwise."""
        tap = self._t.tap
        if not isinstance(tap, TapPort):
            raise MessageError(f"task {self._t.name} is not an exception task")
        if not tap.fresh:
            t = self._t
            tap.waiter = t
            t.unwait = forget
            self._k.block(t, TaskState.WAITING)
            self._arm_timeout(timeout, "the exception tap")
            try:
                yield BLOCK
            finally:
                tap.waiter = None
        src, value, _at = tap.take()
        return src, value

    def estop(self, reason: str) -> int:
        """Emergency stop: every actuator with a safe value gets it, at once. Returns how many
        were written here (every other satellite is told to do the same)."""
        return self._mm.estop(self._t.name, reason)

    def suspend_task(self, name: str) -> None:
        """Freeze task ``name`` where it is (assassin only; any lower command task).
        Raises MessageError if this task has no assassin link to it."""
        self._assassin_link(name)
        self._mm.suspend_task(self._mm.tsktab.get(name), self._t.name)
        self._mm.event("suspend", f"{self._t.name} suspended {name}")

    def resume_task(self, name: str) -> None:
        """Undo :meth:`suspend_task` (assassin only)."""
        self._assassin_link(name)
        self._mm.resume_task(self._mm.tsktab.get(name))

    def _assassin_link(self, name: str) -> Link:
        link = self._t.special_links.get(name)
        if link is None:
            raise MessageError(f"task {self._t.name} has no assassin link to {name}")
        return link


def _head(p: InPort) -> Any:
    """The message a fresh port would give next (without taking it)."""
    return p.fifo[0][0] if p.fifo is not None else p.value


def _accepts(when: Callable[[str, Any], bool], source: str, value: Any) -> bool:
    """``when(source, value)``; a filter that raises accepts (a failure is never masked)."""
    try:
        return bool(when(source, value))
    except Exception:
        log.exception("wait_any filter failed on a message from %s", source)
        return True
