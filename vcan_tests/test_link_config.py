"""Link configuration: loopback only, no scouting off the host, validated system-file sections."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from chcos.comm.config import LinkConfig, TlsSettings, UsrPwdAuth
from chcos.comm.section import link_config_from_section
from chcos.errors import ConfigError


def test_defaults_are_safe() -> None:
    cfg = LinkConfig(7447, (7448, 7449)).to_json()
    assert cfg["mode"] == "peer"
    assert cfg["listen"]["endpoints"] == ["tcp/127.0.0.1:7447"]
    assert cfg["connect"]["endpoints"] == ["tcp/127.0.0.1:7448", "tcp/127.0.0.1:7449"]
    assert cfg["connect"]["timeout_ms"] == -1
    assert cfg["connect"]["exit_on_failure"] is False
    assert cfg["scouting"]["multicast"] == {"enabled": False, "listen": False}
    assert cfg["scouting"]["gossip"]["autoconnect"] == []
    assert cfg["scouting"]["gossip"]["multihop"] is False
    assert cfg["transport"]["link"]["protocols"] == ["tcp"]
    assert cfg["transport"]["shared_memory"]["enabled"] is False
    assert cfg["adminspace"]["enabled"] is False
    assert cfg["plugins_loading"]["enabled"] is False
    assert "auth" not in cfg["transport"]


def test_zenoh_accepts_it_and_keeps_the_safety_keys() -> None:
    z = LinkConfig(7447, (7448,), lease_ms=1500).to_zenoh()
    assert json.loads(z.get_json("scouting/multicast/enabled")) is False
    assert json.loads(z.get_json("scouting/multicast/listen")) is False
    assert json.loads(z.get_json("scouting/gossip/autoconnect")) == []
    assert json.loads(z.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(z.get_json("transport/link/tx/lease")) == 1500
    # and nothing in the whole configuration names any address but the loopback one
    text = str(z)
    assert "224.0.0.224" not in text and "[::]" not in text and "0.0.0.0" not in text


def test_connect_only_node_has_no_listener() -> None:
    cfg = LinkConfig(None, (7448,))
    assert cfg.listen_endpoints == []
    assert cfg.to_json()["listen"]["endpoints"] == []


@pytest.mark.parametrize(
    ("kwargs", "fragment"),
    [
        ({"listen_port": 0}, "link.listen: expected a TCP port number 1..65535, got 0"),
        ({"listen_port": 70000}, "link.listen"),
        ({"listen_port": "7447"}, "link.listen"),
        ({"listen_port": 1, "connect_ports": (2, 0)}, r"link.connect\[1\]"),
        ({"listen_port": 1, "connect_ports": (2, 2)}, "expected distinct ports"),
        ({"listen_port": 1, "connect_ports": (1,)}, "own listen port"),
        ({"listen_port": None}, "expected a listen port, at least one connect port"),
        ({"listen_port": 1, "connect_ports": [2]}, "expected a tuple of ports"),
        ({"listen_port": 1, "lease_ms": 5}, "link.lease_ms: expected an integer 100..3600000"),
        ({"listen_port": 1, "retry_ms": 1.5}, "link.retry_ms"),
    ],
)
def test_bad_link_configs_are_refused(kwargs: dict[str, Any], fragment: str) -> None:
    with pytest.raises(ConfigError, match=fragment):
        LinkConfig(**kwargs)


def test_usrpwd_auth(tmp_path: Path) -> None:
    users = tmp_path / "users.txt"
    users.write_text("sat1:pw1\n")
    cfg = LinkConfig(7447, auth=UsrPwdAuth("sat1", "pw1", users)).to_json()
    assert cfg["transport"]["auth"]["usrpwd"] == {
        "user": "sat1",
        "password": "pw1",
        "dictionary_file": str(users),
    }
    assert "pw1" not in repr(UsrPwdAuth("sat1", "pw1", users))


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (("", "pw"), "link.auth.user: expected a non-empty name"),
        (("a:b", "pw"), "without ':'"),
        (("a", ""), "link.auth.password"),
        (("a", "pw", Path("/nonexistent/users.txt")), "link.auth.dictionary_file"),
    ],
)
def test_bad_auth_is_refused(args: tuple[Any, ...], fragment: str) -> None:
    with pytest.raises(ConfigError, match=fragment):
        UsrPwdAuth(*args)


def _pem_files(tmp_path: Path, *names: str) -> list[Path]:
    paths = []
    for name in names:
        path = tmp_path / name
        path.write_text("-----BEGIN CERTIFICATE-----\n")
        paths.append(path)
    return paths


def test_tls_switches_protocol_and_sets_paths(tmp_path: Path) -> None:
    ca, cert, key = _pem_files(tmp_path, "ca.pem", "cert.pem", "key.pem")
    tls = TlsSettings(ca, listen_certificate=cert, listen_private_key=key)
    cfg = LinkConfig(7447, (7448,), tls=tls)
    j = cfg.to_json()
    assert j["listen"]["endpoints"] == ["tls/127.0.0.1:7447"]
    assert j["connect"]["endpoints"] == ["tls/127.0.0.1:7448"]
    assert j["transport"]["link"]["protocols"] == ["tls"]
    assert j["transport"]["link"]["tls"]["listen_certificate"] == str(cert)
    assert j["transport"]["link"]["tls"]["root_ca_certificate"] == str(ca)
    cfg.to_zenoh()


def test_tls_validation(tmp_path: Path) -> None:
    ca, cert, key = _pem_files(tmp_path, "ca.pem", "cert.pem", "key.pem")
    with pytest.raises(ConfigError, match=r"link\.tls\.root_ca_certificate: expected an existing"):
        TlsSettings(tmp_path / "missing.pem")
    with pytest.raises(ConfigError, match="listen_certificate and listen_private_key together"):
        TlsSettings(ca, listen_certificate=cert)
    with pytest.raises(ConfigError, match="enable_mtls: expected connect_certificate"):
        TlsSettings(ca, enable_mtls=True)
    with pytest.raises(ConfigError, match="on a node that listens"):
        LinkConfig(7447, tls=TlsSettings(ca))
    # a connect-only node may go without a listen certificate
    LinkConfig(
        None, (7447,), tls=TlsSettings(ca, connect_certificate=cert, connect_private_key=key)
    )


def test_section_with_everything(tmp_path: Path) -> None:
    (tmp_path / "users.txt").write_text("sat1:pw1\nsat2:pw2\n")
    ca, cert, key = _pem_files(tmp_path, "ca.pem", "cert.pem", "key.pem")
    cfg = link_config_from_section(
        {
            "listen": 7447,
            "connect": [7448, 7449],
            "lease_ms": 2000,
            "retry_ms": 50,
            "auth": {"user": "sat1", "password": "pw1", "dictionary_file": "users.txt"},
            "tls": {
                "root_ca_certificate": "ca.pem",
                "listen_certificate": str(cert),
                "listen_private_key": "key.pem",
                "enable_mtls": False,
            },
        },
        base_dir=tmp_path,
    )
    assert cfg.listen_port == 7447
    assert cfg.connect_ports == (7448, 7449)
    assert cfg.lease_ms == 2000 and cfg.retry_ms == 50
    assert cfg.auth == UsrPwdAuth("sat1", "pw1", tmp_path / "users.txt")
    assert cfg.tls is not None
    assert cfg.tls.root_ca_certificate == ca
    assert cfg.tls.listen_private_key == key


@pytest.mark.parametrize(
    ("section", "fragment"),
    [
        ([], "sys.toml: link: expected a table of keys, got list"),
        ({"listen": 1, "port": 2}, r"sys.toml: link.port: unknown key; expected one of"),
        ({"listen": "x"}, "sys.toml: link.listen: expected a TCP port"),
        ({"listen": 1, "connect": 2}, "sys.toml: link.connect: expected a list of ports"),
        ({"listen": 1, "connect": [2, "3"]}, r"sys.toml: link.connect\[1\]"),
        ({"listen": 1, "auth": {"user": "a"}}, "sys.toml: link.auth.password: expected"),
        ({"listen": 1, "auth": {"user": "a", "password": "b", "x": 1}}, "link.auth.x: unknown"),
        (
            {"listen": 1, "auth": {"user": "a", "password": "b", "dictionary_file": "nope"}},
            "link.auth.dictionary_file: expected an existing file",
        ),
        ({"listen": 1, "tls": {}}, "link.tls.root_ca_certificate: expected a CA"),
        ({"listen": 1, "lease_ms": 0}, "sys.toml: link: link.lease_ms"),
        ({}, "expected a listen port"),
    ],
)
def test_bad_sections_are_refused(section: Any, fragment: str, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=fragment):
        link_config_from_section(section, where="sys.toml: link", base_dir=tmp_path)


def test_tls_section_flag_types(tmp_path: Path) -> None:
    _pem_files(tmp_path, "ca.pem")
    with pytest.raises(ConfigError, match=r"link\.tls\.enable_mtls: expected true or false"):
        link_config_from_section(
            {"connect": [1], "tls": {"root_ca_certificate": "ca.pem", "enable_mtls": "yes"}},
            base_dir=tmp_path,
        )
