"""section - the ``[link]`` section of a system file, read into a :class:`LinkConfig`.

Every key is checked; an unknown key or a bad value raises ConfigError naming the key and what
was expected, and the section is rejected whole.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from chcos.comm.config import LinkConfig, check_host, check_port
from chcos.comm.tls import TlsSettings, UsrPwdAuth, check_file
from chcos.errors import ConfigError

_SECTION_KEYS = frozenset(
    {"listen", "connect", "lease_ms", "retry_ms", "auth", "tls", "listen_host", "connect_hosts"}
)
_AUTH_KEYS = frozenset({"user", "password", "dictionary_file"})
_TLS_KEYS = frozenset(
    {
        "root_ca_certificate",
        "listen_certificate",
        "listen_private_key",
        "connect_certificate",
        "connect_private_key",
        "enable_mtls",
        "verify_name_on_connect",
    }
)



def _expect_mapping(where: str, value: object, allowed: frozenset[str]) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise ConfigError(f"{where}: expected a table of keys, got {type(value).__name__}")
    for key in value:
        if key not in allowed:
            raise ConfigError(
                f"{where}.{key}: unknown key; expected one of {', '.join(sorted(allowed))}"
            )
    return value


def link_config_from_section(
    section: Mapping[str, Any], *, where: str = "link", base_dir: Path | None = None
) -> LinkConfig:
    """Build a :class:`LinkConfig` from the ``[link]`` section of a system file.

    ``where`` prefixes error messages (e.g. ``"sysfile.toml: link"``); relative file paths are
    resolved against ``base_dir``. Keys::

        listen = 7447                 # this node's port on 127.0.0.1 (optional)
        connect = [7448, 7449]        # the other peers' ports
        listen_host = "10.0.0.2"      # optional: the address to listen on (default 127.0.0.1)
        connect_hosts = ["10.0.0.3", "10.0.0.4"]  # optional: one address per connect port
        lease_ms = 3000               # optional
        retry_ms = 100                # optional
        [link.auth]                   # optional: Zenoh usrpwd
        user = "sat1"
        password = "..."
        dictionary_file = "users.txt" # lines user:password this node accepts
        [link.tls]                    # optional: root_ca_certificate, listen_certificate,
                                      # listen_private_key, connect_certificate,
                                      # connect_private_key, enable_mtls, verify_name_on_connect

    Raises ConfigError naming the key and what was expected; the section is rejected whole.
    """
    sec = _expect_mapping(where, section, _SECTION_KEYS)
    listen = sec.get("listen")
    listen_port = None if listen is None else check_port(f"{where}.listen", listen)
    connect = sec.get("connect", [])
    if not isinstance(connect, list | tuple):
        raise ConfigError(f"{where}.connect: expected a list of ports, got {connect!r}")
    ports = tuple(check_port(f"{where}.connect[{i}]", p) for i, p in enumerate(connect))
    auth = None
    if "auth" in sec:
        a = _expect_mapping(f"{where}.auth", sec["auth"], _AUTH_KEYS)
        for key in ("user", "password"):
            if not isinstance(a.get(key), str) or not a[key]:
                raise ConfigError(f"{where}.auth.{key}: expected a non-empty string")
        dictionary = None
        if "dictionary_file" in a:
            dictionary = check_file(
                f"{where}.auth.dictionary_file", a["dictionary_file"], base_dir
            )
        auth = UsrPwdAuth(a["user"], a["password"], dictionary)
    tls = None
    if "tls" in sec:
        t = _expect_mapping(f"{where}.tls", sec["tls"], _TLS_KEYS)
        if "root_ca_certificate" not in t:
            raise ConfigError(f"{where}.tls.root_ca_certificate: expected a CA certificate path")

        def opt_file(key: str) -> Path | None:
            return check_file(f"{where}.tls.{key}", t[key], base_dir) if key in t else None

        flags: dict[str, bool] = {}
        for key, default in (("enable_mtls", False), ("verify_name_on_connect", True)):
            value = t.get(key, default)
            if not isinstance(value, bool):
                raise ConfigError(f"{where}.tls.{key}: expected true or false, got {value!r}")
            flags[key] = value
        try:
            tls = TlsSettings(
                check_file(f"{where}.tls.root_ca_certificate", t["root_ca_certificate"], base_dir),
                listen_certificate=opt_file("listen_certificate"),
                listen_private_key=opt_file("listen_private_key"),
                connect_certificate=opt_file("connect_certificate"),
                connect_private_key=opt_file("connect_private_key"),
                enable_mtls=flags["enable_mtls"],
                verify_name_on_connect=flags["verify_name_on_connect"],
            )
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from exc
    kwargs: dict[str, Any] = {}
    if "listen_host" in sec:
        kwargs["listen_host"] = check_host(f"{where}.listen_host", sec["listen_host"])
    if "connect_hosts" in sec:
        hosts = sec["connect_hosts"]
        if not isinstance(hosts, list | tuple):
            raise ConfigError(f"{where}.connect_hosts: expected a list of addresses")
        kwargs["connect_hosts"] = tuple(
            check_host(f"{where}.connect_hosts[{i}]", h) for i, h in enumerate(hosts))
    for key in ("lease_ms", "retry_ms"):
        if key in sec:
            kwargs[key] = sec[key]
    try:
        return LinkConfig(listen_port, ports, auth=auth, tls=tls, **kwargs)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from exc
