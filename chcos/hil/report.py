"""report - the HIL evidence as HTML sections for a page a person reads (the welding cell's run
report, :mod:`chcos.apps.weld.report`): the device-state coverage table, and the first
divergences from a golden trace with a plot of each diverging signal, golden against new, around
the instant they part (drawn with :mod:`chcos.hil.svgplot`, as the report's other pictures).
"""

from __future__ import annotations

import html
from collections.abc import Sequence

from chcos.hil.catalogue import StateClass
from chcos.hil.coverage import Coverage, ordered_states
from chcos.hil.diff import DiffResult, Divergence
from chcos.hil.svgplot import ML, MT, H, W, axes, path, scale
from chcos.hil.trace import Entry

#: how many diverging signals are drawn, and the seconds shown before and after each parts
PLOTS = 4
BEFORE, AFTER = 2.0, 3.0
#: the styles these sections need (the page's own style sheet holds the rest)
STYLE = """
.cov td.none { color: #999; } .cov td.full { background: #d9ead3; }
.cov td.part { background: #fff2cc; } .cov td.zero { background: #f4cccc; }
.cov td, .cov th { border-bottom: 1px solid #eee; }
.golden { fill: none; stroke: #1f4e79; stroke-width: 2; }
.new { fill: none; stroke: #c0392b; stroke-width: 1.5; stroke-dasharray: 5 3; }
.parts { stroke: #e00; stroke-width: 1; }
"""


def coverage_html(cov: Coverage, title: str = "Device states reached") -> str:
    """A section: one row per subject, one column per state class (``reached/catalogued``,
    coloured), the share of the catalogue reached, and per subject what was not reached."""
    classes = [c for c in StateClass
               if any(e.state.cls is c for se in cov.subjects.values()
                      for e in se.states.values())]
    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in classes)
    rows = []
    for se in sorted(cov.subjects.values(), key=lambda se: (str(se.subject.kind),
                                                             se.subject.name)):
        cells = []
        for c in classes:
            cat = [e for e in se.states.values() if e.state.cls is c and e.catalogued]
            if not cat:
                cells.append('<td class="none">-</td>')
                continue
            n = sum(1 for e in cat if e.tests)
            cls = "full" if n == len(cat) else "zero" if n == 0 else "part"
            tip = html.escape(", ".join(f"{e.state.name}{'' if e.tests else ' (not reached)'}"
                                        for e in cat))
            cells.append(f'<td class="{cls}" title="{tip}">{n}/{len(cat)}</td>')
        missing = ", ".join(e.state.name for e in ordered_states(se)
                            if e.catalogued and not e.tests)
        rows.append(f"<tr><th>{html.escape(f'{se.subject.kind} {se.subject.name}')}</th>"
                    f"{''.join(cells)}<td>{html.escape(missing) or 'all reached'}</td></tr>")
    reached, total = cov.counts()
    return (f"<h2>{html.escape(title)}</h2>"
            f"<p>{reached} of {total} catalogued states reached ({cov.share():.1f} %): what each "
            f"device, bus and task can reach comes from its map and profile "
            f"(docs/hil-evidence.md).</p>"
            f'<table class="cov"><tr><th>subject</th>{head}<th>not reached</th></tr>'
            f"{''.join(rows)}</table>")


def _numeric(entries: Sequence[Entry]) -> list[tuple[float, float]]:
    return [(e.t, float(e.value)) for e in entries
            if isinstance(e.value, int | float) and not isinstance(e.value, bool)]


def _series(entries: Sequence[Entry], subject: str) -> list[tuple[float, float]]:
    """The subject's numeric signal: its values, else the commands it was sent."""
    mine = [e for e in entries if e.subject == subject]
    values = _numeric([e for e in mine if e.kind == "value"])
    return values or _numeric([e for e in mine if e.kind == "command"])


def _steps(points: Sequence[tuple[float, float]], t0: float, t1: float
           ) -> list[tuple[float, float]]:
    """``points`` as a step line over ``t0..t1`` (each value held until the next)."""
    out: list[tuple[float, float]] = []
    held: float | None = None
    for t, v in points:
        if t < t0:
            held = v
            continue
        if t > t1:
            break
        if held is not None:
            out.append((max(t0, out[-1][0] if out else t0), held))
            out.append((t, held))
        out.append((t, v))
        held = v
    if held is not None:
        out.append((out[-1][0] if out else t0, held))
        out.append((t1, held))
    return out


def _plot(d: Divergence, result: DiffResult) -> str:
    g = _series(result.golden.entries, d.subject)
    n = _series(result.new.entries, d.subject)
    if not g and not n:
        return ""
    t0, t1 = max(0.0, d.t - BEFORE), d.t + AFTER
    gs, ns = _steps(g, t0, t1), _steps(n, t0, t1)
    ys = [v for _, v in gs + ns] or [0.0]
    lo, hi = min(ys), max(ys)
    pad = (hi - lo) * 0.1 or 1.0
    yr = (lo - pad, hi + pad)
    fx, fy = scale(t0, t1, ML, ML + W), scale(*yr, MT + H, MT)
    mark = (f'<line x1="{fx(d.t):.1f}" y1="{MT}" x2="{fx(d.t):.1f}" y2="{MT + H}" '
            f'class="parts"/>')
    return axes(f"{d.subject}: golden (solid) and new (dashed), parting at t={d.t:.6f} s",
                "time (s)", d.subject, (t0, t1), yr,
                path(gs, fx, fy, "golden") + path(ns, fx, fy, "new") + mark,
                f"diverge-plot diverge-{html.escape(d.subject)}")


def divergence_html(result: DiffResult, title: str = "Against the golden run") -> str:
    """A section: the golden and new traces compared, the first divergence of each subject,
    and a plot of each of the first :data:`PLOTS` diverging signals."""
    head = (f"<h2>{html.escape(title)}</h2><p>{html.escape(result.golden.path)} "
            f"({len(result.golden.entries)} records) against this run "
            f"({len(result.new.entries)} records): {result.subjects} subjects compared, ")
    if result.same:
        return head + "the same.</p>"
    items = "".join(f"<li>{html.escape(d.describe())}</li>" for d in result.divergences[:50])
    more = (f"<li>... and {len(result.divergences) - 50} more</li>"
            if len(result.divergences) > 50 else "")
    plots = "".join(_plot(d, result) for d in result.divergences[:PLOTS])
    return (head + f"{len(result.divergences)} diverge, the first at "
            f"t={result.divergences[0].t:.6f} s.</p>"
            f'<ul class="divergences">{items}{more}</ul>{plots}')
