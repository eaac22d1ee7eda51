"""cli - ``chcos map`` (a sysfile.map drawn as text, dot or SVG) and ``chcos view`` (live page).

``chcos map [MAP] [--format text|dot|svg] [-o FILE] [--implicit]``
    reads a sysfile.map (default ./sysfile.map) and prints the hierarchy, levels top to bottom.

``chcos view [MAP | --example NAME] [--port 0] [--invoke TASK]... [--duration S] [--terminal]
[--users FILE]``
    rebuilds the system from MAP (or builds a named example the caller supplies, see
    :data:`ExampleBuilder`; ``chcos view --example fig65`` is :mod:`chcos.cli.view`), runs it on
    real time, and
    serves the live page on 127.0.0.1 (port 0: a free one); prints the URL. Read-only unless
    ``--users`` names a users file (operator credentials). ``--terminal`` also
    redraws the hierarchy as text, with message rates, once a second.

``chcos view --system SYSTEM.toml [--users FILE]``
    attaches to running satellites through the host's link (see :mod:`chcos.viewer.remote`)
    instead of running a system here.
"""

from __future__ import annotations

import argparse
import sys
import threading
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple, TextIO, cast

from chcos.errors import ChcosError
from chcos.kernel.clock import Clock
from chcos.system import sysmap
from chcos.viewer import ViewerError
from chcos.viewer.graph import render_dot, render_svg

if TYPE_CHECKING:
    from chcos.system.embedded import System
    from chcos.viewer.server import Viewer


def map_main(argv: Sequence[str], out: TextIO | None = None) -> int:
    """``chcos map``: print a sysfile.map as text, dot or SVG; returns the exit status (1 with
    a message on stderr if the map cannot be read)."""
    from chcos.system.textview import render_text

    out = out or sys.stdout
    p = argparse.ArgumentParser(prog="chcos map", description="Draw a sysfile.map: levels top "
                                "to bottom, tasks with machine, status, owner and priority, "
                                "links with type and priority.")
    p.add_argument("map", nargs="?", default="sysfile.map", help="the map (./sysfile.map)")
    p.add_argument("--format", "-f", choices=("text", "dot", "svg"), default="text")
    p.add_argument("-o", "--output", help="write to this file instead of stdout")
    p.add_argument("--implicit", action="store_true",
                   help="also draw implicit links (exception taps, assassin and host links)")
    args = p.parse_args(list(argv))
    try:
        doc = sysmap.read(args.map)
        if args.format == "text":
            body = render_text(doc, implicit=args.implicit) + "\n"
        elif args.format == "dot":
            body = render_dot(doc, args.implicit)
        else:
            body = render_svg(doc, implicit=args.implicit) + "\n"
        if args.output:
            Path(args.output).write_text(body, encoding="utf-8")
        else:
            out.write(body)
    except (ChcosError, OSError) as exc:
        print(f"chcos map: {exc}", file=sys.stderr)
        return 1
    return 0


class Example(NamedTuple):
    """A system to view by name (``chcos view --example NAME``): the built system (not yet
    started), the host script to run on it before it starts (or None), the tasks to invoke once
    it runs."""

    system: System
    script: Path | None
    invokes: list[str]


ExampleBuilder = Callable[[Clock, Path], Example]
"""Builds an :class:`Example` on a clock with its files in a work directory; raises ChcosError
if it cannot. The command line (:mod:`chcos.cli.view`) supplies the applications' builders: the
viewer itself knows no application."""


def _build(args: argparse.Namespace, examples: Mapping[str, ExampleBuilder]
           ) -> tuple[System, Path | None, list[str]]:
    """The system to view (on real time), the host script to run on it before it starts, and
    the tasks to invoke once it runs. Raises ChcosError if it cannot be built."""
    from chcos.kernel.clock import RealClock
    from chcos.system.embedded import System

    if args.example:
        workdir = Path(args.workdir or f"out/{args.example}")
        workdir.mkdir(parents=True, exist_ok=True)
        ex = examples[args.example](RealClock(), workdir)
        return ex.system, ex.script, list(args.invoke or ex.invokes)
    path = Path(args.map or "sysfile.map")
    system = System.from_map(path, clock=RealClock(),
                             map_path=Path(args.workdir) / "sysfile.map" if args.workdir
                             else None)
    return system, None, list(args.invoke or [])


