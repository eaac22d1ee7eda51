"""sysfile - the system file: what one CHC-OS system spread over satellites is made of.

A TOML file (the thesis' ``sysfile``) naming the system, its device maps and task path, and the
satellites with the loopback port each listens on::

    [system]
    name = "fig65"                         # Zenoh key prefix chcos/<name>/...
    devmaps = ["maps/fig65.toml"]          # relative to this file
    task_path = ["tasks"]
    base_dir = "."                         # relative file names in installs start here
    install = "install.chcos"              # optional: host script(s) ``chcos run`` executes
    state_dir = "/var/lib/chcos"           # optional: run state goes to <state_dir>/<name>/
    secret_file = "fig65.secret"           # optional: default <state_dir>/<name>/secret.json
    cpus = [1]                             # optional: ``chcos run`` pins its process to these

    [[satellite]]
    machine = 0
    port = 17447
    host = "127.0.0.1"                     # optional: its address (IPv4, IPv6 or a name)
    cpus = [0]                             # optional: the satellite pins its process to these

    [link]                                 # optional: lease_ms, retry_ms, auth, tls
    [link.auth]                            # Zenoh user/password; a node with a dictionary_file
    user = "host"                          # refuses sessions whose credentials are not in it
    password = "..."
    dictionary_file = "users.txt"

Every node builds its Zenoh configuration from it (:func:`link_config_for`): a satellite listens on
its own address and port and connects to every satellite of a lower machine number (one TCP/TLS
connection per pair: with authentication on, Zenoh refuses the second session a pair would
open if both sides connected, and the refused side would retry it every second for ever --
eclipse-zenoh/zenoh issue 2577); a host
only connects, to every satellite. Multicast scouting is off (see :mod:`chcos.comm.config`).

Security (see README "Security"): without ``[link.auth]`` every node authenticates with the
system's secret (:mod:`chcos.comm.secret`, generated on first use in the state directory), and
without ``[link.tls]`` a loopback system talks mutual TLS with certificates of its own, made on
first use by the openssl tool in ``<state_dir>/<name>/tls/`` (so that a local process that takes
a stopped satellite's port can neither pass for it nor read what is sent to it);
a system with a satellite on a non-loopback address is refused unless ``[link.tls]`` has mutual
TLS (or TLS plus ``[link.auth]`` with a dictionary); ``[link.auth]`` without
``dictionary_file`` is refused. Run state (each satellite's sysfile.map) lives in
``<state_dir>/<name>/`` (default ``$CHCOS_STATE_DIR``, else ``$XDG_STATE_HOME/chcos``, else
``~/.local/state/chcos``), never beside the task sources, and one system never adopts another's.

``chcos run SYSTEM`` runs every machine in one process: it needs no ``[[satellite]]`` table (one
is required only by ``chcos satellite`` and ``chcos host``), and executes ``system.install``, a
host script (``install``, ``setpri``, ``invoke`` lines) or a list of them run in order, before it
starts the clock.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from chcos.comm.config import (
    LOOPBACK,
    LinkConfig,
    TlsSettings,
    UsrPwdAuth,
    check_host,
)
from chcos.comm.secret import SystemSecret, load_or_create, loopback_pki
from chcos.comm.section import link_config_from_section
from chcos.errors import ConfigError
from chcos.helpers import load_toml
from chcos.system.affinity import parse_cpus

log = logging.getLogger("chcos.satellites.sysfile")

_TOP = {"system", "satellite", "link"}
_SYSTEM = {"name", "devmaps", "task_path", "base_dir", "state_dir", "secret_file",
           "install", "cpus"}
_SAT = {"machine", "port", "host", "cpus"}


def default_state_base() -> Path:
    """Where run state goes when the system file names no ``state_dir``: ``$CHCOS_STATE_DIR``,
    else ``$XDG_STATE_HOME/chcos``, else ``~/.local/state/chcos``."""
    if os.environ.get("CHCOS_STATE_DIR"):
        return Path(os.environ["CHCOS_STATE_DIR"]).resolve()
    xdg = os.environ.get("XDG_STATE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".local" / "state") / "chcos"


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
    hosts: dict[int, str] = field(default_factory=dict)  # machine -> address (default loopback)
    state_base: Path | None = None
    secret_file: Path | None = None
    install: tuple[Path, ...] = ()  # host scripts ``chcos run`` executes (system.install)
    #: the CPUs ``chcos run`` pins its process to (system.cpus; None: not pinned)
    cpus: frozenset[int] | None = None
    #: machine -> the CPUs that satellite pins its process to ([[satellite]] cpus)
    satellite_cpus: dict[int, frozenset[int]] = field(default_factory=dict)

    @property
    def prefix(self) -> str:
        """The Zenoh key prefix of this system."""
        return f"chcos/{self.name}"

    @property
    def state_dir(self) -> Path:
        """This system's own run-state directory, ``<state_dir>/<name>``."""
        return (self.state_base or default_state_base()) / self.name

    def map_path(self, machine: int) -> Path:
        """Where satellite ``machine`` keeps its sysfile.map (in the state directory)."""
        return self.state_dir / f"m{machine}.map"

    def host_of(self, machine: int) -> str:
        """The address satellite ``machine`` listens on."""
        return self.hosts.get(machine, LOOPBACK)

    def secret(self) -> SystemSecret:
        """The system's secret, generated on first use (mode 0600). Raises ConfigError if the
        file belongs to another system or is readable by others."""
        return load_or_create(self.secret_file or self.state_dir / "secret.json", self.name)


