"""cellrun - ``chcos run SYSTEM``: run a user's own cell from its system file.

:func:`~chcos.cli.cellsystem.open_cell` (:mod:`chcos.cli.cellsystem`) builds the system a system
file describes in one process, on real time against the buses the maps name or on virtual time
against simulated slaves; with ``outputs=False`` actuator writes are logged and never reach a
driver; the command line runs that way on real time unless ``--outputs on`` is given. :func:`run`
is the whole command: it runs until Ctrl-C, SIGTERM or the duration, prints each device's value,
age and status, each task's state and the message rate once a second (times since the start),
then puts every actuator at its safe value and prints a summary; its result says whether the run
was healthy.

A full disk is an error, never a traceback: a ``--workdir`` (or ``--log``) that cannot be written
stops the command with status 2 and one line naming the file and the error (``No space left on
device (ENOSPC)``) before the cell starts; a disk that fills while the cell runs keeps it under
control (sysfile.map and the log are records: :mod:`chcos.system.mapfile`), and the summary
says what could not be written, which makes the run unhealthy (status 1).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import logging.handlers
import math
import os
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any, TextIO

from chcos.cli.cellsystem import Cell, CellSystem, OutputsOff, SinceStartClock, open_cell
from chcos.devices.entry import DeviceStatus
from chcos.errors import ChcosError
from chcos.hil.evidence import RunEvidence
from chcos.north.services import NorthOptions, add_north_arguments
from chcos.system.mapfile import describe_os_error
from chcos.system.textview import bus_status_lines

#: Bytes written (and fsync'd) to prove that a workdir takes a file before the cell starts.
PROBE_BYTES = 64 * 1024

__all__ = ["Cell", "CellSystem", "LogFile", "OutputsOff", "RunResult", "SinceStartClock", "main",
           "open_cell", "parser", "problems", "report", "run", "show_progress"]


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
    written, a sysfile.map that could not be written."""
    found = []
    mapfile = cell.system.sysmgr.map
    if mapfile.error is not None:
        found.append(f"could not be written: {mapfile.error} ({mapfile.failures} failed "
                     "write(s); the tables ran as installed)")
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
    for o in cell.system.devtab.safe_outcomes.values():
        if not o.written:
            units = cell.system.devtab.get(o.device).spec.units
            found.append(f"actuator {o.device}: safe value {_value(o.value, units)} NOT "
                         f"written at the end: {o.reason}")
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
    for line in bus_status_lines(cell.system.devtab.statuses()):
        print(f"  {line}", file=out)
    print(f"  messages: {snap['messages']} ({snap['messages'] / secs:.0f}/s)", file=out)
    outcomes = cell.system.devtab.safe_outcomes
    for e in cell.system.devtab:
        if e.is_sensor or e.spec.safe_value is None:
            continue
        o = outcomes.get(e.name)
        if o is None:
            how = ("left to the satellite that drives it" if e.driver is None
                   else "NOT written: never issued")
        elif not o.written:
            how = f"NOT written: {o.reason}"
        elif not cell.system.outputs:
            how = "written (logged, not sent: outputs off)"
        else:
            how = "written" if o.attempts == 1 else f"written (attempt {o.attempts})"
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
        north: NorthOptions | None = None, pin: bool = False, values: Sequence[str] = (),
        plants: Sequence[str] = (),
        write_checks: Sequence[Callable[[], str | None]] = (),
        traces: Sequence[str | Path] = ()) -> RunResult:
    """The ``chcos run SYSTEM`` job: build, run until ``stop`` is set (SIGINT/SIGTERM in the
    command), or ``duration`` seconds of clock time, printing progress every ``period``; then
    safe values and the summary. ``north`` names the north-side services (OPC UA, Modbus
    facade, metrics, the live view) to serve while it runs; they need real time. ``pin``: the
    process (the command's own) is pinned first to the CPUs of ``system.cpus``, if any. Raises
    ChcosError if the system or a service cannot be set up (ConfigError for CPUs this process
    may not use). ``values`` and ``plants`` drive the simulated slaves (``virtual`` only; see
    :func:`~chcos.cli.cellsystem.open_cell`). ``write_checks`` say what else could not be
    written (the ``--log`` file: :meth:`LogFile.check`); a workdir that cannot be written is a
    ChcosError before the cell starts. ``traces`` are the files the run's trace goes to
    (:class:`chcos.hil.evidence.RunEvidence`; one that cannot be written makes the run
    unhealthy)."""
    from chcos.north.services import start as start_north
    from chcos.satellites import sysfile
    from chcos.system.affinity import pin_process

    if north is not None and north.any and virtual:
        raise ChcosError("north-side services (--opcua, --modbus-facade, --metrics, --view) "
                         "need real time: leave out --virtual")
    stop = stop or threading.Event()
    out = out or sys.stdout
    cpus = sysfile.load(system_file).cpus if pin else None
    if cpus is not None:  # before the drivers' threads start (they inherit it)
        pin_process(cpus, f"{Path(system_file).resolve()}: system.cpus")
        print(f"pinned to CPU(s) {', '.join(map(str, sorted(cpus)))} (system.cpus)", file=out)
    if workdir is not None:
        check_writable(Path(workdir))
    tracer = _tracer(system_file, traces, virtual)
    with contextlib.ExitStack() as stack:
        try:
            cell = stack.enter_context(open_cell(
                system_file, virtual=virtual, outputs=outputs, workdir=workdir, values=values,
                plants=plants, observe=[lambda c: tracer.attach(c.system, c.start)]
                if tracer is not None else ()))
        except OSError as exc:
            raise ChcosError(f"cannot set up the cell: {exc.filename or ''}: "
                             f"{describe_os_error(exc)}") from exc
        s = cell.system
        if s.sysmgr.map.error is not None:  # the install script's map: before the cell starts
            raise ChcosError(f"{s.sysmgr.map.error} (the workdir must take sysfile.map: "
                             "--workdir DIR)")
        print(f"system {cell.sf.name}: {len(s.devtab)} devices, {len(s.tsktab)} tasks, "
              f"{'virtual time, simulated slaves' if virtual else 'real time'}, outputs "
              f"{'on' if outputs else 'OFF: actuator writes are logged, not sent'}; Ctrl-C "
              "stops", file=out)
        if not outputs and not virtual:
            print("  (give --outputs on to drive the actuators)", file=out)
        # (only with a CAN bus: the simulators' module, and every bus library, loads then)
        if not virtual and any(b.kind in ("can", "canopen") for b in s.devmap.buses):
            from chcos.apps.sim.from_map import process_local

            for bus in process_local(s.devmap):
                print(f"  warning: bus {bus.name} ({bus.file}) is on python-can's 'virtual' "
                      "interface, which lives inside this process: a simulator in another "
                      "process (chcos sim --from) is never heard. Use interface = "
                      "\"udp_multicast\" or a vcan channel, or run with --virtual", file=out)
        for a in cell.answers:
            print(f"  host: {a}", file=out)
        logging.getLogger("chcos.run").info(
            "system %s (%s): %d devices, %d tasks, %s, outputs %s", cell.sf.name, cell.sf.path,
            len(s.devtab), len(s.tsktab), "virtual time" if virtual else "real time",
            "on" if outputs else "off")
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
        snap = cell.snapshot()  # the devices as the run left them (the shutdown window's
        cell.close()            # readings, on virtual time, come after it)
        found = problems(cell, snap)
        runlog = logging.getLogger("chcos.run")
        if found:
            runlog.warning("system %s: UNHEALTHY after %.1f s: %s", cell.sf.name, snap["t"],
                           "; ".join(found))
        else:
            runlog.info("system %s: healthy after %.1f s, %d messages", cell.sf.name,
                        snap["t"], snap["messages"])
        # what could not be written, the log line just above included, is in the summary
        found += [f"could not be written: {e}" for check in write_checks
                  if (e := check()) is not None]
        if tracer is not None:  # after the shutdown: its safe values are part of the run
            found += [f"could not be written: {e}" for e in tracer.finish()]
        report(cell, snap, found, out)
        return RunResult(not found, found, snap["t"], snap)


