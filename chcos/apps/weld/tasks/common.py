"""common - what the welding cell's tasks share: errors, geometry, the linear-image analysis,
the spike filter and the gap tracker.

Messages are typed: the commands and D3's alarm are the dataclasses of
:mod:`chcos.apps.weld.tasks.messages` (a console command, a dict, is converted at the boundary by
``messages.from_host``), the sensory messages those of :mod:`chcos.apps.weld.tasks.sensed`, the
completions those of :mod:`chcos.apps.weld.tasks.results`; each is received with ``match``.
"""

from __future__ import annotations

import math
import types
from collections import deque
from collections.abc import Generator, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

from chcos.apps.weld.kinematics import Arm, ToolPose
from chcos.apps.weld.tasks.messages import refused
from chcos.apps.weld.tasks.sensed import GapImage, SensorFailed, TipPose
from chcos.errors import ChcosError, SensorFailure
from chcos.user.context import Port, TaskContext
from drivers.codecs.cia402 import Cia402Error, Mode, Op, Result, State

ARM = Arm()
"""The welding arm's geometry (the same DH table as the cell): T5 and inverse kinematics."""

PIXELS = 64
PITCH = 0.5
"""Linear sensor: 64 pixels, 0.5 mm apart; pixel index grows towards the tool's left."""
LOOK_AHEAD = 5.0
"""The linear sensor looks 5 mm ahead of the tip along the tool x axis."""

Vec = tuple[float, float, float]


class WeldTaskError(ChcosError):
    """A welding-cell task could not do what its commander asked. The message names the task and
    what was expected; it reaches the commander as the text of an abnormal completion."""


class GasFailure(WeldTaskError):
    """Shielding gas failed (bottle empty or no flow) while the weld needed it."""


class WireFailure(WeldTaskError):
    """The electrode supply ran out (A5.s: nothing left on the spool) while the weld needed it."""


class ServoFailure(WeldTaskError):
    """A joint's position sensor failed (servo timeout): the arm cannot be moved safely."""


class MotionFailed(WeldTaskError):
    """A move could not be made: out of reach, stalled, or taken over by another commander."""


class SearchFail(WeldTaskError):
    """The spiral search found no start-of-gap marker."""


class TargetNotSighted(WeldTaskError):
    """The approach found no target marker under the linear sensor."""


class TipStillStuck(WeldTaskError):
    """The electrode stayed frozen to the plate after the unstick manoeuvre."""


class ArcFailure(WeldTaskError):
    """The arc did not strike (no temperature rise) after the weld was turned on."""


class WeldAborted(WeldTaskError):
    """A weld or an inspection stopped because a lower task failed; names that task."""


# ---- the joint drives (CiA 402 axes joint1..joint5) --------------------------------------------
AXES = tuple(f"joint{j}" for j in range(1, 6))
"""The joint drives as axes (``ctx.axis``); A6 has them on its output ports (it owns them while
it runs), beside the safe-torque-off relay ``drives_enable``."""


@types.coroutine
def confirmed(command: Any) -> Generator[Any, Any, Result]:
    """Await an axis command (``ctx.axis(name).enable()``...) until the drive confirmed it: its
    :class:`drivers.codecs.cia402.Result`. Raises what the command raises."""
    result: Result = yield from command
    return result


def joints_enabled(ctx: TaskContext) -> bool:
    """True if every joint drive confirmed OPERATION ENABLED in CSP."""
    return all(ctx.axis(name).state is State.OPERATION_ENABLED
               and ctx.axis(name).mode == Mode.CSP for name in AXES)


async def enable_joints(ctx: TaskContext, who: str) -> None:
    """Switch the safe-torque-off relay ``drives_enable`` on, then put every joint drive in
    CSP and enable it, one after the other, each confirmed by its statusword. Raises
    ServoFailure naming the drive, the state it reached and 0x603F when one is not enabled
    (or is busy stopping)."""
    ctx.write("drives_enable", 1.0)
    for name in AXES:
        axis = ctx.axis(name)
        try:
            if axis.mode != Mode.CSP:
                await confirmed(axis.set_mode())
            if axis.state is not State.OPERATION_ENABLED:
                await confirmed(axis.enable())
        except Cia402Error as exc:
            raise ServoFailure(f"{who}: joint drive {name} not enabled: {exc}") from exc


