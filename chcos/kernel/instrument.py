"""instrument - hooks into the kernel and message manager, and two ready-made listeners.

The kernel calls an instrument only when one is installed (one truth test on the hot path
otherwise). Subclass :class:`Instrument` and override what you need; every hook is a no-op here.
:class:`Counters` counts task executions and messages per task, link and level;
:class:`Latency` keeps message latency samples (send to delivery) for percentiles.
"""

from __future__ import annotations

from collections import Counter
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from chcos.tables.messages import Link
    from chcos.tables.tasks import TaskEntry


class Instrument:
    """Base listener; all hooks do nothing. Hooks run on the kernel thread and must not block."""

    def task_scheduled(self, task: TaskEntry) -> None:
        """``task`` was made ready."""

    def before_step(self, task: TaskEntry) -> None:
        """``task`` is about to run until its next wait."""

    def after_step(self, task: TaskEntry) -> None:
        """``task`` gave the processor back."""

    def task_blocked(self, task: TaskEntry) -> None:
        """``task`` now waits (message, semaphore, owner, sleep)."""

    def message_sent(self, link: Link) -> None:
        """A message entered ``link``."""

    def message_overwritten(self, link: Link) -> None:
        """A message on ``link`` replaced an unread older one (newest wins)."""

    def message_delivered(self, link: Link, latency: float) -> None:
        """The receiver took a message from ``link``, ``latency`` seconds after it was sent."""

    def event(self, kind: str, detail: str) -> None:
        """A system event: install, setpri, preemption, abnormal completion, estop..."""


class Counters(Instrument):
    """Counts executions per task and per level, and messages per link."""

    def __init__(self) -> None:
        self.steps: Counter[str] = Counter()
        self.activations: Counter[str] = Counter()
        self.steps_by_level: Counter[int] = Counter()
        self.sent: Counter[str] = Counter()
        self.overwritten: Counter[str] = Counter()
        self.delivered: Counter[str] = Counter()
        self.events: list[tuple[str, str]] = []

    def before_step(self, task: TaskEntry) -> None:
        """Count one execution of ``task``."""
        self.steps[task.name] += 1
        self.steps_by_level[task.level] += 1

    def message_sent(self, link: Link) -> None:
        """Count a message on ``link``."""
        self.sent[link.name] += 1

    def message_overwritten(self, link: Link) -> None:
        """Count an overwrite on ``link``."""
        self.overwritten[link.name] += 1

    def message_delivered(self, link: Link, latency: float) -> None:
        """Count a delivery on ``link``."""
        self.delivered[link.name] += 1

    def event(self, kind: str, detail: str) -> None:
        """Keep the event."""
        self.events.append((kind, detail))


class Latency(Instrument):
    """Message latency samples (seconds), bounded to the newest ``keep`` samples."""

    def __init__(self, keep: int = 100_000) -> None:
        self.keep = keep
        self.samples: list[float] = []

    def message_delivered(self, link: Link, latency: float) -> None:
        """Record one latency sample."""
        if len(self.samples) >= self.keep:
            del self.samples[: self.keep // 2]
        self.samples.append(latency)

    def percentile(self, q: float) -> float:
        """The ``q``-th percentile (0..100) of the samples; raises ValueError if there are none."""
        if not self.samples:
            raise ValueError("no latency samples")
        s = sorted(self.samples)
        i = min(len(s) - 1, max(0, round(q / 100 * (len(s) - 1))))
        return s[i]
