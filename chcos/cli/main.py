"""main - the ``chcos`` command: a thin dispatcher to each subcommand's own module.

:data:`DESCRIPTION` is what ``chcos --help`` shows; each subcommand's parser and help live in its
module (``chcos.cli.cellrun``, ``chcos.apps.weld.runner``, ``chcos.cli.scaffold``,
``chcos.cli.diff``, ``chcos.devices.importers``,
``chcos.cli.monitor``, ``chcos.apps.sim``, ``chcos.devices.devmap``, ``chcos.viewer.cli``), except
``shell``,
``satellite`` and ``host``, which are here.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

from chcos.errors import ChcosError, CommandSyntaxError

DESCRIPTION = """\
chcos runs CHC-OS control hierarchies on real field buses (CAN, CANopen, Modbus, serial).

Your own cell:
  chcos new DIR                  create a cell project (system file, device map, task, tests)
  chcos run SYSTEM               run a system file until Ctrl-C (--virtual, --outputs off, ...)
  chcos monitor SYSTEM           commission a live bus: listen-only, mismatches flagged
  chcos import eds|dbc|modbus F  write a device map from an EDS, a DBC or a register list
  chcos check FILE...            validate device maps without opening a bus
                                 (--system SYSTEM: a system file and its maps)
  chcos sim --from MAP           simulated slaves for every device of a map
  chcos diff GOLDEN NEW          compare two traces of a run (chcos run --virtual --trace FILE)

The thesis' systems:
  chcos run [weld]               the arc-welding cell end to end (chcos run weld --help)
  chcos run --example fig65      the figure 6.5 system

Consoles and views:
  chcos shell [MAP...]           host commands to an in-process system (script or stdin)
  chcos satellite -m N --system SYSTEM   one machine of a multi-process system
  chcos host --system SYSTEM [COMMAND]   host commands to running satellites
  chcos map [sysfile.map]        draw the hierarchy (text, dot, svg)
  chcos view                     live web page of a running system
  chcos sim KIND                 one simulated device (can, serial, canopen, modbus, weld)

