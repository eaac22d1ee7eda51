"""diff - what two traces of a run disagree on: the first divergence of each device and task,
with its time, and a summary.

Each subject (a device, a bus, a task) is compared on its own, in two ways:

* its values (``value`` records) as a signal: the value it held at every instant either trace
  changed it, equal within the subject's tolerance (numbers: ``|a - b| <= tolerance``, the
  default 0 meaning exactly; NaN equals NaN; anything else exactly). A run whose sensor jitters
  within the tolerance may record more changes and still be the same;
* everything else (status changes, commands and confirmations, failed writes, bus errors,
  events) as a sequence: the n-th record of one trace against the n-th of the other, at the
  same time, of the same kind, with the same value (within the tolerance for numbers) and the
  same cause class. The text for people (a failure's reason) is compared only with
  ``text=True``: it carries addresses and wall-clock figures that differ between runs.

The subject's first divergence is the earliest of the two. :func:`compare` returns a
:class:`DiffResult`; :func:`report_lines` is what ``chcos diff`` prints.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from chcos.hil.trace import Entry, Trace

#: the tolerance key that applies to every subject without one of its own
ANY = "*"
#: what a divergence of two value signals is called
HELD, ONE_SIDED = "value held", "a value only one trace has"


@dataclass(frozen=True)
class Divergence:
    """Where one subject's two traces part: at time ``t``, what the golden trace has there
    (None: nothing more) and what the new one has."""

    subject: str
    t: float
    golden: Entry | None
    new: Entry | None
    what: str

    def describe(self) -> str:
        """One line: the subject, the time, both sides (for a value: what each trace holds
        then, and since when)."""
        g = self._side(self.golden)
        n = self._side(self.new)
        lines = (f" [lines {self.golden.line if self.golden else '-'}/"
                 f"{self.new.line if self.new else '-'}]")
        return (f"{self.subject}: first divergence at t={self.t:.6f} s ({self.what}): "
                f"golden {g}, new {n}{lines if (self.golden or self.new) else ''}")

    def _side(self, e: Entry | None) -> str:
        if e is None:
            return "nothing"
        if self.what in (HELD, ONE_SIDED):
            return f"holds {e.value!r} (since t={e.t:.6f} s)"
        return e.describe()


@dataclass
class DiffResult:
    """The comparison of ``golden`` and ``new``: the first divergence of every subject that
    has one, earliest first."""

    golden: Trace
    new: Trace
    divergences: list[Divergence] = field(default_factory=list)
    subjects: int = 0

    @property
    def same(self) -> bool:
        """True if no subject diverges."""
        return not self.divergences

    @property
    def first(self) -> Divergence | None:
        """The earliest divergence (None if the traces agree)."""
        return self.divergences[0] if self.divergences else None


def _number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def close(a: Any, b: Any, tolerance: float) -> bool:
    """True if ``a`` and ``b`` are the same value within ``tolerance`` (see the module doc)."""
    if _number(a) and _number(b):
        if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
            return True
        if tolerance == 0:
            return bool(a == b) and type(a) is type(b)
        return bool(abs(a - b) <= tolerance)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(close(x, y, tolerance) for x, y in zip(a, b,
                                                                                strict=True))
    return type(a) is type(b) and bool(a == b)


def _signal(subject: str, g: Sequence[Entry], n: Sequence[Entry], tol: float
            ) -> Divergence | None:
    """The first instant at which the two value signals differ (see the module doc)."""
    times = sorted({e.t for e in g} | {e.t for e in n})
    i = j = 0
    gv: Entry | None = None
    nv: Entry | None = None
    for t in times:
        while i < len(g) and g[i].t <= t:
            gv, i = g[i], i + 1
        while j < len(n) and n[j].t <= t:
            nv, j = n[j], j + 1
        if gv is None or nv is None:
            return Divergence(subject, t, gv, nv, ONE_SIDED)
        if not close(gv.value, nv.value, tol):
            return Divergence(subject, t, gv, nv, HELD)
    return None


def _sequence(subject: str, g: Sequence[Entry], n: Sequence[Entry], tol: float,
              text: bool) -> Divergence | None:
    """The first record at which the two sequences differ (see the module doc)."""
    for a, b in zip(g, n, strict=False):
        what = ("time" if a.t != b.t else "kind" if a.kind != b.kind
                else "value" if not close(a.value, b.value, tol)
                else "cause" if a.cause != b.cause
                else "text" if text and a.text != b.text else "")
        if what:
            return Divergence(subject, min(a.t, b.t), a, b, what)
    if len(g) > len(n):
        return Divergence(subject, g[len(n)].t, g[len(n)], None, "missing in the new trace")
    if len(n) > len(g):
        return Divergence(subject, n[len(g)].t, None, n[len(g)], "not in the golden trace")
    return None


def _split(entries: Sequence[Entry], subject: str) -> tuple[list[Entry], list[Entry]]:
    values = [e for e in entries if e.subject == subject and e.kind == "value"]
    rest = [e for e in entries if e.subject == subject and e.kind != "value"]
    return values, rest


def compare(golden: Trace, new: Trace, tolerance: Mapping[str, float] | None = None,
            text: bool = False) -> DiffResult:
    """Compare two traces subject by subject (see the module doc); ``tolerance`` maps a
    subject (or ``*``, every other) to the largest difference of its numbers that still
    counts as the same."""
    tol = dict(tolerance or {})
    subjects = list(dict.fromkeys([*golden.subjects(), *new.subjects()]))
    by_g: dict[str, list[Entry]] = {s: [] for s in subjects}
    by_n: dict[str, list[Entry]] = {s: [] for s in subjects}
    for e in golden.entries:
        by_g[e.subject].append(e)
    for e in new.entries:
        by_n[e.subject].append(e)
    result = DiffResult(golden, new, subjects=len(subjects))
    for s in subjects:
        t = tol.get(s, tol.get(ANY, 0.0))
        gv, gr = _split(by_g[s], s)
        nv, nr = _split(by_n[s], s)
        found = [d for d in (_signal(s, gv, nv, t), _sequence(s, gr, nr, t, text))
                 if d is not None]
        if found:
            result.divergences.append(min(found, key=lambda d: d.t))
    result.divergences.sort(key=lambda d: (d.t, d.subject))
    return result


def parse_tolerances(items: Sequence[str]) -> dict[str, float]:
    """``NAME=NUMBER`` items (``level=0.5``, ``*=0.01``) as a tolerance map. Raises
    ValueError naming the bad item."""
    out: dict[str, float] = {}
    for item in items:
        name, sep, number = item.partition("=")
        try:
            value = float(number)
        except ValueError:
            value = math.nan
        if not sep or not name or not math.isfinite(value) or value < 0:
            raise ValueError(f"--tolerance {item!r}: expected DEVICE=NUMBER (>= 0), e.g. "
                             "level=0.5, or *=NUMBER for every device")
        out[name] = value
    return out


def report_lines(result: DiffResult, limit: int = 20) -> list[str]:
    """What ``chcos diff`` prints: the first divergences (``limit`` at most) and a summary."""
    g, n = result.golden, result.new
    out: list[str] = []
    for d in result.divergences[:limit]:
        out.append(f"  {d.describe()}")
    if len(result.divergences) > limit:
        out.append(f"  ... and {len(result.divergences) - limit} more subject(s)")
    head = (f"{g.path} ({len(g.entries)} records) and {n.path} ({len(n.entries)} records): "
            f"{result.subjects} subject(s) compared, ")
    first = result.first
    if first is None:
        out.append(head + "the same")
    else:
        out.append(head + f"{len(result.divergences)} diverge; the first at "
                   f"t={first.t:.6f} s: {first.subject}")
    return out
