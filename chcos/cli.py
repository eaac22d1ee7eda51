"""cli - the ``chcos`` command.

``chcos run``     the main job: the arc-welding cell end to end (``--example fig65``: the thesis'
                  figure 6.5 system)
``chcos shell``   a host console: an in-process system that reads host commands (install,
                  setpri, invoke, suspend, resume, close, inject, map) from a script or stdin
``chcos check``   validate device-map files without touching a bus
``chcos map``     draw a sysfile.map as the hierarchy (text, dot or svg)
``chcos view``    serve a live page of a running system on 127.0.0.1
``chcos sim``     simulated field devices (CAN, CANopen, Modbus, serial)
``chcos satellite -m N --system FILE``  run machine N of a multi-satellite system
``chcos host --system FILE [COMMAND...]``  host commands to a running multi-satellite system
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

from chcos.errors import ChcosError


def _run_example(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="chcos run --example fig65",
                                 description="the thesis' figure 6.5 example system")
    ap.add_argument("--duration", type=float, default=20.0, help="seconds of clock time")
    ap.add_argument("--real-time", action="store_true", help="wall-clock time, not virtual")
    ap.add_argument("--workdir", help="where the map, log and test file go (default out/fig65)")
    args = ap.parse_args(argv)
    from chcos import fig65run

    fig65run.run(args.duration, real_time=args.real_time,
                 workdir=Path(args.workdir) if args.workdir else None)
    return 0


def _shell(args: argparse.Namespace) -> int:
    from chcos.clock import RealClock, VirtualClock
    from chcos.system import System

    clock = VirtualClock() if args.virtual else RealClock()
    system = System(args.devmap, clock=clock, task_path=args.task_path or ["."],
                    base_dir=args.base_dir, map_path=args.map)
    lines: Iterable[str] = (Path(args.script).read_text(encoding="utf-8").splitlines()
                            if args.script else sys.stdin)
    if not args.virtual:
        system.start()
    def execute(line: str) -> str:
        if line.strip().startswith("run ") and args.virtual:
            system.run_for(float(line.split()[1]))
            return ""
        return system.execute(line)

    try:
        return _console(lines, execute)
    finally:
        system.shutdown()


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

    from chcos import sysfile
    from chcos.link.transport import enable_zenoh_logging
    from chcos.satellite import Satellite

    stops = {signal.SIGTERM, signal.SIGINT}
    signal.pthread_sigmask(signal.SIG_BLOCK, stops)
    enable_zenoh_logging("warn")  # Zenoh reports refused (unauthenticated) sessions
    sf = sysfile.load(args.system)
    with Satellite(sf, args.machine) as sat:
        sat.start()
        print(f"satellite {args.machine} of {sf.name} up ({len(sat.log)} log entries)",
              flush=True)
        signal.sigwait(stops)
    return 0


def _host(args: argparse.Namespace) -> int:
    from chcos import sysfile
    from chcos.host import Host

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
    """Entry point of the ``chcos`` console script; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:2] == ["check", "--system"]:
        from chcos.sysfile import check_main as check_system

        return check_system(argv[2:])
    if argv[:1] == ["check"]:
        from chcos.devmap import check_main

        return check_main(argv[1:])
    if argv[:1] == ["sim"]:
        from chcos.sim.cli import main as sim_main

        return sim_main(argv[1:])
    if argv[:1] == ["run"]:
        rest = argv[1:]
        if rest[:2] == ["--example", "fig65"] or rest[:1] == ["--example=fig65"]:
            return _run_example(rest[2:] if rest[:1] == ["--example"] else rest[1:])
        from chcos.weldrun import main as weld_main

        return weld_main(rest)
    if argv[:1] == ["map"]:
        from chcos.viewer.cli import map_main

        return map_main(argv[1:])
    if argv[:1] == ["view"]:
        from chcos.viewer.cli import view_main

        return view_main(argv[1:])
    parser = argparse.ArgumentParser(prog="chcos", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    sub = parser.add_subparsers(dest="cmd", required=True)
    sub.add_parser("run", help="the main job: the arc-welding cell (chcos run --help); "
                               "--example fig65 runs the thesis' figure 6.5 system")
    p = sub.add_parser("shell", help="host console for an in-process system")
    p.add_argument("devmap", nargs="*", help="device-map files")
    p.add_argument("--script", help="read commands from this file instead of stdin")
    p.add_argument("--task-path", action="append", help="directory of task modules")
    p.add_argument("--base-dir", default=".", help="relative file names start here")
    p.add_argument("--map", default="sysfile.map", help="where sysfile.map is written")
    p.add_argument("--virtual", action="store_true",
                   help="virtual time: the script advances it with 'run SECONDS'")
    p.set_defaults(func=_shell)
    p = sub.add_parser("satellite", help="run one machine of a multi-satellite system")
    p.add_argument("-m", "--machine", type=int, required=True)
    p.add_argument("--system", required=True, help="the system file (TOML)")
    p.set_defaults(func=_satellite)
    p = sub.add_parser("host", help="host commands to a running multi-satellite system")
    p.add_argument("--system", required=True, help="the system file (TOML)")
    p.add_argument("--script", help="read commands from this file")
    p.add_argument("--wait", type=float, default=0.0,
                   help="first wait this many seconds for every satellite to be up")
    p.add_argument("command", nargs=argparse.REMAINDER, help="one command, e.g. setpri -9 A4 C1")
    p.set_defaults(func=_host)
    sub.add_parser("map", help="draw a sysfile.map (chcos map [MAP] --format text|dot|svg)")
    sub.add_parser("view", help="live page of a running system (chcos view --example fig65)")
    sub.add_parser("check", help="validate device-map files (chcos check FILE...) or system "
                                 "files (chcos check --system FILE...)")
    sub.add_parser("sim", help="simulated field devices (chcos sim KIND ...)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.ERROR,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args))
    except ChcosError as exc:
        print(f"chcos: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
