"""gm - the G and M modules of Appendix 1's NBS hierarchy on the welding cell, and level 0.

The thesis gives the H modules (the transcribed tables, :mod:`chcos.apps.nbs.statetable`) but no
G or M module; :class:`CellModules` writes the ones the tables name for the welding cell, and
nothing more, over one common world model (:class:`World`). :class:`chcos.apps.nbs.weldcell.NbsCell`
binds them to a running cell:

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
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from chcos.apps.nbs.adapter import DevtabIO, NbsOnSystem
from chcos.apps.nbs.executor import CommonMemory, LevelContext, NbsExecutor, Order, Report, TableH
from chcos.apps.nbs.statetable import Call
from chcos.apps.weld.kinematics import UnreachableError
from chcos.apps.weld.model import CellConfig
from chcos.apps.weld.tasks.common import ARM, AXES, LOOK_AHEAD, analyse, left, pose_of

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


@dataclass
class World:
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


def _direction(w: World, d: object) -> tuple[float, float, float]:
    if isinstance(d, str):
        if d.strip() == "-z":
            return (0.0, 0.0, 1.0)  # "-z" of the tool: away from the work, i.e. up
        raise ValueError(f"level 0: direction {d!r}: expected degrees or '-z'")
    a = w.heading + math.radians(float(d))  # type: ignore[arg-type]
    return (math.cos(a), math.sin(a), 0.0)


class CellModules:
    """G1..G3, M1..M3 and level 0 (H1's ``[lower]`` commands, :meth:`actuate`) over the common
    world model ``w``. :attr:`nbs` (the cycle on the System) and :attr:`h3` (H3, whose plan
    steps G3 follows) are bound once the hierarchy is built; a module runs only inside a cycle.
    """

    def __init__(self, world: World) -> None:
        self.w = world
        self.nbs: NbsOnSystem | None = None
        self.h3: TableH | None = None

    @property
    def ex(self) -> NbsExecutor:
        """The NBS executor the modules run in (bound with :attr:`nbs`)."""
        assert self.nbs is not None, "CellModules: not bound to a cycle yet"
        return self.nbs.executor

    def _io(self) -> DevtabIO:
        assert self.nbs is not None, "CellModules: not bound to a cycle yet"
        return self.nbs.io

    def _h3(self) -> TableH:
        assert self.h3 is not None, "CellModules: H3 not bound yet"
        return self.h3

    # ---- level 0 and level 1 -----------------------------------------------------------------
    def _write(self, ctx: LevelContext, device: str, value: object) -> None:
        if self.w.intruder and any(device == d for d, _ in SAFE):
            return  # the reflex holds the safe value while the light curtain is broken
        ctx.write(device, value)

    def g1(self, ctx: LevelContext) -> None:
        w = self.w
        # the safety reflex: poll the light curtain every cycle
        present = bool(ctx.read("intruder") or 0)
        if present and not w.intruder:
            seen = self._io().arrived("intruder") or ctx.now
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
            # the joint drives (CiA 402) take targets only once enabled: until they all say so,
            # the targets are written again every cycle
            if all(ctx.read(f"{a}.state") == "OPERATION_ENABLED" for a in AXES):
                self.w.last_targets = q

    def _order1(self) -> Order | None:
        order = self.ex.memory.get(CommonMemory.cmd(1))
        return order if isinstance(order, Order) else None

    def m1(self, ctx: LevelContext) -> None:
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

    def actuate(self, call: Call, ctx: LevelContext) -> None:
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
                for axis in AXES:       # the CiA 402 state machine: the command code ENABLE
                    self._write(ctx, axis, 1)
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
    def g2(self, ctx: LevelContext) -> None:
        w = self.w
        volts = float(ctx.read("arc_volts") or 0.0)  # type: ignore[arg-type]
        # a short: set-point on but the arc voltage ~0 in a reading taken after the set-point
        # settled (a reading from before the last INCR VOLTAGE would look like a short)
        seen_at = self._io().arrived("arc_volts")
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

    def m2(self, ctx: LevelContext) -> None:
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
    def g3(self, ctx: LevelContext) -> None:
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
        m3 = self._h3().machine
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

    def m3(self, ctx: LevelContext) -> None:
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
