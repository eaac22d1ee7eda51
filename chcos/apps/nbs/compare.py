"""compare - the welding job under CHC and under NBS, one after the other, side by side.

``chcos run --hierarchy nbs`` lands here (:func:`run_side_by_side`): the CHC job
(:func:`chcos.apps.weld.cell.open_cell` with the standard install script, ``invoke E2``) and then
the
NBS job (:class:`chcos.apps.nbs.weldcell.NbsCell`, Appendix 1's H1..H3 cycled every 28 ms) run the
same scenario on the same binding and seed, each on a fresh cell on virtual time (or real time).
Each writes its HTML report (``chcos.apps.weld.report``): ``weld-report.html`` and
``weld-report-nbs.html`` side by side. The table printed at the end compares executions per
second per level, messages, the reaction latency to an intruder (interrupt to all safe values)
and to a stuck tip (the electrode freezing to the plate to the arc voltage being cut), the weld
length and the share of the seam welded in the temperature band; under it, for NBS, the table
rows that reported a failure and where each H machine stands.

Errors: ChcosError as :func:`chcos.apps.weld.cell.open_cell` raises them; KernelError when an NBS
cycle
fails.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

from chcos.apps.nbs.weldcell import NBS_SCRIPT, NbsCell
from chcos.apps.weld.cell import open_cell

__all__ = ["WriteLog", "print_side_by_side", "run_side_by_side", "tip_latencies"]


class WriteLog:
    """Remembers when (model time) the arc voltage set-point was written 0, for the stuck-tip
    reaction latency; hooked on a System's Devtab ``on_write``."""

    def __init__(self, cell: Any) -> None:
        self.model = cell.model
        self.cuts: list[float] = []
        self.volts: list[tuple[float, float]] = []
        cell.system.devtab.on_write.append(self._write)

    def _write(self, device: str, value: Any) -> None:
        if device == "volts_set" and value is not None:
            self.volts.append((float(self.model.t), float(value)))
            if float(value) == 0.0:
                self.cuts.append(float(self.model.t))

    def powered(self, t: float) -> bool:
        """True if the arc voltage set-point last written before ``t`` was above 0."""
        before = [v for when, v in self.volts if when <= t]
        return bool(before) and before[-1] > 0.0


def tip_latencies(model: Any, log: WriteLog) -> list[float | None]:
    """Seconds from each stuck tip while the power source was on (the model's ``froze``
    event, or a ``tip-stuck`` fault without precursor that fired with the voltage on) to the
    next time the arc voltage was cut (None: never). A tip stuck with the power off needs no
    reaction and is not counted."""
    out: list[float | None] = []
    for e in model.events:
        if e.fault.kind != "tip-stuck" or e.action not in ("froze", "fired"):
            continue
        if e.action == "fired" and any(x.fault is e.fault and x.action in ("froze", "averted")
                                       for x in model.events):
            continue  # a precursor: the freeze (if any) is its own event
        if not log.powered(e.t):
            continue
        later = [c for c in log.cuts if c >= e.t - 1e-9]
        out.append(min(later) - e.t if later else None)
    return out


def _run_chc(binding: str, scenario: str, seed: int, real_time: bool, duration: float,
             workdir: Path, report: Path, out: TextIO) -> dict[str, Any]:
    with open_cell(binding, scenario=scenario, seed=seed, real_time=real_time,
                   workdir=workdir / "chc") as cell:
        log = WriteLog(cell)
        print(f"CHC: {cell.start_job()}", file=out, flush=True)
        cell.run(duration)
        summary = cell.summary()
        summary["hierarchy"] = "chc"
        summary["tip_latency_s"] = tip_latencies(cell.model, log)
        summary["report"] = str(cell.write_report(report, f"welding cell under CHC, {binding} "
                                                          f"binding"))
    return summary


def _run_nbs(binding: str, scenario: str, seed: int, real_time: bool, duration: float,
             workdir: Path, report: Path, out: TextIO) -> dict[str, Any]:
    with open_cell(binding, scenario=scenario, seed=seed, real_time=real_time,
                   workdir=workdir / "nbs", script=NBS_SCRIPT) as cell:
        log = WriteLog(cell)
        nbs = NbsCell(cell)
        nbs.start_job()
        print("NBS: H3 INSPECT GAP, then WELD GAP, cycle 28 ms", file=out, flush=True)
        nbs.run(duration)
        nbs.nbs.stop()
        summary = nbs.summary()
        summary["tip_latency_s"] = tip_latencies(cell.model, log)
        summary["report"] = str(_write(cell, summary, report,
                                       f"welding cell under NBS, {binding} binding"))
    return summary


def _write(cell: Any, summary: dict[str, Any], path: Path, title: str) -> Path:
    from chcos.apps.weld.report import write_report

    samples = cell.recorder.samples if cell.recorder is not None else []
    return write_report(path, summary, samples, title)