def _tracer(system_file: str | Path, traces: Sequence[str | Path], virtual: bool
            ) -> RunEvidence | None:
    """The ``--trace`` files' tracer (None without any); the system's name in the header."""
    if not traces:
        return None
    from chcos.satellites import sysfile

    return RunEvidence(traces, system=sysfile.load(system_file).name,
                     clock="virtual" if virtual else "real")


def check_writable(workdir: Path) -> None:
    """Make sure ``workdir`` takes a file (created, PROBE_BYTES written and fsync'd, removed).
    Raises ChcosError naming the directory and the error (ENOSPC, EACCES, EROFS...)."""
    probe = workdir / f".chcos-probe-{os.getpid()}"
    try:
        workdir.mkdir(parents=True, exist_ok=True)
        with open(probe, "wb") as fh:
            fh.write(b"\0" * PROBE_BYTES)
            fh.flush()
            os.fsync(fh.fileno())
    except OSError as exc:
        raise ChcosError(f"--workdir {workdir}: cannot write there: "
                         f"{describe_os_error(exc)}") from exc
    finally:
        with contextlib.suppress(OSError):
            probe.unlink()


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
        for line in bus_status_lines(s.devtab.statuses()):
            print(f"  {line}", file=out, flush=True)
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
    ap.add_argument("--value", action="append", default=[], metavar="DEVICE=SCRIPT",
                    help="with --virtual: a simulated sensor's value, as in chcos sim --from: a "
                         "number, ramp(start, end, period), sine(center, amplitude, period), "
                         "square(low, high, period) or csv(FILE[, column]) (repeatable)")
    ap.add_argument("--plant", action="append", default=[], metavar="FILE.py:FUNCTION",
                    help="with --virtual: a plant model called every 10 ms of clock time as "
                         "FUNCTION(seconds, slaves); it reads the actuators (slaves.get(name)) "
                         "and sets the sensors (slaves.set(name, value)) (repeatable)")
    ap.add_argument("--log", metavar="FILE",
                    help="also log to FILE, at INFO level with times (device failures, "
                         "restarts, task ends, the summary), rotated at --log-size")
    ap.add_argument("--log-size", type=float, default=10.0, metavar="MB",
                    help="rotate the log file at this many megabytes (default 10)")
    ap.add_argument("--log-keep", type=int, default=5, metavar="N",
                    help="keep N rotated log files, FILE.1 ... FILE.N (default 5)")
    ap.add_argument("-v", "--verbose", action="store_true",
                    help="log at INFO level (also accepted before 'run': chcos -v run ...)")
    ap.add_argument("--trace", action="append", default=[], metavar="FILE",
                    help="write the run's trace to FILE: every device value and status change, "
                         "every command written and confirmed, task events, on the run's clock "
                         "(a text file that diffs well, chcos diff; .gz compressed; .mcap: MCAP "
                         "for viewers, needs chcos[mcap]) (repeatable)")
    add_north_arguments(ap)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    """``chcos run SYSTEM``. Exit status 0: the run was healthy; 1: it ran but something was
    wrong (listed in the summary); 2: the system could not be built."""
    ap = parser()
    args = ap.parse_args(argv)
    if args.verbose:
        logging.getLogger().setLevel(logging.INFO)
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        ap.error(f"--duration {args.duration}: expected seconds > 0")
    if not (math.isfinite(args.log_size) and args.log_size > 0) or args.log_keep < 1:
        ap.error("--log-size: expected megabytes > 0; --log-keep: expected a count >= 1")
    stop = threading.Event()
    try:
        logfile = LogFile(args.log, args.log_size, args.log_keep) if args.log else None
    except OSError as exc:
        print(f"chcos run: --log {args.log}: {describe_os_error(exc)}", file=sys.stderr)
        return 2

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    old = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        result = run(args.system, virtual=args.virtual, duration=args.duration,
                     outputs=args.outputs == "on" or (args.outputs is None and args.virtual),
                     workdir=args.workdir, stop=stop, north=NorthOptions.from_args(args),
                     pin=True, values=args.value, plants=args.plant,
                     write_checks=[logfile.check] if logfile is not None else [],
                     traces=args.trace)
    except ChcosError as exc:
        print(f"chcos run: {exc}", file=sys.stderr)
        logging.getLogger("chcos.run").error("chcos run: %s", exc)
        return 2
    finally:
        for sig, previous in old.items():
            signal.signal(sig, previous)
        if logfile is not None:
            logfile.close()
    return 0 if result.healthy else 1


