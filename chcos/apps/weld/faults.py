"""faults - fault injection for the welding cell: what goes wrong, when, and scenario parsing.

A :class:`Fault` is a kind, a trigger and a few parameters. Kinds (thesis appendix 2 exceptions):

=================  ===========================================================================
``gap-wide``       the gap is ``width`` mm (default 4.0) over ``length`` mm (default 20)
``gap-narrow``     the gap is ``width`` mm (default 0.8) over ``length`` mm (default 20)
``tip-stuck``      the electrode freezes to the metal (arc voltage 0 until freed); with
                   ``precursor`` s the wire first stubs into the pool over that time (the arc
                   shortens, its voltage sinks) and freezes at the end - unless the wire feed
                   is cut below half its speed meanwhile, which lets the arc recover
``gas-empty``      the gas bottle is empty (pressure 0 bar)
``wire-empty``     the electrode wire spool runs out (nothing left to feed)
``sensor-dropout`` sensor ``sensor`` stops reporting, for ``for`` s (default: for good)
``servo-timeout``  joint ``joint`` (1..5) stops responding and freezes, for ``for`` s
``intruder``       the light curtain is broken, for ``for`` s (default: until cleared)
=================  ===========================================================================

Triggers: :class:`Immediate`, :class:`AtTime` (simulated time, s) or :class:`AtSeam` (arc length
along the seam, mm: fires when the torch tip reaches it at working distance, i.e. within the
cell's ``fault_lateral_tolerance`` of the seam and ``fault_height_tolerance`` above the plate).
A ``tip-stuck`` fault holds the arm wherever the tip is when it fires. A gap fault triggered at a
seam position is a defect of the plate at ``s..s+length`` and exists from the start; triggered in
time (or immediately) it starts at the seam position under the tip when it fires.

Scenario strings (:func:`parse_scenario`) are comma-separated items
``kind[(param=value;...)][@trigger]``, e.g. ``"tip-stuck@s=120mm,intruder(for=2s)@t=8s"`` or
``"sensor-dropout(arc_temperature;for=1.5s)@t=3s"``; a first parameter without ``=`` is the kind's
main parameter (``sensor`` or ``joint``). Parameters may also be separated by commas inside the
parentheses. Triggers are ``t=<time>``, ``s=<length>`` or ``now``; times take ``s``/``ms`` (bare
numbers are s), lengths ``mm``/``cm``/``m`` (bare numbers are mm). TOML
(:func:`parse_scenario_toml`, :func:`scenario_from_table`) uses ``[[fault]]`` tables with the
same keys: ``kind``, ``t`` or ``s`` (numbers in s / mm, or strings with units), ``width``,
``length``, ``for``, ``sensor``, ``joint``.
Every syntax error is a :class:`chcos.errors.ConfigError` that names the offending token.
"""

from __future__ import annotations

import math
import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, get_args

from chcos.errors import ConfigError

FaultKind = Literal[
    "gap-wide",
    "gap-narrow",
    "tip-stuck",
    "gas-empty",
    "sensor-dropout",
    "servo-timeout",
    "intruder",
    "wire-empty",
]
FAULT_KINDS: tuple[FaultKind, ...] = get_args(FaultKind)

SENSOR_NAMES: tuple[str, ...] = (
    "joint1",
    "joint2",
    "joint3",
    "joint4",
    "joint5",
    "arc_temperature",
    "arc_voltage",
    "arc_current",
    "gas_bottle_pressure",
    "gas_line_pressure",
    "gas_flow",
    "wire_speed",
    "wire_remaining",
    "gap_markers",
    "linear_sensor",
    "intruder",
)
"""Every sensor of the cell by name (the names a ``sensor-dropout`` may use)."""

_PARAMS: dict[str, tuple[str, ...]] = {
    "gap-wide": ("width", "length"),
    "gap-narrow": ("width", "length"),
    "tip-stuck": ("precursor",),
    "gas-empty": (),
    "wire-empty": (),
    "sensor-dropout": ("sensor", "for"),
    "servo-timeout": ("joint", "for"),
    "intruder": ("for",),
}
_MAIN_PARAM: dict[str, str] = {"sensor-dropout": "sensor", "servo-timeout": "joint"}
_DEFAULT_WIDTH: dict[str, float] = {"gap-wide": 4.0, "gap-narrow": 0.8}
_TIME_UNITS: dict[str, float] = {"": 1.0, "s": 1.0, "ms": 0.001}
_LENGTH_UNITS: dict[str, float] = {"": 1.0, "mm": 1.0, "cm": 10.0, "m": 1000.0}
_QUANTITY = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([a-z]*)\s*$")