def run_side_by_side(binding: str = "direct", *, scenario: str = "", seed: int = 0,
                     real_time: bool = False, duration: float = 300.0,
                     workdir: str | Path | None = None, report_to: str | Path | None = None,
                     out: TextIO | None = None) -> dict[str, dict[str, Any]]:
    """Run the job under CHC, then under NBS (see the module doc); print the side-by-side
    summary to ``out`` and return both summaries (``{"chc": ..., "nbs": ...}``). Reports go to
    ``report_to`` (CHC) and the same name with ``-nbs`` before the suffix (NBS); default
    ``weld-report.html`` in ``workdir`` (else in the state directory, as ``chcos run``)."""
    import sys
    import tempfile

    stream = out if out is not None else sys.stdout
    if report_to is None:
        from chcos.satellites.sysfile import default_state_base

        report_to = (Path(workdir) if workdir is not None
                     else default_state_base() / "weld") / "weld-report.html"
    base = Path(report_to)
    nbs_report = base.with_name(f"{base.stem}-nbs{base.suffix or '.html'}")
    with tempfile.TemporaryDirectory(prefix="weld-both-") as tmp:
        work = Path(workdir) if workdir is not None else Path(tmp)
        print(f"welding cell on the {binding} binding, scenario: {scenario or 'none'}, "
              f"{'real' if real_time else 'virtual'} time: CHC, then NBS", file=stream)
        chc = _run_chc(binding, scenario, seed, real_time, duration, work, base, stream)
        nbs = _run_nbs(binding, scenario, seed, real_time, duration, work, nbs_report, stream)
    print_side_by_side(chc, nbs, stream)
    return {"chc": chc, "nbs": nbs}


def _ms(values: list[float | None]) -> str:
    if not values:
        return "none in this run"
    return ", ".join("never" if v is None else f"{1000 * v:.1f} ms" for v in values)


def _outcome(s: dict[str, Any]) -> str:
    oc = s.get("outcome")
    if not oc:
        return "unfinished"
    return str(oc.get("outcome", "?"))


def print_side_by_side(chc: dict[str, Any], nbs: dict[str, Any], out: TextIO) -> None:
    """Print the two summaries as one table (rows: figure; columns: CHC, NBS), then NBS's
    failing table rows and standing machines."""
    rows: list[tuple[str, Callable[[dict[str, Any]], str]]] = [
        ("job outcome", _outcome),
        ("clock time", lambda s: f"{s['seconds']:.1f} s"),
        ("weld length", lambda s: f"{s['welded_mm']:.0f} of {s['seam_mm']:.0f} mm"),
        ("in band", lambda s: f"{s['in_band_mm']:.0f} mm = {s['in_band_pct']:.1f} %"),
    ]
    levels = sorted(set(chc["steps_by_level"]) | set(nbs["steps_by_level"]))
    for lvl in levels:
        rows.append((f"level {lvl} executions/s", _level_rate(lvl)))
    rows += [
        ("messages in all", lambda s: f"{s['messages_total']} ({_rate(s, s['messages_total'])})"),
        ("intruder -> safe", lambda s: _ms(s["latency_s"])),
        ("stuck tip -> arc cut", lambda s: _ms(s.get("tip_latency_s", []))),
    ]
    w0 = max(len(r[0]) for r in rows)
    cells = [(name, fn(chc), fn(nbs)) for name, fn in rows]
    w1 = max(len("CHC"), *(len(c[1]) for c in cells))
    print("\nside by side (same scenario, same binding)", file=out)
    print(f"  {'':{w0}}  {'CHC':{w1}}  NBS", file=out)
    for name, a, b in cells:
        print(f"  {name:{w0}}  {a:{w1}}  {b}", file=out)
    print("  messages: CHC counts link messages, NBS common-memory order/report writes per level "
          "and device writes", file=out)
    if nbs.get("failures"):
        print("NBS table rows that reported a failure (first firing of each):", file=out)
        for f in nbs["failures"]:
            print(f"  {f}", file=out)
    if not nbs.get("outcome"):
        print("NBS machines at the end:", file=out)
        for s in nbs.get("standing", []):
            print(f"  {s}", file=out)
    for s in (chc, nbs):
        if s.get("report"):
            print(f"  {s['hierarchy'].upper()} run as a picture: {s['report']}", file=out)


def _level_rate(level: int) -> Callable[[dict[str, Any]], str]:
    def rate(s: dict[str, Any]) -> str:
        return _rate(s, s["steps_by_level"].get(level, 0))

    return rate


def _rate(s: dict[str, Any], n: int) -> str:
    return f"{n / max(1e-9, s['seconds']):.0f}/s"
