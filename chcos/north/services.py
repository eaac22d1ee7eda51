"""services - start the north-side services of a running system from one set of options.

``chcos run`` (and any runner) calls :func:`add_north_arguments` on its argument parser and
:func:`start` with the running :class:`~chcos.system.embedded.System`; :meth:`NorthHandle.stop`
ends them
all. Flags (every address is loopback unless given; a service not named does not start):

``--metrics [HOST:PORT]``        Prometheus endpoint (default 127.0.0.1:9464)
``--modbus-facade [HOST:PORT]``  Modbus TCP facade (default 127.0.0.1:5020)
``--opcua [ENDPOINT]``           OPC UA server (default opc.tcp://127.0.0.1:4840/chcos/)
``--view [HOST:PORT]``           the live page (default 127.0.0.1:8765)
``--north-users FILE``           accounts and roles (:mod:`chcos.north.auth`): without it the
                                 view and OPC UA are read-only
``--metrics-token FILE``         bearer token scrapers must send (required off loopback)
``--north-tls-cert/--north-tls-key``  certificate and key (PEM): TLS for the metrics endpoint
                                 and the view, the OPC UA server certificate (Basic256Sha256);
                                 required for any address off loopback
``--modbus-allow-remote``        let the Modbus facade bind off loopback (Modbus has neither
                                 authentication nor TLS, so this is never implied)

``chcos north passwd`` reads a password (twice, from the terminal, or once from stdin) and prints
the hash for a users file.
"""

from __future__ import annotations

import argparse
import getpass
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TextIO

from chcos.north import NorthError

if TYPE_CHECKING:
    from chcos.serving.auth import Users
    from chcos.system.embedded import System

DEFAULTS = {"metrics": "127.0.0.1:9464", "modbus_facade": "127.0.0.1:5020",
            "opcua": "opc.tcp://127.0.0.1:4840/chcos/", "view": "127.0.0.1:8765"}


def host_port(text: str, what: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:PORT`` for IPv6) as (host, port); raises NorthError naming the
    flag."""
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535 or not host:
        raise NorthError(f"--{what} {text!r}: expected HOST:PORT, e.g. 127.0.0.1:8765")
    return host.strip("[]"), int(port)


def add_north_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the north-side flags (see the module doc) to ``parser``."""
    g = parser.add_argument_group("north side (services for SCADA, HMIs and monitoring)")
    g.add_argument("--metrics", nargs="?", const=DEFAULTS["metrics"], metavar="HOST:PORT",
                   help=f"serve Prometheus metrics (default {DEFAULTS['metrics']})")
    g.add_argument("--modbus-facade", nargs="?", const=DEFAULTS["modbus_facade"],
                   metavar="HOST:PORT",
                   help=f"serve the Modbus TCP facade (default {DEFAULTS['modbus_facade']})")
    g.add_argument("--opcua", nargs="?", const=DEFAULTS["opcua"], metavar="ENDPOINT",
                   help=f"serve OPC UA (default {DEFAULTS['opcua']})")
    g.add_argument("--view", nargs="?", const=DEFAULTS["view"], metavar="HOST:PORT",
                   help=f"serve the live page (default {DEFAULTS['view']})")
    g.add_argument("--metrics-token", metavar="FILE",
                   help="file holding the bearer token a scraper must send (Authorization: "
                        "Bearer ...); required for metrics off loopback")
    g.add_argument("--north-users", metavar="FILE",
                   help="users file (roles observer/operator/supervisor); without it the view "
                        "and OPC UA are read-only")
    g.add_argument("--north-tls-cert", metavar="PEM", help="TLS certificate (off loopback)")
    g.add_argument("--north-tls-key", metavar="PEM", help="TLS key (off loopback)")
    g.add_argument("--modbus-allow-remote", action="store_true",
                   help="let the Modbus facade bind an address off loopback (Modbus has no "
                        "authentication or TLS)")


