"""config - safe-by-default Zenoh configurations for the chcos inter-satellite link.

Topology: **full mesh of equal peers, each listening on its own loopback port.** Every satellite
(the host included) runs a Zenoh session in ``peer`` mode that listens on ``127.0.0.1:<its
port>`` and connects to the ports of the other satellites named in the system file, retrying in
the background for ever (:func:`chcos.satellites.sysfile.link_config_for` has each satellite
connect to the
lower-numbered ones only, so that each pair shares one connection). Why:

* no router: a killed satellite takes only its own links down; the others keep talking directly
  (a router or a host-as-hub would be a single point of failure);
* a killed satellite is noticed at once: its TCP connections are reset by the OS, Zenoh drops the
  session and withdraws its liveliness tokens; a machine that vanishes without a reset is noticed
  when its lease (``lease_ms``) expires;
* a late joiner (or a restarted satellite) connects to the lower-numbered satellites already up;
  the higher-numbered ones reach it by their background retries. Opening a session
  never waits for absent peers: connections are made in the background (a peer that is up is
  typically reached within a millisecond on loopback; synchronise on liveliness tokens, not on
  ``open`` returning).

Everything that could send to a non-loopback address is off: multicast scouting (neither sent nor
listened for), gossip never auto-connects to locators learnt from others, only ``tcp`` (or ``tls``)
is admitted, and endpoints are built here from port numbers on ``127.0.0.1`` unless a host
address is given (``listen_host``, ``connect_hosts``: a satellite on another computer). A
configuration that listens on or connects to a non-loopback address is refused unless it uses
TLS with mutual authentication, or TLS with user/password authentication
(:meth:`LinkConfig.check_exposure`); the wildcard addresses 0.0.0.0 and :: are always refused.

Zenoh keys set by :meth:`LinkConfig.to_json` (and why):

=========================================== ===============================================
``mode = "peer"``                            equal peers, no router to fail (see above)
``listen.endpoints``                         ``<proto>/127.0.0.1:<listen_port>`` only
``listen.exit_on_failure = true``            a taken port fails ``open`` instead of retrying
``listen.timeout_ms = 0``                    do not wait on the listener
``connect.endpoints``                        ``<proto>/127.0.0.1:<port>`` of every other peer
``connect.timeout_ms = -1``                  retry absent peers for ever, in the background (0
                                             would try once and give up; ``open`` does not
                                             block either way with exit_on_failure false)
``connect.exit_on_failure = false``          absent peers are retried in the background
``connect.retry.*``                          first retry after ``retry_ms``, backing off x2 to 1 s
``scouting.delay = 0``                       nothing to scout for: do not delay ``open``
``scouting.multicast.enabled = false``       no UDP multicast scouting sent (224.0.0.224)
``scouting.multicast.listen = false``        nor answered
``scouting.gossip.enabled = true``           gossip only travels on established (loopback)
                                             sessions; kept on because 1.10 warns it cannot
                                             de-duplicate data without it
``scouting.gossip.multihop = false``         gossip goes one hop only
``scouting.gossip.autoconnect = []``         never connect to a locator learnt by gossip (it
                                             could be a non-loopback address)
``timestamping.enabled = false``             chcos stamps its own messages (codec header)
``adminspace.enabled = false``               no remote introspection/writes of the session
``plugins_loading.enabled = false``          never load shared libraries from search paths
``transport.link.protocols``                 whitelist: ``["tcp"]``, or ``["tls"]`` with TLS
``transport.link.tx.lease``                  ``lease_ms``: silence after which a peer is dead
``transport.link.tx.keep_alive = 4``         4 keep-alives per lease
``transport.unicast.qos.enabled = true``     per-priority queues (chcos priorities map onto them)
``transport.shared_memory.enabled = false``  no /dev/shm segments that a kill -9 would leak
``transport.auth.usrpwd.*``                  optional user/password authentication
``transport.link.tls.*``                     optional TLS certificates
=========================================== ===============================================

Authentication (Zenoh ``usrpwd``) and TLS settings are in :mod:`chcos.comm.tls`; the ``[link]``
section of a system file is read by :mod:`chcos.comm.section`.
"""

from __future__ import annotations

import ipaddress
import json
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from chcos.comm.tls import TlsSettings, UsrPwdAuth
from chcos.errors import ConfigError

if TYPE_CHECKING:
    import zenoh

__all__ = ["LOOPBACK", "LinkConfig", "TlsSettings", "UsrPwdAuth", "check_host", "check_port",
           "is_loopback"]

LOOPBACK = "127.0.0.1"
DEFAULT_LEASE_MS = 3000
DEFAULT_RETRY_MS = 100
MAX_RETRY_MS = 1000

