"""report - the welding run as a picture: one self-contained HTML page with inline SVG.

:class:`Recorder` samples the cell while it runs (a kernel timer, every ``period`` s of clock
time: the tip's seam position, lateral offset and stand-off, the arc temperature and voltage,
the job's phase); :func:`write_report` draws, from the samples and the run's summary, the arc
temperature along the seam against its band, the position over time, the phases, the faults and
how each was handled, and the assassin's reaction. No script, no external file: the page opens
anywhere. Raises ChcosError if the file cannot be written.
"""

from __future__ import annotations

import html
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from chcos.apps.weld.model import WeldCell
from chcos.errors import ChcosError
from chcos.hil.report import STYLE as EVIDENCE_STYLE
from chcos.hil.svgplot import ML, MT, H, W, axes, path, scale
from chcos.kernel.scheduler import Kernel, Timer


@dataclass
class Sample:
    """One look at the cell: time (s), seam position s and lateral offset (mm), stand-off (mm),
    arc temperature (degC), arc voltage set-point (V), the job's phase."""

    t: float
    s: float
    lateral: float
    standoff: float
    temp: float
    volts: float
    phase: str


@dataclass
class Recorder:
    """Samples ``model`` (and ``phase()``) every ``period`` s on ``kernel``'s clock."""

    kernel: Kernel
    model: WeldCell
    phase: Callable[[], str]
    period: float = 0.1
    samples: list[Sample] = field(default_factory=list)
    _timer: Timer | None = None

    def start(self) -> None:
        """Start sampling (a periodic kernel timer)."""
        self._timer = self.kernel.call_at(self.kernel.clock.now(), self._sample, self.period)

    def stop(self) -> None:
        """Stop sampling."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _sample(self) -> None:
        m = self.model
        sp = m.seam_point
        self.samples.append(Sample(self.kernel.clock.now(), sp.s, sp.lateral, m.standoff,
                                   m.temperature, m.voltage_setpoint, self.phase()))



PHASE_COLOURS = ("#cfe2f3", "#d9ead3", "#fff2cc", "#f4cccc", "#d9d2e9", "#fce5cd", "#d0e0e3",
                 "#ead1dc", "#e6e6e6")


def render(summary: dict[str, Any], samples: Sequence[Sample], title: str,
           evidence: str = "") -> str:
    """The report page (HTML text) for a run's ``summary`` and its ``samples``; ``evidence``
    is HTML of the run's HIL evidence (:mod:`chcos.hil.report`: the device states reached, the
    divergences from a golden run), shown after the pictures."""
    lo, hi = summary["band"]
    seam = float(summary["seam_mm"])
    t_end = max((s.t for s in samples), default=1.0)
    t0 = min((s.t for s in samples), default=0.0)
    arc = [(s.s, s.temp) for s in samples if s.volts > 0 and 0.0 <= s.s <= seam]
    ymax = max([hi * 1.15, *(t for _, t in arc)]) if arc else hi * 1.15
    xr = (0.0, seam)
    yr = (0.0, ymax)
    fx = scale(*xr, ML, ML + W)
    fy = scale(*yr, MT + H, MT)
    band = (f'<rect x="{ML}" y="{fy(hi):.1f}" width="{W}" height="{fy(lo) - fy(hi):.1f}" '
            f'class="band"/>')
    temp_fig = axes("Arc temperature along the seam (the band shaded)", "seam position s (mm)",
                    "degC", xr, yr, band + path(arc, fx, fy, "temp"), "temp-plot")
    # position over time, with the phases as coloured spans behind
    tr = (t0, t_end)
    ft = scale(*tr, ML, ML + W)
    pos = [(s.t, s.s) for s in samples]
    smin = min([0.0, *(p for _, p in pos)])
    smax = max([seam, *(p for _, p in pos)])
    smin, smax = max(smin, -100.0), min(smax, seam + 100.0)
    fs = scale(smin, smax, MT + H, MT)
    spans: list[tuple[float, float, str]] = []
    for s in samples:
        if spans and spans[-1][2] == s.phase:
            spans[-1] = (spans[-1][0], s.t, s.phase)
        else:
            spans.append((s.t, s.t, s.phase))
    names = list(dict.fromkeys(p for _, _, p in spans))
    colour = {p: PHASE_COLOURS[i % len(PHASE_COLOURS)] for i, p in enumerate(names)}
    rects = "".join(
        f'<rect x="{ft(a):.1f}" y="{MT}" width="{max(0.5, ft(b) - ft(a)):.1f}" height="{H}" '
        f'fill="{colour[p]}" class="phase"><title>{html.escape(p)} {a:.1f}-{b:.1f} s'
        f'</title></rect>' for a, b, p in spans)
    fault_marks = "".join(
        f'<line x1="{ft(t):.1f}" y1="{MT}" x2="{ft(t):.1f}" y2="{MT + H}" class="fault"/>'
        for t in _fault_times(summary))
    pos_fig = axes("Tip position along the seam over time (phases behind, faults in red)",
                   "time (s)", "s (mm)", tr, (smin, smax),
                   rects + path([(t, max(smin, min(smax, p))) for t, p in pos], ft, fs, "pos")
                   + fault_marks, "pos-plot")
    so = [(s.t, s.standoff) for s in samples]
    so_hi = min(60.0, max([12.0, *(v for _, v in so)]))
    fso = scale(0.0, so_hi, MT + H, MT)
    so_fig = axes("Stand-off over time", "time (s)", "mm above the plate", tr, (0.0, so_hi),
                  path([(t, max(0.0, min(so_hi, v))) for t, v in so], ft, fso, "standoff"),
                  "standoff-plot")
    legend = "".join(f'<span class="key" style="background:{colour[p]}">{html.escape(p)}</span>'
                     for p in names)
    oc = summary.get("outcome") or {"outcome": "unfinished", "reason": ""}
    lat = summary.get("latency_s") or []
    rows = "".join(f"<li>{html.escape(f)}</li>" for f in summary.get("faults", [])) or \
        "<li>none</li>"
    handled = "".join(f"<li>{html.escape(h)}</li>" for h in summary.get("handled", [])) or \
        "<li>nothing to handle</li>"
    assassin = ", ".join("never" if x is None else f"{1000 * x:.2f} ms" for x in lat) or \
        "no intruder interrupt in this run"
    figures = [
        ("outcome", f"{oc.get('outcome')}" + (f" ({oc['reason']})" if oc.get("reason") else "")),
        ("weld length", f"{summary['welded_mm']:.0f} of {seam:.0f} mm"),
        ("in band", f"{summary['in_band_mm']:.0f} mm = {summary['in_band_pct']:.1f} % "
                    f"(band {lo:.0f}..{hi:.0f} degC)"),
        ("clock time", f"{summary['seconds']:.1f} s, binding {summary['binding']}"),
        ("messages", f"{summary['messages_total']}"),
        ("assassin reaction", assassin),
    ]
    table = "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(str(v))}</td></tr>"
                    for k, v in figures)
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>
body {{ font: 14px sans-serif; margin: 1.5em; color: #222; }}
figure {{ margin: 1em 0; }} figcaption {{ font-weight: bold; margin-bottom: .3em; }}
svg text {{ font: 11px sans-serif; fill: #333; }}
.grid {{ stroke: #ddd; stroke-width: 1; }} .frame {{ fill: none; stroke: #888; }}
.band {{ fill: #b6d7a8; opacity: .6; }} .temp {{ fill: none; stroke: #c0392b; stroke-width: 1.5; }}
.pos {{ fill: none; stroke: #1f4e79; stroke-width: 2; }}
.standoff {{ fill: none; stroke: #7f6000; stroke-width: 1.5; }}
.fault {{ stroke: #e00; stroke-width: 2; stroke-dasharray: 4 3; }}
.key {{ display: inline-block; padding: 2px 6px; margin: 2px; border: 1px solid #aaa; }}
table {{ border-collapse: collapse; }} th, td {{ text-align: left; padding: 2px 10px; }}
{EVIDENCE_STYLE}
</style></head><body>
<h1>{html.escape(title)}</h1>
<table class="figures">{table}</table>
{temp_fig}
{pos_fig}
<div class="legend">{legend}</div>
{so_fig}
{evidence}
<h2>Faults injected</h2><ul class="faults">{rows}</ul>
<h2>How they were handled</h2><ul class="handled">{handled}</ul>
</body></html>
"""


def _fault_times(summary: dict[str, Any]) -> list[float]:
    out = []
    for f in summary.get("faults", []):
        try:
            out.append(float(f.split("t=")[1].split("s")[0]))
        except (IndexError, ValueError):
            continue
    return out


def write_report(path: str | Path, summary: dict[str, Any], samples: Sequence[Sample],
                 title: str = "welding cell run", evidence: str = "") -> Path:
    """Write the report page to ``path`` (with ``evidence``, see :func:`render`); returns it.
    Raises ChcosError if it cannot."""
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(render(summary, samples, title, evidence), encoding="utf-8")
    except OSError as exc:
        raise ChcosError(f"{p}: cannot write the run report: {exc}") from exc
    return p