@dataclass
class NorthOptions:
    """Which services to start and where (None: not started)."""

    metrics: str | None = None
    modbus_facade: str | None = None
    opcua: str | None = None
    view: str | None = None
    users: Users | None = None
    tls_cert: str | None = None
    tls_key: str | None = None
    modbus_allow_remote: bool = False
    metrics_token: str | None = None

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> NorthOptions:
        """Options from :func:`add_north_arguments`' flags; raises ConfigError for a bad users
        file."""
        users = None
        if getattr(args, "north_users", None):
            from chcos.serving.auth import Users

            users = Users.from_file(args.north_users)
        return cls(args.metrics, args.modbus_facade, args.opcua, args.view, users,
                   args.north_tls_cert, args.north_tls_key,
                   bool(getattr(args, "modbus_allow_remote", False)),
                   getattr(args, "metrics_token", None))

    @property
    def any(self) -> bool:
        """True if any service is asked for."""
        return any((self.metrics, self.modbus_facade, self.opcua, self.view))


@dataclass
class NorthHandle:
    """The running services: their addresses by name, and :meth:`stop`."""

    urls: dict[str, str] = field(default_factory=dict)
    services: dict[str, Any] = field(default_factory=dict)
    _stops: list[Callable[[], None]] = field(default_factory=list)

    def stop(self) -> None:
        """Stop every service (last started first; never raises)."""
        while self._stops:
            try:
                self._stops.pop()()
            except Exception:  # stopping goes on
                import logging

                logging.getLogger("chcos.north").exception("stopping a north service failed")

    def __enter__(self) -> NorthHandle:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def start(system: System, options: NorthOptions) -> NorthHandle:
    """Start the services ``options`` name on the running ``system``. Raises NorthError (every
    service started so far stopped again) if one cannot start."""
    h = NorthHandle()
    try:
        if options.metrics:
            from chcos.north.metrics import serve as serve_metrics

            host, port = host_port(options.metrics, "metrics")
            m = serve_metrics(system, host, port, certfile=options.tls_cert,
                              keyfile=options.tls_key, token_file=options.metrics_token)
            h.services["metrics"], h.urls["metrics"] = m, m.url
            h._stops.append(m.stop)
        if options.modbus_facade:
            from chcos.north.modbus_facade import ModbusFacade

            host, port = host_port(options.modbus_facade, "modbus-facade")
            f = ModbusFacade(system, host, port,
                             allow_remote=options.modbus_allow_remote).start()
            h.services["modbus"] = f
            h.urls["modbus"] = f"modbus-tcp://{host}:{f.port}"
            h._stops.append(f.stop)
        if options.opcua:
            from chcos.north.opcua_process import OpcUaProcess

            o = OpcUaProcess(system, options.opcua, users=options.users,
                             certificate=options.tls_cert, private_key=options.tls_key).start()
            h.services["opcua"], h.urls["opcua"] = o, o.endpoint
            h._stops.append(o.stop)
        if options.view:
            from chcos.viewer import ViewerError
            from chcos.viewer.server import Viewer

            host, port = host_port(options.view, "view")
            ctx = None
            if options.tls_cert and options.tls_key:
                import ssl

                ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
                ctx.load_cert_chain(options.tls_cert, options.tls_key)
            try:
                v = Viewer(system, host, port, users=options.users, ssl_context=ctx).start()
            except ViewerError as exc:
                raise NorthError(str(exc)) from exc
            h.services["view"], h.urls["view"] = v, v.url
            h._stops.append(v.stop)
    except BaseException:
        h.stop()
        raise
    return h


def north_main(argv: Sequence[str], stdin: TextIO | None = None) -> int:
    """``chcos north passwd``: print a password hash for a users file. Returns 0, or 1 if the
    two entries differ or the password is empty."""
    from chcos.serving.auth import hash_password

    ap = argparse.ArgumentParser(prog="chcos north", description="North-side accounts.")
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("passwd", help="read a password, print its hash for a users file")
    ap.parse_args(list(argv))
    src = stdin or sys.stdin
    if src.isatty():
        pw = getpass.getpass("password: ")
        if getpass.getpass("again: ") != pw:
            print("chcos north passwd: the two entries differ", file=sys.stderr)
            return 1
    else:
        pw = src.readline().rstrip("\n")
    if not pw:
        print("chcos north passwd: empty password", file=sys.stderr)
        return 1
    print(hash_password(pw))
    return 0


__all__ = ["DEFAULTS", "NorthHandle", "NorthOptions", "add_north_arguments", "host_port",
           "north_main", "start"]
