"""results - what the welding cell's tasks complete with: one frozen dataclass per kind, read
by the commander from ``Completion.result`` (:func:`chcos.apps.weld.tasks.messages.expect`).

* level 1: :class:`BandSet` (A1), :class:`VoltsSet` (A2), :class:`GasSet` (A3),
  :class:`Reached` (A4, also B3's), :class:`WireSet` (A5), :class:`Memorized` (A6, also what
  A6's world model answers for ``position <tag>``);
* level 2: :class:`Stopped` (B2), :class:`Stepped` (B4), :class:`Aligned` (B5);
* level 3: :class:`Freed` (C1's unstick), :class:`StartFound` (C2);
* level 4: :class:`Inspection` (D1), :class:`Welded` (D2).

A task that runs on after it took its command (A7, C1 watching, D3, E1) completes with a word
(``running``, ``watching``, ``idle``, ``armed``), B1 with ``off`` once the weld is off. The job
E2 answers the host with a plain dict (its outcome, shown by ``chcos run`` and the viewer) that
holds its subordinates' results as records (:func:`chcos.apps.weld.tasks.messages.record`).
In-process values, like :mod:`chcos.apps.weld.tasks.sensed`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal


# ---- level 1 -----------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class BandSet:
    """A1 took its command: the temperature band now compared with (None: no band)."""

    band: Sequence[float] | None


@dataclass(frozen=True, slots=True)
class VoltsSet:
    """A2 took its command: the arc voltage now maintained (V)."""

    volts: float


@dataclass(frozen=True, slots=True)
class GasSet:
    """A3 took its command: whether the gas valve is open."""

    valve: bool


@dataclass(frozen=True, slots=True)
class WireSet:
    """A5 took its command: the wire feed speed now set (mm/s)."""

    speed: float


@dataclass(frozen=True, slots=True)
class Reached:
    """A4: the tip is ``at`` [x, y, z] (mm) after the command ``op``: a ``move`` reached its
    point, or a ``hold``, ``stop`` or ``monitor`` was taken where the tip stood."""

    at: Sequence[float]
    op: Literal["move", "hold", "stop", "monitor"] = "move"


@dataclass(frozen=True, slots=True)
class Memorized:
    """A6: the position stored under ``tag`` (T5: ``pos`` mm, ``yaw`` rad; the joint angles
    ``thetas``) at ``t`` (s); whether the drives were ``stopped``, and each drive's state
    name after a stop or an enable (``drives``)."""

    tag: str
    pos: Sequence[float]
    yaw: float
    thetas: Sequence[float]
    t: float
    stopped: bool
    drives: Mapping[str, str]


# ---- level 2 -----------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Stopped:
    """B2: what each level-1 task answered to the stop (the completion status, or the status
    and the error), by task name."""

    answers: Mapping[str, str]


@dataclass(frozen=True, slots=True)
class Stepped:
    """B4: how A4's move ended (the completion ``status``) and A4's result (None when A4 was
    pre-empted)."""

    status: str
    result: Reached | None


@dataclass(frozen=True, slots=True)
class Aligned:
    """B5: the tip stands at the start of the gap, ``at`` [x, y, z] (mm), with tool ``yaw``."""

    at: Sequence[float]
    yaw: float


# ---- level 3 -----------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Freed:
    """C1: the tip came free after a lift of ``lift`` mm; ``memorized`` is where it stuck."""

    memorized: Memorized
    lift: float


@dataclass(frozen=True, slots=True)
class StartFound:
    """C2: the tip stands at the start of the gap, ``at`` [x, y, z] (mm), with tool ``yaw``
    along the gap, after ``searched_mm`` of search with ``plan`` (``none``: no search)."""

    at: Sequence[float]
    yaw: float
    searched_mm: float
    plan: str


# ---- level 4 -----------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Inspection:
    """D1: the inspection's outcome, ``OK`` or ``fail`` (``reason``: ``too wide`` or ``too
    narrow``, the ``width`` that failed it) ``at_mm`` along the gap, from ``start`` [x, y, z]
    along ``heading``; the length inspected and the widths seen (None: none seen)."""

    inspection: Literal["OK", "fail"]
    reason: str
    at_mm: float
    width: float | None
    start: Sequence[float]
    heading: float
    length_mm: float
    width_min: float | None
    width_max: float | None

    @property
    def ok(self) -> bool:
        """True if the gap passed the inspection."""
        return self.inspection == "OK"


@dataclass(frozen=True, slots=True)
class Welded:
    """D2: the gap welded, ``welded_mm`` long, the share of temperature samples ``in_band``,
    how often the tip was freed (``unstuck``), the travel speeds used [min, max] (mm/s)."""

    welded_mm: float
    in_band: float
    unstuck: int
    speed_range: Sequence[float]

