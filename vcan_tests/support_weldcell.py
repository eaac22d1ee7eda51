"""support_weldcell - run the welding job for the weldcell scenario tests and keep what it did.

:func:`run_job` builds the cell (:func:`chcos.apps.weld.cell.open_cell`) on a binding, starts the
job,
runs it on virtual time until it has an outcome (or a limit), and returns a :class:`JobRun`
holding everything the tests check, captured *before* the shutdown writes its safe values.
:func:`faulty_b4` is the test-only task that makes a task raise mid-weld.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from chcos.apps.weld.cell import Cell, open_cell
from chcos.apps.weld.tasks import B4
from chcos.apps.weld.tasks.messages import Step
from chcos.user.context import EventKind, TaskContext

M = "vcan_tests.support_weldcell"
FAIL_ON_WELD_MOVE = 150
"""faulty_b4 raises on this activation at welding speed (10 a second: about 15 s into the weld)."""


async def faulty_b4(ctx: TaskContext, command: Any) -> Any:
    """B4, except that its ``FAIL_ON_WELD_MOVE``-th move at welding speed (< 10 mm/s) raises
    (counting the newer commands a running activation takes up as well)."""

    def count(cmd: Any) -> None:
        if isinstance(cmd, Step) and cmd.speed < 10:
            n = ctx.world.command.get("weld_moves", 0) + 1
            ctx.world.command["weld_moves"] = n
            if n == FAIL_ON_WELD_MOVE:
                raise RuntimeError(f"injected fault in B4 on weld move {n}")

    count(command)
    await B4._order(ctx, command)
    while True:
        ev = await ctx.wait_any(completions=["A4"], commands=True)
        if ev.kind is not EventKind.COMMAND:
            break
        count(ev.value)
        await B4._order(ctx, ev.value)
    return {"status": ev.value.status.value, "result": ev.value.result}


@dataclass
class JobRun:
    """What a job did: E2's outcome, the summary figures, the actuator outputs and the cell
    model's state at the end, snapshots of world models, task statistics."""

    outcome: dict[str, Any] | None
    summary: dict[str, Any]
    outputs: dict[str, Any]
    model: dict[str, Any]
    worlds: dict[str, dict[str, dict[str, Any]]]
    tasks: dict[str, dict[str, Any]]
    devices: dict[str, str]
    irq_errors: list[str]
    events: list[tuple[str, str]]
    extra: dict[str, Any] = field(default_factory=dict)
    #: the joint drives as they saw themselves at the end of the job (before the shutdown) and
    #: after it: power state, power states entered, controlwords received (see drive_facts)
    drives: dict[str, dict[str, Any]] = field(default_factory=dict)
    drives_after: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: the drives' power states sampled every 0.1 s of the run, by the job's phase
    drive_phases: dict[str, set[str]] = field(default_factory=dict)


def drive_facts(cell: Cell) -> dict[str, dict[str, Any]]:
    """What each joint drive holds on its side (the simulator's, not chcos's view): ``power``
    (its state), ``history`` (every state entered, oldest first), ``received`` (every
    controlword applied, in order), ``ignored`` (targets it did not take)."""
    return {f"joint{j}": {"power": d.power.name, "history": [p.name for p in d.model.history],
                          "received": list(d.received), "ignored": d.ignored_targets}
            for j, d in enumerate(cell.drives, 1)}


def watch_drives(cell: Cell, period: float = 0.1) -> dict[str, set[str]]:
    """Sample the drives' power states every ``period`` s of the kernel clock, keyed by the
    job's phase at that moment (filled in as the run goes)."""
    seen: dict[str, set[str]] = {}
    kernel = cell.system.kernel

    def sample() -> None:
        seen.setdefault(cell.phase(), set()).update(d.power.name for d in cell.drives)

    kernel.call_at(kernel.clock.now(), sample, period)
    return seen


def buses_or_skip(binding: str, *, always: bool = False) -> None:
    """Skip the real-bus variant unless it always runs or CHCOS_WELD_BUSES=1 (an opt-in run)."""
    if binding != "buses" or always:
        return
    from vcan_tests.support_env import opt_in

    opt_in("CHCOS_WELD_BUSES", "full welding jobs on the real buses take about a minute each; "
           "the good gap always runs on them")


def run_job(binding: str = "direct", scenario: str = "", *, limit: float = 150.0,
            replace: dict[str, str] | None = None, command: dict[str, Any] | None = None,
            after: Callable[[Cell], dict[str, Any]] | None = None,
            tmp: Any = None, script: Any = None) -> JobRun:
    """Run the job (see the module doc). ``after(cell)`` runs once the job is over, before the
    capture; what it returns lands in :attr:`JobRun.extra`. ``script`` replaces the cell's
    install script."""
    kw: dict[str, Any] = {} if script is None else {"script": script}
    with open_cell(binding, scenario=scenario, replace=replace, workdir=tmp, **kw) as cell:
        phases = watch_drives(cell)
        cell.start_job(command)
        cell.run(limit)
        extra = after(cell) if after is not None else {}
        drives = drive_facts(cell)
        m = cell.model
        s = cell.system
        run = JobRun(
            outcome=cell.outcome(), summary=cell.summary(), outputs=cell.outputs(),
            model={"volts": m.voltage_setpoint, "gas": m.gas_valve, "wire": m.wire_setpoint,
                   "temp": m.temperature, "s": m.seam_point.s, "stuck": m.tip_stuck,
                   "events": [(e.t, e.fault.kind, e.action) for e in m.events],
                   "enabled": getattr(next(iter(s.devtab.drivers), None), "enabled", None),
                   "pos": m.pose.position},
            worlds={t.name: cell.world(t.name) for t in s.tsktab},
            tasks={t.name: {"level": t.level, "role": t.role.value, "abnormal": t.abnormal,
                            "last_error": t.last_error, "frozen": t.frozen,
                            "activations": t.activations} for t in s.tsktab},
            devices={d.name: d.status.value for d in s.devtab},
            irq_errors=list(s.kernel.irq_errors), events=list(cell.counters.events),
            extra=extra, drives=drives, drive_phases=phases)
    run.drives_after = drive_facts(cell)      # the shutdown's safe stops, as the drives saw them
    return run