async def quick_stop_joints(ctx: TaskContext, who: str) -> dict[str, str]:
    """Quick-stop every joint drive that is enabled (decelerating; one already in its safe
    stop, after an e-stop, joins that), each confirmed by its statusword, then drop the relay.
    Returns each drive's state name afterwards. Raises ServoFailure naming a drive that did
    not stop."""
    states: dict[str, str] = {}
    for name in AXES:
        axis = ctx.axis(name)
        if axis.state is State.OPERATION_ENABLED or axis.status.busy is Op.SAFE_STOP:
            try:
                await confirmed(axis.quick_stop())
            except Cia402Error as exc:
                if axis.state is State.OPERATION_ENABLED and axis.status.busy is not Op.SAFE_STOP:
                    ctx.write("drives_enable", 0.0)
                    raise ServoFailure(f"{who}: joint drive {name} did not stop: {exc}") \
                        from exc
        state = axis.state
        states[name] = "unknown" if state is None else state.name
    ctx.write("drives_enable", 0.0)
    return states


def setting(ctx: TaskContext, value: Any, key: str, default: Any) -> Any:
    """A typed command's field ``value``, else the install-time parameter ``key``, else
    ``default`` (a field left None means: as installed)."""
    return ctx.params.get(key, default) if value is None else value


async def latest(ctx: TaskContext, port: Port, timeout: float = 0.5) -> Any:
    """The newest message on ``port``: a waiting one, else the last one this task saw (kept in
    its world model), else wait up to ``timeout`` s for one. Raises SensorFailure for a failed
    sensor, ReadTimeout if nothing comes."""
    key = f"last:{port}"
    value = ctx.poll(port)
    if value is None:
        value = ctx.world.sensory.get(key)
    if value is None:
        value = await ctx.read(port, timeout=timeout)
    ctx.world.sensory[key] = value
    return value


async def tip_pose(ctx: TaskContext, who: str) -> TipPose:
    """A4's newest report of the tip pose (:func:`latest` on the port ``A4``). Raises
    ServoFailure naming ``who`` when A4 reports a failed joint sensor, MessageError naming
    ``who`` for any other message, ReadTimeout if A4 reports nothing."""
    match await latest(ctx, "A4"):
        case TipPose() as pose:
            return pose
        case SensorFailed(device=device, reason=reason):
            raise ServoFailure(f"{who}: A4 reports joint sensor {device} failed ({reason})")
        case other:
            raise refused(who, other, "a TipPose from A4")


def report_failure(ctx: TaskContext, exc: SensorFailure) -> None:
    """Send a sensor failure upward once per episode (kept in the world model) and note it."""
    failed: set[str] = ctx.world.sensory.setdefault("failed", set())
    if exc.device not in failed:
        failed.add(exc.device)
        ctx.put(SensorFailed(exc.device, exc.reason, ctx.now))


async def await_recovery(ctx: TaskContext, exc: SensorFailure) -> None:
    """After a sensor failure, wait (without polling) until the failed sensor delivers again:
    its next reading is kept as the last value seen (see :func:`latest`)."""
    if exc.device not in ctx.inputs:
        await ctx.sleep(0.1)  # not one of this task's inputs: nothing to wait on
        return
    ev = await ctx.wait_any([exc.device])
    if ev.kind == "message":
        ctx.world.sensory[f"last:{exc.device}"] = ev.value


def clear_failure(ctx: TaskContext, device: str) -> None:
    """Forget a reported failure of ``device`` (it delivers again)."""
    failed: set[str] = ctx.world.sensory.setdefault("failed", set())
    failed.discard(device)


