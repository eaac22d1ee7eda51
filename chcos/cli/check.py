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

from chcos.errors import ChcosError

__all__ = ["check_system", "main", "parser"]


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
    from chcos.devices.devmap import check
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
        dmap, errors, warnings = check(list(sf.devmaps))
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
        from chcos.devices.devmap import check_main as check_maps

        status = check_maps(maps)
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
