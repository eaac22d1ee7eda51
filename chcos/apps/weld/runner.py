"""runner - the main job: the arc-welding cell of appendix 2 inspects and welds its gap.

Builds the System on one of two bindings of the same device table (``chcos/apps/weld/DEVICES.md``):

* ``direct`` - ``chcos/apps/weld/maps/weld_direct.toml``: the cell model in-process
(chcos/apps/weld/direct.py);
* ``buses`` - the real-bus simulator :class:`chcos.apps.weld.plant.WeldSim` on virtual CAN (CANopen
  servos and raw-CAN sensors), Modbus TCP and a serial line, with the device map that
  :func:`chcos.apps.weld.plant.cell_devmap` writes for it;

installs the hierarchy with the thesis-syntax script ``chcos/apps/weld/install.chcos``, starts the
job
(``invoke E2``) and runs on virtual time (as fast as possible; the default) or real time, with a
fault scenario (``chcos.apps.weld.faults`` syntax), optional recording of all raw-CAN traffic and a
duration limit. Once per simulated second it prints the phase, the tip's position along the
seam, the arc temperature against its band and the message rate; at the end a summary: weld
length, share of the seam welded in the temperature band, the faults seen and how each was
handled, task executions and messages per level, and the assassin's reaction latency (interrupt
to safe values).

:func:`open_cell` gives the running cell to tests; :func:`run` is the whole job with its report;
:func:`main` is the command line (``chcos run``).
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import math
import os
import socket
import sys
import tempfile
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from chcos import resources
from chcos.apps.weld import WeldCell, parse_scenario
from chcos.apps.weld.report import Recorder, write_report
from chcos.apps.weld.tasks import HERE as TASK_PATH
from chcos.apps.weld.tasks import SCRIPT
from chcos.devices.devmap import load
from chcos.errors import ChcosError, ConfigError
from chcos.kernel.clock import Clock, RealClock, VirtualClock
from chcos.kernel.instrument import Counters, Instrument
from chcos.north.services import NorthOptions, add_north_arguments
from chcos.system.embedded import System
from chcos.tables.messages import Link, LinkType

DIRECT_MAP = resources.path("chcos.apps.weld", "maps", "weld_direct.toml")
BINDINGS = ("direct", "buses")
SAFE_DEVICES = ("drives_enable", "volts_set", "wire_set", "gas_valve")
"""The actuators that must be at their safe value (0) after an emergency stop."""
_channels = itertools.count()


class WeldRunError(ChcosError):
    """The welding job could not be set up: unknown binding, the real-bus simulator missing."""


class Timeline(Instrument):
    """Watches the interrupt that matters (the light curtain) and every actuator write, so the
    assassin's reaction latency can be measured: from the first ``intruder`` = 1 reading that
    reached a task link to the moment every one of :data:`SAFE_DEVICES` was written 0."""

    def __init__(self, system: System) -> None:
        self.system = system
        self.interrupts: list[float] = []
        self.safe_at: list[float | None] = []
        self._active = False
        self._pending: set[str] = set()
        self.writes: Counter[str] = Counter()
        system.devtab.on_write.append(self._write)

    def message_sent(self, link: Link) -> None:
        """A sensory message left a device: catch the rising edge of ``intruder``."""
        if link.src != "intruder":
            return
        present = bool(self.system.devtab.get("intruder").value)
        if present and not self._active:
            self.interrupts.append(self.system.kernel.clock.now())
            self.safe_at.append(None)
            self._pending = set(SAFE_DEVICES)
        self._active = present

    def _write(self, device: str, value: Any) -> None:
        self.writes[device] += 1
        if self._pending and device in self._pending and value == 0:
            self._pending.discard(device)
            if not self._pending:
                self.safe_at[-1] = self.system.kernel.clock.now()

    def latencies(self) -> list[float | None]:
        """Seconds from each intruder interrupt to all safe values (None: never safe)."""
        return [None if s is None else s - t for t, s in zip(self.interrupts, self.safe_at,
                                                             strict=True)]


@dataclass
class Cell:
    """A running welding cell: the System, the cell model behind its devices, instruments."""

    system: System
    model: WeldCell
    binding: str
    counters: Counters
    timeline: Timeline
    started: float = 0.0
    closers: list[Callable[[], None]] = field(default_factory=list)
    injector: Callable[[str], None] | None = None
    recorder: Recorder | None = None

    def write_report(self, path: str | Path, title: str | None = None) -> Path:
        """Write the run as a picture (``chcos.apps.weld.report``: one self-contained HTML page) to
        ``path``; returns it. Raises ChcosError if it cannot be written."""
        samples = self.recorder.samples if self.recorder is not None else []
        return write_report(path, self.summary(), samples,
                            title or f"welding cell, {self.binding} binding")

    # ---- driving the job --------------------------------------------------------------------
    def start_job(self, command: dict[str, Any] | None = None) -> str:
        """``invoke E2`` (with ``command``) from the host."""
        self.started = self.system.kernel.clock.now()
        return self.system.invoke("E2", command)

    def world(self, task: str) -> dict[str, dict[str, Any]]:
        """A snapshot of task ``task``'s world model (for reports and tests)."""
        wm = self.system.tsktab.get(task).world
        return wm.snapshot() if wm is not None else {"sensory": {}, "command": {}}

    def outcome(self) -> dict[str, Any] | None:
        """E2's outcome once the job has finished, else None."""
        out = self.world("E2")["command"].get("outcome")
        return dict(out) if isinstance(out, dict) else None

    def phase(self) -> str:
        """What the job is doing now (E2's phase, refined by D1's or D2's)."""
        top = str(self.world("E2")["command"].get("phase", "idle"))
        sub = {"inspect": "D1", "weld": "D2"}.get(top)
        if sub is not None:
            inner = self.world(sub)["command"].get("phase")
            if inner:
                return f"{top}/{inner}"
        return top

    def run(self, seconds: float, *, until_done: bool = True,
            each_second: Callable[[Cell], None] | None = None) -> float:
        """Run for at most ``seconds`` of clock time (in 1 s slices; ``each_second`` is called
        after each); with ``until_done`` stop once the job has an outcome. Returns the time
        run."""
        t0 = self.system.kernel.clock.now()
        while self.system.kernel.clock.now() - t0 < seconds - 1e-9:
            step = min(1.0, seconds - (self.system.kernel.clock.now() - t0))
            self.system.run_for(step)
            if each_second is not None:
                each_second(self)
            if until_done and self.outcome() is not None:
                break
        return self.system.kernel.clock.now() - t0

    def inject(self, fault: str) -> None:
        """Inject one fault (scenario-item syntax, e.g. ``"intruder(for=1s)"``) now. Raises
        ConfigError for a bad fault."""
        if self.injector is not None:
            self.injector(fault)
        else:
            from chcos.apps.weld import parse_fault

            self.model.inject(parse_fault(fault))

    def outputs(self) -> dict[str, Any]:
        """The last value commanded to every actuator of the cell."""
        return {d.name: d.value for d in self.system.devtab if not d.is_sensor}

    def close(self) -> None:
        """Shut the System down (safe values out), then the simulator if any."""
        try:
            self.system.shutdown()
        finally:
            for close in reversed(self.closers):
                close()

    # ---- the report -------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """The figures of the run (see the module doc), as a dict."""
        s = self.system
        model = self.model
        prog = model.progress()
        band = model.config.weld_band
        in_band = prog.welded - prog.too_hot - prog.too_cold
        steps: Counter[int] = Counter()
        for t in s.tsktab:
            steps[t.level] += t.steps
        level = {t.name: t.level for t in s.tsktab}
        msgs: Counter[str] = Counter()
        for lk in s.msgtab:
            if lk.type is LinkType.SENSORY:
                key = f"level {level[lk.src]} up" if lk.src in level else "devices up"
            else:
                key = f"level {level[lk.src]} down" if lk.src in level else "host down"
            msgs[key] += lk.sent
        faults = [f"t={e.t:6.2f} s {e.action:7s} {e.fault.describe()}" for e in model.events]
        handled = []
        for a in self.world("D3")["sensory"].get("alarms", []):
            handled.append(f"t={a['t']:6.2f} s D3 alarm {a['alarm']}: {a['detail']}")
        for r in self.world("E1")["sensory"].get("reactions", []):
            handled.append(f"t={r['seen']:6.2f} s E1 e-stop ({r['estop_writes']} safe values), "
                           f"suspended {', '.join(r['suspended'])}, B2: {r.get('b2')}")
        for t in s.tsktab:
            if t.abnormal:
                handled.append(f"{t.name}: {t.abnormal} abnormal completion(s), last: "
                               f"{t.last_error}")
        unstuck = self.world("D2")["command"].get("unstuck", 0)
        if unstuck:
            handled.append(f"D2: tip freed by C1 {unstuck} time(s), welding resumed")
        for p in self.world("C2")["command"].get("plans", []):
            if not p["ok"]:
                handled.append(f"C2: plan {p['plan']} failed ({p['error']}); the world model "
                               f"chose the next permissible plan")
        retracts = self.world("D2")["command"].get("retracts", 0)
        if retracts:
            handled.append(f"C1 recognized a tip about to stick (learned) {retracts} time(s); D2 "
                           f"cut the wire feed for a moment")
        elapsed = s.kernel.clock.now() - self.started
        return {
            "binding": self.binding, "seconds": elapsed, "outcome": self.outcome(),
            "seam_mm": prog.length, "welded_mm": prog.welded,
            "in_band_mm": in_band, "in_band_pct": 100.0 * in_band / prog.length,
            "too_hot_mm": prog.too_hot, "too_cold_mm": prog.too_cold, "no_gas_mm": prog.no_gas,
            "band": band, "faults": faults, "handled": handled,
            "steps_by_level": dict(sorted(steps.items())), "messages": dict(sorted(msgs.items())),
            "messages_total": sum(lk.sent for lk in s.msgtab),
            "latency_s": self.timeline.latencies(), "outputs": self.outputs(),
        }


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _direct_map(scenario: str, seed: int) -> Any:
    devmap = load([DIRECT_MAP])
    buses = tuple(dataclasses.replace(b, options={**b.options, "scenario": scenario,
                                                  "seed": seed})
                  if b.kind == "weld-direct" else b for b in devmap.buses)
    return dataclasses.replace(devmap, buses=buses)


