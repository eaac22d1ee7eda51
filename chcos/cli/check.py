"""check - ``chcos check``: validate device maps and system files without opening anything.

``chcos check FILE...`` checks device maps together (:func:`chcos.devices.devmap.check`);
``chcos check --system SYSTEM...`` checks each system file: its keys, its satellites and their
link settings when it has any (a system run by ``chcos run`` in one process needs none), and the
device maps it names, checked together as ``chcos check`` would. Every problem is a line naming
the file; nothing ends in a traceback.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from chcos.devices.spec import BusSpec, DeviceMap
from chcos.errors import ChcosError

__all__ = ["check_maps", "check_system", "main", "parser", "shared_multicast_ports"]

UDP_DEFAULT_PORT = 43113
"""python-can's udp_multicast port when a bus names none."""


def shared_multicast_ports(dmap: DeviceMap) -> list[str]:
    """A warning per pair of ``udp_multicast`` buses on one UDP port: a socket bound to a port
    hears every group joined on it, so each bus would receive the other's frames. Give each bus
    its own group and port."""
    by_port: dict[int, list[BusSpec]] = {}
    for bus in dmap.buses:
        if bus.kind in ("can", "canopen") and bus.options.get("interface") == "udp_multicast":
            port = bus.options.get("port", UDP_DEFAULT_PORT)
            by_port.setdefault(port if isinstance(port, int) else -1, []).append(bus)
    return [f"{later.file}: {later.key} ({later.name}): udp_multicast port {port} is also "
            f"bus {buses[0].name}'s ({buses[0].file}): each would hear the other's frames; "
            "give every bus its own port (and group)"
            for port, buses in by_port.items() if port > 0 for later in buses[1:]]


def check_maps(paths: Sequence[str | Path]) -> tuple[DeviceMap | None, list[str], list[str]]:
    """:func:`chcos.devices.devmap.check` plus :func:`shared_multicast_ports`' warnings."""
    from chcos.devices.devmap import check

    dmap, errors, warnings = check(list(paths))
    if dmap is not None:
        warnings = [*warnings, *shared_multicast_ports(dmap)]
    return dmap, errors, warnings


def parser() -> argparse.ArgumentParser:
    """The command line of ``chcos check``."""
    ap = argparse.ArgumentParser(
        prog="chcos check",
        description="Validate device-map files (no bus is opened; warns about maps that are "
                    "legal but misbehave), or with --system the system files and the device "
                    "maps they name. Exit status 0: valid; 1: an error (each names its file).")
    ap.add_argument("files", nargs="*", metavar="FILE", help="device-map TOML files, checked "
                                                            "together")
    ap.add_argument("--system", action="append", default=[], metavar="SYSTEM",
                    help="a system file (TOML) to check with its device maps (repeatable; "
                         "'--system A B' checks both)")
    return ap


def check_system(path: str) -> tuple[list[str], list[str], str]:
    """Check one system file: returns ``(errors, warnings, summary)``; never raises for a bad
    file (each problem is a line naming it)."""
    from chcos.satellites import sysfile

    try:
        sf = sysfile.load(path)
    except ChcosError as exc:
        return [str(exc)], [], ""
    auth = ""
    if sf.satellites:
        try:
            cfg = sysfile.link_config_for(sf, None)
        except ChcosError as exc:
            return [str(exc)], [], ""
        auth = ("mutual TLS" if cfg.tls is not None and cfg.tls.enable_mtls
                else "TLS + user/password" if cfg.tls is not None
                else "user/password" if cfg.auth is not None else "the system secret")
    errors: list[str] = []
    warnings: list[str] = []
    devices = 0
    if sf.devmaps:
        dmap, errors, warnings = check_maps(list(sf.devmaps))
        devices = len(dmap.devices) if dmap is not None else 0
    if sf.satellites:
        where = ", ".join(f"{m}@{sf.host_of(m)}:{p}" for m, p in sorted(sf.satellites.items()))
        how = f"satellites {where}; peers authenticated by {auth}"
    else:
        how = "one process (no [[satellite]]: chcos run, not chcos satellite)"
    summary = (f"ok: system {sf.name} ({path}): {how}; {len(sf.devmaps)} device map(s), "
               f"{devices} devices")
    return errors, warnings, summary


def main(argv: Sequence[str]) -> int:
    """``chcos check``; returns the exit status (0 valid, 1 an error, 2 a bad command line)."""
    ap = parser()
    args = ap.parse_args(list(argv))
    # "chcos check --system A B": every file is a system file, as the form always had it
    systems: list[str] = list(args.system)
    maps: list[str] = list(args.files)
    if list(argv)[:1] == ["--system"]:
        systems += maps
        maps = []
    if not systems and not maps:
        ap.error("expected device-map files or --system SYSTEM")
    status = 0
    if maps:
        dmap, errors, warnings = check_maps(maps)
        for w in warnings:
            print(f"warning: {w}", file=sys.stderr)
        if dmap is None:
            print(f"{len(errors)} error(s) in device map {', '.join(maps)}:\n"
                  + "\n".join(errors), file=sys.stderr)
            status = 1
        else:
            print(f"ok: {len(dmap.buses)} buses, {len(dmap.devices)} devices"
                  + (f", {len(warnings)} warning(s)" if warnings else ""))
    for path in systems:
        errors, warnings, summary = check_system(path)
        for w in warnings:
            print(f"warning: {w}", file=sys.stderr)
        if errors:
            print(f"{len(errors)} error(s) in system {path}:\n" + "\n".join(errors),
                  file=sys.stderr)
            status = 1
        else:
            print(summary + (f", {len(warnings)} warning(s)" if warnings else ""))
    return status
