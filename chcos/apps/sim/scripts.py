"""scripts - value scripts of simulated sensors: a function of time given as text (``ramp``,
``sine``, ``square``, a constant, or ``csv:FILE[:COLUMN]``, a recorded trace), see
:func:`parse_script`. Used by :class:`chcos.apps.sim.from_map.SimSlaves` and ``chcos sim``.
"""

from __future__ import annotations

import bisect
import csv
import math
import re
from collections.abc import Callable
from pathlib import Path

from chcos.errors import ConfigError

Script = Callable[[float], float]
"""A sensor's value (engineering units) as a function of time in seconds."""


# ---- scripted values --------------------------------------------------------------------------
def _args(text: str, names: tuple[str, ...], spec: str) -> list[float]:
    vals: dict[str, float] = {}
    parts = [p.strip() for p in text.split(",") if p.strip()]
    for i, p in enumerate(parts):
        key, eq, v = p.partition("=")
        name = key.strip() if eq else (names[i] if i < len(names) else "")
        if name not in names:
            raise ConfigError(f"value script {spec!r}: unexpected argument {p!r}; expected "
                              f"{', '.join(names)}")
        try:
            vals[name] = float(v if eq else p)
        except ValueError:
            raise ConfigError(f"value script {spec!r}: {name} {p!r} is not a number") from None
    missing = [n for n in names if n not in vals]
    if missing:
        raise ConfigError(f"value script {spec!r}: missing {', '.join(missing)} (expected "
                          f"{spec.split('(')[0]}({', '.join(names)}))")
    return [vals[n] for n in names]


def csv_trace(path: str | Path, column: str | None = None) -> Script:
    """A value following a CSV trace: first column the time in seconds, ``column`` (default the
    second) the value; linear between rows, the last value held after the end. Raises
    ConfigError naming the file and row."""
    path = Path(path)
    try:
        rows = list(csv.reader(path.read_text(encoding="utf-8").splitlines()))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the trace: {exc}") from exc
    if len(rows) < 2:
        raise ConfigError(f"{path}: expected a header row (t, value...) and at least one row")
    header = [h.strip() for h in rows[0]]
    col = 1 if column is None else (header.index(column) if column in header else -1)
    if col < 1 or col >= len(header):
        raise ConfigError(f"{path}: no column {column!r}; columns: {', '.join(header[1:])}")
    ts: list[float] = []
    vs: list[float] = []
    for no, row in enumerate(rows[1:], 2):
        if not row or not "".join(row).strip():
            continue
        try:
            t, v = float(row[0]), float(row[col])
        except (ValueError, IndexError):
            raise ConfigError(f"{path}: row {no}: expected numbers in columns {header[0]} and "
                              f"{header[col]}") from None
        if ts and t < ts[-1]:
            raise ConfigError(f"{path}: row {no}: time {t} goes backwards")
        ts.append(t)
        vs.append(v)

    def at(now: float) -> float:
        i = bisect.bisect_right(ts, now)
        if i == 0:
            return vs[0]
        if i == len(ts):
            return vs[-1]
        t0, t1, v0, v1 = ts[i - 1], ts[i], vs[i - 1], vs[i]
        return v0 if t1 == t0 else v0 + (v1 - v0) * (now - t0) / (t1 - t0)

    return at


def parse_script(spec: str, base_dir: Path | None = None) -> Script:
    """A value script from its text: ``42``, ``ramp(start, end, period)`` (saw-tooth),
    ``sine(center, amplitude, period)``, ``square(low, high, period)``, ``csv(FILE[, column])``;
    arguments also as ``name=value``. Raises ConfigError naming the script and what was
    expected."""
    text = spec.strip()
    try:
        value = float(text)
        return lambda now: value
    except ValueError:
        pass
    m = re.fullmatch(r"(\w+)\((.*)\)", text)
    if not m:
        raise ConfigError(f"value script {spec!r}: expected a number, ramp(start, end, period), "
                          "sine(center, amplitude, period), square(low, high, period) or "
                          "csv(FILE[, column])")
    fn, body = m.group(1), m.group(2)
    if fn == "csv":
        parts = [p.strip() for p in body.split(",")]
        path = Path(parts[0])
        if base_dir is not None and not path.is_absolute():
            path = base_dir / path
        return csv_trace(path, parts[1] if len(parts) > 1 else None)
    if fn == "ramp":
        start, end, period = _args(body, ("start", "end", "period"), spec)
        return lambda now: start + (end - start) * ((now % period) / period)
    if fn == "sine":
        center, amplitude, period = _args(body, ("center", "amplitude", "period"), spec)
        return lambda now: center + amplitude * math.sin(2 * math.pi * now / period)
    if fn == "square":
        low, high, period = _args(body, ("low", "high", "period"), spec)
        return lambda now: low if (now % period) < period / 2 else high
    raise ConfigError(f"value script {spec!r}: unknown function {fn!r}; expected ramp, sine, "
                      "square or csv")