def _add_record(mapfile: Path, record: Path) -> None:
    """Give every raw-CAN bus of ``mapfile`` a ``record`` option (one log file per bus)."""
    lines = mapfile.read_text(encoding="utf-8").splitlines()
    out: list[str] = []
    n = 0
    for line in lines:
        out.append(line)
        if line.strip() == 'kind = "can"':
            n += 1
            out.append(f'record = "{(record.parent / f"{record.stem}-{n}{record.suffix}")}"')
    mapfile.write_text("\n".join(out) + "\n", encoding="utf-8")


@contextmanager
def open_cell(binding: str = "direct", *, scenario: str = "", seed: int = 0,
              real_time: bool = False, record: str | Path | None = None,
              workdir: str | Path | None = None,
              script: str | Path = SCRIPT, replace: dict[str, str] | None = None,
              interface: str = "virtual", channels: tuple[str, str] | None = None
              ) -> Iterator[Cell]:
    """The welding cell, booted and installed, ready for :meth:`Cell.start_job`; shut down on
    exit. ``replace`` maps task names to code references (``pkg.mod:fn``) installed instead of
    the standard code (test-only tasks). ``interface``/``channels`` put the buses binding's two
    CAN buses (CANopen, raw sensors) on python-can ``virtual`` channels of their own (default) or
    on given channels of another interface, e.g. ``socketcan`` ``("vcan0", "vcan1")``.
    Raises WeldRunError for an unknown binding or a missing
    real-bus simulator, ConfigError for a bad scenario, InstallError if the script fails."""
    if binding not in BINDINGS:
        raise WeldRunError(f"binding {binding!r}: expected one of {', '.join(BINDINGS)}")
    parse_scenario(scenario)  # ConfigError early, naming the bad item
    clock: Clock = RealClock() if real_time else VirtualClock()
    tmp: tempfile.TemporaryDirectory[str] | None = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="weldrun-")
        workdir = tmp.name
    work = Path(workdir)
    work.mkdir(parents=True, exist_ok=True)
    closers: list[Callable[[], None]] = []
    if tmp is not None:
        closers.append(tmp.cleanup)
    sim: Any = None
    try:
        if binding == "direct":
            if record is not None:
                raise WeldRunError("--record needs the real buses (--binding buses): the direct "
                                   "binding has no CAN traffic to record")
            system = System(_direct_map(scenario, seed), clock=clock, task_path=[TASK_PATH],
                            base_dir=work, map_path=work / "sysfile.map")
        else:
            try:
                from chcos.apps.weld.plant import WeldSim, cell_devmap
            except ImportError as exc:
                raise WeldRunError("the real-bus simulator chcos.apps.weld.plant is not available: "
                                  f"{exc}") from exc
            n = next(_channels)
            chans = channels or (f"weld-co-{os.getpid()}-{n}", f"weld-can-{os.getpid()}-{n}")
            ports = _free_port(), _free_port()
            mapfile = cell_devmap(work, canopen_channel=chans[0], sensor_channel=chans[1],
                                  modbus_port=ports[0], serial_port=ports[1],
                                  interface=interface)
            if record is not None:
                _add_record(mapfile, Path(record).resolve())
            sim = WeldSim(canopen_channel=chans[0], sensor_channel=chans[1],
                          modbus_port=ports[0], serial_port=ports[1], scenario=scenario,
                          seed=seed, interface=interface)
            closers.append(sim.close)
            system = System([mapfile], clock=clock, task_path=[TASK_PATH], base_dir=work,
                            map_path=work / "sysfile.map")
        counters = Counters()
        system.kernel.add_instrument(counters)
        timeline = Timeline(system)
        system.kernel.add_instrument(timeline)
        for line in Path(script).read_text(encoding="utf-8").splitlines():
            words = line.split()
            if replace and len(words) > 2 and words[0] == "install" and not words[-1].startswith(
                    "sysfile"):
                name = next((w for w in words[1:] if not w.startswith("-")), "")
                if name in replace:
                    line = line.replace(f" {name} ", f" {name}={replace[name]} ", 1)
            system.execute(line)
        if sim is not None:
            sim.attach(system.kernel)
            model = sim.model
        else:
            model = next(d.cell for d in system.devtab.drivers if hasattr(d, "cell"))
        cell = Cell(system, model, binding, counters, timeline, closers=closers,
                    injector=sim.inject if sim is not None else None)
        cell.recorder = Recorder(system.kernel, model, cell.phase)
        cell.recorder.start()
    except BaseException:
        for close in reversed(closers):
            close()
        raise
    try:
        yield cell
    finally:
        cell.close()