class _RotatingLog(logging.handlers.RotatingFileHandler):
    """The log file's handler: a record that cannot be written (a full disk) costs one line
    on stderr per distinct error, never a traceback, and is counted; the file is reopened at
    the next record."""

    error: str | None = None
    failures = 0

    def handleError(self, record: logging.LogRecord) -> None:
        exc = sys.exc_info()[1]
        self.failures += 1
        what = describe_os_error(exc) if isinstance(exc, OSError) else repr(exc)
        text = f"cannot write {self.baseFilename}: {what}"
        if text != self.error:
            with contextlib.suppress(OSError):
                print(f"chcos run: {text}; the cell goes on, log lines are lost",
                      file=sys.stderr, flush=True)
        self.error = text
        stream, self.stream = self.stream, None
        if stream is not None:
            with contextlib.suppress(OSError):
                stream.close()  # its unwritten buffer goes with it


class LogFile:
    """``chcos run --log``: a rotating log file on the root logger at INFO level while the run
    lasts (the terminal keeps the level the command line set): the file is renamed ``FILE.1``
    (older ones shifted, ``keep`` kept) when it would grow past ``megabytes``. :meth:`close`
    puts the levels back. Raises OSError if the file cannot be opened."""

    def __init__(self, path: str, megabytes: float, keep: int) -> None:
        self.handler = _RotatingLog(path, maxBytes=int(megabytes * 1024 * 1024),
                                    backupCount=keep, encoding="utf-8")
        self.handler.setLevel(logging.INFO)
        self.handler.setFormatter(logging.Formatter(
            "%(asctime)s %(levelname)s %(name)s: %(message)s"))
        root = logging.getLogger()
        self._root_level = root.level
        self._quieted = [h for h in root.handlers if h.level == logging.NOTSET]
        for h in self._quieted:
            h.setLevel(root.level)
        root.addHandler(self.handler)
        if root.level > logging.INFO or root.level == logging.NOTSET:
            root.setLevel(logging.INFO)

    def check(self) -> str | None:
        """Flush the file; what could not be written to it, in one line (None: all was)."""
        self.handler.acquire()
        try:
            if self.handler.stream is not None:
                self.handler.stream.flush()
        except OSError as exc:
            self.handler.failures += 1
            self.handler.error = f"cannot write {self.handler.baseFilename}: " \
                                 f"{describe_os_error(exc)}"
        finally:
            self.handler.release()
        if self.handler.error is None:
            return None
        return f"{self.handler.error} ({self.handler.failures} failed write(s))"

    def close(self) -> None:
        """Detach and close the file; the root logger and the terminal get their levels back
        (a close that cannot flush raises nothing: :meth:`check` said what was lost)."""
        root = logging.getLogger()
        root.removeHandler(self.handler)
        with contextlib.suppress(OSError):
            self.handler.close()
        root.setLevel(self._root_level)
        for h in self._quieted:
            h.setLevel(logging.NOTSET)
