"""cellrun - ``chcos run SYSTEM``: run a user's own cell from its system file.

:func:`open_cell` builds the system a system file describes (:mod:`chcos.satellites.sysfile`:
device maps,
task path, install script) in one process, every machine in it: on real time against the buses
the maps name, or on virtual time against simulated slaves generated from the maps
(:mod:`chcos.apps.sim.from_map`). With ``outputs=False`` actuator writes are logged and never reach
a
driver (commissioning a live bus without driving anything); the command line runs that way on
real time unless ``--outputs on`` is given. :func:`run` is the whole command:
it runs until Ctrl-C, SIGTERM or the duration, prints each device's value, age and status, each
task's state and the message rate once a second (times since the start), then puts every
actuator at its safe value and prints a summary; its result says whether the run was healthy.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any, TextIO

from chcos.apps.sim.from_map import SimSlaves, simulate
from chcos.devices.devmap import load
from chcos.devices.entry import DeviceEntry, DeviceStatus
from chcos.errors import ChcosError
from chcos.kernel.clock import Clock, RealClock, VirtualClock
from chcos.kernel.instrument import Counters
from chcos.north.services import NorthOptions, add_north_arguments
from chcos.satellites import sysfile
from chcos.system.embedded import System
from drivers.base import Driver


class SinceStartClock(RealClock):
    """Wall-clock time counted from the clock's creation, so every time a user sees (progress,
    ``map``, events) reads as seconds since the start, not the machine's uptime. Only for a
    system in one process: satellites keep :class:`RealClock`, whose times agree across
    processes."""

    def __init__(self) -> None:
        self.origin = time.monotonic()

    def now(self) -> float:
        """Seconds since this clock was made."""
        return time.monotonic() - self.origin

    def idle(self, wake: threading.Event, deadline: float | None) -> None:
        """Wait on ``wake`` until the deadline (or forever if there is none)."""
        if deadline is None:
            wake.wait()
        else:
            delay = deadline - self.now()
            if delay > 0:
                wake.wait(delay)


class OutputsOff(Driver):
    """Stands in for an actuator's driver when outputs are off: every write is logged (clock
    time since the start, device, raw value) and goes nowhere. The real driver keeps reading
    the bus's sensors."""

    kind = "outputs-off"

    def __init__(self, inner: Driver, log: Callable[[str, Any], None]) -> None:
        super().__init__(inner.bus, list(inner.devices.values()), inner.host)
        self.inner = inner
        self._log = log
        self._running = True        # stands in for a driver that is already running

    def start(self) -> None:
        """Nothing to open: the wrapped driver is already running."""

    def _write(self, device: str, value: Any) -> None:
        """Log the write instead of sending it."""
        self._log(device, value)

    def stop(self) -> None:
        """Nothing to close: Devtab stops the wrapped driver."""

    def settle(self, timeout: float) -> bool:
        """Nothing is ever outstanding here."""
        return True


class CellSystem(System):
    """A :class:`System` whose actuator writes can be switched off at the drivers
    (``outputs=False``): see :class:`OutputsOff`."""

    def __init__(self, *args: Any, outputs: bool = True,
                 on_output: Callable[[str, Any], None] | None = None, **kw: Any) -> None:
        self.outputs = outputs
        self._on_output = on_output or (lambda device, value: None)
        super().__init__(*args, **kw)

    def start_drivers(self, machines: Iterable[int]) -> None:
        """Start the drivers; with outputs off, put an :class:`OutputsOff` in front of every
        actuator."""
        super().start_drivers(machines)
        if self.outputs:
            return
        for e in self.devtab:
            if not e.is_sensor and e.driver is not None and not isinstance(e.driver,
                                                                           OutputsOff):
                e.driver = OutputsOff(e.driver, self._on_output)