def check_port(where: str, value: object) -> int:
    """``value`` if it is a TCP port 1..65535. Raises ConfigError naming ``where``."""
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 65535:
        raise ConfigError(f"{where}: expected a TCP port number 1..65535, got {value!r}")
    return value


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an IPv4/IPv6 address, bracketed or not, or a name) is this computer's
    loopback: 127.0.0.0/8, ::1 or ``localhost``."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def check_host(where: str, value: object) -> str:
    """``value`` if it is an IPv4 or IPv6 address or a host name (not a wildcard address).
    Raises ConfigError naming ``where`` otherwise."""
    if not isinstance(value, str) or not value or len(value) > 253:
        raise ConfigError(f"{where}: expected an IPv4/IPv6 address or a host name, got {value!r}")
    try:
        addr = ipaddress.ip_address(value)
    except ValueError:
        labels = value.rstrip(".").split(".")
        if not all(lb and len(lb) <= 63 and lb.replace("-", "").isalnum()
                   and not lb.startswith("-") for lb in labels):
            raise ConfigError(
                f"{where}: expected an IPv4/IPv6 address or a host name, got {value!r}") from None
        return value
    if addr.is_unspecified or addr.is_multicast:
        raise ConfigError(f"{where}: {value} is a wildcard or multicast address; expected the "
                          "address of one interface (chcos never listens on every interface)")
    return value