@dataclass(frozen=True)
class Immediate:
    """Fire as soon as the fault is injected (or the scenario is loaded)."""


@dataclass(frozen=True)
class AtTime:
    """Fire when simulated time reaches ``t`` (s)."""

    t: float


@dataclass(frozen=True)
class AtSeam:
    """Fire when the torch tip, near the seam at working height, reaches arc length ``s`` (mm)."""

    s: float


Trigger = Immediate | AtTime | AtSeam


@dataclass(frozen=True)
class Fault:
    """One fault: ``kind``, when it fires, and its parameters. ``width`` and ``length`` are mm (gap
    faults), ``duration`` s (``None``: lasts until cleared), ``sensor`` a name from
    :data:`SENSOR_NAMES`, ``joint`` 1..5.

    Raises ConfigError if a parameter does not fit the kind.
    """

    kind: FaultKind
    trigger: Trigger = field(default_factory=Immediate)
    width: float | None = None
    length: float = 20.0
    duration: float | None = None
    sensor: str | None = None
    joint: int | None = None
    precursor: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise ConfigError(f"fault kind {self.kind!r}: expected one of {', '.join(FAULT_KINDS)}")
        if self.kind in _DEFAULT_WIDTH and self.width is None:
            object.__setattr__(self, "width", _DEFAULT_WIDTH[self.kind])
        if self.width is not None and not (math.isfinite(self.width) and self.width >= 0.0):
            raise ConfigError(f"fault {self.kind}: width={self.width} mm, expected >= 0")
        if not (math.isfinite(self.length) and self.length > 0.0):
            raise ConfigError(f"fault {self.kind}: length={self.length} mm, expected > 0")
        if self.duration is not None and not (math.isfinite(self.duration) and self.duration > 0):
            raise ConfigError(f"fault {self.kind}: for={self.duration} s, expected > 0")
        if self.kind == "sensor-dropout" and self.sensor not in SENSOR_NAMES:
            raise ConfigError(
                f"fault sensor-dropout: sensor={self.sensor!r}, expected one of "
                f"{', '.join(SENSOR_NAMES)}"
            )
        if not (math.isfinite(self.precursor) and self.precursor >= 0.0):
            raise ConfigError(f"fault {self.kind}: precursor={self.precursor} s, expected >= 0")
        if self.kind == "servo-timeout" and self.joint not in (1, 2, 3, 4, 5):
            raise ConfigError(f"fault servo-timeout: joint={self.joint!r}, expected 1..5")
        if isinstance(self.trigger, AtTime) and not (
            math.isfinite(self.trigger.t) and self.trigger.t >= 0.0
        ):
            raise ConfigError(f"fault {self.kind}: t={self.trigger.t} s, expected >= 0")
        if isinstance(self.trigger, AtSeam) and not math.isfinite(self.trigger.s):
            raise ConfigError(f"fault {self.kind}: s={self.trigger.s} mm, expected a number")

    def describe(self) -> str:
        """The fault in scenario-string syntax (parses back to an equal fault)."""
        params: list[str] = []
        if self.kind in _DEFAULT_WIDTH:
            params += [f"width={self.width!r}mm", f"length={self.length!r}mm"]
        if self.sensor is not None:
            params.append(f"sensor={self.sensor}")
        if self.joint is not None:
            params.append(f"joint={self.joint}")
        if self.duration is not None:
            params.append(f"for={self.duration!r}s")
        if self.precursor > 0.0:
            params.append(f"precursor={self.precursor!r}s")
        text = self.kind + (f"({';'.join(params)})" if params else "")
        if isinstance(self.trigger, AtTime):
            text += f"@t={self.trigger.t!r}s"
        elif isinstance(self.trigger, AtSeam):
            text += f"@s={self.trigger.s!r}mm"
        return text


@dataclass(frozen=True)
class Scenario:
    """An ordered list of faults to inject into a cell."""

    faults: tuple[Fault, ...] = ()

    def describe(self) -> str:
        """The scenario in scenario-string syntax."""
        return ",".join(f.describe() for f in self.faults)


