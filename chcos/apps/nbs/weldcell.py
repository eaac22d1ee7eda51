"""weldcell - Appendix 1's NBS hierarchy (H1..H3 with their G and M modules) on the welding cell.

The NBS baseline runs the SAME simulated welding hardware as the CHC job: the cell is opened with
:func:`chcos.apps.weld.cell.open_cell` on either binding (``direct`` or ``buses``) with a script
that
installs no CHC task (``chcos/apps/nbs/weld.chcos``), and :func:`chcos.apps.nbs.adapter.attach`
cycles the
three levels on the System's kernel every 28 ms through its Devtab. The H modules are the
transcribed tables (``chcos/apps/nbs/tables``, unchanged); the thesis gives no G or M module, so
this
module writes the ones the tables name, and nothing more:

the G and M modules and level 0 are :mod:`chcos.apps.nbs.gm` (module doc there).

The job (level 4, the operator) gives H3 ``INSPECT GAP`` and, once it is done without ``gap
notOK``, ``WELD GAP``. :func:`run_nbs` runs it and returns the same summary keys as the CHC
run (``chcos.apps.weld.cell.Cell.summary``) plus the NBS figures; :func:`diagnose` names the
table row
the job is stuck in when it does not finish.

Errors: ChcosError from the cell's set-up (as :func:`chcos.apps.weld.cell.open_cell`),
KernelError when
an NBS cycle fails (a StateTableError inside it is named).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from chcos import resources
from chcos.apps.nbs.adapter import NbsOnSystem, attach
from chcos.apps.nbs.executor import CommonMemory, Level, LevelContext, TableH
from chcos.apps.nbs.gm import CellModules, World
from chcos.apps.nbs.statetable import Facts, Machine, Row, StateTable, Step, load_builtin
from chcos.helpers import is_number

__all__ = ["NBS_SCRIPT", "Fired", "NbsCell", "diagnose", "job_params"]

NBS_SCRIPT = resources.path("chcos.apps.nbs", "weld.chcos")
INSTALL = resources.path("chcos.apps.weld", "install.chcos")


def job_params(script: Path = INSTALL) -> tuple[tuple[float, float, float], float]:
    """E2's ``start``, ``z`` and ``heading`` parameters from the CHC install script, so both
    hierarchies run the same job: (start point (x, y, z) mm, heading rad). Raises ValueError
    if the script has no E2 line with them."""
    for line in script.read_text(encoding="utf-8").splitlines():
        words = line.split()
        if len(words) > 1 and words[0] == "install" and "E2" in words:
            params = dict(re.findall(r"--param (\w+)=(\S+)", line))
            x, y = (float(v) for v in params["start"].strip("[]").split(","))
            return (x, y, float(params["z"])), float(params["heading"])
    raise ValueError(f"{script}: no 'install ... E2' line with --param start/z/heading")


@dataclass(frozen=True)
class Fired:
    """A row that reported a failure up (``... fail``, ``... notOK``): when, where, why."""

    t: float
    module: str
    row: Row
    facts: str
    why: str = ""

    def describe(self) -> str:
        """One line: the table row and what G/M said when it fired."""
        r = self.row
        lower = "-" if r.lower is None else (
            r.lower.name + (f"({', '.join(a.text for a in r.lower.args)})" if r.lower.args else ""))
        return (f"t={self.t:7.2f} s {self.module} {r.command} row {r.index} (state "
                f"{'-' if r.state is None else r.state} -> {r.next_state}, lower {lower}, up "
                f"{r.up!r}) because no earlier row held ({self.why or 'none'}); {self.facts}")


class _TracingMachine(Machine):
    """A Machine that hands every fired row to ``on_row`` (the failure log), with why the
    earlier rows of the same command and state did not fire."""

    def __init__(self, table: StateTable, on_row: Callable[[Row, str], None]) -> None:
        super().__init__(table)
        self.on_row = on_row

    def step(self, facts: Facts, report: str | None,
             values: Mapping[str, object] | None = None) -> Step:
        """As :meth:`Machine.step`, then report the row that fired."""
        state, variables = self.state, dict(self.variables)
        out = super().step(facts, report, values)
        if out.row is not None:
            up = out.row.up or ""
            why = ""
            if up.endswith("fail") or up.endswith("notOK"):
                why = self._why_not_earlier(out.row, state, facts, report, variables,
                                            values or {})
            self.on_row(out.row, why)
        return out

    def _why_not_earlier(self, fired: Row, state: int, facts: Facts, report: str | None,
                         variables: Mapping[str, object], values: Mapping[str, object]) -> str:
        """'row k: <terms that did not hold>' for each earlier row of the command."""
        parts: list[str] = []
        for row in self.table.command(fired.command).rows:
            if row is fired:
                break
            if row.state is not None and row.state != state:
                continue
            false: list[str] = []
            for terms, sensory in ((row.sensory, True), (row.report, False)):
                for term in terms:
                    if not self.table._holds(row, (term,), facts, report, variables, values,
                                             sensory=sensory):
                        false.append(term.text)
            parts.append(f"row {row.index} needs {' and '.join(false) or '(nothing)'}")
        return "; ".join(parts)


class NbsCell:
    """The NBS hierarchy bound to a running cell's System (see the module doc).

    ``cell`` is a :class:`chcos.apps.weld.cell.Cell` opened with :data:`NBS_SCRIPT`.
    """

    def __init__(self, cell: Any, period: float = 0.028) -> None:
        self.cell = cell
        self.system = cell.system
        start, heading = job_params()
        self.gm = CellModules(World(start, heading, cell.model.config))
        self.w = self.gm.w
        self.w.yaw = heading
        gm = self.gm
        self.h = [TableH(load_builtin("H1"), actuate=gm.actuate),
                  TableH(load_builtin("H2")), TableH(load_builtin("H3"))]
        self.failures: list[Fired] = []
        for i, h in enumerate(self.h, start=1):
            h.machine = _TracingMachine(h.machine.table, self._row_logger(i))
        self.mem_writes = {"down": [0, 0, 0], "up": [0, 0, 0]}
        gm.h3 = self.h[2]
        levels = [Level(gm.g1, gm.m1, self._counted(0)),
                  Level(gm.g2, gm.m2, self._counted(1)),
                  Level(gm.g3, gm.m3, self._counted(2))]
        self.nbs: NbsOnSystem = attach(self.system.kernel, self.system.devtab, levels,
                                       period=period, source="nbs")
        gm.nbs = self.nbs
        self.ex = self.nbs.executor
        self.job: list[tuple[float, str]] = []
        self.gap_not_ok = False
        self.outcome: dict[str, Any] | None = None
        self.started = 0.0
        self.system.devtab.on_write.append(self._on_write)
        self.device_writes = 0
        cell.recorder.phase = self.phase

    # ---- running -----------------------------------------------------------------------------
    def start_job(self) -> None:
        """Start the cycle and give H3 INSPECT GAP (what E2 does first in the CHC job)."""
        self.started = self.system.kernel.clock.now()
        self.nbs.start()
        self._command("INSPECT GAP")

    def _command(self, name: str) -> None:
        self.job.append((self.system.kernel.clock.now(), name))
        self.ex.command(name)

    def step_job(self) -> None:
        """The operator above H3: INSPECT GAP, then WELD GAP; sets :attr:`outcome` at the end."""
        if self.outcome is not None:
            return
        rep = self.ex.report(3)
        if rep == "gap notOK":
            self.gap_not_ok = True
        if not self.h[2].machine.idle:
            return
        current = self.job[-1][1]
        if current == "INSPECT GAP" and rep == "inspect done":
            if self.gap_not_ok:
                self.outcome = {"outcome": "failed", "reason": "H3 INSPECT GAP: gap notOK"}
            else:
                self._command("WELD GAP")
        elif current == "WELD GAP" and rep in ("weld done", "weld fail"):
            self.outcome = {"outcome": "welded" if rep == "weld done" else "failed",
                            "reason": f"H3 WELD GAP reported {rep!r}"}
        if self.outcome is not None:
            self.nbs.stop()

    def run(self, seconds: float, each_second: Callable[[Any], None] | None = None) -> float:
        """Run for at most ``seconds`` (in 1 s slices) or until the job ends; returns the time
        run."""
        kernel = self.system.kernel
        t0: float = kernel.clock.now()
        while kernel.clock.now() - t0 < seconds - 1e-9 and self.outcome is None:
            step = min(1.0, seconds - (kernel.clock.now() - t0))
            end = kernel.clock.now() + step
            while kernel.clock.now() < end - 1e-9 and self.outcome is None:
                self.nbs.scheduler.run_until(min(end, kernel.clock.now() + 0.28))
                self.step_job()
            if each_second is not None:
                each_second(self)
        return float(kernel.clock.now()) - t0

    def phase(self) -> str:
        """The job's command and H3's state (for the report)."""
        if not self.job:
            return "idle"
        m = self.h[2].machine
        name = self.job[-1][1].split()[0].lower()
        return f"{name}/H3 state {m.state}" if not m.idle else f"{name}/done"

    def _row_logger(self, level: int) -> Callable[[Row, str], None]:
        def log(row: Row, why: str) -> None:
            up = row.up or ""
            if not (up.endswith("fail") or up.endswith("notOK")):
                return
            if any(f.row is row for f in self.failures) or len(self.failures) >= 50:
                return
            ctx = self.ex.context(level)
            true = sorted(k for k, v in ctx.facts.items() if not callable(v) and v)
            vals = {k: v for k, v in ctx.values.items()
                    if is_number(v)}
            shown = ", ".join(f"{k}={v:.1f}" for k, v in sorted(vals.items()))
            self.failures.append(Fired(ctx.now, f"H{level}", row,
                                       f"G{level}/M{level}: {shown}; true: {', '.join(true)}",
                                       why))

        return log

    # ---- the report -------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """The run's figures under the keys of :meth:`chcos.apps.weld.cell.Cell.summary` (so
        :func:`chcos.apps.weld.report.write_report` draws it), plus ``hierarchy``, ``executions``
        per module, ``failures`` (rows that reported a failure up, with what G/M said) and
        ``standing`` (where each H machine stands at the end)."""
        model = self.cell.model
        prog = model.progress()
        in_band = prog.welded - prog.too_hot - prog.too_cold
        counts = self.ex.counts
        steps = {n: counts[f"G{n}"] + counts[f"M{n}"] + counts[f"H{n}"] for n in (1, 2, 3)}
        msgs: dict[str, int] = {}
        for i in range(3):
            msgs[f"level {i + 1} down"] = self.mem_writes["down"][i]
            msgs[f"level {i + 1} up"] = self.mem_writes["up"][i]
        msgs["device writes"] = self.device_writes
        faults = [f"t={e.t:6.2f} s {e.action:7s} {e.fault.describe()}" for e in model.events]
        handled = [f"t={t:6.2f} s G1 reflex: intruder -> safe values" + (
            "" if a is None else f" {1000 * (a - t):.2f} ms later")
                   for t, a in zip(self.w.intruder_seen, self.w.safe_at, strict=True)]
        handled += [f"table row reporting a failure: {f.describe()}" for f in self.failures]
        handled += [f"level 0: goal unreachable, {u}" for u in self.w.unreachable]
        return {
            "hierarchy": "nbs", "binding": self.cell.binding,
            "seconds": self.system.kernel.clock.now() - self.started, "outcome": self.outcome,
            "seam_mm": prog.length, "welded_mm": prog.welded,
            "in_band_mm": in_band, "in_band_pct": 100.0 * in_band / prog.length,
            "too_hot_mm": prog.too_hot, "too_cold_mm": prog.too_cold, "no_gas_mm": prog.no_gas,
            "band": model.config.weld_band, "faults": faults, "handled": handled,
            "steps_by_level": steps, "messages": msgs,
            "messages_total": sum(msgs.values()),
            "latency_s": [None if a is None else a - t
                          for t, a in zip(self.w.intruder_seen, self.w.safe_at, strict=True)],
            "outputs": self.cell.outputs(), "executions": counts, "cycles": self.ex.cycles,
            "failures": [f.describe() for f in self.failures], "standing": diagnose(self),
            "job": [f"t={t:.2f} s {name}" for t, name in self.job],
        }

    # ---- counting ----------------------------------------------------------------------------
    def _counted(self, i: int) -> Callable[[LevelContext], None]:
        h = self.h[i]

        def module(ctx: LevelContext) -> None:
            n = ctx.level
            down, up = CommonMemory.cmd(n - 1), CommonMemory.report(n)
            before = (ctx.mem.written_at(down), ctx.mem.written_at(up))
            before_obj = (ctx.mem.get(down), ctx.mem.get(up))
            h(ctx)
            if ctx.mem.get(down) is not before_obj[0] or ctx.mem.written_at(down) != before[0]:
                self.mem_writes["down"][i] += 1
            if ctx.mem.get(up) is not before_obj[1] or ctx.mem.written_at(up) != before[1]:
                self.mem_writes["up"][i] += 1

        return module

    def _on_write(self, device: str, value: Any) -> None:
        self.device_writes += 1

def diagnose(nc: NbsCell) -> list[str]:
    """Where each H machine stands and the row that fired last (for an unfinished job)."""
    out: list[str] = []
    for i, h in enumerate(nc.h, start=1):
        m = h.machine
        cmd = m.command.name if m.command is not None else "-"
        shown = ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}"
                          for k, v in sorted(m.variables.items()))
        out.append(f"H{i} {cmd} state {m.state}, report {m.report!r}"
                   + (f", variables {shown}" if shown else ""))
    return out