class SpikeFilter:
    """Median of the last three samples: one wild sample (a spike) never gets through."""

    def __init__(self) -> None:
        self.window: deque[float] = deque(maxlen=3)

    def push(self, value: float) -> float:
        """Add a sample; return the filtered value."""
        self.window.append(float(value))
        return sorted(self.window)[len(self.window) // 2]


# ---- geometry --------------------------------------------------------------------------------
def pose_of(thetas: Sequence[float]) -> ToolPose:
    """T5 of joint angles ``thetas`` (forward kinematics) as a tool pose."""
    return ARM.tool_pose(thetas)


def unit(v: Sequence[float]) -> Vec:
    """``v`` scaled to length 1 (a zero vector stays zero)."""
    n = math.sqrt(sum(c * c for c in v))
    if n < 1e-12:
        return (0.0, 0.0, 0.0)
    return (v[0] / n, v[1] / n, v[2] / n)


def add(p: Sequence[float], d: Sequence[float], k: float = 1.0) -> Vec:
    """``p + k * d``."""
    return (p[0] + k * d[0], p[1] + k * d[1], p[2] + k * d[2])


def dist(a: Sequence[float], b: Sequence[float]) -> float:
    """Euclidean distance of two points (2-D or 3-D)."""
    return math.sqrt(sum((x - y) ** 2 for x, y in zip(a, b, strict=False)))


def left(yaw: float) -> tuple[float, float]:
    """The unit vector to the tool's left in the plate plane (pixel index grows this way)."""
    return (-math.sin(yaw), math.cos(yaw))


# ---- the linear image (A7.s, B5.s, D1.s) ------------------------------------------------------
def offset_mm(index: float) -> float:
    """Lateral offset (mm, positive to the tool's left) of pixel ``index`` from the centre."""
    return (index - (PIXELS - 1) / 2.0) * PITCH


def dark_runs(pixels: str) -> list[tuple[int, int]]:
    """The dark runs of a binary image as (first, last) pixel indices."""
    runs: list[tuple[int, int]] = []
    start = -1
    for i, ch in enumerate(pixels):
        if ch == "1" and start < 0:
            start = i
        elif ch != "1" and start >= 0:
            runs.append((start, i - 1))
            start = -1
    if start >= 0:
        runs.append((start, len(pixels) - 1))
    return runs


@dataclass(frozen=True)
class LinearImage:
    """What A7 makes of one linear image: the pattern (``none``, ``gap``, ``start`` for the
    three-bar start marker, ``end`` for the two wide bars of the end marker), the gap's centre
    (mm to the tool's left of the sensor centre) and width (mm), and the marker centre."""

    pattern: str
    centre: float | None
    width: float | None
    marker_centre: float | None = None
    runs: tuple[tuple[int, int], ...] = field(default_factory=tuple)


def analyse(pixels: str, hint: float = 0.0) -> LinearImage:
    """Classify a linear image and find the gap in it; ``hint`` is where the gap was last seen
    (mm), used to pick the gap among several dark runs."""
    runs = dark_runs(pixels)
    if not runs:
        return LinearImage("none", None, None)
    centres = [(a + b) / 2.0 for a, b in runs]
    widths = [b - a + 1 for a, b in runs]
    pattern = "gap"
    marker: float | None = None
    gap_run: int | None = None
    for i in range(len(runs) - 2):  # start marker: three bars, centres 6 mm (12 px) apart
        c0, c1, c2 = centres[i], centres[i + 1], centres[i + 2]
        if (9 <= c1 - c0 <= 15 and 9 <= c2 - c1 <= 15
                and max(widths[i], widths[i + 2]) <= 7):
            pattern, marker, gap_run = "start", (c0 + c2) / 2.0, i + 1
            break
    if pattern == "gap":
        wide = [i for i, w in enumerate(widths) if w >= 6]
        for i in range(len(wide) - 1):  # end marker: two wide bars, centres 10 mm apart
            a, b = wide[i], wide[i + 1]
            if 16 <= centres[b] - centres[a] <= 24:
                pattern, marker = "end", (centres[a] + centres[b]) / 2.0
                inner = [k for k in range(a + 1, b)]
                gap_run = inner[0] if inner else None
                break
    if pattern == "gap":
        gap_run = min(range(len(runs)), key=lambda k: abs(offset_mm(centres[k]) - hint))
    if gap_run is None:
        return LinearImage(pattern, None, None, offset_mm(marker) if marker is not None else None,
                           tuple(runs))
    return LinearImage(pattern, offset_mm(centres[gap_run]), widths[gap_run] * PITCH,
                       offset_mm(marker) if marker is not None else None, tuple(runs))


# ---- gap tracking (D1.s / D2.s: predicted next centre of the gap) ----------------------------
class Tracker:
    """Follows the gap: turns each sighting (tip pose + gap offset in the linear image) into a
    point of the gap in the plate plane, keeps the recent ones, estimates the gap's heading and
    predicts the next centre ``ahead`` mm on. :meth:`steer` gives the direction the tip should
    move in (towards the newest gap point, about 5 mm ahead of the tip, with a height
    correction) and the yaw that keeps the sensor looking along the gap.

    The height is held by the range sensor (A7's ``range``, the distance from the sensor to the
    surface 5 mm ahead): :meth:`ranged` takes each reading, and the first one (or ``standoff``)
    is the stand-off to hold; a surface that rises or falls is followed. Without readings the
    tip keeps the height ``z_work`` it started at."""

    def __init__(self, heading: float, z_work: float, keep: int = 16,
                 standoff: float | None = None) -> None:
        self.points: deque[tuple[float, float]] = deque(maxlen=keep)
        self.heading = heading
        self.z_work = z_work
        self.travelled = 0.0
        self._last_pos: tuple[float, float] | None = None
        self.standoff = standoff
        self.ranges: deque[float] = deque(maxlen=5)

    def ranged(self, range_mm: Any) -> None:
        """Take a range reading (mm; None or negative: nothing in range, ignored)."""
        if range_mm is None:
            return
        r = float(range_mm)
        if not (0.0 <= r <= 100.0):
            return
        if self.standoff is None:
            self.standoff = r
        self.ranges.append(r)

    def sighting(self, pos: Sequence[float], yaw: float, centre: float) -> tuple[float, float]:
        """Record the gap seen ``centre`` mm left of the sensor while the tip is at ``pos``
        with yaw ``yaw``; returns the gap point (x, y) in mm."""
        lx, ly = left(yaw)
        sx = pos[0] + LOOK_AHEAD * math.cos(yaw)
        sy = pos[1] + LOOK_AHEAD * math.sin(yaw)
        g = (sx + centre * lx, sy + centre * ly)
        if not self.points or dist(self.points[-1], g) >= 0.3:
            self.points.append(g)
        far = [p for p in self.points if dist(p, g) >= 3.0]
        if far:
            ref = far[-1]
            self.heading = math.atan2(g[1] - ref[1], g[0] - ref[0])
        return g

    def moved(self, pos: Sequence[float]) -> float:
        """Add the tip's plate-plane movement to :attr:`travelled` (in steps of at least
        0.5 mm, so that measurement noise does not add up); returns the total (mm)."""
        p = (pos[0], pos[1])
        if self._last_pos is None:
            self._last_pos = p
        elif dist(self._last_pos, p) >= 0.5:
            self.travelled += dist(self._last_pos, p)
            self._last_pos = p
        return self.travelled

    def predict(self, ahead: float = 5.0) -> tuple[float, float] | None:
        """The predicted next gap centre ``ahead`` mm beyond the newest sighting (None before
        the first one)."""
        if not self.points:
            return None
        g = self.points[-1]
        return (g[0] + ahead * math.cos(self.heading), g[1] + ahead * math.sin(self.heading))

    def steer(self, pos: Sequence[float]) -> tuple[Vec, float]:
        """(direction d, yaw) for the next 5 mm move of the tip at ``pos``."""
        if self.points:
            g = self.points[-1]
            dx, dy = g[0] - pos[0], g[1] - pos[1]
            if math.hypot(dx, dy) < 2.0:  # the newest point is not ahead any more
                dx, dy = math.cos(self.heading), math.sin(self.heading)
        else:
            dx, dy = math.cos(self.heading), math.sin(self.heading)
        n = math.hypot(dx, dy)
        if self.ranges and self.standoff is not None:
            # the surface ahead is range below the sensor: hold the stand-off above it
            surface = pos[2] - sum(self.ranges) / len(self.ranges)
            self.z_work = surface + self.standoff
        dz = max(-0.5, min(0.5, (self.z_work - pos[2]) / LOOK_AHEAD))
        return (dx / n, dy / n, dz), self.heading


def sighted(msg: object, which: Literal["start", "end"]) -> bool:
    """True if ``msg`` is an A7 image that says the ``which`` marker is under the sensor (a
    failure or nothing is no sighting)."""
    match msg:
        case GapImage(start=start, end=end):
            return start if which == "start" else end
        case _:
            return False
