"""runner - the main job: the arc-welding cell of appendix 2 inspects and welds its gap.

Builds the cell (:func:`chcos.apps.weld.cell.open_cell`, on the ``direct`` or the ``buses``
binding), starts the job (``invoke E2``) and runs on virtual time (as fast as possible; the
default) or real time, with a fault scenario (``chcos.apps.weld.faults`` syntax), optional
recording of all raw-CAN traffic and a duration limit. Once per simulated second it prints the
phase, the tip's position along the seam, the arc temperature against its band and the message
rate; at the end a summary: weld length, share of the seam welded in the temperature band, the
faults seen and how each was handled, task executions and messages per level, and the assassin's
reaction latency (interrupt to safe values).

:func:`run` is the whole job with its report; :func:`main` is the command line (``chcos run``).
:func:`open_cell` and :class:`Cell` (from :mod:`chcos.apps.weld.cell`) are also reachable
here.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, TextIO

from chcos.apps.weld.cell import BINDINGS, SAFE_DEVICES, Cell, WeldRunError, open_cell
from chcos.apps.weld.report import write_report
from chcos.errors import ChcosError, ConfigError
from chcos.north.services import NorthOptions, add_north_arguments

__all__ = ["BINDINGS", "SAFE_DEVICES", "Cell", "WeldRunError", "main", "open_cell", "report",
           "run"]

def _progress(out: TextIO) -> Callable[[Cell], None]:
    last = {"sent": 0, "t": 0.0}

    def show(cell: Cell) -> None:
        s = cell.system
        now = s.kernel.clock.now()
        sent = sum(lk.sent for lk in s.msgtab)
        dt = max(1e-9, now - last["t"])
        rate = (sent - last["sent"]) / dt
        last.update(sent=sent, t=now)
        m = cell.model
        lo, hi = m.config.weld_band
        temp = m.temperature
        where = "in band" if lo <= temp <= hi else "below band" if temp < lo else "ABOVE band"
        if temp < lo and m.voltage_setpoint == 0:
            where = "arc off"
        print(f"  t={now:6.1f} s  {cell.phase():<18.18s} seam s={m.seam_point.s:7.1f} mm  "
              f"arc {temp:6.0f} degC ({where}, band {lo:.0f}..{hi:.0f})  "
              f"messages/s {rate:6.0f}", file=out, flush=True)

    return show


def report(summary: dict[str, Any], out: TextIO) -> None:
    """Print the end-of-run summary."""
    p = summary
    oc = p["outcome"] or {"outcome": "unfinished (duration limit)", "reason": ""}
    print("\nsummary", file=out)
    print(f"  binding {p['binding']}, {p['seconds']:.1f} s of clock time", file=out)
    print(f"  job outcome: {oc['outcome']}" + (f" ({oc['reason']})" if oc.get("reason") else ""),
          file=out)
    print(f"  weld length {p['welded_mm']:.0f} of {p['seam_mm']:.0f} mm; in the temperature band "
          f"{p['band'][0]:.0f}..{p['band'][1]:.0f} degC: {p['in_band_mm']:.0f} mm = "
          f"{p['in_band_pct']:.1f} % of the seam (too hot {p['too_hot_mm']:.0f} mm, too cold "
          f"{p['too_cold_mm']:.0f} mm, without gas {p['no_gas_mm']:.0f} mm)", file=out)
    print("  faults injected:" + ("" if p["faults"] else " none"), file=out)
    for f in p["faults"]:
        print(f"    {f}", file=out)
    print("  how they were handled:" + ("" if p["handled"] else " nothing to handle"), file=out)
    for h in p["handled"]:
        print(f"    {h}", file=out)
    secs = max(1e-9, p["seconds"])
    for lvl, n in p["steps_by_level"].items():
        print(f"  level {lvl}: {n} task executions ({n / secs:.0f}/s)", file=out)
    for key, n in p["messages"].items():
        print(f"  messages {key}: {n}", file=out)
    print(f"  messages in all: {p['messages_total']} ({p['messages_total'] / secs:.0f}/s)",
          file=out)
    lat = [x for x in p["latency_s"] if x is not None]
    if p["latency_s"]:
        print("  assassin reaction (intruder interrupt -> all safe values): "
              + ", ".join("never" if x is None else f"{1000 * x:.2f} ms" for x in p["latency_s"])
              + (f" (worst {1000 * max(lat):.2f} ms)" if lat else ""), file=out)
    else:
        print("  assassin reaction: no intruder interrupt in this run", file=out)
    for line in summary.get("golden") or ():
        print(f"  golden run: {line.strip()}", file=out)
    for line in summary.get("not_written") or ():
        print(f"  could not be written: {line}", file=out)
    if summary.get("report"):
        print(f"  the run as a picture: {summary['report']}", file=out)


def run(binding: str = "direct", *, scenario: str = "", seed: int = 0, real_time: bool = False,
        record: str | Path | None = None, duration: float = 300.0,
        workdir: str | Path | None = None, out: TextIO = sys.stdout,
        north: NorthOptions | None = None,
        report_to: str | Path | None = None, traces: Sequence[str | Path] = (),
        golden: str | Path | None = None,
        tolerance: Mapping[str, float] | None = None) -> dict[str, Any]:
    """Run the main job (see the module doc) and return the summary figures; ``north`` names
    the north-side services to serve while it runs (:mod:`chcos.north.services`); the run's
    picture (``chcos.apps.weld.report``) goes to ``report_to`` (default: ``weld-report.html`` beside
    the map in ``workdir``, or in the welding cell's state directory, ``<state base>/weld``
    (:func:`chcos.satellites.sysfile.default_state_base`), when the map is temporary — never into
    the
    source tree). The run is watched from its start (:class:`chcos.hil.evidence.RunEvidence`):
    its trace goes to ``traces``, the device states it reached into the report, and with
    ``golden`` (a trace file) the report shows where the run parts from it (within
    ``tolerance`` per device), with the diverging signals drawn; ``summary["golden"]`` holds the
    comparison's lines. Raises ChcosError (WeldRunError, ConfigError, InstallError, BusError,
    NorthError, TraceError for an unreadable ``golden``) if the cell or a service cannot be set
    up."""
    from chcos.north.services import start as start_north

    if report_to is None:
        from chcos.satellites.sysfile import default_state_base

        report_to = (Path(workdir) if workdir is not None
                     else default_state_base() / "weld") / "weld-report.html"
    from chcos.hil.evidence import RunEvidence
    from chcos.hil.trace import read_trace

    reference = read_trace(golden) if golden is not None else None   # unreadable: before the run
    evidence = RunEvidence(traces, coverage=True, system=f"weld ({binding})",
                           clock="real" if real_time else "virtual")
    with open_cell(binding, scenario=scenario, seed=seed, real_time=real_time, record=record,
                   workdir=workdir, observe=[evidence.attach]) as cell:
        print(f"welding cell on the {binding} binding, scenario: {scenario or 'none'}, "
              f"{'real' if real_time else 'virtual'} time", file=out)
        services = start_north(cell.system, north) if north is not None and north.any else None
        try:
            for name, url in (services.urls.items() if services else ()):
                print(f"  {name}: {url}", file=out, flush=True)
            print(f"  host: {cell.start_job()}", file=out)
            cell.run(duration, each_second=_progress(out))
            summary = cell.summary()
        finally:
            if services is not None:
                services.stop()
    # after the shutdown: its safe values are part of the run's trace
    summary["not_written"] = evidence.finish()
    summary["golden"], html = _evidence_html(evidence, reference, tolerance)
    samples = cell.recorder.samples if cell.recorder is not None else []
    summary["report"] = str(write_report(report_to, summary, samples,
                                         f"welding cell, {binding} binding", html))
    report(summary, out)
    return summary


def _evidence_html(evidence: Any, reference: Any, tolerance: Mapping[str, float] | None
                   ) -> tuple[list[str], str]:
    """The report's evidence sections (the states reached; the divergences from the golden
    ``reference``, if any) and the comparison's lines for the summary."""
    from chcos.hil.diff import compare, report_lines
    from chcos.hil.report import coverage_html, divergence_html

    cov = evidence.coverage()
    html = coverage_html(cov, "Device states this run reached") if cov is not None else ""
    if reference is None:
        return [], html
    result = compare(reference, evidence.trace, tolerance)
    return report_lines(result, 5), html + divergence_html(result)