def _progress(out: TextIO) -> Callable[[Cell], None]:
    last = {"sent": 0, "t": 0.0}

    def show(cell: Cell) -> None:
        s = cell.system
        now = s.kernel.clock.now()
        sent = sum(cell.counters.sent.values())
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
    if summary.get("report"):
        print(f"  the run as a picture: {summary['report']}", file=out)


def run(binding: str = "direct", *, scenario: str = "", seed: int = 0, real_time: bool = False,
        record: str | Path | None = None, duration: float = 300.0,
        workdir: str | Path | None = None, out: TextIO = sys.stdout,
        north: NorthOptions | None = None,
        report_to: str | Path | None = None) -> dict[str, Any]:
    """Run the main job (see the module doc) and return the summary figures; ``north`` names
    the north-side services to serve while it runs (:mod:`chcos.north.services`); the run's
    picture (``chcos.apps.weld.report``) goes to ``report_to`` (default: ``weld-report.html`` beside
    the map in ``workdir``, or in the welding cell's state directory, ``<state base>/weld``
    (:func:`chcos.satellites.sysfile.default_state_base`), when the map is temporary — never into
    the
    source tree). Raises
    ChcosError (WeldRunError, ConfigError, InstallError, BusError, NorthError) if the cell or
    a service cannot be set up."""
    from chcos.north.services import start as start_north

    if report_to is None:
        from chcos.satellites.sysfile import default_state_base

        report_to = (Path(workdir) if workdir is not None
                     else default_state_base() / "weld") / "weld-report.html"
    with open_cell(binding, scenario=scenario, seed=seed, real_time=real_time, record=record,
                   workdir=workdir) as cell:
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
        summary["report"] = str(cell.write_report(report_to))
    report(summary, out)
    return summary


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
    ap.add_argument("--hierarchy", choices=("chc", "nbs"), default="chc",
                    help="chc (default): the CHC-OS task hierarchy; nbs: run the job under CHC "
                         "and then under the NBS baseline (Appendix 1's H1-H3, cyclic at 28 ms) "
                         "on the same scenario and binding, and print both side by side")
    args = ap.parse_args(argv)
    if not (math.isfinite(args.duration) and args.duration > 0):
        ap.error(f"--duration {args.duration}: expected seconds > 0")
    if args.hierarchy == "nbs":
        return _main_nbs(ap, args)
    try:
        north = NorthOptions.from_args(args)
        if north.any and not args.real_time:
            print("chcos run: north-side services asked for: running on real time",
                  file=sys.stderr)
        summary = run(args.binding, scenario=args.scenario, seed=args.seed,
                      real_time=args.real_time or north.any, record=args.record,
                      duration=args.duration, workdir=args.workdir, north=north,
                      report_to=args.report)
    except (ChcosError, ConfigError) as exc:
        print(f"chcos run: {exc}", file=sys.stderr)
        return 2
    return 0 if summary["outcome"] is not None else 1


def _main_nbs(ap: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """``chcos run --hierarchy nbs``: CHC, then NBS, side by side (chcos.apps.nbs.compare)."""
    from chcos.apps.nbs.compare import run_side_by_side

    if args.record or NorthOptions.from_args(args).any:
        ap.error("--hierarchy nbs: --record and north-side services are for the CHC job alone")
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