@dataclass
class Cell:
    """A user's system, built and installed; see :func:`open_cell`."""

    sf: sysfile.SystemFile
    system: CellSystem
    counters: Counters
    slaves: SimSlaves | None
    virtual: bool
    start: float = 0.0
    answers: list[str] = field(default_factory=list)
    outputs_log: list[tuple[float, str, Any]] = field(default_factory=list)
    safe_written: dict[str, Any] = field(default_factory=dict)
    closed: bool = False

    def now(self) -> float:
        """Seconds of clock time since the start of the run."""
        return self.system.kernel.clock.now() - self.start

    def run_for(self, seconds: float) -> None:
        """Run ``seconds`` of clock time (virtual time: as fast as possible)."""
        self.system.run_for(seconds)

    def device(self, name: str) -> DeviceEntry:
        """The Devtab entry of device ``name``; raises DeviceError if there is none."""
        return self.system.devtab.get(name)

    def messages(self) -> int:
        """Messages sent on every link so far."""
        return sum(lk.sent for lk in self.system.msgtab)

    def snapshot(self) -> dict[str, Any]:
        """Devices, tasks and counters as plain data (call on the kernel thread or while the
        kernel is stopped; :meth:`System.call` does that)."""
        now = self.system.kernel.clock.now()
        devices = [{"name": e.name, "direction": e.spec.direction, "value": e.value,
                    "units": e.spec.units, "status": e.status.value, "reason": e.reason,
                    "age": None if e.updated_at is None else now - e.updated_at,
                    "readings": e.readings, "commands": e.commands, "rejected": e.rejected,
                    "driven": e.driver is not None}
                   for e in self.system.devtab]
        tasks = [{"name": t.name, "level": t.level, "machine": t.machine,
                  "state": t.state.value, "steps": t.steps, "completions": t.completions,
                  "abnormal": t.abnormal, "error": t.last_error}
                 for t in self.system.tsktab]
        return {"t": now - self.start, "devices": devices, "tasks": tasks,
                "messages": self.messages(),
                "bus_errors": dict(self.system.devtab.last_bus_error),
                "bus_error_count": sum(self.system.devtab.bus_errors.values())}

    def close(self) -> None:
        """Stop the kernel, put every actuator at its safe value (recorded in
        :attr:`safe_written`), stop the drivers and the simulated slaves. Idempotent."""
        if self.closed:
            return
        self.closed = True
        self.system.stop()
        self.system.devtab.on_write.append(self._safe_write)
        try:
            self.system.shutdown()
        finally:
            if self.slaves is not None:
                self.slaves.close()

    def _safe_write(self, device: str, value: Any) -> None:
        self.safe_written[device] = value


def _boot_lines(sf: sysfile.SystemFile, machines: Iterable[int]) -> list[str]:
    return [f"install -m{m} sysfile" for m in sorted(set(machines))]


@contextmanager
def open_cell(system_file: str | Path, *, virtual: bool = False, outputs: bool = True,
              workdir: str | Path | None = None, clock: Clock | None = None,
              quiet_slaves: bool = False) -> Iterator[Cell]:
    """Build and install the system of ``system_file``; shut it down (actuators safe) on exit.

    ``virtual``: virtual time against simulated slaves from the device maps; ``outputs=False``:
    actuator writes logged, not sent; ``workdir``: where sysfile.map goes (default a temporary
    directory). Without ``system.install`` every machine of the maps is loaded and nothing is
    installed. Raises ConfigError for a bad system file or device map (naming it), BusError if a
    bus cannot be opened, InstallError naming the script's file and line."""
    sf = sysfile.load(system_file)
    devmap = load(list(sf.devmaps)) if sf.devmaps else None
    slaves = None
    tmp: tempfile.TemporaryDirectory[str] | None = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="chcos-run-")
        workdir = tmp.name
    work = Path(workdir)
    work.mkdir(parents=True, exist_ok=True)
    cell: Cell | None = None
    try:
        if devmap is not None and virtual:
            slaves = simulate(devmap)
            devmap = slaves.devmap
        holder: list[Cell] = []

        def logged(device: str, value: Any) -> None:
            if holder:
                holder[0].outputs_log.append((holder[0].now(), device, value))

        system = CellSystem(devmap if devmap is not None else (), outputs=outputs,
                            on_output=logged,
                            clock=clock or (VirtualClock() if virtual else SinceStartClock()),
                            task_path=list(sf.task_path), base_dir=sf.base_dir,
                            map_path=work / "sysfile.map")
        if slaves is not None:
            slaves.attach(system.kernel)
        counters = Counters()
        system.kernel.add_instrument(counters)
        cell = Cell(sf, system, counters, slaves, virtual)
        holder.append(cell)
        cell.start = system.kernel.clock.now()
        if sf.install:
            for script in sf.install:
                cell.answers += system.run_script(script)
        else:
            machines = {d.machine for d in system.devmap.devices}
            for line in _boot_lines(sf, machines):
                cell.answers.append(system.execute(line))
    except BaseException:
        if cell is not None:
            cell.close()
        elif slaves is not None:
            slaves.close()
        if tmp is not None:
            tmp.cleanup()
        raise
    try:
        yield cell
    finally:
        try:
            cell.close()
        finally:
            if tmp is not None:
                tmp.cleanup()


# ---- the terminal ---------------------------------------------------------------------------
def _value(v: Any, units: str) -> str:
    if v is None:
        return "-"
    text = f"{v:.4g}" if isinstance(v, float) else str(v)
    return f"{text} {units}".strip()