def load(path: str | Path) -> SystemFile:
    """Read and check a system file. Raises ConfigError naming the file, the key and what was
    expected."""
    path = Path(path).resolve()
    doc = load_toml(path, "system file")
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
    def opt_dir(key: str) -> Path | None:
        v = sys_sec.get(key)
        if v is None:
            return None
        if not isinstance(v, str) or not v:
            raise fail(f"system.{key}", "expected a path")
        return (base / v).resolve()

    sats: dict[int, int] = {}
    hosts: dict[int, str] = {}
    cpus_of: dict[int, frozenset[int]] = {}
    entries = doc.get("satellite", [])
    if not isinstance(entries, list):
        raise fail("satellite", "expected [[satellite]] tables")
    for i, sat in enumerate(entries):
        where = f"satellite[{i}]"
        if not isinstance(sat, dict):
            raise fail(where, "expected a table")
        for key in sat:
            if key not in _SAT:
                raise fail(f"{where}.{key}", "unknown key, expected machine, port, host and cpus")
        m, port = sat.get("machine"), sat.get("port")
        if not isinstance(m, int) or isinstance(m, bool) or m < 0:
            raise fail(f"{where}.machine", "expected a machine number >= 0")
        if not isinstance(port, int) or isinstance(port, bool) or not 1 <= port <= 65535:
            raise fail(f"{where}.port", "expected a TCP port 1..65535")
        if m in sats:
            raise fail(f"{where}.machine", f"machine {m} named twice")
        host = sat.get("host", LOOPBACK)
        try:
            check_host(f"{where}.host", host)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from exc
        if (host, port) in {(hosts[k], p) for k, p in sats.items()}:
            raise fail(f"{where}.port", f"port {port} used twice")
        sats[m] = port
        hosts[m] = host
        sat_cpus = parse_cpus(sat.get("cpus"), f"{path}: {where}.cpus")
        if sat_cpus is not None:
            cpus_of[m] = sat_cpus
    link = doc.get("link", {})
    if not isinstance(link, dict) or {"listen", "connect", "listen_host",
                                      "connect_hosts"} & set(link):
        raise fail("link", "expected a table without listen/connect (ports and addresses come "
                           "from [[satellite]])")
    auth = link.get("auth")
    if isinstance(auth, dict) and "dictionary_file" not in auth:
        raise fail("link.auth.dictionary_file",
                   "missing: a satellite with [link.auth] but no dictionary file accepts no "
                   "peer (the mesh never forms); add dictionary_file = \"users.txt\" with a "
                   "user:password line for each node, or drop [link.auth] to use the "
                   "system's generated secret")
    install = sys_sec.get("install", [])
    if isinstance(install, str):
        install = [install]
    if not isinstance(install, list) or not all(isinstance(p, str) for p in install):
        raise fail("system.install", "expected the path of a host script, or a list of them")
    sf = SystemFile(path, name, paths("devmaps"), paths("task_path"), (base / base_dir).resolve(),
                    sats, link, hosts, opt_dir("state_dir"), opt_dir("secret_file"),
                    tuple((base / p).resolve() for p in install),
                    parse_cpus(sys_sec.get("cpus"), f"{path}: system.cpus"), cpus_of)
    # a single-process system (no [[satellite]]) opens no link; else check the [link] section
    # and what each node exposes now
    for m in ([None, *sats] if sats else []):
        cfg = link_config_for(sf, m)
        cfg.check_exposure(f"{path}: " + ("host" if m is None else f"satellite {m}")
                           + f" ({', '.join(cfg.exposed)})")
    return sf


