"""sensed - the sensory messages the welding cell's tasks put up the hierarchy: one frozen
dataclass per kind, received with ``match`` on the class.

* :class:`SensorFailed` - a level-1 task's sensor failed (A1..A7; D3 raises ``sensor failure``);
* level 1: :class:`ArcTemp` (A1), :class:`ArcVolts` (A2), :class:`GasState` (A3),
  :class:`TipPose` (A4), :class:`WireState` (A5), :class:`GapImage` (A7);
* level 2: :class:`WeldState` (B1), :class:`TargetState` (B5);
* level 3: :class:`TipState` (C1), :class:`GapStartState` (C2);
* level 4: :class:`GapInspected` (D1), :class:`WeldTemp`, :class:`WeldTip`, :class:`WeldDone`
  (D2); D3's :class:`chcos.apps.weld.tasks.messages.Alarm`.

A receiver matches the kinds it reads and refuses any other with an error naming itself and
the message (:func:`chcos.apps.weld.tasks.messages.refused`); the exception task D3 hears every
lower task and judges the kinds it knows. The world models keep a message's fields as a plain
record (:func:`chcos.apps.weld.tasks.messages.record`) where the viewer shows them.

These are in-process values: the welding cell runs in one satellite. The link codec between
satellites (:mod:`chcos.comm.codec`) carries JSON and refuses a dataclass with a LinkError, so a
hierarchy split across satellites converts at that boundary (``record`` one way, the class
called with the record's fields the other).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

Compared = Literal["below", "within", "above"]
"""Where A1's temperature lies against the band."""


@dataclass(frozen=True, slots=True)
class SensorFailed:
    """A level-1 task's sensor ``device`` failed (``reason``) at ``t`` (s); sent once per
    episode, until the sensor delivers again."""

    device: str
    reason: str
    t: float


# ---- level 1 -----------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class ArcTemp:
    """A1: the filtered arc temperature (degC) and where it lies against the ``band`` [low,
    high] its commander gave (``cmp`` None without a band)."""

    temp: float
    cmp: Compared | None
    band: Sequence[float] | None


@dataclass(frozen=True, slots=True)
class ArcVolts:
    """A2: the filtered arc voltage (V) and current (A), and the voltage set (``setpoint``)."""

    volts: float
    amps: float
    setpoint: float


@dataclass(frozen=True, slots=True)
class GasState:
    """A3: the bottle pressure (bar, ``empty`` below A3's ``empty_bar``), the flow (L/min,
    ``flow_ok`` from A3's ``min_flow``) and whether the valve is open."""

    bottle: float
    empty: bool
    flow: float
    flow_ok: bool
    valve: bool


@dataclass(frozen=True, slots=True)
class TipPose:
    """A4: T5, the tip position ``pos`` [x, y, z] (mm) and tool ``yaw`` (rad), whether a move
    is under way, at ``t`` (s)."""

    pos: Sequence[float]
    yaw: float
    moving: bool
    t: float


@dataclass(frozen=True, slots=True)
class WireState:
    """A5: the electrode speed (mm/s) and the speed set (``setpoint``); installed with the
    supply ``wire_left``, the wire ``left`` on the spool (m) and whether it is ``empty`` (None
    without a supply reading)."""

    wire: float
    setpoint: float
    left: float | None = None
    empty: bool | None = None


@dataclass(frozen=True, slots=True)
class GapImage:
    """A7: one linear image analysed: the distance to the surface ahead (``range``, mm), the
    ``pattern`` (``none``, ``gap``, ``start``, ``end``), the gap's ``centre`` and ``width`` (mm,
    None when no gap is seen), the ``marker`` centre, whether the start or end marker is under
    the sensor (detector flag or bar pattern), at ``t`` (s)."""

    range: float
    pattern: str
    centre: float | None
    width: float | None
    marker: float | None
    start: bool
    end: bool
    t: float


# ---- level 2 -----------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class WeldState:
    """B1: the weld is ``on``, ``off``, or failed (``fail``, with the ``reason``)."""

    weld: Literal["on", "off", "fail"]
    reason: str = ""


@dataclass(frozen=True, slots=True)
class TargetState:
    """B5: the start marker ``sighted`` (two images in a row), ``not sighted``, ``passed`` or
    ``centred``; its offset ``marker`` (mm) when sighted, the tip position ``at`` when passed or
    centred, at ``t`` (s)."""

    target: Literal["sighted", "not sighted", "passed", "centred"]
    marker: float | None
    at: Sequence[float] | None
    t: float


# ---- level 3 -----------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class TipState:
    """C1: the tip is ``stuck``, ``free``, or about to stick (``sticking``, the learned
    recognizer) since ``since`` (s)."""

    tip: Literal["stuck", "free", "sticking"]
    since: float


@dataclass(frozen=True, slots=True)
class GapStartState:
    """C2: ``searching`` (with the ``plan``), at the ``start`` of the gap, or ``not found``;
    ``at`` is the probable start searched around, or where the tip stands at the start."""

    gap: Literal["searching", "start", "not found"]
    plan: str | None
    at: Sequence[float]
    t: float


# ---- level 4 -----------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class GapInspected:
    """D1: the ``target`` (gap) sighted, the predicted ``next_centre`` [x, y] (mm), the last
    ``width`` (mm) and whether it is OK, the distance ``travelled`` (mm), at ``t`` (s); the last
    one carries the ``inspection`` outcome (``OK``/``fail``)."""

    target: bool
    next_centre: Sequence[float] | None
    width: float | None
    width_ok: bool
    travelled: float
    t: float
    inspection: str | None = None


@dataclass(frozen=True, slots=True)
class WeldTemp:
    """D2: the arc temperature compared with D2's prediction (``cmp`` ``equal``, ``above`` or
    ``below``, the ``error`` degC), the distance ``travelled`` (mm) in ``phase``, at ``t``."""

    temp: float
    cmp: Literal["equal", "above", "below"]
    error: float
    travelled: float
    phase: str
    t: float


@dataclass(frozen=True, slots=True)
class WeldTip:
    """D2: C1 reported the tip ``sticking`` (D2 cuts the wire feed) or ``stuck`` (D2 has it
    freed), after ``travelled`` mm, the ``phase`` D2 goes on in, at ``t`` (s)."""

    tip: Literal["sticking", "stuck"]
    travelled: float
    phase: str
    t: float


@dataclass(frozen=True, slots=True)
class WeldDone:
    """D2: the gap is welded, ``travelled`` mm, at ``t`` (s)."""

    travelled: float
    t: float