@dataclass(frozen=True)
class LinkConfig:
    """Where one satellite listens and whom it connects to, all on 127.0.0.1.

    ``listen_port`` is this node's port (``None``: connect-only, e.g. a tool); ``connect_ports``
    are the other peers' ports; ``lease_ms`` is how long a silent peer is still believed alive;
    ``retry_ms`` is the first back-off when a peer is not up yet.

    Raises ConfigError (from the constructor) on a bad port, a node connecting to itself, a
    duplicate port, no endpoint at all, or a TLS node without a listen certificate.
    """

    listen_port: int | None
    connect_ports: tuple[int, ...] = ()
    lease_ms: int = DEFAULT_LEASE_MS
    retry_ms: int = DEFAULT_RETRY_MS
    auth: UsrPwdAuth | None = None
    tls: TlsSettings | None = None
    listen_host: str = LOOPBACK
    connect_hosts: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        check_host("link.listen_host", self.listen_host)
        if not isinstance(self.connect_hosts, tuple) or (
                self.connect_hosts and len(self.connect_hosts) != len(self.connect_ports)):
            raise ConfigError("link.connect_hosts: expected a tuple with one address per "
                              "connect port, or ()")
        for i, host in enumerate(self.connect_hosts):
            check_host(f"link.connect_hosts[{i}]", host)
        if self.listen_port is not None:
            check_port("link.listen", self.listen_port)
        if not isinstance(self.connect_ports, tuple):
            raise ConfigError(
                f"link.connect: expected a tuple of ports, got {type(self.connect_ports).__name__}"
            )
        for i, port in enumerate(self.connect_ports):
            check_port(f"link.connect[{i}]", port)
        pairs = self.connect_pairs
        if len(set(pairs)) != len(pairs):
            raise ConfigError(f"link.connect: expected distinct ports, got {self.connect_ports}")
        if self.listen_port is not None and (self.listen_host, self.listen_port) in pairs:
            raise ConfigError(
                f"link.connect: port {self.listen_port} is this node's own listen port; expected "
                "only the other peers' ports"
            )
        if self.listen_port is None and not self.connect_ports:
            raise ConfigError("link: expected a listen port, at least one connect port, or both")
        for name, low, high in (("lease_ms", 100, 3_600_000), ("retry_ms", 10, 60_000)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise ConfigError(
                    f"link.{name}: expected an integer {low}..{high} (milliseconds), got {value!r}"
                )
        if self.auth is not None and not isinstance(self.auth, UsrPwdAuth):
            raise ConfigError("link.auth: expected a UsrPwdAuth")
        if self.tls is not None:
            if not isinstance(self.tls, TlsSettings):
                raise ConfigError("link.tls: expected a TlsSettings")
            if self.listen_port is not None and self.tls.listen_certificate is None:
                raise ConfigError(
                    "link.tls.listen_certificate: expected (with listen_private_key) on a node "
                    "that listens"
                )

    @property
    def connect_pairs(self) -> list[tuple[str, int]]:
        """(host, port) of every peer this node connects to."""
        hosts = self.connect_hosts or (LOOPBACK,) * len(self.connect_ports)
        return list(zip(hosts, self.connect_ports, strict=True))

    @property
    def protocol(self) -> str:
        """``"tls"`` when TLS is configured, else ``"tcp"``."""
        return "tls" if self.tls is not None else "tcp"

    def endpoint(self, port: int, host: str = LOOPBACK) -> str:
        """The Zenoh endpoint string for ``port`` on ``host`` (IPv6 in brackets)."""
        return f"{self.protocol}/{f'[{host}]' if ':' in host else host}:{port}"

    @property
    def listen_endpoints(self) -> list[str]:
        """Where this node listens (empty for a connect-only node)."""
        return ([] if self.listen_port is None
                else [self.endpoint(self.listen_port, self.listen_host)])

    @property
    def connect_endpoints(self) -> list[str]:
        """Whom this node connects to."""
        return [self.endpoint(port, host) for host, port in self.connect_pairs]

    @property
    def exposed(self) -> list[str]:
        """The non-loopback addresses this node listens on or connects to."""
        hosts = [h for h, _ in self.connect_pairs]
        if self.listen_port is not None:
            hosts.insert(0, self.listen_host)
        return [h for h in dict.fromkeys(hosts) if not is_loopback(h)]

    def check_exposure(self, where: str = "link") -> None:
        """Refuse a configuration that talks to a non-loopback address without TLS and peer
        authentication (mutual TLS, or user/password with a dictionary over TLS). Raises
        ConfigError saying what to add."""
        exposed = self.exposed
        if not exposed:
            return
        tls = self.tls
        if tls is None:
            raise ConfigError(
                f"{where}: {', '.join(exposed)} is not a loopback address: add a [link.tls] "
                "table with root_ca_certificate, listen_certificate, listen_private_key, "
                "connect_certificate, connect_private_key and enable_mtls = true (or TLS with "
                "[link.auth] user, password and dictionary_file)")
        if not tls.enable_mtls and (self.auth is None or self.auth.dictionary_file is None):
            raise ConfigError(
                f"{where}: {', '.join(exposed)} is not a loopback address and peers are not "
                "authenticated: set enable_mtls = true in [link.tls] (with "
                "connect_certificate and connect_private_key), or add [link.auth] with user, "
                "password and dictionary_file")

    def to_json(self) -> dict[str, Any]:
        """The Zenoh configuration as a JSON-able dict (see the module docstring for each key)."""
        transport: dict[str, Any] = {
            "link": {
                "protocols": [self.protocol],
                "tx": {"lease": self.lease_ms, "keep_alive": 4},
            },
            "unicast": {"qos": {"enabled": True}},
            "shared_memory": {"enabled": False},
        }
        if self.auth is not None:
            usrpwd: dict[str, Any] = {"user": self.auth.user, "password": self.auth.password}
            if self.auth.dictionary_file is not None:
                usrpwd["dictionary_file"] = str(self.auth.dictionary_file)
            transport["auth"] = {"usrpwd": usrpwd}
        if self.tls is not None:
            tls: dict[str, Any] = {
                "root_ca_certificate": str(self.tls.root_ca_certificate),
                "enable_mtls": self.tls.enable_mtls,
                "verify_name_on_connect": self.tls.verify_name_on_connect,
            }
            for name in (
                "listen_certificate",
                "listen_private_key",
                "connect_certificate",
                "connect_private_key",
            ):
                value = getattr(self.tls, name)
                if value is not None:
                    tls[name] = str(value)
            transport["link"]["tls"] = tls
        return {
            "mode": "peer",
            "listen": {
                "endpoints": self.listen_endpoints,
                "exit_on_failure": True,
                "timeout_ms": 0,
            },
            "connect": {
                "endpoints": self.connect_endpoints,
                "timeout_ms": -1,
                "exit_on_failure": False,
                "retry": {
                    "period_init_ms": self.retry_ms,
                    "period_max_ms": max(self.retry_ms, MAX_RETRY_MS),
                    "period_increase_factor": 2,
                },
            },
            "scouting": {
                "delay": 0,
                "multicast": {"enabled": False, "listen": False},
                "gossip": {"enabled": True, "multihop": False, "autoconnect": []},
            },
            "timestamping": {"enabled": False},
            "adminspace": {"enabled": False},
            "plugins_loading": {"enabled": False},
            "transport": transport,
        }

    def to_zenoh(self) -> zenoh.Config:
        """A fresh :class:`zenoh.Config`. Raises ConfigError if Zenoh rejects it. (Zenoh is
        imported here, when a link is opened: checking a configuration needs none, and it comes
        with the ``satellites`` extra.)"""
        import zenoh

        try:
            return zenoh.Config.from_json5(json.dumps(self.to_json()))
        except zenoh.ZError as exc:
            raise ConfigError(f"link: Zenoh rejected the configuration: {exc}") from exc
