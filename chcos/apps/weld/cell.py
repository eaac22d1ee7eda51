"""cell - the welding cell of appendix 2 built and running: :func:`open_cell` and :class:`Cell`.

Builds the System on one of two bindings of the same device table
(``chcos/apps/weld/DEVICES.md``):

* ``direct`` - ``chcos/apps/weld/maps/weld_direct.toml``: the cell model in-process
  (:mod:`chcos.apps.weld.direct`);
* ``buses`` - the real-bus simulator :class:`chcos.apps.weld.plant.WeldSim` on virtual CAN
  (CANopen servos and raw-CAN sensors), Modbus TCP and a serial line, with the device map that
  :func:`chcos.apps.weld.simmap.cell_devmap` writes for it;

installs the hierarchy with the thesis-syntax script ``chcos/apps/weld/install.chcos`` and hands
the running cell (:class:`Cell`: drive the job, inject faults, the run's figures) to the command
line (:mod:`chcos.apps.weld.runner`), the NBS comparison and tests. :class:`Timeline` measures the
assassin's reaction latency (interrupt to safe values).
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import tempfile
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from chcos import resources
from chcos.apps.weld import WeldCell, parse_scenario
from chcos.apps.weld.direct import WeldDirectDriver
from chcos.apps.weld.report import Recorder, write_report
from chcos.apps.weld.servo import JointDrive
from chcos.apps.weld.tasks import HERE as TASK_PATH
from chcos.apps.weld.tasks import SCRIPT
from chcos.devices.devmap import load
from chcos.errors import ChcosError
from chcos.helpers import free_ports
from chcos.kernel.clock import Clock, RealClock, VirtualClock
from chcos.kernel.instrument import Counters, Instrument
from chcos.system.digest import EventRecord
from chcos.system.embedded import System
from chcos.tables.messages import Link, LinkType

DIRECT_MAP = resources.path("chcos.apps.weld", "maps", "weld_direct.toml")
BINDINGS = ("direct", "buses")
SAFE_DEVICES = ("drives_enable", "volts_set", "wire_set", "gas_valve")
"""The actuators that must be at their safe value (0) after an emergency stop."""
_channels = itertools.count()


class WeldRunError(ChcosError):
    """The welding job could not be set up: unknown binding, the real-bus simulator missing."""


class CellCounters(Counters):
    """:class:`Counters` keeping the events only: executions are each task's ``steps`` in Tsktab
    and messages each link's counts in Msgtab, and hooking them would make the kernel tell every
    step and the message layer every message (stamped for its latency) to the instruments."""

    before_step = Instrument.before_step
    message_sent = Instrument.message_sent
    message_overwritten = Instrument.message_overwritten
    message_delivered = Instrument.message_delivered


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
    #: the joint drives as the drives see themselves (joint 1..5): state, controlwords received
    drives: list[JointDrive] = field(default_factory=list)
    #: called before the System's shutdown (on real time the simulator goes on on wall-clock
    #: time, its kernel timers no longer running; on virtual time they run in the shutdown
    #: window, :meth:`chcos.kernel.scheduler.Kernel.run_drivers`)
    before_shutdown: list[Callable[[], None]] = field(default_factory=list)
    injector: Callable[[str], None] | None = None
    recorder: Recorder | None = None
    #: every system event with its clock time, from the install on (for the run digest)
    events: EventRecord | None = None

    def write_report(self, path: str | Path, title: str | None = None,
                     evidence: str = "") -> Path:
        """Write the run as a picture (``chcos.apps.weld.report``: one self-contained HTML page) to
        ``path``, with the run's HIL ``evidence`` (HTML, :mod:`chcos.hil.report`); returns it.
        Raises ChcosError if it cannot be written."""
        samples = self.recorder.samples if self.recorder is not None else []
        return write_report(path, self.summary(), samples,
                            title or f"welding cell, {self.binding} binding", evidence)

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
        """Shut the System down (safe values out: the simulator, if any, goes on meanwhile, on
        the virtual clock or the wall clock, so the joint drives confirm their safe stop),
        then the simulator."""
        try:
            for prepare in self.before_shutdown:
                prepare()
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


def _direct_map(scenario: str, seed: int) -> Any:
    devmap = load([DIRECT_MAP])
    buses = tuple(b.with_options({**b.options, "scenario": scenario, "seed": seed})
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
              interface: str = "virtual", channels: tuple[str, str] | None = None,
              observe: Sequence[Callable[[System], None]] = ()) -> Iterator[Cell]:
    """The welding cell, booted and installed, ready for :meth:`Cell.start_job`; shut down on
    exit. ``replace`` maps task names to code references (``pkg.mod:fn``) installed instead of
    the standard code (test-only tasks). ``interface``/``channels`` put the buses binding's two
    CAN buses (CANopen, raw sensors) on python-can ``virtual`` channels of their own (default) or
    on given channels of another interface, e.g. ``socketcan`` ``("vcan0", "vcan1")``.
    ``observe`` are called with the System once it is built, before the install script runs
    (the HIL evidence watches it from there: :mod:`chcos.hil.observe`).
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
                from chcos.apps.weld.plant import WeldSim
                from chcos.apps.weld.simmap import cell_devmap
            except ImportError as exc:
                raise WeldRunError("the real-bus simulator chcos.apps.weld.plant is not available: "
                                  f"{exc}") from exc
            n = next(_channels)
            chans = channels or (f"weld-co-{os.getpid()}-{n}", f"weld-can-{os.getpid()}-{n}")
            ports = free_ports(2)
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
            # the simulator steps on the kernel's clock: the drivers supervise its heartbeats
            # there too (before the install starts them)
            system.devtab.peers_on_clock = clock.virtual
        for watch in observe:
            watch(system)
        counters = CellCounters()
        system.kernel.add_instrument(counters)
        events = EventRecord(system.kernel.clock)
        system.kernel.add_instrument(events)
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
            assert sim.servo is not None
            drives = [sim.servo.drives[nid] for nid in sorted(sim.servo.drives)]
        else:
            direct = next(d for d in system.devtab.drivers if isinstance(d, WeldDirectDriver))
            model, drives = direct.cell, direct.drives
        cell = Cell(system, model, binding, counters, timeline, closers=closers,
                    injector=sim.inject if sim is not None else None,
                    drives=drives,
                    before_shutdown=[sim.continue_realtime]
                    if sim is not None and real_time else [], events=events)
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
