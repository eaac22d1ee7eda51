"""messages - the typed messages the welding cell's tasks send each other: one frozen dataclass
per message kind, received with ``match`` on the class.

* the level-1 set-points :class:`SetBand` (A1), :class:`SetVolts` (A2), :class:`SetGas` (A3),
  :class:`SetWire` (A5): a field left None leaves that set-point as it is;
* A6's command :class:`DrivesCommand`;
* A4's motion commands :class:`MoveTo`, :class:`HoldMotion`, :class:`StopMotion`,
  :class:`Monitor` (:data:`MotionCommand`);
* B4's :class:`Step` (or :class:`HoldMotion`) (:data:`StepCommand`);
* B1's :class:`WeldOn` / :class:`WeldOff` (:data:`WeldCommand`);
* B3's :class:`GoHome`, B5's :class:`Approach`;
* the job E2's own :class:`Job` (from the host: ``invoke E2 inspect_only=true``...);
* the job's :class:`Inspect` (D1) and :class:`Weld` (D2), and their :class:`FindStart` (C2);
* C1's :class:`WatchTip` / :class:`IdleTip` / :class:`Unstick` (:data:`TipCommand`);
* D3's :class:`Alarm`, read by E1 and E2.

A command typed at the console (``invoke A4 op=move p=[500,0,250]``) arrives as a dict: it is
converted at the boundary, by :func:`from_host`, into the receiver's message class, and every
other wrong message is refused by :func:`refused`, naming the task and the message. The sensory
messages the tasks put up are in :mod:`chcos.apps.weld.tasks.sensed`, what they complete with in
:mod:`chcos.apps.weld.tasks.results`; :func:`expect` reads a completion's result as its class,
:func:`record` gives a message's fields as a plain dict (world models, the job's outcome).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any, TypeVar

from chcos.errors import MessageError

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

M = TypeVar("M")


# ---- the level-1 set-points (A1, A2, A3, A5) ---------------------------------------------------
@dataclass(frozen=True, slots=True)
class SetBand:
    """A1: the temperature band ``[low, high]`` (degC) the arc temperature is compared with."""

    band: Sequence[float] | None = None


@dataclass(frozen=True, slots=True)
class SetVolts:
    """A2: the arc voltage to set and maintain (V)."""

    volts: float | None = None


@dataclass(frozen=True, slots=True)
class SetGas:
    """A3: the gas valve, ``"on"``/``"off"`` (``True``/``1`` also mean on)."""

    gas: str | bool | int | None = None

    @property
    def on(self) -> bool:
        """True if the valve is to be opened."""
        return self.gas in ("on", 1, True)


@dataclass(frozen=True, slots=True)
class SetWire:
    """A5: the wire feed ``speed`` (mm/s), or a ``step`` that advances (positive) or retards
    (negative) it; ``empty_m``: below this much wire on the spool it is empty (None: A5's
    install parameter, else 0.05 m)."""

    speed: float | None = None
    step: float | None = None
    empty_m: float | None = None


@dataclass(frozen=True, slots=True)
class DrivesCommand:
    """A command of A6 (stop/memorize position, and the joint drives' power), in this order:
    ``stop`` quick-stops the joint drives and drops the relay; ``enable`` switches the relay on
    and enables the drives; ``memorize`` stores the position under that tag (None: nothing
    memorized)."""

    stop: bool = False
    enable: bool = False
    memorize: str | None = "last"


# ---- A4: move to position p at speed s ---------------------------------------------------------
@dataclass(frozen=True, slots=True)
class MoveTo:
    """A4: move the tip along a straight line to ``p`` (mm) at ``speed`` mm/s, turning the tool
    to ``yaw`` (rad; None: the yaw it has)."""

    p: Sequence[float]
    speed: float = 20.0
    yaw: float | None = None


@dataclass(frozen=True, slots=True)
class HoldMotion:
    """A4 (and B4): keep the joints where they are."""


@dataclass(frozen=True, slots=True)
class StopMotion:
    """A4: keep the joints where they are and drop ``drives_enable`` (safe torque off)."""


@dataclass(frozen=True, slots=True)
class Monitor:
    """A4: no motion, just report the pose (also what no command means)."""


MotionCommand = MoveTo | HoldMotion | StopMotion | Monitor
"""What A4 accepts."""


# ---- B4: move 5 mm in direction d --------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Step:
    """B4: move ``dist`` mm from the present tip position along direction ``d`` (a 3-vector,
    normalised by B4) at ``speed`` mm/s with tool yaw ``yaw`` (None: unchanged)."""

    d: Sequence[float] = (0.0, 0.0, 0.0)
    dist: float = 5.0
    speed: float = 5.0
    yaw: float | None = None


StepCommand = Step | HoldMotion
"""What B4 accepts."""


# ---- B3: go home, B5: approach target ----------------------------------------------------------
@dataclass(frozen=True, slots=True)
class GoHome:
    """B3: move the tip to ``home`` [x, y, z] (mm) at ``speed`` mm/s (None: B3's install
    parameters, else [500, 0, 250] and 100 mm/s)."""

    home: Sequence[float] | None = None
    speed: float | None = None


@dataclass(frozen=True, slots=True)
class Approach:
    """B5: centre the tip on the start marker with tool yaw ``yaw`` (None: the yaw it has),
    ending ``backoff`` mm before it (None: B5's install parameter, else 1.5 mm)."""

    yaw: float | None = None
    backoff: float | None = None


# ---- C2, D1, D2: find the start, inspect, weld ------------------------------------------------
# A field left None is taken from the receiver's install parameters, else its default.
@dataclass(frozen=True, slots=True)
class FindStart:
    """C2: find and centre on the start-of-gap marker near ``start`` [x, y] (mm), the gap
    heading ``heading`` (rad), the tip at height ``z`` (mm); the search's speeds and sizes."""

    start: Sequence[float] | None = None
    heading: float | None = None
    z: float | None = None
    speed: float | None = None
    travel: float | None = None
    pitch: float | None = None
    radius: float | None = None
    raster_radius: float | None = None
    raster_length: float | None = None
    raster_step: float | None = None


@dataclass(frozen=True, slots=True)
class Job:
    """E2: the job: the gap's probable ``start`` [x, y] (mm), ``heading`` (rad) and the tip
    height ``z`` (mm), the ``home`` [x, y, z] to return to; ``inspect_only`` skips the weld."""

    start: Sequence[float] | None = None
    heading: float | None = None
    z: float | None = None
    home: Sequence[float] | None = None
    inspect_only: bool | None = None


@dataclass(frozen=True, slots=True)
class Inspect:
    """D1: inspect the gap from near ``start`` (heading, z as :class:`FindStart`) at ``speed``
    mm/s; widths below ``too_narrow`` or above ``too_wide`` mm, ``confirm`` sightings in a row,
    are defects; ``steer`` is the steering period (s)."""

    start: Sequence[float] | None = None
    heading: float | None = None
    z: float | None = None
    speed: float | None = None
    too_narrow: float | None = None
    too_wide: float | None = None
    confirm: int | None = None
    steer: float | None = None


@dataclass(frozen=True, slots=True)
class Weld:
    """D2: weld the gap from near ``start`` (heading, z as :class:`FindStart`) at ``speed``
    mm/s, holding the arc temperature in ``band`` [low, high] degC (``deadband`` degC) with
    ``volts`` V and ``wire`` mm/s, waiting ``strike`` s for the arc; ``steer`` is the steering
    period (s)."""

    start: Sequence[float] | None = None
    heading: float | None = None
    z: float | None = None
    speed: float | None = None
    band: Sequence[float] | None = None
    volts: float | None = None
    wire: float | None = None
    steer: float | None = None
    deadband: float | None = None
    strike: float | None = None


# ---- B1: turn the weld on/off ------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class WeldOn:
    """B1: turn the weld on. A field left None is taken from B1's install parameters (else its
    default): ``volts`` (24 V), ``wire`` (80 mm/s), ``gas_wait`` (1 s), ``gas_grace`` (0.15 s)."""

    volts: float | None = None
    wire: float | None = None
    gas_wait: float | None = None
    gas_grace: float | None = None


@dataclass(frozen=True, slots=True)
class WeldOff:
    """B1: voltage, wire and gas off."""


WeldCommand = WeldOn | WeldOff
"""What B1 accepts."""


# ---- C1: unstick tip / tip stuck-free ----------------------------------------------------------
@dataclass(frozen=True, slots=True)
class WatchTip:
    """C1: watch for a stuck tip while the weld runs (also what no command means)."""


@dataclass(frozen=True, slots=True)
class IdleTip:
    """C1: stop watching."""


@dataclass(frozen=True, slots=True)
class Unstick:
    """C1: free a stuck tip, lifting it ``lift`` mm (None: C1's install parameter, else 10)."""

    lift: float | None = None


TipCommand = WatchTip | IdleTip | Unstick
"""What C1 accepts."""


# ---- D3: the alarm -----------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Alarm:
    """D3's alarm (``intruder``, ``sensor failure``, ``unexpected heat``, ``overheat``) with what
    was seen and when (``t``, s)."""

    kind: str
    detail: str
    t: float

    def record(self) -> dict[str, Any]:
        """The alarm as a plain record (``{"alarm", "detail", "t"}``), as D3's world model keeps
        it for the report and the viewer."""
        return {"alarm": self.kind, "detail": self.detail, "t": self.t}


# ---- the host boundary and refusals ------------------------------------------------------------
def from_host(task: str, raw: object, kinds: Mapping[str, type[M]],
              default: str | Callable[[Mapping[str, Any]], str], expected: str) -> M:
    """The command typed at the console for ``task`` (a dict ``{"op": name, field: value...}``)
    as the message class ``kinds[op]`` (``op`` missing: ``default``, or what ``default`` makes
    of the dict). Anything but a dict is refused (:func:`refused`, saying the ``expected``
    messages). Raises MessageError naming the task for an unknown op or a key the message does
    not have."""
    if not isinstance(raw, Mapping):
        raise refused(task, raw, expected)
    op = raw.get("op", default if isinstance(default, str) else default(raw))
    cls = kinds.get(op) if isinstance(op, str) else None
    if cls is None:
        raise MessageError(f"{task}: unknown op {op!r} in {dict(raw)!r} "
                           f"(expected one of {', '.join(kinds)})")
    names = {f.name for f in fields(cls)}  # type: ignore[arg-type]
    extra = sorted(set(raw) - names - {"op"})
    if extra:
        raise MessageError(f"{task}: {op}: unknown key(s) {', '.join(extra)} in {dict(raw)!r} "
                           f"(expected {', '.join(sorted(names)) or 'none'})")
    try:
        return cls(**{k: v for k, v in raw.items() if k != "op"})
    except TypeError as exc:
        raise MessageError(f"{task}: {op}: {exc}") from exc


def refused(task: str, message: object, expected: str) -> MessageError:
    """The error a task raises for a message it does not take: names the task, what it expects
    and the message received."""
    return MessageError(f"{task}: expected {expected}, got {message!r}")


def expect(task: str, message: object, cls: type[M]) -> M:
    """``message`` (a completion's result, a world model's answer) as the ``cls`` ``task``
    expects; raises MessageError naming the task, the class and the message otherwise."""
    if isinstance(message, cls):
        return message
    raise refused(task, message, f"a {cls.__name__}")


def record(message: DataclassInstance) -> dict[str, Any]:
    """The fields of ``message`` as a plain dict (not recursive), as a world model keeps them
    for the viewer and the job reports them to the host."""
    return {f.name: getattr(message, f.name) for f in fields(message)}
