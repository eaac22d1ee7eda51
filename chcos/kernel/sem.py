"""sem - counting semaphores for tasks (the thesis' semwait/semsignal, Xinu's wait/signal)."""

from __future__ import annotations

import types
from collections import deque
from collections.abc import Generator
from typing import Any

from chcos.errors import KernelError
from chcos.kernel.scheduler import BLOCK, Kernel
from chcos.tables.tasks import TaskEntry, TaskState


class Semaphore:
    """A counting semaphore on one kernel; waiters are served first come first served."""

    def __init__(self, kernel: Kernel, count: int = 0) -> None:
        if count < 0:
            raise ValueError(f"semaphore count must be >= 0, got {count}")
        self.kernel = kernel
        self.count = count
        self._waiters: deque[TaskEntry] = deque()

    @types.coroutine
    def wait(self) -> Generator[Any, Any, None]:
        """Take one unit, waiting (WAITING state) while there is none. Raises KernelError when
        not awaited from a task."""
        t = self.kernel.current
        if t is None:
            raise KernelError("Semaphore.wait() must be awaited by a task")
        if self.count > 0:
            self.count -= 1
            return
        self._waiters.append(t)
        self.kernel.block(t, TaskState.WAITING)
        try:
            yield BLOCK
        finally:
            if t in self._waiters:  # cancelled while waiting
                self._waiters.remove(t)

    def signal(self) -> None:
        """Give one unit back, readying the first waiter if there is one."""
        while self._waiters:
            t = self._waiters.popleft()
            if t.coro is not None and not t.cancelling:
                self.kernel.wake(t, t.base_prio)
                return
        self.count += 1

    @property
    def waiting(self) -> int:
        """How many tasks wait."""
        return len(self._waiters)
