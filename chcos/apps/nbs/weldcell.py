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

* **level 0** (the servo/actuator layer below H1; the commands of H1's ``[lower]`` section):
  ``GET THETA TO(p)`` sets a point-to-point goal (written as joint targets; the drives move at
  their configured speed - the cell has no speed actuator, so MOVE TO P's ``speed`` is not
  used); ``GET THETA DIR(d, dist)`` sets a straight-line goal ``dist`` mm in direction ``d``
  (degrees in the plate plane counted from the job's heading, or ``'-z'`` for up) that
  ``MOTORS ON(speed)`` follows at ``speed`` mm/s (the set-point advances once per cycle);
  ``MOTORS ON``/``OFF`` is ``drives_enable``; ``INCR VOLTAGE`` raises ``volts_set`` by
  :data:`VOLT_STEP`, ``CUT VOLTAGE`` sets 0; ``OPEN``/``CLOSE VALVE`` is ``gas_valve``;
  ``SPEEDUP(v)``/``SLOWDOWN(v)`` set ``wire_set``; ``MEMORIZE(p)`` stores p.
* **G1/M1**: joint angles to the tip pose (forward kinematics), the level-0 reports as facts
  relative to the order H1 is running, one of three as the tables expect (``arrived`` = the tip
  within :data:`ARRIVED_MM` of that order's goal, ``timeout`` = not arrived and the order has run
  longer than its allowance, else ``not arrived``), ``gas flowing``
  (``gas_flow``), ``bottle full`` (``gas_bottle``), ``arc on`` (the power source sees an arc:
  set-point on, arc voltage neither short-circuit nor open-circuit), ``motors on``, ``aligned``
  (the linear image shows the start-of-gap marker); values ``temp``, ``threshold`` (the bottom
  of the weld band) and ``speed`` (the wire feed, rounded to the table's step of 1 mm/s).
  **G1 is also the cell's safety reflex**: NBS has no exception task or assassin and Appendix 1
  no row for the light curtain, so G1 polls ``intruder`` every cycle and, while it is set, writes
  the safe values and blocks level-0 writes to those actuators.
* **G2/M2**: ``gas on/off``, ``arc on/off`` (so TURN ON/OFF WELD can decide before H1
  answers, see tables/NOTES.md), ``tip stuck`` (the power source shorted: set-point on, arc
  voltage ~0 in a reading taken :data:`SETTLE_S` after the set-point was written; latched
  until the tip has risen :data:`FREED_MM` above where it stuck), ``wait done`` (M2's timer:
  :data:`WAIT_S` after H1's last ``move done``), value ``home``.
* **G3/M3**: from the linear image (5 mm ahead of the tip): ``pos(gapcentre)``, ``gapwidth
  OK``, ``at(gapend)`` (end marker); ``pos(nextcentre)`` (= ``pos(next gapcentre)``) is a gap
  centre in view not yet steered to: consumed by ``dir_to(pos)``, re-armed when H2 reports
  ``move done`` (one new centre per 5 mm step) or H3 enters a new state (a new plan step);
  ``tip stuck``; ``timeout`` (H2 has reported ``tip stuck`` for :data:`UNSTICK_TIMEOUT_S`);
  values ``pos``, ``start``, ``target``, ``dir_to``, ``temp``, ``threshold`` (the middle of the
  band). The job parameters (start, heading, z) are E2's in ``chcos/apps/weld/install.chcos``.

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

import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from chcos import resources
from chcos.apps.nbs.adapter import NbsOnSystem, attach
from chcos.apps.nbs.executor import CommonMemory, Level, LevelContext, Order, Report, TableH
from chcos.apps.nbs.statetable import Call, Facts, Machine, Row, StateTable, Step, load_builtin
from chcos.apps.weld.kinematics import UnreachableError
from chcos.apps.weld.model import CellConfig
from chcos.apps.weld.tasks.common import ARM, LOOK_AHEAD, analyse, left, pose_of

__all__ = ["NBS_SCRIPT", "Fired", "NbsCell", "diagnose", "job_params"]

NBS_SCRIPT = resources.path("chcos.apps.nbs", "weld.chcos")
INSTALL = resources.path("chcos.apps.weld", "install.chcos")
SAFE = (("drives_enable", 0), ("volts_set", 0.0), ("wire_set", 0.0), ("gas_valve", 0))
"""The actuators G1's intruder reflex puts safe (the CHC run's SAFE_DEVICES)."""
VOLT_STEP = 0.5
"""V added to the arc voltage set-point per INCR VOLTAGE (once per 28 ms cycle)."""
ARRIVED_MM = 0.5
"""Level 0 says ``arrived`` when the tip is this close to the goal of H1's order."""
FREED_MM = 3.0
"""M2 says ``tip free`` once a stuck tip has risen this far above where it stuck."""
WAIT_S = 0.5
"""M2's ``wait done``: seconds after H1's last ``move done``."""
SETTLE_S = 0.05
"""G2 trusts an arc-voltage reading this long after the set-point was last written."""
UNSTICK_TIMEOUT_S = 20.0
"""M3's ``timeout`` for UNSTICK TIP."""
GAP_OK_MM = (1.0, 6.0)
"""Acceptable gap width (mm) for G3's ``gapwidth OK``."""


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


@dataclass
class _World:
    """What the G and M modules of all three levels know (the NBS common world model)."""

    start: tuple[float, float, float]
    heading: float
    cfg: CellConfig
    tip: tuple[float, float, float] | None = None
    yaw: float = 0.0
    # level 0
    goal: tuple[float, float, float] | None = None
    goal_yaw: float = 0.0
    setpoint: tuple[float, float, float] | None = None
    linear: bool = False
    speed: float = 1.0
    motors: bool = False
    volts: float = 0.0
    volts_at: float = 0.0
    valve: int = 0
    wire: float = 0.0
    memorized: object = None
    order_goal: dict[int, tuple[float, float, float]] = field(default_factory=dict)
    order_start: dict[int, float] = field(default_factory=dict)
    last_targets: tuple[float, ...] | None = None
    # safety
    intruder: bool = False
    intruder_seen: list[float] = field(default_factory=list)
    safe_at: list[float | None] = field(default_factory=list)
    # level 2
    stuck_z: float | None = None
    move_done_at: float | None = None
    # level 3
    centre: tuple[float, float, float] | None = None
    width: float | None = None
    end_seen: bool = False
    armed: bool = True
    plan: tuple[int, int] = (0, 0)
    stuck_report_since: float | None = None
    unreachable: list[str] = field(default_factory=list)


def _direction(w: _World, d: object) -> tuple[float, float, float]:
    if isinstance(d, str):
        if d.strip() == "-z":
            return (0.0, 0.0, 1.0)  # "-z" of the tool: away from the work, i.e. up
        raise ValueError(f"level 0: direction {d!r}: expected degrees or '-z'")
    a = w.heading + math.radians(float(d))  # type: ignore[arg-type]
    return (math.cos(a), math.sin(a), 0.0)


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
        self.w = _World(start, heading, cell.model.config)
        self.w.yaw = heading
        self.h = [TableH(load_builtin("H1"), actuate=self._actuate),
                  TableH(load_builtin("H2")), TableH(load_builtin("H3"))]
        self.failures: list[Fired] = []
        for i, h in enumerate(self.h, start=1):
            h.machine = _TracingMachine(h.machine.table, self._row_logger(i))
        self.mem_writes = {"down": [0, 0, 0], "up": [0, 0, 0]}
        levels = [Level(self._g1, self._m1, self._counted(0)),
                  Level(self._g2, self._m2, self._counted(1)),
                  Level(self._g3, self._m3, self._counted(2))]
        self.nbs: NbsOnSystem = attach(self.system.kernel, self.system.devtab, levels,
                                       period=period, source="nbs")
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
                    if isinstance(v, float | int) and not isinstance(v, bool)}
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

    # ---- level 0 and level 1 -----------------------------------------------------------------
    def _write(self, ctx: LevelContext, device: str, value: object) -> None:
        if self.w.intruder and any(device == d for d, _ in SAFE):
            return  # the reflex holds the safe value while the light curtain is broken
        ctx.write(device, value)

    def _g1(self, ctx: LevelContext) -> None:
        w = self.w
        # the safety reflex: poll the light curtain every cycle
        present = bool(ctx.read("intruder") or 0)
        if present and not w.intruder:
            seen = self.nbs.io.arrived("intruder") or ctx.now
            w.intruder_seen.append(seen)
            for device, value in SAFE:
                ctx.write(device, value)
            w.motors, w.volts, w.wire, w.valve = False, 0.0, 0.0, 0
            w.safe_at.append(ctx.now)
        w.intruder = present
        thetas = [ctx.read(f"theta{j}") for j in range(1, 6)]
        if all(isinstance(t, float | int) for t in thetas):
            pose = pose_of([float(t) for t in thetas])  # type: ignore[arg-type]
            w.tip = (pose.position[0], pose.position[1], pose.position[2])
            w.yaw = pose.yaw
        self._servo(ctx)

    def _servo(self, ctx: LevelContext) -> None:
        """Level 0's interpolator: a straight-line goal is approached at ``speed`` mm/s."""
        w = self.w
        if not w.motors or w.goal is None or w.intruder:
            return
        if w.linear:
            sp = w.setpoint or w.tip or w.goal
            dx = [g - s for g, s in zip(w.goal, sp, strict=True)]
            dist = math.sqrt(sum(c * c for c in dx))
            stepmm = max(0.0, w.speed) * self.ex.period  # a speed <= 0 does not move
            if stepmm <= 0.0:
                return
            if dist > stepmm:
                sp = (sp[0] + dx[0] * stepmm / dist, sp[1] + dx[1] * stepmm / dist,
                      sp[2] + dx[2] * stepmm / dist)
            else:
                sp = w.goal
            w.setpoint = sp
            self._targets(ctx, sp, w.goal_yaw)
        else:
            self._targets(ctx, w.goal, w.goal_yaw)

    def _targets(self, ctx: LevelContext, p: tuple[float, float, float], yaw: float) -> None:
        q = None
        for y in (yaw, self.w.heading, self.w.cfg.home_yaw):  # wrist limits: the first that fits
            try:
                q = ARM.inverse_down(p, y)
                break
            except UnreachableError as exc:
                err = exc
        if q is None:
            if len(self.w.unreachable) < 10:
                self.w.unreachable.append(f"t={ctx.now:.2f} s: {err}")
            return
        if q != self.w.last_targets:
            for j, v in enumerate(q, start=1):
                self._write(ctx, f"target{j}", v)
            self.w.last_targets = q

    def _order1(self) -> Order | None:
        order = self.ex.memory.get(CommonMemory.cmd(1))
        return order if isinstance(order, Order) else None

    def _m1(self, ctx: LevelContext) -> None:
        w = self.w
        cfg = w.cfg
        order = self._order1()
        now = ctx.now
        goal: tuple[float, float, float] | None = None
        allowance = 5.0
        if order is not None:
            w.order_start.setdefault(order.serial, now)
            if order.call.name in ("MOVE TO P", "APPROACH") and order.call.args:
                goal = _point(order.call.args[0])
                allowance = 60.0
            elif order.call.name == "MOVE 5mm DIR":
                goal = w.order_goal.get(order.serial)
                spd = float(order.call.args[1]) if len(order.call.args) > 1 else 0.9  # type: ignore[arg-type]
                allowance = 5.0 + 2.0 * 5.0 / spd if spd > 0 else 10.0
        elapsed = now - w.order_start[order.serial] if order is not None else 0.0
        arrived = (goal is not None and w.tip is not None
                   and math.dist(goal, w.tip) <= ARRIVED_MM)
        timeout = not arrived and elapsed > allowance
        flow = float(ctx.read("gas_flow") or 0.0)  # type: ignore[arg-type]
        bottle = float(ctx.read("gas_bottle") or 0.0)  # type: ignore[arg-type]
        volts = float(ctx.read("arc_volts") or 0.0)  # type: ignore[arg-type]
        temp = float(ctx.read("arc_temp") or cfg.ambient)  # type: ignore[arg-type]
        wire = float(ctx.read("wire_speed") or 0.0)  # type: ignore[arg-type]
        arc = w.volts > 0 and 1.0 < volts < w.volts + cfg.open_circuit_extra / 2
        image = ctx.read("linear")
        aligned = isinstance(image, str) and analyse(image).pattern == "start"
        f = ctx.facts
        f.update({
            # level 0 reports one of three (tables/NOTES.md, H1 MOVE TO P row 4)
            "arrived": arrived, "timeout": timeout, "not arrived": not arrived and not timeout,
            "arc on": arc, "arc off": not arc,
            "bottle full": bottle > 2.0, "bottle empty": bottle <= 2.0,
            "gas flowing": flow > 1.0, "gas not flowing": flow <= 1.0,
            "motors on": w.motors, "motors off": not w.motors,
            "aligned": aligned, "not aligned": not aligned,
        })
        ctx.values.update({"temp": temp, "threshold": cfg.weld_band[0],
                           "speed": float(round(wire))})

    def _actuate(self, call: Call, ctx: LevelContext) -> None:
        """Level 0: execute one command H1 issued this cycle (see the module doc)."""
        w = self.w
        name, args = call.name, call.args
        order = self._order1()
        if name == "GET THETA TO":
            p = _point(args[0])
            if p is not None:
                w.goal, w.linear, w.goal_yaw, w.setpoint = p, False, w.heading, None
        elif name == "GET THETA DIR":
            base = w.tip or w.start
            u = _direction(w, args[0])
            if u[2] == 0.0 and w.goal is not None:
                base = (base[0], base[1], w.goal[2])  # in the plate plane: keep the commanded
                # height (re-reading it from the noisy joints would let the stand-off drift)
            dist = float(args[1])  # type: ignore[arg-type]
            w.goal = (base[0] + u[0] * dist, base[1] + u[1] * dist, base[2] + u[2] * dist)
            w.linear, w.setpoint = True, base
            if not isinstance(args[0], str) and abs(float(args[0])) <= 45.0:  # type: ignore[arg-type]
                w.goal_yaw = math.atan2(u[1], u[0])  # the sensor looks along the travel
            else:
                w.goal_yaw = w.yaw
            if order is not None:
                w.order_goal[order.serial] = w.goal
        elif name == "MOTORS ON":
            w.speed = float(args[0]) if args else 0.9  # type: ignore[arg-type]
            if not w.motors and not w.intruder:
                # enable first: the drives overwrite targets written while they are disabled
                self._write(ctx, "drives_enable", 1)
                w.motors, w.last_targets = True, None
                if w.goal is not None and not w.linear:
                    self._targets(ctx, w.goal, w.goal_yaw)
        elif name == "MOTORS OFF":
            if w.motors:
                self._write(ctx, "drives_enable", 0)
            # the drives hold their targets where the joints stand while disabled: the next
            # MOTORS ON must write the targets again
            w.motors, w.setpoint, w.last_targets = False, None, None
        elif name == "INCR VOLTAGE":
            w.volts, w.volts_at = min(w.cfg.max_voltage, w.volts + VOLT_STEP), ctx.now
            self._write(ctx, "volts_set", w.volts)
        elif name == "KEEP VOLTAGE":
            pass
        elif name == "CUT VOLTAGE":
            if w.volts != 0.0:
                w.volts = 0.0
                self._write(ctx, "volts_set", 0.0)
        elif name in ("OPEN VALVE", "CLOSE VALVE"):
            v = 1 if name == "OPEN VALVE" else 0
            if w.valve != v:
                w.valve = v
                self._write(ctx, "gas_valve", v)
        elif name in ("SPEEDUP", "SLOWDOWN"):
            feed = max(0.0, min(250.0, float(args[0])))  # type: ignore[arg-type]
            if feed != w.wire:
                w.wire = feed
                self._write(ctx, "wire_set", feed)
        elif name == "MEMORIZE":
            w.memorized = args[0] if args else None

    # ---- level 2 -----------------------------------------------------------------------------
    def _g2(self, ctx: LevelContext) -> None:
        w = self.w
        volts = float(ctx.read("arc_volts") or 0.0)  # type: ignore[arg-type]
        # a short: set-point on but the arc voltage ~0 in a reading taken after the set-point
        # settled (a reading from before the last INCR VOLTAGE would look like a short)
        seen_at = self.nbs.io.arrived("arc_volts")
        shorted = (w.volts > 0 and volts < 1.0 and seen_at is not None
                   and seen_at >= w.volts_at + SETTLE_S)
        if shorted and w.stuck_z is None and w.tip is not None:
            w.stuck_z = w.tip[2]
        if w.stuck_z is not None and w.tip is not None and w.tip[2] >= w.stuck_z + FREED_MM:
            w.stuck_z = None
        f1 = self.ex.context(1).facts
        ctx.facts.update({
            "tip stuck": w.stuck_z is not None, "tip free": w.stuck_z is None,
            "gas on": bool(f1["gas flowing"]), "gas off": bool(f1["gas not flowing"]),
            "arc on": bool(f1["arc on"]), "arc off": bool(f1["arc off"]),
        })

    def _m2(self, ctx: LevelContext) -> None:
        w = self.w
        rep = ctx.mem.get(CommonMemory.report(1))
        if isinstance(rep, Report) and rep.text == "move done":
            if w.move_done_at is None:
                w.move_done_at = ctx.now
        else:
            w.move_done_at = None
        ctx.facts["wait done"] = w.move_done_at is not None and ctx.now - w.move_done_at >= WAIT_S
        ctx.facts["timeout"] = False
        h = w.cfg.home_position
        ctx.values["home"] = (h[0], h[1], h[2])

    # ---- level 3 -----------------------------------------------------------------------------
    def _g3(self, ctx: LevelContext) -> None:
        w = self.w
        image = ctx.read("linear")
        w.centre, w.width = None, None
        if isinstance(image, str) and w.tip is not None:
            seen = analyse(image)
            if seen.centre is not None and seen.width is not None:
                ahead = (math.cos(w.yaw), math.sin(w.yaw))
                lx, ly = left(w.yaw)
                off = seen.centre
                w.centre = (w.tip[0] + LOOK_AHEAD * ahead[0] + off * lx,
                            w.tip[1] + LOOK_AHEAD * ahead[1] + off * ly, w.start[2])
                w.width = seen.width
        if bool(ctx.read("end_marker") or 0):
            w.end_seen = True
        rep = ctx.mem.get(CommonMemory.report(2))
        if isinstance(rep, Report) and rep.text == "move done":
            w.armed = True
        m3 = self.h[2].machine
        plan = (m3.activations, m3.state)
        if plan != w.plan:
            if plan[0] != w.plan[0]:
                w.end_seen = False  # a new H3 command: the end marker is looked for afresh
            w.plan, w.armed = plan, True
        if isinstance(rep, Report) and rep.text == "tip stuck":
            if w.stuck_report_since is None:
                w.stuck_report_since = ctx.now
        else:
            w.stuck_report_since = None

    def _m3(self, ctx: LevelContext) -> None:
        w = self.w
        ok = w.width is not None and GAP_OK_MM[0] <= w.width <= GAP_OK_MM[1]
        nextc = w.centre is not None and w.armed
        ctx.facts.update({
            "pos(gapcentre)": w.centre is not None,
            "pos(nextcentre)": nextc, "pos(next gapcentre)": nextc,
            "gapwidth OK": w.centre is not None and ok,
            "gapwidth notOK": w.centre is not None and not ok,
            "at(gapend)": w.end_seen, "notat(gapend)": not w.end_seen,
            "tip stuck": bool(self.ex.context(2).facts["tip stuck"]),
            "timeout": (w.stuck_report_since is not None
                        and ctx.now - w.stuck_report_since > UNSTICK_TIMEOUT_S),
        })
        temp = self.ex.context(1).values.get("temp", w.cfg.ambient)
        ctx.values.update({
            "pos": w.centre if w.centre is not None else w.tip, "start": w.start,
            "target": "gapstart", "dir_to": self._dir_to, "temp": temp,
            "threshold": sum(w.cfg.weld_band) / 2.0,
        })

    def _dir_to(self, pos: object) -> float:
        """M3's ``GET DIR(d) TO pos``: degrees from the job heading towards ``pos``; consumes
        the next-centre sighting (it is re-armed by H2's next ``move done``)."""
        w = self.w
        w.armed = False
        p = _point(pos)
        if p is None or w.tip is None:
            return 0.0
        a = math.atan2(p[1] - w.tip[1], p[0] - w.tip[0]) - w.heading
        return math.degrees(math.atan2(math.sin(a), math.cos(a)))


def _point(value: object) -> tuple[float, float, float] | None:
    """A point argument of a level-0 command as (x, y, z) mm, or None when it names no point:
    the symbolic target ``gapstart`` of FIND START OF GAP / APPROACH(t) is not a place to go
    (APPROACH only checks ``aligned``; the spiral's MOVE 5mm DIR steps do the moving)."""
    if isinstance(value, tuple | list) and len(value) == 3:
        return (float(value[0]), float(value[1]), float(value[2]))
    return None


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