def main(argv: Sequence[str] | None = None) -> int:
    """``chcos run``: the welding job. Returns 0 when the job finished (whatever its outcome),
    1 when it hit the duration limit, 2 when the cell could not be built."""
    ap = argparse.ArgumentParser(
        prog="chcos run [weld]",
        description="The welding cell of the thesis (appendix 2): a five-joint manipulator "
                    "inspects a curving gap and welds it, on simulated buses (virtual CAN, "
                    "Modbus TCP, serial) or the protocol-free model, on virtual time unless "
                    "--real-time. Prints progress once a simulated second and a summary. Exit "
                    "status 0 when the job finished, 1 at the duration limit, 2 when the cell "
                    "could not be built. 'chcos run SYSTEM' runs your own cell instead; "
                    "'chcos run --example fig65' the thesis' figure 6.5 system.")
    ap.add_argument("--binding", choices=BINDINGS, default="buses",
                    help="buses (default): the simulated cell on virtual CAN (CANopen servos, "
                         "raw CAN), Modbus TCP and serial; direct: the model in-process, no "
                         "protocols (fastest)")
    ap.add_argument("--scenario", default="",
                    help='faults, e.g. "tip-stuck@s=120mm,intruder(for=2s)@t=8s"')
    ap.add_argument("--seed", type=int, default=0, help="measurement-noise seed")
    ap.add_argument("--real-time", action="store_true", help="run on wall-clock time")
    ap.add_argument("--record", metavar="FILE.log",
                    help="record all raw-CAN traffic (buses binding; one file per bus)")
    ap.add_argument("--duration", type=float, default=300.0,
                    help="stop after this many seconds of clock time (default 300)")
    ap.add_argument("--workdir", help="where sysfile.map goes (default: a temporary directory)")
    add_north_arguments(ap)
    ap.add_argument("--report", metavar="FILE.html",
                    help="where the run's picture goes (default: weld-report.html in --workdir, "
                         "else in the state directory: $CHCOS_STATE_DIR/weld or "
                         "~/.local/state/chcos/weld)")
    ap.add_argument("--trace", action="append", default=[], metavar="FILE",
                    help="write the run's trace to FILE (as chcos run SYSTEM --trace: .gz "
                         "compressed, .mcap MCAP; repeatable)")
    ap.add_argument("--golden", metavar="FILE",
                    help="compare the run's trace with the golden trace FILE: the summary and "
                         "the report show the first divergences, the report draws the "
                         "diverging signals (chcos diff compares two files)")
    ap.add_argument("--tolerance", action="append", default=[], metavar="DEVICE=NUMBER",
                    help="with --golden: numbers of DEVICE within NUMBER are the same "
                         "(repeatable; *=NUMBER for every device)")
    ap.add_argument("--hierarchy", choices=("chc", "nbs"), default="chc",
                    help="chc (default): the CHC-OS task hierarchy; nbs: run the job under CHC "
                         "and then under the NBS baseline (Appendix 1's H1-H3, cyclic at 28 ms) "
                         "on the same scenario and binding, and print both side by side")
    args = ap.parse_args(argv)
    if not (math.isfinite(args.duration) and args.duration > 0):
        ap.error(f"--duration {args.duration}: expected seconds > 0")
    if args.hierarchy == "nbs":
        return _main_nbs(ap, args)
    from chcos.hil.diff import parse_tolerances

    try:
        tolerance = parse_tolerances(args.tolerance)
    except ValueError as exc:
        ap.error(str(exc))
    try:
        north = NorthOptions.from_args(args)
        if north.any and not args.real_time:
            print("chcos run: north-side services asked for: running on real time",
                  file=sys.stderr)
        summary = run(args.binding, scenario=args.scenario, seed=args.seed,
                      real_time=args.real_time or north.any, record=args.record,
                      duration=args.duration, workdir=args.workdir, north=north,
                      report_to=args.report, traces=args.trace, golden=args.golden,
                      tolerance=tolerance)
    except (ChcosError, ConfigError) as exc:
        print(f"chcos run: {exc}", file=sys.stderr)
        return 2
    return 0 if summary["outcome"] is not None else 1


def _main_nbs(ap: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """``chcos run --hierarchy nbs``: CHC, then NBS, side by side (chcos.apps.nbs.compare)."""
    from chcos.apps.nbs.compare import run_side_by_side

    if args.record or NorthOptions.from_args(args).any or args.trace or args.golden:
        ap.error("--hierarchy nbs: --record, --trace, --golden and north-side services are for "
                 "the CHC job alone")
    try:
        both = run_side_by_side(args.binding, scenario=args.scenario, seed=args.seed,
                                real_time=args.real_time, duration=args.duration,
                                workdir=args.workdir, report_to=args.report)
    except (ChcosError, ConfigError) as exc:
        print(f"chcos run: {exc}", file=sys.stderr)
        return 2
    return 0 if all(s["outcome"] is not None for s in both.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