def show_progress(snap: dict[str, Any], rate: float, out: TextIO) -> None:
    """Print one progress block: time since start, message rate, devices, tasks. On a terminal
    the block replaces the previous one (the screen is redrawn); otherwise blocks follow each
    other (logs, pipes)."""
    if out.isatty():
        out.write("\033[H\033[J")  # cursor home, clear: a live table
    width = max([len(d["name"]) for d in snap["devices"]] +
                [len(t["name"]) for t in snap["tasks"]] + [8])
    print(f"t={snap['t']:7.1f} s  messages/s {rate:7.0f}  bus errors "
          f"{snap['bus_error_count']}", file=out)
    for d in snap["devices"]:
        age = "never" if d["age"] is None else f"{d['age']:.1f} s ago"
        status = d["status"] + (f" ({d['reason']})" if d["reason"] else "")
        print(f"  {d['direction']:<8} {d['name']:<{width}} {_value(d['value'], d['units']):>16}"
              f"  {age:<12} {status}", file=out)
    for t in snap["tasks"]:
        err = f"  last error: {t['error']}" if t["abnormal"] else ""
        print(f"  task     {t['name']:<{width}} level {t['level']} machine {t['machine']}  "
              f"{t['state']:<9} executions {t['steps']}{err}", file=out)
    out.flush()


def problems(cell: Cell, snap: dict[str, Any]) -> list[str]:
    """What made the run unhealthy: devices failed or stale at the end, sensors on a bus that
    never delivered, tasks that ended abnormally, bus errors, actuators whose safe value was not
    written."""
    found = []
    for d in snap["devices"]:
        if not d["driven"]:
            continue
        if d["status"] in (DeviceStatus.FAILED.value, DeviceStatus.STALE.value):
            found.append(f"device {d['name']} is {d['status']}: {d['reason']}")
        elif d["direction"] == "sensor" and d["readings"] == 0:
            found.append(f"sensor {d['name']} never delivered a value")
    for t in snap["tasks"]:
        if t["abnormal"]:
            found.append(f"task {t['name']} ended abnormally {t['abnormal']} time(s): "
                         f"{t['error']}")
    for bus, err in snap["bus_errors"].items():
        found.append(f"bus {bus}: {err}")
    for e in cell.system.devtab:
        safe = e.spec.safe_value
        if not e.is_sensor and e.driver is not None and safe is not None \
                and cell.safe_written.get(e.name) != safe:
            found.append(f"actuator {e.name}: safe value {safe} not written at the end")
    return found


def report(cell: Cell, snap: dict[str, Any], found: list[str], out: TextIO) -> None:
    """Print the end-of-run summary."""
    secs = max(1e-9, snap["t"])
    print("\nsummary", file=out)
    print(f"  system {cell.sf.name} ({cell.sf.path}), {snap['t']:.1f} s of "
          f"{'virtual' if cell.virtual else 'real'} time, outputs "
          f"{'on' if cell.system.outputs else 'off (logged, not sent)'}", file=out)
    for d in snap["devices"]:
        what = (f"{d['readings']} readings" if d["direction"] == "sensor"
                else f"{d['commands']} commands, {d['rejected']} refused")
        print(f"  {d['direction']:<8} {d['name']:<16} last {_value(d['value'], d['units'])}, "
              f"{what}, {d['status']}", file=out)
    for t in snap["tasks"]:
        print(f"  task     {t['name']:<16} {t['steps']} executions, {t['completions']} "
              f"completions, {t['abnormal']} abnormal", file=out)
    print(f"  messages: {snap['messages']} ({snap['messages'] / secs:.0f}/s)", file=out)
    for e in cell.system.devtab:
        if not e.is_sensor and e.spec.safe_value is not None:
            done = e.name in cell.safe_written
            how = "written" if done else "NOT written"
            if done and not cell.system.outputs:
                how += " (logged, not sent: outputs off)"
            print(f"  safe value {e.name} = {_value(e.spec.safe_value, e.spec.units)}: {how}",
                  file=out)
    if not cell.system.outputs:
        print(f"  actuator writes logged, not sent: {len(cell.outputs_log)}", file=out)
    if found:
        print("  UNHEALTHY:", file=out)
        for p in found:
            print(f"    {p}", file=out)
    else:
        print("  healthy", file=out)
    out.flush()


@dataclass
class RunResult:
    """What :func:`run` returns."""

    healthy: bool
    problems: list[str]
    seconds: float
    snapshot: dict[str, Any]