'chcos COMMAND --help' describes each command. Warnings go to stderr; -v adds INFO messages.
"""


def _run_example(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="chcos run --example fig65",
                                 description="the thesis' figure 6.5 example system")
    ap.add_argument("--duration", type=float, default=20.0, help="seconds of clock time")
    ap.add_argument("--real-time", action="store_true", help="wall-clock time, not virtual")
    ap.add_argument("--workdir", help="where the map, log and test file go (default out/fig65)")
    ap.add_argument("--tty", help="a terminal for A4 instead of /dev/tty0, e.g. $(tty): lines "
                                  "typed there reach C1 ('stop', 'shutdown'); implies --real-time")
    args = ap.parse_args(argv)
    from chcos.apps.fig65 import runner as fig65run

    fig65run.run(args.duration, real_time=args.real_time or bool(args.tty),
                 workdir=Path(args.workdir) if args.workdir else None, tty=args.tty)
    return 0


def _run_help() -> int:
    """``chcos run --help``: the three forms of ``chcos run`` on one page."""
    import contextlib
    import io

    from chcos.cli.cellrun import parser as cell_parser

    print(cell_parser().format_help())
    weld = io.StringIO()
    with contextlib.redirect_stdout(weld), contextlib.suppress(SystemExit):
        from chcos.apps.weld.runner import main as weld_main

        weld_main(["--help"])
    print(weld.getvalue())
    print("usage: chcos run --example fig65 [--duration S] [--real-time] [--workdir DIR]\n\n"
          "The thesis' figure 6.5 system (section 6.1.5) on virtual time: executions and "
          "messages per second against the thesis' estimate.")
    return 0


def _shell(args: argparse.Namespace) -> int:
    import threading

    from chcos.cli.cellrun import SinceStartClock
    from chcos.kernel.clock import VirtualClock
    from chcos.system.embedded import System

    clock = VirtualClock() if args.virtual else SinceStartClock()
    base_dir, map_path = args.base_dir, args.map
    if args.workdir:
        Path(args.workdir).mkdir(parents=True, exist_ok=True)
        base_dir = base_dir or args.workdir
        map_path = map_path or str(Path(args.workdir) / "sysfile.map")
    system = System(args.devmap, clock=clock, task_path=args.task_path or ["."],
                    base_dir=base_dir or ".", map_path=map_path or "sysfile.map")
    lines: Iterable[str] = (Path(args.script).read_text(encoding="utf-8").splitlines()
                            if args.script else sys.stdin)
    if not args.virtual:
        system.start()
    def execute(line: str) -> str:
        words = line.split()
        if words[:1] == ["run"]:
            try:
                seconds = float(words[1]) if len(words) == 2 else -1.0
            except ValueError:
                seconds = -1.0
            if not 0 <= seconds <= 1e6:
                raise CommandSyntaxError(f"run: expected 'run SECONDS' (0..1e6), got "
                                         f"{line.strip()!r}")
            if args.virtual:
                system.run_for(seconds)
            else:  # the kernel runs on its own thread: let it, then go on with the script
                threading.Event().wait(seconds)
            return ""
        return system.execute(line)

    reported: list[str] = []

    def map_failure() -> None:
        """A sysfile.map that could not be written: one line, once per failure (the map is a
        record: the script goes on, the status becomes 1)."""
        error = system.sysmgr.map.error
        if error is not None and (not reported or reported[-1] != error):
            reported.append(error)
            print(f"error: {error}", file=sys.stderr, flush=True)

    def execute_and_check(line: str) -> str:
        try:
            return execute(line)
        finally:
            map_failure()

    try:
        status = _console(lines, execute_and_check)
    finally:
        system.shutdown()
    map_failure()  # the last write, at shutdown
    return status or (1 if reported else 0)


def _console(lines: Iterable[str], execute: Callable[[str], str]) -> int:
    """Execute host command lines until ``quit``; errors are printed and make the status 1."""
    status = 0
    for line in lines:
        if line.strip() in ("quit", "exit"):
            break
        try:
            answer = execute(line)
        except ChcosError as exc:
            print(f"error: {exc}", file=sys.stderr)
            status = 1
            continue
        if answer:
            print(answer, flush=True)
    return status


def _satellite(args: argparse.Namespace) -> int:
    """Run one satellite until SIGTERM or SIGINT, then stop it cleanly (actuators safe).

    The stop signals are blocked in every thread (set before any is started, so Zenoh's and the
    drivers' threads inherit the mask) and taken by ``sigwait`` in the main thread: a signal
    that the kernel happened to deliver to another thread would otherwise leave a main thread
    asleep in a lock wait that nothing interrupts."""
    import signal

    from chcos.comm.transport import enable_zenoh_logging
    from chcos.satellites import sysfile
    from chcos.satellites.satellite import Satellite
    from chcos.system.affinity import pin_process

    stops = {signal.SIGTERM, signal.SIGINT}
    signal.pthread_sigmask(signal.SIG_BLOCK, stops)
    enable_zenoh_logging("warn")  # Zenoh reports refused (unauthenticated) sessions
    sf = sysfile.load(args.system)
    cpus = sf.satellite_cpus.get(args.machine)
    if cpus is not None:  # before Zenoh's and the drivers' threads start (they inherit it)
        pin_process(cpus, f"{sf.path}: [[satellite]] machine {args.machine}: cpus")
    with Satellite(sf, args.machine) as sat:
        sat.start()
        print(f"satellite {args.machine} of {sf.name} up ({len(sat.log)} log entries)",
              flush=True)
        signal.sigwait(stops)
    return 0


def _host(args: argparse.Namespace) -> int:
    from chcos.satellites import sysfile
    from chcos.satellites.host import Host

    sf = sysfile.load(args.system)
    with Host(sf) as host:
        if args.wait:
            host.wait_for(sorted(sf.satellites), timeout=args.wait)
        lines: Iterable[str]
        if args.command:
            lines = [" ".join(args.command)]
        elif args.script:
            lines = Path(args.script).read_text(encoding="utf-8").splitlines()
        else:
            lines = sys.stdin
        return _console(lines, host.execute)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``chcos`` console script; returns the exit status. A reader that goes
    away (``chcos run --help | head -1``) ends the command quietly, as ``cat`` does."""
    try:
        return _dispatch(list(sys.argv[1:] if argv is None else argv))
    except BrokenPipeError:
        # what is still buffered for the closed pipe must not fail again at exit
        import os

        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
        return 1


def _verbose(argv: list[str]) -> list[str]:
    """``-v``/``--verbose`` before the command, or anywhere among ``run``'s arguments: INFO
    messages on; the rest of ``argv``."""
    if argv[:1] in (["-v"], ["--verbose"]):
        logging.getLogger().setLevel(logging.INFO)
        argv = argv[1:]
    if argv[:1] == ["run"] and ("-v" in argv or "--verbose" in argv):
        logging.getLogger().setLevel(logging.INFO)
        argv = [a for a in argv if a not in ("-v", "--verbose")]
    return argv


#: The subcommands another module parses itself: name -> (module, its main, the help line).
#: Imported only when asked for, so ``chcos check`` loads no simulator and no north service.
DELEGATED: dict[str, tuple[str, str, str]] = {
    "new": ("chcos.cli.scaffold", "main", "create a new cell project (chcos new DIR)"),
    "import": ("chcos.devices.importers", "main", "device map from an EDS, a DBC or a Modbus "
               "register list (chcos import eds|dbc|modbus FILE)"),
    "monitor": ("chcos.cli.monitor", "main", "commission a live bus listen-only (chcos monitor "
                "SYSTEM)"),
    "check": ("chcos.cli.check", "main", "validate device-map files (chcos check FILE...) or "
              "system files (chcos check --system FILE...)"),
    "diff": ("chcos.cli.diff", "main", "compare two traces of a run (chcos diff GOLDEN NEW)"),
    "sim": ("chcos.apps.sim.cli", "main", "simulated devices (chcos sim KIND ..., chcos sim "
            "--from MAP)"),
    "map": ("chcos.viewer.cli", "map_main", "draw a sysfile.map (chcos map [MAP] --format "
            "text|dot|svg)"),
    "view": ("chcos.cli.view", "view_main", "live page of a running system (chcos view "
             "--example fig65)"),
    "facade": ("chcos.north.modbus_facade", "facade_main", "north-side facades (chcos facade "
               "modbus --print-map FILE)"),
    "north": ("chcos.north.services", "north_main", "north-side accounts (chcos north passwd: "
              "a password hash)"),
}


def _dispatch(argv: list[str]) -> int:
    """Hand ``argv`` to its subcommand; returns the exit status."""
    # warnings are shown by default (a handler set by an embedding program or pytest is kept)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    argv = _verbose(argv)
    cmd, rest = (argv[0], argv[1:]) if argv else ("", [])
    if cmd == "run":
        return _run(rest)
    if cmd == "sim" and rest[:1] and rest[0].split("=")[0] == "--from":
        from chcos.apps.sim.from_map import main as sim_from_main

        return sim_from_main(rest)
    if cmd in DELEGATED:
        module, func, _help = DELEGATED[cmd]
        sub_main: Callable[[list[str]], int] = getattr(importlib.import_module(module), func)
        return sub_main(rest)
    args = _parser().parse_args(argv)
    if args.verbose:
        logging.getLogger().setLevel(logging.INFO)
    try:
        return int(args.func(args))
    except ChcosError as exc:
        print(f"chcos: {exc}", file=sys.stderr)
        return 1


def _run(rest: list[str]) -> int:
    """``chcos run``: a system file, the welding cell (no file, or ``weld``) or figure 6.5."""
    if rest[:1] in (["-h"], ["--help"]):
        return _run_help()
    if rest[:2] == ["--example", "fig65"] or rest[:1] == ["--example=fig65"]:
        return _run_example(rest[2:] if rest[:1] == ["--example"] else rest[1:])
    if rest[:1] == ["weld"]:
        rest = rest[1:]
    elif rest and not rest[0].startswith("-"):
        from chcos.cli.cellrun import main as cell_main

        return cell_main(rest)
    from chcos.apps.weld.runner import main as weld_main

    return weld_main(rest)


def _parser() -> argparse.ArgumentParser:
    """The parser of the subcommands this module carries out (``shell``, ``satellite``,
    ``host``), listing the others for ``chcos --help``."""
    parser = argparse.ArgumentParser(prog="chcos", description=DESCRIPTION,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    sub = parser.add_subparsers(dest="cmd", required=True, metavar="COMMAND")
    sub.add_parser("run", help="run a system file, the welding cell or figure 6.5 "
                               "(chcos run --help)")
    _shell_parser(sub)
    p = sub.add_parser("satellite", help="run one machine of a multi-process system",
                       description="Run machine N of the system file's satellites in this "
                                   "process (its kernel, tasks and devices) until Ctrl-C or "
                                   "SIGTERM; actuators go to their safe values on the way out.")
    p.add_argument("-m", "--machine", type=int, required=True, metavar="N",
                   help="the machine number (a [[satellite]] of the system file)")
    p.add_argument("--system", required=True, metavar="SYSTEM", help="the system file (TOML)")
    p.set_defaults(func=_satellite)
    p = sub.add_parser("host", help="host commands to a running multi-process system",
                       description="Connect to the satellites of a system file and carry out "
                                   "host commands: one given on the command line, or every "
                                   "line of --script, or stdin.")
    p.add_argument("--system", required=True, metavar="SYSTEM", help="the system file (TOML)")
    p.add_argument("--script", help="read commands from this file")
    p.add_argument("--wait", type=float, default=0.0, metavar="S",
                   help="first wait up to S seconds for every satellite to be up")
    p.add_argument("command", nargs=argparse.REMAINDER, help="one command, e.g. setpri -9 A4 C1")
    p.set_defaults(func=_host)
    for name, (_module, _func, text) in DELEGATED.items():
        sub.add_parser(name, help=text)
    return parser


def _shell_parser(sub: Any) -> None:
    """``chcos shell``'s arguments."""
    p = sub.add_parser("shell", help="host console for an in-process system",
                       description="Build a system from device maps in this process and carry "
                                   "out host commands (install, setpri, invoke, suspend, "
                                   "resume, close, inject, axis, map) from --script or stdin, one "
                                   "per line; 'quit' ends. 'run SECONDS' lets the system run that "
                                   "long (on real time the kernel runs meanwhile anyway; with "
                                   "--virtual only 'run', and an axis command while it waits for "
                                   "the drive, advance the clock). To run "
                                   "a whole cell until Ctrl-C, use 'chcos run SYSTEM'.")
    p.add_argument("devmap", nargs="*", metavar="MAP", help="device-map files")
    p.add_argument("--script", help="read commands from this file instead of stdin")
    p.add_argument("--task-path", action="append", metavar="DIR",
                   help="directory where task code is found (repeatable; default .)")
    p.add_argument("--workdir", metavar="DIR",
                   help="where sysfile.map goes and relative file names start")
    p.add_argument("--base-dir", metavar="DIR",
                   help="relative file names in installs start here (default: --workdir or .)")
    p.add_argument("--map", metavar="FILE",
                   help="where sysfile.map is written (default: --workdir/sysfile.map or "
                        "./sysfile.map)")
    p.add_argument("--virtual", action="store_true",
                   help="virtual time: only 'run SECONDS' advances it")
    p.set_defaults(func=_shell)


if __name__ == "__main__":
    raise SystemExit(main())
