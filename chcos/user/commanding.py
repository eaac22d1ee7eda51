"""commanding - the command side of the task handle: sensory output (tputc), actuator and file
output (putc), invoking lower tasks and waiting for their completion (topen, tclose, teotsk,
msgstat), priorities, the emergency stop and the assassin's calls.

Sending upward and writing to actuators never block; ``invoke``, ``done`` and ``call`` are
awaited.
"""

from __future__ import annotations

import types
from collections.abc import Callable, Generator
from functools import partial
from typing import Any

from chcos.errors import MessageError
from chcos.kernel.scheduler import BLOCK, Kernel
from chcos.messages.manager import MessageManager
from chcos.messages.waits import forget
from chcos.tables.messages import PRIORITIES, Completion, Link, LinkStatus
from chcos.tables.tasks import TaskEntry, TaskState
from chcos.user.ports import Port, TaskHandle


class Commanding(TaskHandle):
    """Output ports, command messages and the assassin (part of
    :class:`chcos.user.context.TaskContext`)."""

    def __init__(self, task: TaskEntry, kernel: Kernel, msgmgr: MessageManager) -> None:
        super().__init__(task, kernel, msgmgr)
        #: ``put(value)``: send ``value`` upward to every task that reads this one (tputc);
        #: never blocks. Returns how many links took it. Raises QueueOverflow if a queued link
        #: was full. (The message manager's put for this task.)
        self.put: Callable[[Any], int] = partial(msgmgr.put, task)

    # ---- sensory output (tputc) and actuator output (putc) ----------------------------------

    def write(self, port: Port, value: Any) -> None:
        """Command actuator (or output file) on ``port`` with ``value``; never blocks.
        Raises DeviceError if the actuator refuses it (outside limits, failed), MessageError if
        the port leads to a task."""
        self._mm.write(self._t, self._out(port), value)

    # ---- command messages (topen, tclose, teotsk, msgstat) ----------------------------------
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
            link.set_priority(max(link.priority, priority))
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

    # ---- emergency stop and assassin --------------------------------------------------------
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