def _quantity(text: str, units: Mapping[str, float], what: str, where: str) -> float:
    """``text`` (``"120mm"``, ``"8s"``, ``"1.5"``) converted by ``units``; ConfigError naming it."""
    m = _QUANTITY.match(text)
    if m is None or m.group(2) not in units:
        raise ConfigError(
            f"{where}: {what} {text!r} is not a number with a unit in "
            f"({', '.join(u for u in units if u)})"
        )
    return float(m.group(1)) * units[m.group(2)]


def _split_top(text: str, where: str) -> list[str]:
    """``text`` split at commas outside parentheses; ConfigError on unbalanced parentheses."""
    parts: list[str] = []
    cur: list[str] = []
    depth = 0
    for ch in text:
        if ch == "(":
            depth += 1
        elif ch == ")":
            depth -= 1
            if depth < 0:
                raise ConfigError(f"{where}: unbalanced ')' in {text!r}")
        if ch == "," and depth == 0:
            parts.append("".join(cur))
            cur = []
        else:
            cur.append(ch)
    if depth:
        raise ConfigError(f"{where}: unclosed '(' in {text!r}")
    parts.append("".join(cur))
    return parts


def _trigger(text: str, where: str) -> Trigger:
    """A trigger token ``t=8s`` / ``s=120mm`` / ``now``."""
    token = text.strip()
    if token == "now":
        return Immediate()
    key, eq, value = token.partition("=")
    key = key.strip()
    if eq and key == "t":
        return AtTime(_quantity(value, _TIME_UNITS, "time", where))
    if eq and key == "s":
        return AtSeam(_quantity(value, _LENGTH_UNITS, "seam position", where))
    raise ConfigError(f"{where}: trigger {token!r}, expected 't=<time>', 's=<length>' or 'now'")


def _build(kind: str, trigger: Trigger, params: Mapping[str, Any], where: str) -> Fault:
    """A Fault from raw parameter values (strings with units, or numbers).

    Raises ConfigError naming the bad parameter."""
    if kind not in FAULT_KINDS:
        raise ConfigError(
            f"{where}: unknown fault kind {kind!r}, expected one of {', '.join(FAULT_KINDS)}"
        )
    allowed = _PARAMS[kind]
    kw: dict[str, Any] = {}
    for key, raw in params.items():
        if key not in allowed:
            expected = ", ".join(allowed) if allowed else "no parameters"
            raise ConfigError(
                f"{where}: parameter {key!r} does not apply to {kind} (expected {expected})"
            )
        if isinstance(raw, bool) or not isinstance(raw, str | int | float):
            raise ConfigError(f"{where}: parameter {key}={raw!r}, expected a number or string")
        text = str(raw)
        if key in ("width", "length"):
            kw[key] = _quantity(text, _LENGTH_UNITS, key, where)
        elif key == "for":
            kw["duration"] = _quantity(text, _TIME_UNITS, "duration", where)
        elif key == "precursor":
            kw["precursor"] = _quantity(text, _TIME_UNITS, "precursor", where)
        elif key == "joint":
            if not re.fullmatch(r"\s*[1-5]\s*", text):
                raise ConfigError(f"{where}: joint {text!r}, expected a joint number 1..5")
            kw["joint"] = int(text)
        else:
            if text not in SENSOR_NAMES:
                raise ConfigError(
                    f"{where}: sensor {text!r} unknown, expected one of {', '.join(SENSOR_NAMES)}"
                )
            kw["sensor"] = text
    main = _MAIN_PARAM.get(kind)
    if main is not None and main not in kw:
        raise ConfigError(f"{where}: {kind} needs a {main} parameter")
    try:
        return Fault(kind, trigger, **kw)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from exc


