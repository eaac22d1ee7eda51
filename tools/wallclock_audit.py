#!/usr/bin/env python3
"""wallclock_audit - which chcos and driver code reads or waits on the wall clock under a virtual
clock: no wall clock under a virtual clock (issue 47).

:class:`WallClockAudit` watches ``time.monotonic``/``monotonic_ns``, ``time.time``/``time_ns``,
``time.perf_counter``/``perf_counter_ns``, ``time.sleep``, and ``threading.Event.wait`` and
``threading.Condition.wait`` given a timeout (what ``queue.Queue.get(timeout=...)``, a future's
``result(timeout=...)`` and the like come down to), on every thread, while a block runs. Each
call is charged to the nearest frame of the watched code (``chcos/`` and ``drivers/`` of this
checkout) on its stack, as ``path:function`` (``drivers/jobs.py:JobDriver.settle``); calls with
no such frame (a library's own loop) and calls made while logging a record (its time stamp) are
not charged. A wait without a timeout is no clock decision and is not counted.

:func:`audit_weld` runs the welding cell (``direct``, the protocol-free binding, or ``buses``)
and :func:`audit_system` a user's system file on virtual time, from building it to its shutdown,
under the audit. ``vcan_tests/test_vtime_wallclock.py`` asserts that the modules already clean
make no such call and prints the rest.
Usage: python -m tools.wallclock_audit [--cell direct|buses] [--system FILE] [--seconds S]
Errors: whatever building the cell raises (ChcosError); exit status 2 then.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from types import FrameType, TracebackType
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
#: the code whose calls are charged (directories of this checkout)
WATCHED = (str(ROOT / "chcos") + "/", str(ROOT / "drivers") + "/")
_LOGGING = str(Path(logging.__file__).parent) + "/"
_CLOCKS = ("monotonic", "monotonic_ns", "time", "time_ns", "perf_counter", "perf_counter_ns")


def charged_frame(frame: FrameType | None) -> str | None:
    """``path:function`` of the nearest frame of the watched code from ``frame`` outwards, or
    None if there is none or the call is made inside logging (a record's time stamp)."""
    depth = 0
    while frame is not None and depth < 60:
        name = frame.f_code.co_filename
        if name.startswith(_LOGGING):
            return None
        if name.startswith(WATCHED):
            rel = Path(name).relative_to(ROOT).as_posix()
            return f"{rel}:{frame.f_code.co_qualname}"
        frame = frame.f_back
        depth += 1
    return None


class _Watched:
    """A clock function that charges each call first: a callable object, not a function, so
    that code storing it as a class attribute (``TIME = time.monotonic``, as pyserial does)
    does not turn it into a method."""

    def __init__(self, real: Callable[..., Any], what: str,
                 charge: Callable[[str], None]) -> None:
        self.real, self.what, self.charge = real, what, charge

    def __call__(self, *args: Any) -> Any:
        self.charge(self.what)
        return self.real(*args)


class WallClockAudit:
    """A context manager: while it is entered, every wall-clock read, sleep and timed wait of
    the watched code is counted in :attr:`calls` by ``path:function`` (see the module doc), and
    by what was called in :attr:`kinds`. Not reentrant; restores everything on exit."""

    def __init__(self) -> None:
        #: calls per ``path:function``
        self.calls: Counter[str] = Counter()
        #: calls per (``path:function``, what was called)
        self.kinds: Counter[tuple[str, str]] = Counter()
        self._lock = threading.Lock()
        self._saved: list[tuple[Any, str, Any]] = []
        self._inside = threading.local()    # in a charged wait (its inner waits are not)

    def _charge(self, what: str) -> None:
        where = charged_frame(sys._getframe(2))   # past _charge and the wrapper
        if where is not None:
            with self._lock:
                self.calls[where] += 1
                self.kinds[(where, what)] += 1

    def _wrap_clock(self, name: str) -> Callable[..., Any]:
        return _Watched(getattr(time, name), f"time.{name}", self._charge)

    def _wrap_wait(self, cls: Any, label: str) -> Callable[..., Any]:
        real = cls.wait
        inside = self._inside

        def watched(obj: Any, timeout: float | None = None) -> Any:
            if timeout is None or getattr(inside, "waiting", False):
                return real(obj, timeout)   # no timeout, or the Condition of an Event's wait
            self._charge(f"{label}.wait(timeout)")
            inside.waiting = True
            try:
                return real(obj, timeout)
            finally:
                inside.waiting = False

        return watched

    def __enter__(self) -> WallClockAudit:
        patches: list[tuple[Any, str, Any]] = [(time, n, self._wrap_clock(n)) for n in _CLOCKS]
        patches.append((time, "sleep", self._wrap_clock("sleep")))
        patches.append((threading.Event, "wait", self._wrap_wait(threading.Event, "Event")))
        patches.append((threading.Condition, "wait",
                        self._wrap_wait(threading.Condition, "Condition")))
        for owner, name, new in patches:
            self._saved.append((owner, name, getattr(owner, name)))
            setattr(owner, name, new)
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        for owner, name, old in reversed(self._saved):
            setattr(owner, name, old)
        self._saved.clear()

    def by_module(self) -> Counter[str]:
        """The calls per watched module (``path``)."""
        out: Counter[str] = Counter()
        for where, n in self.calls.items():
            out[where.split(":", 1)[0]] += n
        return out


def audit_weld(binding: str, seconds: float) -> WallClockAudit:
    """Build the welding cell on ``binding``, run its job ``seconds`` of virtual time and shut
    it down, under the audit. Raises what :func:`chcos.apps.weld.cell.open_cell` raises."""
    from chcos.apps.weld.cell import open_cell

    audit = WallClockAudit()
    with audit, open_cell(binding) as cell:
        cell.start_job()
        cell.run(seconds)
    return audit


def audit_system(system_file: str | Path, seconds: float) -> WallClockAudit:
    """Build a user's system on virtual time against its simulated slaves (``chcos run
    --virtual``), run ``seconds`` and shut it down, under the audit. Raises ChcosError as
    :func:`chcos.cli.cellsystem.open_cell` does."""
    from chcos.cli.cellsystem import open_cell

    audit = WallClockAudit()
    with audit, open_cell(system_file, virtual=True) as cell:
        cell.run_for(seconds)
    return audit


def report(audit: WallClockAudit) -> list[str]:
    """The table: one line per ``path:function`` (most calls first) with what it called."""
    lines = []
    for where, n in audit.calls.most_common():
        what = ", ".join(f"{k} {c}" for (w, k), c in sorted(audit.kinds.items()) if w == where)
        lines.append(f"{n:8d}  {where}  ({what})")
    return lines


def main(argv: list[str] | None = None) -> int:
    """Run the cell under the audit and print the table; 0, 2 if the cell cannot be built."""
    from chcos.errors import ChcosError

    doc = __doc__ or "wallclock_audit"
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--cell", choices=("direct", "buses"), default="buses",
                    help="the welding cell's binding (default buses)")
    ap.add_argument("--system", help="a system file to run instead of the welding cell")
    ap.add_argument("--seconds", type=float, default=5.0, help="virtual seconds (5)")
    args = ap.parse_args(argv)
    logging.getLogger("chcos").setLevel(logging.CRITICAL)
    try:
        audit = (audit_system(args.system, args.seconds) if args.system
                 else audit_weld(args.cell, args.seconds))
    except ChcosError as exc:
        print(f"wallclock_audit: {exc}", file=sys.stderr)
        return 2
    what = args.system or f"the welding cell ({args.cell})"
    print(f"wall-clock calls from chcos/ and drivers/ while {what} ran {args.seconds} s of "
          f"virtual time: {sum(audit.calls.values())} in {len(audit.calls)} functions")
    for line in report(audit):
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
