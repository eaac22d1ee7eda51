"""sysfile - the system file: what one CHC-OS system spread over satellites is made of.

A TOML file (the thesis' ``sysfile``) naming the system, its device maps and task path, and the
satellites with the loopback port each listens on::

    [system]
    name = "fig65"                         # Zenoh key prefix chcos/<name>/...
    devmaps = ["../busconfig/fig65.toml"]  # relative to this file
    task_path = ["tasks"]
    base_dir = "."                         # relative file names in installs start here
    install = "install.chcos"              # optional: host script(s) ``chcos run`` executes

    [[satellite]]
    machine = 0
    port = 17447

    [link]                                 # optional: lease_ms, retry_ms, auth, tls
    [link.auth]                            # Zenoh user/password; a node with a dictionary_file
    user = "host"                          # refuses sessions whose credentials are not in it
    password = "..."
    dictionary_file = "users.txt"

Every node builds its Zenoh configuration from it (:func:`link_config_for`): a satellite listens on
its own port and connects to every other satellite; a host only connects. Everything is on
127.0.0.1 with multicast scouting off (see :mod:`chcos.link.config`).

``chcos run SYSTEM`` runs every machine in one process: it needs no ``[[satellite]]`` table (one
is required only by ``chcos satellite`` and ``chcos host``), and executes ``system.install``, a
host script (``install``, ``setpri``, ``invoke`` lines) or a list of them run in order, before it
starts the clock.
"""

from __future__ import annotations

import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from chcos.errors import ConfigError
from chcos.link.config import LinkConfig, link_config_from_section

_TOP = {"system", "satellite", "link"}
_SYSTEM = {"name", "devmaps", "task_path", "base_dir", "install"}
_SAT = {"machine", "port"}


@dataclass(frozen=True)
class SystemFile:
    """A parsed system file; paths are absolute."""

    path: Path
    name: str
    devmaps: tuple[Path, ...]
    task_path: tuple[Path, ...]
    base_dir: Path
    satellites: dict[int, int]  # machine -> port
    link: Mapping[str, Any] = field(default_factory=dict)
    install: tuple[Path, ...] = ()  # host scripts ``chcos run`` executes (system.install)

    @property
    def prefix(self) -> str:
        """The Zenoh key prefix of this system."""
        return f"chcos/{self.name}"

    def map_path(self, machine: int) -> Path:
        """Where satellite ``machine`` keeps its sysfile.map."""
        return self.base_dir / f"sysfile-m{machine}.map"


def load(path: str | Path) -> SystemFile:
    """Read and check a system file. Raises ConfigError naming the file, the key and what was
    expected."""
    path = Path(path).resolve()
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read system file: {exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    base = path.parent

    def fail(key: str, what: str) -> ConfigError:
        return ConfigError(f"{path}: {key}: {what}")

    for key in doc:
        if key not in _TOP:
            raise fail(key, f"unknown key, expected one of {', '.join(sorted(_TOP))}")
    sys_sec = doc.get("system")
    if not isinstance(sys_sec, dict):
        raise fail("system", "missing [system] table")
    for key in sys_sec:
        if key not in _SYSTEM:
            raise fail(f"system.{key}",
                       f"unknown key, expected one of {', '.join(sorted(_SYSTEM))}")
    name = sys_sec.get("name")
    if not isinstance(name, str) or not name.replace("-", "").replace("_", "").isalnum():
        raise fail("system.name", "expected a name of letters, digits, - and _")

    def paths(key: str) -> tuple[Path, ...]:
        v = sys_sec.get(key, [])
        if not isinstance(v, list) or not all(isinstance(p, str) for p in v):
            raise fail(f"system.{key}", "expected a list of paths")
        return tuple((base / p).resolve() for p in v)

    base_dir = sys_sec.get("base_dir", ".")
    if not isinstance(base_dir, str):
        raise fail("system.base_dir", "expected a path")
    sats: dict[int, int] = {}
    entries = doc.get("satellite", [])
    if not isinstance(entries, list):
        raise fail("satellite", "expected [[satellite]] tables")
    for i, sat in enumerate(entries):
        where = f"satellite[{i}]"
        if not isinstance(sat, dict):
            raise fail(where, "expected a table")
        for key in sat:
            if key not in _SAT:
                raise fail(f"{where}.{key}", "unknown key, expected machine and port")
        m, port = sat.get("machine"), sat.get("port")
        if not isinstance(m, int) or isinstance(m, bool) or m < 0:
            raise fail(f"{where}.machine", "expected a machine number >= 0")
        if not isinstance(port, int) or isinstance(port, bool) or not 1 <= port <= 65535:
            raise fail(f"{where}.port", "expected a TCP port 1..65535")
        if m in sats:
            raise fail(f"{where}.machine", f"machine {m} named twice")
        if port in sats.values():
            raise fail(f"{where}.port", f"port {port} used twice")
        sats[m] = port
    link = doc.get("link", {})
    if not isinstance(link, dict) or "listen" in link or "connect" in link:
        raise fail("link", "expected a table without listen/connect (ports come from "
                           "[[satellite]])")
    install = sys_sec.get("install", [])
    if isinstance(install, str):
        install = [install]
    if not isinstance(install, list) or not all(isinstance(p, str) for p in install):
        raise fail("system.install", "expected the path of a host script, or a list of them")
    sf = SystemFile(path, name, paths("devmaps"), paths("task_path"), (base / base_dir).resolve(),
                    sats, link, tuple((base / p).resolve() for p in install))
    if sats:  # a single-process system (no [[satellite]]) opens no link
        link_config_for(sf, None)  # check the [link] section now
    return sf


def link_config_for(sf: SystemFile, machine: int | None) -> LinkConfig:
    """The Zenoh configuration of satellite ``machine`` (None: a host, which only connects).
    Raises ConfigError for a bad [link] section."""
    section: dict[str, Any] = dict(sf.link)
    if machine is not None:
        section["listen"] = sf.satellites[machine]
    section["connect"] = [p for m, p in sorted(sf.satellites.items()) if m != machine]
    return link_config_from_section(section, where=f"{sf.path}: link", base_dir=sf.path.parent)
