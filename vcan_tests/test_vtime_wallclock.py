"""No wall clock under a virtual clock (issue 47): the welding cell run on virtual time under
tools.wallclock_audit (every wall-clock read, sleep and timed wait of chcos/ and drivers/ code,
on every thread, charged to the function that made it). The modules already clean make no such
call; the rest is printed (``pytest -s``), for the bus branches of issue 47 to empty. The lead
moves a module into CLEAN once its branch has landed."""

from __future__ import annotations

import logging
import threading
import time

import pytest

from tools.wallclock_audit import WallClockAudit, audit_weld, report

#: the code that makes no wall-clock call on a virtual-time path, on either binding: the kernel,
#: the device manager, the message layer and the task API, the welding cell's model, simulator
#: and protocol-free binding
CLEAN = ("chcos/kernel/", "chcos/devices/", "chcos/messages/", "chcos/user/", "chcos/tables/",
         "chcos/apps/weld/direct.py", "chcos/apps/weld/plant.py", "chcos/apps/weld/cell.py",
         "chcos/apps/weld/model.py", "chcos/apps/weld/seam.py", "chcos/apps/weld/tasks/")
#: the one wall clock allowed everywhere: when sysfile.map is written (file I/O paced by what a
#: write costs; no figure of the run depends on it)
PACING = ("chcos/system/mapfile.py",)


def _dirty(audit: WallClockAudit, prefixes: tuple[str, ...]) -> list[str]:
    return [line for line in report(audit)
            if any(line.split()[1].startswith(p) for p in prefixes)]


def test_the_audit_charges_the_calling_function_and_restores_everything() -> None:
    from chcos.kernel.clock import RealClock

    before = (time.monotonic, time.sleep, threading.Event.wait)
    audit = WallClockAudit()
    with audit:
        # a real clock's idle wait: one time.monotonic, one Event.wait with a timeout
        RealClock().idle(threading.Event(), RealClock.now() + 0.001)
        threading.Event().wait(0)        # from the test: not watched code, not charged
        logging.getLogger("chcos.test").warning("a record's time stamp is not charged")
    assert (time.monotonic, time.sleep, threading.Event.wait) == before
    assert dict(audit.kinds) == {
        ("chcos/kernel/clock.py:RealClock.idle", "time.monotonic"): 1,
        ("chcos/kernel/clock.py:RealClock.idle", "Event.wait(timeout)"): 1}


def test_the_protocol_free_binding_runs_without_a_wall_clock() -> None:
    audit = audit_weld("direct", 10.0)
    print("\n".join(["", "wall-clock calls, direct binding:", *report(audit)]))
    assert all(any(line.split()[1].startswith(p) for p in PACING) for line in report(audit)), \
        report(audit)


@pytest.mark.slow
def test_on_the_simulated_buses_the_clean_modules_make_no_wall_clock_call() -> None:
    audit = audit_weld("buses", 3.0)
    print("\n".join(["", "wall-clock calls on the simulated buses (for the bus branches of "
                         "issue 47 to empty):", *report(audit)]))
    assert _dirty(audit, CLEAN) == []
    # the audit sees the buses' drivers: they still wait on the wall clock (the list above)
    assert any(w.startswith("drivers/") for w in audit.calls)