def view_main(argv: Sequence[str], *, examples: Mapping[str, ExampleBuilder] | None = None,
              stop: threading.Event | None = None,
              on_ready: Callable[[Viewer], None] | None = None, out: TextIO | None = None
              ) -> int:
    """``chcos view``: run a system on real time and serve its live page until ``--duration``
    passes, Ctrl-C, or ``stop`` is set; ``on_ready(viewer)`` is called once the page is up.
    ``examples`` are the systems ``--example NAME`` may build. Returns the exit status (1 with a
    message on stderr if the system or server cannot start)."""
    from chcos.system.textview import render_text
    from chcos.viewer.server import Viewer
    from chcos.viewer.snapshot import EventLog, Snapshotter

    out = out or sys.stdout
    p = argparse.ArgumentParser(prog="chcos view", description="Serve the live hierarchy of a "
                                "running system on a web page (and the terminal).")
    p.add_argument("map", nargs="?", help="sysfile.map to rebuild the system from")
    examples = dict(examples or {})
    p.add_argument("--example", choices=sorted(examples),
                   help="view a named example system (" + (", ".join(sorted(examples)) or "none")
                        + ")")
    p.add_argument("--system", metavar="FILE",
                   help="attach to the running satellites of this system file through the "
                        "host's (authenticated) link instead of running a system here")
    p.add_argument("--workdir", help="where the example's files and the map go")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (127.0.0.1)")
    p.add_argument("--port", type=int, default=0, help="port (0: a free one)")
    p.add_argument("--invoke", action="append", help="invoke this task once running")
    p.add_argument("--period", type=float, default=0.1, help="seconds between snapshots")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--terminal", action="store_true",
                   help="also redraw the hierarchy as text on the terminal once a second")
    p.add_argument("--users", metavar="FILE",
                   help="operator credentials (a users file, see chcos.north.auth): who may log "
                        "in on the page and issue setpri/invoke; without it the page is "
                        "read-only")
    p.add_argument("--read-only", action="store_true",
                   help="refuse commands from the page even with --users")
    args = p.parse_args(list(argv))
    if sum(bool(x) for x in (args.map, args.example, args.system)) > 1:
        p.error("give one of a map, --example or --system")
    if args.system:
        return _view_remote(args, stop, on_ready, out)
    stop = stop or threading.Event()
    system: System | None = None
    viewer: Viewer | None = None
    try:
        system, script, invokes = _build(args, examples)
        events = EventLog(system.kernel.clock)
        system.kernel.add_instrument(events)
        if script is not None:
            system.run_script(script)
        system.start()
        for task in invokes:
            print(f"host: {system.execute(f'invoke {task}')}", file=out)
        users = None
        if args.users and not args.read_only:
            from chcos.serving.auth import Users

            users = Users.from_file(args.users)
        viewer = Viewer(system, args.host, args.port, period=args.period, events=events,
                        users=users).start()
        print(f"chcos view: serving {viewer.url}", file=out, flush=True)
        if on_ready is not None:
            on_ready(viewer)
        clock = system.kernel.clock
        end = None if args.duration is None else clock.now() + args.duration
        terminal = Snapshotter(system, events) if args.terminal else None
        while True:
            if terminal is not None:  # its own snapshotter: the page's runs on its own thread
                snap = terminal.take(None, svg=False)
                out.write("\x1b[H\x1b[2J" + render_text(snap["map"], rates=snap["rates"])
                          + f"\n\n{viewer.url}\n")
                out.flush()
            left = None if end is None else end - clock.now()
            if left is not None and left <= 0:
                break
            wait = 1.0 if terminal is not None else left
            if stop.wait(wait if left is None or wait is None else min(wait, left)):
                break
    except KeyboardInterrupt:
        pass
    except (ChcosError, OSError) as exc:
        print(f"chcos view: {exc}", file=sys.stderr)
        return 1
    finally:
        if viewer is not None:
            viewer.stop()
        if system is not None:
            system.shutdown()
    return 0


def _view_remote(args: argparse.Namespace, stop: threading.Event | None,
                 on_ready: Callable[[Viewer], None] | None, out: TextIO) -> int:
    """``chcos view --system FILE``: serve the page of running satellites until stopped."""
    from chcos.satellites import sysfile
    from chcos.satellites.host import Host
    from chcos.viewer.remote import HostSystem
    from chcos.viewer.server import Viewer
    from chcos.viewer.snapshot import EventLog

    stop = stop or threading.Event()
    host: Host | None = None
    viewer: Viewer | None = None
    try:
        host = Host(sysfile.load(args.system))
        remote = HostSystem(host)
        events = EventLog(remote.kernel.clock)
        remote.kernel.add_instrument(events)
        remote.map_doc()  # fails early (LinkError) if no satellite answers
        users = None
        if args.users and not args.read_only:
            from chcos.serving.auth import Users

            users = Users.from_file(args.users)
        # duck-typed: the viewer reads only map_doc, execute, the clock and the event hook
        viewer = Viewer(cast("System", remote), args.host, args.port,
                        period=max(args.period, 0.25), events=events, users=users).start()
        print(f"chcos view: serving {viewer.url} (satellites of {args.system})", file=out,
              flush=True)
        if on_ready is not None:
            on_ready(viewer)
        stop.wait(args.duration)
    except KeyboardInterrupt:
        pass
    except (ChcosError, OSError) as exc:
        print(f"chcos view: {exc}", file=sys.stderr)
        return 1
    finally:
        if viewer is not None:
            viewer.stop()
        if host is not None:
            host.close()
    return 0


__all__ = ["Example", "ExampleBuilder", "ViewerError", "map_main", "view_main"]
