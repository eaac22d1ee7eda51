"""affinity - pin a chcos process, every thread of it, to the CPUs its system file names.

A cell controller keeps its control process on CPUs of its own (``[system] cpus`` for ``chcos
run``, ``[[satellite]] cpus`` for a satellite): the kernel, driver and reader threads then hand
over to each other on one CPU's run queue instead of waking each other across CPUs, which on a
virtual machine costs an inter-processor interrupt through the hypervisor per wake-up (measured
on the emergency path: see README "Performance"). On Linux ``sched_setaffinity`` pins one
thread, and a new thread inherits its creator's CPUs; :func:`pin_process` therefore sets every
thread the process has (``/proc/self/task``), so it may be called before or after threads start.

Errors: :class:`~chcos.errors.ConfigError` naming the key and what was expected.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from chcos.errors import ConfigError

__all__ = ["available", "parse_cpus", "pin_process"]


def parse_cpus(value: Any, where: str) -> frozenset[int] | None:
    """The CPU numbers of a ``cpus`` key (None when the key is absent, ``value`` None).
    Raises ConfigError naming ``where`` unless it is a non-empty list of CPU numbers >= 0."""
    if value is None:
        return None
    if (not isinstance(value, list) or not value
            or not all(isinstance(c, int) and not isinstance(c, bool) and c >= 0 for c in value)):
        raise ConfigError(f"{where}: expected a non-empty list of CPU numbers >= 0 "
                          f"(e.g. cpus = [1]), got {value!r}")
    return frozenset(value)


def available() -> frozenset[int]:
    """The CPUs this process may run on now."""
    return frozenset(os.sched_getaffinity(0))


def _threads() -> list[int]:
    try:
        return [int(p.name) for p in Path("/proc/self/task").iterdir() if p.name.isdigit()]
    except OSError:
        return [0]  # no /proc: the calling thread (its children inherit)


def pin_process(cpus: Iterable[int], where: str) -> frozenset[int]:
    """Pin every thread of this process (and so the threads it starts later) to ``cpus``;
    returns the CPUs the calling thread could use before, for a caller that gives them back
    later (a wider set than now is fine: the machine decides what it allows). Raises
    ConfigError naming ``where`` when a CPU is not one the machine lets this process use
    (nothing is changed then)."""
    want = frozenset(cpus)
    before = available()
    bad = ", ".join(str(c) for c in sorted(want)) or "-"
    try:
        os.sched_setaffinity(0, want)  # the calling thread first: the machine's own check
        got = available()
    except (OSError, OverflowError, ValueError):
        got = frozenset()
    if not want or got != want:
        if got:
            os.sched_setaffinity(0, before)
            bad = ", ".join(str(c) for c in sorted(want - got))
        raise ConfigError(f"{where}: CPU(s) {bad} not available to this process; expected "
                          f"CPUs this machine lets it use ({os.cpu_count()} online, it runs on "
                          f"{', '.join(map(str, sorted(before)))} now)")
    for tid in _threads():
        try:
            os.sched_setaffinity(tid, want)
        except ProcessLookupError:  # the thread ended meanwhile
            continue
    return before
