"""Link over TLS: peers whose certificates chain to the configured CA connect; a peer that trusts
another CA refuses the session (and logs why). Certificates are made by the openssl tool."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from chcos.comm import LinkConfig, TlsSettings, Transport
from vcan_tests.conftest import require
from vcan_tests.netutil import free_port
from vcan_tests.support_link import Child, Collector, child_args


@pytest.fixture(autouse=True)
def _openssl() -> None:
    require(shutil.which("openssl"), "the openssl tool (apt-get install openssl)")

EXT = """subjectAltName = IP:127.0.0.1
basicConstraints = CA:FALSE
keyUsage = digitalSignature, keyEncipherment
extendedKeyUsage = serverAuth, clientAuth
"""


def _run(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=60)


def _pki(root: Path) -> tuple[Path, Path, Path]:
    """A CA and a certificate for 127.0.0.1 signed by it: (ca.pem, cert.pem, key.pem)."""
    root.mkdir()
    (root / "ext.cnf").write_text(EXT)
    _run("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem",
         "-days", "2", "-subj", "/CN=chcos test CA", cwd=root)  # fmt: skip
    _run("req", "-newkey", "rsa:2048", "-nodes", "-keyout", "key.pem", "-out", "cert.csr",
         "-subj", "/CN=127.0.0.1", cwd=root)  # fmt: skip
    _run("x509", "-req", "-in", "cert.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
         "-CAcreateserial", "-out", "cert.pem", "-days", "2", "-extfile", "ext.cnf",
         cwd=root)  # fmt: skip
    return root / "ca.pem", root / "cert.pem", root / "key.pem"


@pytest.fixture(scope="module")
def pkis(tmp_path_factory: pytest.TempPathFactory) -> tuple[tuple[Path, Path, Path], ...]:
    base = tmp_path_factory.mktemp("pki")
    return _pki(base / "good"), _pki(base / "other")


def test_tls_peers_connect(pkis: tuple[tuple[Path, Path, Path], ...]) -> None:
    ca, cert, key = pkis[0]
    tls = TlsSettings(ca, listen_certificate=cert, listen_private_key=key)
    pa, pb = free_port(), free_port()
    with Transport(LinkConfig(pa, tls=tls)) as a, Transport(LinkConfig(pb, (pa,), tls=tls)) as b:
        joins = Collector()
        a.watch("chcos/alive/*", joins, lambda _k: None)
        b.announce("chcos/alive/b")
        assert joins.get() == "chcos/alive/b"
        assert a.peers() == [b.zid]
        links = a._session.info.links()
        assert [str(link.src).split("/")[0] for link in links] == ["tls"]


def test_a_peer_trusting_another_ca_is_refused(
    pkis: tuple[tuple[Path, Path, Path], ...],
) -> None:
    ca, cert, key = pkis[0]
    host_port = free_port()
    tls = TlsSettings(ca, listen_certificate=cert, listen_private_key=key)
    with Transport(LinkConfig(host_port, tls=tls)) as host:
        joins = Collector()
        host.watch("chcos/alive/*", joins, lambda _k: None)
        args = child_args(
            listen=free_port(),
            connect=[host_port],
            token="chcos/alive/stranger",
            tls=pkis[1],  # its own CA does not sign the host's certificate
            # failed TLS handshakes are logged at debug level by the connection orchestrator
            zenoh_log="warn,zenoh::net::runtime::orchestrator=debug",
        )
        with Child(args) as child:
            child.expect("ready")
            line = child.wait_log(f"Unable to connect to configured peer tls/127.0.0.1:{host_port}")
            assert "invalid peer certificate" in line
            assert child.peers() == []
            assert host.peers() == []
            assert joins.empty()
            assert child.stop() == 0