def link_config_for(sf: SystemFile, machine: int | None,
                    secret: SystemSecret | None = None) -> LinkConfig:
    """The Zenoh configuration of satellite ``machine`` (None: a host, which only connects):
    it listens on its own address and connects to the satellites of lower machine numbers.
    Without a [link.auth] section and with the system's ``secret``, the node authenticates with
    the user/password of its role and checks peers against the secret's dictionary. Raises
    ConfigError for a bad [link] section."""
    from dataclasses import replace

    section: dict[str, Any] = dict(sf.link)
    if machine is not None:
        section["listen"] = sf.satellites[machine]
    others = [m for m in sorted(sf.satellites) if machine is None or m < machine]
    section["connect"] = [sf.satellites[m] for m in others]
    section["connect_hosts"] = [sf.host_of(m) for m in others]
    if machine is not None:
        section["listen_host"] = sf.host_of(machine)
    cfg = link_config_from_section(section, where=f"{sf.path}: link", base_dir=sf.path.parent)
    changes: dict[str, Any] = {}
    if secret is not None and "auth" not in sf.link:
        role = "host" if machine is None else "satellite"
        changes["auth"] = UsrPwdAuth(role, secret.password(role), secret.dictionary())
    if secret is not None and "tls" not in sf.link and not cfg.exposed:
        files = loopback_pki(sf.state_dir, sf.name)
        if files is None:
            log.warning("%s: no openssl tool to make the loopback TLS certificates: peers "
                        "authenticate by user/password and seals only (install openssl to "
                        "have mutual TLS on loopback too)", sf.path)
        else:
            ca, cert, key = files
            changes["tls"] = TlsSettings(ca, cert, key, cert, key, enable_mtls=True)
    try:
        return replace(cfg, **changes)
    except ConfigError as exc:
        raise ConfigError(f"{sf.path}: link: {exc}") from exc


def check_main(argv: list[str]) -> int:
    """``chcos check --system FILE...``: validate system files (keys, satellites, exposure: a
    non-loopback satellite without mutual TLS or TLS plus a user dictionary is refused, saying
    what to add) without starting anything. Prints one ``ok`` line per file and returns 0, or
    prints the error and returns 1."""
    import sys

    if not argv:
        print("chcos check --system FILE...: expected at least one system file", file=sys.stderr)
        return 1
    for arg in argv:
        try:
            sf = load(arg)
        except ConfigError as exc:
            print(str(exc), file=sys.stderr)
            return 1
        cfg = link_config_for(sf, None)
        auth = ("mutual TLS" if cfg.tls is not None and cfg.tls.enable_mtls
                else "TLS + user/password" if cfg.tls is not None
                else "user/password" if cfg.auth is not None else "the system secret")
        where = ", ".join(f"{m}@{sf.host_of(m)}:{p}" for m, p in sorted(sf.satellites.items()))
        print(f"ok: system {sf.name}: satellites {where}; peers authenticated by {auth}; "
              f"state in {sf.state_dir}")
    return 0