def parse_fault(item: str) -> Fault:
    """One scenario item ``kind[(params)][@trigger]`` as a :class:`Fault`; ConfigError on errors."""
    where = f"fault {item.strip()!r}"
    head, at, trig = item.partition("@")
    trigger: Trigger = _trigger(trig, where) if at else Immediate()
    head = head.strip()
    params: dict[str, str] = {}
    if "(" in head or ")" in head:
        m = re.fullmatch(r"([^()]*)\(([^()]*)\)", head)
        if m is None:
            raise ConfigError(f"{where}: {head!r} is not 'kind(param=value;...)'")
        kind = m.group(1).strip()
        if kind not in FAULT_KINDS:
            raise ConfigError(
                f"{where}: unknown fault kind {kind!r}, expected one of {', '.join(FAULT_KINDS)}"
            )
        tokens = [t.strip() for t in re.split(r"[;,]", m.group(2)) if t.strip()]
        for i, token in enumerate(tokens):
            key, eq, value = token.partition("=")
            if not eq:
                main = _MAIN_PARAM.get(kind)
                if i != 0 or main is None:
                    raise ConfigError(f"{where}: parameter {token!r} is not 'name=value'")
                key, value = main, token
            key = key.strip()
            if key in params:
                raise ConfigError(f"{where}: parameter {key!r} given twice")
            params[key] = value.strip()
    else:
        kind = head
    if not kind:
        raise ConfigError(f"{where}: empty fault kind")
    return _build(kind, trigger, params, where)


def parse_scenario(text: str) -> Scenario:
    """A scenario from a comma-separated string, e.g. ``"tip-stuck@s=120mm,intruder@t=8s"``.

    An empty or blank string is the empty scenario. Raises ConfigError naming the bad token.
    """
    if not text.strip():
        return Scenario()
    items = _split_top(text, f"scenario {text!r}")
    faults = []
    for item in items:
        if not item.strip():
            raise ConfigError(f"scenario {text!r}: empty item between commas")
        faults.append(parse_fault(item))
    return Scenario(tuple(faults))


def scenario_from_table(table: Mapping[str, Any], source: str = "<table>") -> Scenario:
    """A scenario from a parsed TOML table holding ``fault = [{kind=..., t=...|s=..., ...}, ...]``.

    Raises ConfigError naming ``source``, the entry (``fault[i]``) and the bad key.
    """
    unknown = set(table) - {"fault"}
    if unknown:
        raise ConfigError(
            f"{source}: unknown key(s) {', '.join(sorted(unknown))}, expected 'fault'"
        )
    entries = table.get("fault", [])
    if not isinstance(entries, Sequence) or isinstance(entries, str):
        raise ConfigError(f"{source}: 'fault' must be an array of tables ([[fault]])")
    faults: list[Fault] = []
    for i, entry in enumerate(entries):
        where = f"{source}: fault[{i}]"
        if not isinstance(entry, Mapping):
            raise ConfigError(f"{where} is {entry!r}, expected a table")
        kind = entry.get("kind")
        if not isinstance(kind, str):
            raise ConfigError(
                f"{where}: missing or non-string 'kind', expected one of {', '.join(FAULT_KINDS)}"
            )
        if "t" in entry and "s" in entry:
            raise ConfigError(f"{where}: both 't' and 's' given, expected at most one trigger")
        trigger: Trigger = Immediate()
        for key, units, what in (("t", _TIME_UNITS, "time"), ("s", _LENGTH_UNITS, "seam position")):
            if key in entry:
                raw = entry[key]
                if isinstance(raw, bool) or not isinstance(raw, str | int | float):
                    raise ConfigError(
                        f"{where}: {key}={raw!r}, expected a number or a string with unit"
                    )
                value = _quantity(str(raw), units, what, where)
                trigger = AtTime(value) if key == "t" else AtSeam(value)
        params = {k: v for k, v in entry.items() if k not in ("kind", "t", "s")}
        faults.append(_build(kind, trigger, params, where))
    return Scenario(tuple(faults))


def parse_scenario_toml(text: str, source: str = "<toml>") -> Scenario:
    """A scenario from TOML text with ``[[fault]]`` tables.

    Raises ConfigError on TOML syntax errors and on bad fault entries."""
    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: invalid TOML: {exc}") from exc
    return scenario_from_table(table, source)


def load_scenario(scenario: Scenario | str | Path | None) -> Scenario:
    """A scenario from a :class:`Scenario`, a scenario string (``"tip-stuck@s=120mm"``), or a
    TOML file (a :class:`Path`, or a string ending in ``.toml``). Raises ConfigError."""
    if scenario is None:
        return Scenario()
    if isinstance(scenario, Scenario):
        return scenario
    if isinstance(scenario, Path) or scenario.strip().endswith(".toml"):
        path = Path(scenario)
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as exc:
            raise ConfigError(f"scenario file {path}: cannot be read: {exc}") from exc
        return parse_scenario_toml(text, str(path))
    return parse_scenario(scenario)