def run(system_file: str | Path, *, virtual: bool = False, duration: float | None = None,
        outputs: bool = True, workdir: str | Path | None = None, period: float = 1.0,
        out: TextIO | None = None, stop: threading.Event | None = None,
        north: NorthOptions | None = None) -> RunResult:
    """The ``chcos run SYSTEM`` job: build, run until ``stop`` is set (SIGINT/SIGTERM in the
    command), or ``duration`` seconds of clock time, printing progress every ``period``; then
    safe values and the summary. ``north`` names the north-side services (OPC UA, Modbus
    facade, metrics, the live view) to serve while it runs; they need real time. Raises
    ChcosError if the system or a service cannot be set up."""
    from chcos.north.services import start as start_north

    if north is not None and north.any and virtual:
        raise ChcosError("north-side services (--opcua, --modbus-facade, --metrics, --view) "
                         "need real time: leave out --virtual")
    stop = stop or threading.Event()
    out = out or sys.stdout
    with open_cell(system_file, virtual=virtual, outputs=outputs, workdir=workdir) as cell:
        s = cell.system
        print(f"system {cell.sf.name}: {len(s.devtab)} devices, {len(s.tsktab)} tasks, "
              f"{'virtual time, simulated slaves' if virtual else 'real time'}, outputs "
              f"{'on' if outputs else 'OFF: actuator writes are logged, not sent'}; Ctrl-C "
              "stops", file=out)
        if not outputs and not virtual:
            print("  (give --outputs on to drive the actuators)", file=out)
        for a in cell.answers:
            print(f"  host: {a}", file=out)
        out.flush()
        if not virtual:
            s.start()
        services = start_north(s, north) if north is not None and north.any else None
        for name, url in (services.urls.items() if services else ()):
            print(f"  {name}: {url}", file=out, flush=True)
        try:
            _loop(cell, virtual, duration, period, stop, out)
        finally:
            if services is not None:
                services.stop()
        s.stop()
        cell.close()
        snap = cell.snapshot()
        found = problems(cell, snap)
        report(cell, snap, found, out)
        return RunResult(not found, found, snap["t"], snap)


def _loop(cell: Cell, virtual: bool, duration: float | None, period: float,
          stop: threading.Event, out: TextIO) -> None:
    """Run ``cell`` until ``stop`` or ``duration``, showing progress every ``period``."""
    s = cell.system
    last_msgs, last_t = 0, 0.0
    tick = 1
    while not stop.is_set():
        due = tick * period
        if duration is not None:
            due = min(due, duration)
        if virtual:
            s.run(until=cell.start + due)
        else:
            stop.wait(max(0.0, due - cell.now()))
        snap = s.call(cell.snapshot)
        rate = (snap["messages"] - last_msgs) / max(1e-9, snap["t"] - last_t)
        last_msgs, last_t = snap["messages"], snap["t"]
        show_progress(snap, rate, out)
        tick += 1
        if duration is not None and snap["t"] >= duration - 1e-9:
            break


def parser() -> argparse.ArgumentParser:
    """The command line of ``chcos run SYSTEM``."""
    ap = argparse.ArgumentParser(
        prog="chcos run",
        description="Run the cell a system file describes (device maps, task path, install "
                    "script), every machine in this process, until Ctrl-C, SIGTERM or "
                    "--duration. Once a second it shows each device's value, age and status, "
                    "each task's state and the message rate; at the end every actuator goes to "
                    "its safe value and a summary says whether the run was healthy (exit status "
                    "0) or not (1, with what was wrong); 2 when the system cannot be built. "
                    "'chcos run' without SYSTEM, or 'chcos run weld', runs the welding cell.")
    ap.add_argument("system", metavar="SYSTEM", help="the system file (TOML)")
    ap.add_argument("--virtual", action="store_true",
                    help="virtual time against simulated slaves generated from the device maps "
                         "(as fast as possible; give --duration)")
    ap.add_argument("--duration", type=float, default=None,
                    help="stop after this many seconds of clock time (default: run until Ctrl-C)")
    ap.add_argument("--outputs", choices=("on", "off"), default=None,
                    help="on: actuator writes go to the buses; off: tasks run, actuator writes "
                         "(safe values included) are logged, never sent. Default: off on real "
                         "time (outputs are on only when asked), on with --virtual")
    ap.add_argument("--workdir",
                    help="where sysfile.map is written (default: a temporary directory)")
    add_north_arguments(ap)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    """``chcos run SYSTEM``. Exit status 0: the run was healthy; 1: it ran but something was
    wrong (listed in the summary); 2: the system could not be built."""
    ap = parser()
    args = ap.parse_args(argv)
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        ap.error(f"--duration {args.duration}: expected seconds > 0")
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    old = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        result = run(args.system, virtual=args.virtual, duration=args.duration,
                     outputs=args.outputs == "on" or (args.outputs is None and args.virtual),
                     workdir=args.workdir, stop=stop, north=NorthOptions.from_args(args))
    except ChcosError as exc:
        print(f"chcos run: {exc}", file=sys.stderr)
        return 2
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
    return 0 if result.healthy else 1

