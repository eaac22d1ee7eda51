"""instrument - hooks into the kernel and message manager, and two ready-made listeners.

The kernel calls an instrument only when one is installed (one truth test on the hot path
otherwise). Subclass :class:`Instrument` and override what you need; every hook is a no-op here.
An instrument whose hook raises is removed and the error logged (as trio does with its
instruments): the kernel and the other instruments carry on, and no task is left half-stepped.
:class:`Counters` counts task executions and messages per task, link and level;
:class:`Latency` keeps message latency samples (send to delivery) for percentiles.
"""

from __future__ import annotations

import logging
from collections import Counter
from typing import Any

from chcos.tables.messages import Link
from chcos.tables.tasks import TaskEntry

log = logging.getLogger("chcos.kernel.instrument")


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
        """The receiver took a message from ``link``, ``latency`` seconds after it was sent
        (told of the messages sent while an instrument listened to this hook)."""

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


#: The hooks of :class:`Instrument`, each with the attribute of :class:`Hooks` that lists the
#: instruments overriding it.
HOOKS = {"task_scheduled": "h_scheduled", "before_step": "h_before", "after_step": "h_after",
         "task_blocked": "h_blocked", "message_sent": "h_sent",
         "message_overwritten": "h_overwritten", "message_delivered": "h_delivered",
         "event": "h_event"}


class Hooks:
    """The installed instruments of a kernel (its ``hooks``), one tuple per hook holding only
    the instruments that override it, so that a hook nobody overrides is one truth test.
    Callers test the tuple (``if hooks.h_sent:``) and then call :meth:`notify`, which removes
    and logs an instrument whose hook raises (the others still hear of the event)."""

    def __init__(self) -> None:
        self.instruments: tuple[Instrument, ...] = ()
        self.h_scheduled: tuple[Instrument, ...] = ()
        self.h_before: tuple[Instrument, ...] = ()
        self.h_after: tuple[Instrument, ...] = ()
        self.h_blocked: tuple[Instrument, ...] = ()
        self.h_sent: tuple[Instrument, ...] = ()
        self.h_overwritten: tuple[Instrument, ...] = ()
        self.h_delivered: tuple[Instrument, ...] = ()
        self.h_event: tuple[Instrument, ...] = ()
        #: the instruments overriding any of before_step, after_step and task_blocked: the
        #: kernel tells a step to instruments only when this is not empty
        self.h_step: tuple[Instrument, ...] = ()
        #: (instrument, hook, error text) of every instrument removed because a hook raised
        self.dropped_instruments: list[tuple[Instrument, str, str]] = []

    def add_instrument(self, instrument: Instrument) -> None:
        """Listen with ``instrument``; only the hooks it overrides are ever called."""
        self.instruments = (*self.instruments, instrument)
        self._rehook()

    def remove_instrument(self, instrument: Instrument) -> None:
        """Stop listening with ``instrument`` (no error if it was not installed)."""
        self.instruments = tuple(i for i in self.instruments if i is not instrument)
        self._rehook()

    def _rehook(self) -> None:
        for hook, attr in HOOKS.items():
            base = getattr(Instrument, hook)
            setattr(self, attr, tuple(i for i in self.instruments
                                      if getattr(type(i), hook, base) is not base))
        self.h_step = tuple(i for i in self.instruments
                            if i in self.h_before or i in self.h_after or i in self.h_blocked)

    @staticmethod
    def still(began: tuple[Instrument, ...],
              hooks: tuple[Instrument, ...]) -> tuple[Instrument, ...]:
        """Those of ``hooks`` (an ``h_*`` tuple now) that were also in ``began`` (one as it was
        when a step began): who hears the end of that step."""
        return tuple(i for i in hooks if i in began)

    def notify(self, hooks: tuple[Instrument, ...], hook: str, *args: Any) -> None:
        """Call ``hook(*args)`` on each of ``hooks`` (one of the ``h_*`` tuples). An instrument
        that raises is removed and logged; the others are still called."""
        for i in hooks:
            try:
                getattr(i, hook)(*args)
            except Exception as exc:
                self._drop(i, hook, exc)

    def _drop(self, instrument: Instrument, hook: str, exc: Exception) -> None:
        text = f"{type(exc).__name__}: {exc}"
        log.error("instrument %r raised in %s and has been removed: %s", instrument, hook, text,
                  exc_info=exc)
        self.dropped_instruments.append((instrument, hook, text))
        del self.dropped_instruments[:-100]
        self.remove_instrument(instrument)

    def event(self, kind: str, detail: str) -> None:
        """Report a system event (install, setpri, pre-emption, abnormal completion, device
        failure, estop...) to the instruments and the log."""
        log_events.info("%s: %s", kind, detail)
        if self.h_event:
            self.notify(self.h_event, "event", kind, detail)


log_events = logging.getLogger("chcos.events")
