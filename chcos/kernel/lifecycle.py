"""lifecycle - how a task's activation is frozen, cancelled and ended, for the scheduler.

:class:`Lifecycle` is owned by :class:`chcos.kernel.scheduler.Kernel`: suspend/resume (a frozen
task keeps its wake-ups for later), cancellation (:class:`chcos.errors.Preempted` thrown in at
its next step), and the end of an activation (returned, pre-empted, failed), which the kernel
tells the layer above through its end handler (:data:`EndHandler`, with an :class:`End`).
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from typing import Any, Protocol

from chcos.errors import KernelError, Preempted
from chcos.tables.tasks import TaskEntry, TaskState

__all__ = ["BLOCK", "YIELD", "End", "EndHandler", "Lifecycle"]

#: Trap a task yields to give the processor back and stay ready.
YIELD = object()
#: Trap a task yields after it has recorded what it waits for.
BLOCK = object()


class End(enum.Enum):
    """How an activation ended, as the kernel tells its end handler."""

    RETURN = "return"        # the task function returned (its value is the result)
    PREEMPTED = "preempted"  # cancelled: Preempted was thrown into it, or it was released
    ERROR = "error"          # it raised (the exception is the value)


EndHandler = Callable[[TaskEntry, End, Any], None]


class Scheduler(Protocol):
    """What :class:`Lifecycle` needs of its kernel (:class:`chcos.kernel.scheduler.Kernel`)."""

    current: TaskEntry | None

    def ready(self, t: TaskEntry, prio: int) -> None:
        """Make ``t`` ready at ``prio``."""

    def unready(self, t: TaskEntry) -> None:
        """Take ``t`` out of the ready queue."""


class Lifecycle:
    """Suspend, resume, cancel and end the activations of ``kernel``'s tasks (owned by the
    kernel, which delegates its ``suspend``, ``resume``, ``cancel`` and ``unhook`` here and
    hands it every step that ends otherwise than in a plain wait or yield)."""

    def __init__(self, kernel: Scheduler) -> None:
        self.kernel = kernel
        self.on_end: EndHandler | None = None

    def unhook(self, t: TaskEntry) -> None:
        """Forget whatever ``t`` was waiting for: its timer or sleep, and what the layer that
        blocked it registered in ``t.unwait``."""
        unwait = t.unwait
        if unwait is not None:
            t.unwait = None
            unwait(t)
        t.sleep_until = None
        if t.timer is not None:
            t.timer.cancel()
            t.timer = None

    def suspend(self, t: TaskEntry) -> None:
        """Freeze ``t`` where it is: it will not run until :meth:`resume`; wake-ups meanwhile are
        kept. Raises KernelError when a task suspends itself (it would never resume)."""
        if t is self.kernel.current:
            raise KernelError(f"task {t.name} cannot suspend itself")
        if t.frozen:
            return
        t.frozen = True
        if t.state is TaskState.READY:
            t.frozen_ready = t.prio
            self.kernel.unready(t)
        else:
            t.frozen_state = t.state  # what it waits in, for resume (a wake-up meanwhile
            # ends the wait and is kept by ready as frozen_ready)
        t.state = TaskState.SUSPENDED

    def resume(self, t: TaskEntry) -> None:
        """Undo :meth:`suspend`: a task that was woken meanwhile becomes ready again."""
        if not t.frozen:
            return
        t.frozen = False
        pending, t.frozen_ready = t.frozen_ready, None
        state, t.frozen_state = t.frozen_state, None
        if pending is not None:
            self.kernel.ready(t, pending)
        elif t.coro is not None and state is not None:
            t.state = state  # still waiting for what it waited for when it was frozen
        else:
            t.state = TaskState.SUSPENDED

    def cancel(self, t: TaskEntry, reason: str) -> None:
        """End ``t``'s current activation: :class:`Preempted` is thrown into it at its next step.
        Does nothing if the task has no activation."""
        if t.coro is None or t.cancelling:
            return
        t.cancelling = True
        self.unhook(t)
        t.throw_exc = Preempted(reason)
        t.send_value = None
        if t is not self.kernel.current:  # (cancelled in its own step: the step ends it)
            frozen, t.frozen = t.frozen, False
            self.kernel.ready(t, max(t.prio, t.base_prio))
            t.frozen = frozen
            if frozen:  # it runs to its end although frozen; resume finds it ready
                t.frozen_state = TaskState.READY

    def raised(self, t: TaskEntry, err: Exception) -> None:
        """``t``'s step raised ``err``: its activation ended (returned, pre-empted, failed)."""
        if isinstance(err, StopIteration):
            self._end(t, End.PREEMPTED if t.cancelling else End.RETURN, err.value)
        elif isinstance(err, Preempted):
            self._end(t, End.PREEMPTED, err)
        else:
            self._end(t, End.PREEMPTED if t.cancelling else End.ERROR, err)

    def odd_trap(self, t: TaskEntry, coro: Any, trap: Any) -> None:
        """``t``'s step ended in something other than a plain block or yield: a cancelled task
        that carried on (or was cancelled during the step), or an await of something not a
        chcos call."""
        if t.cancelling:  # it caught the cancellation and carried on: end it for good
            coro.close()
            self._end(t, End.PREEMPTED, None)
        else:
            coro.close()
            self._end(t, End.ERROR, KernelError(
                f"task {t.name} awaited something that is not a chcos call ({trap!r})"))

    def _end(self, t: TaskEntry, how: End, value: Any) -> None:
        t.coro = None
        t.send_value = None   # a next activation's first step sends None
        t.throw_exc = None
        t.cancelling = False
        self.unhook(t)
        if self.on_end is not None:
            self.on_end(t, how, value)
        else:
            t.state = TaskState.SUSPENDED
