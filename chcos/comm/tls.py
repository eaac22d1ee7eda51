"""tls - the TLS and user/password settings of a chcos link node (see :mod:`chcos.comm.config`).

Authentication (Zenoh ``usrpwd``): a node presents ``user``/``password`` when it connects, and a
node with a ``dictionary_file`` (lines ``user:password``) refuses incoming sessions whose
credentials are not in it. In a mesh every node should have all three. TLS: certificate paths
(PEM) for listening and connecting, optionally mutual.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from chcos.errors import ConfigError


def check_file(where: str, value: object, base_dir: Path | None) -> Path:
    """``value`` as a path (relative ones under ``base_dir``) to an existing file. Raises
    ConfigError naming ``where`` otherwise."""
    if isinstance(value, Path):
        path = value
    elif isinstance(value, str) and value:
        path = Path(value)
    else:
        raise ConfigError(f"{where}: expected a file path string, got {value!r}")
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    if not path.is_file():
        raise ConfigError(f"{where}: expected an existing file, {str(path)!r} is not one")
    return path


@dataclass(frozen=True)
class UsrPwdAuth:
    """Zenoh user/password authentication: the credentials this node presents when it connects,
    and (optionally) the dictionary of ``user:password`` lines it accepts from others.

    Raises ConfigError (from the constructor) on an empty user or password, a ``:`` in the user,
    or a dictionary path that is not an existing file."""

    user: str
    password: str
    dictionary_file: Path | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.user, str) or not self.user or ":" in self.user:
            raise ConfigError(
                f"link.auth.user: expected a non-empty name without ':', got {self.user!r}"
            )
        if not isinstance(self.password, str) or not self.password:
            raise ConfigError("link.auth.password: expected a non-empty string")
        if self.dictionary_file is not None:
            check_file("link.auth.dictionary_file", self.dictionary_file, None)

    def __repr__(self) -> str:  # never print the password
        return (
            f"UsrPwdAuth(user={self.user!r}, password='***', "
            f"dictionary_file={self.dictionary_file!r})"
        )


@dataclass(frozen=True)
class TlsSettings:
    """TLS certificate paths (PEM). A listening node needs ``listen_certificate`` and
    ``listen_private_key``; a connecting node checks the listener against
    ``root_ca_certificate``. With ``enable_mtls`` the connecting node must also present
    ``connect_certificate``/``connect_private_key``, which the listener checks against the CA.
    ``verify_name_on_connect`` checks that the listener's certificate names 127.0.0.1.

    Raises ConfigError (from the constructor) on a missing file or an incomplete pair."""

    root_ca_certificate: Path
    listen_certificate: Path | None = None
    listen_private_key: Path | None = None
    connect_certificate: Path | None = None
    connect_private_key: Path | None = None
    enable_mtls: bool = False
    verify_name_on_connect: bool = True

    def __post_init__(self) -> None:
        check_file("link.tls.root_ca_certificate", self.root_ca_certificate, None)
        for name in (
            "listen_certificate",
            "listen_private_key",
            "connect_certificate",
            "connect_private_key",
        ):
            value = getattr(self, name)
            if value is not None:
                check_file(f"link.tls.{name}", value, None)
        if (self.listen_certificate is None) != (self.listen_private_key is None):
            raise ConfigError(
                "link.tls: expected listen_certificate and listen_private_key together"
            )
        if (self.connect_certificate is None) != (self.connect_private_key is None):
            raise ConfigError(
                "link.tls: expected connect_certificate and connect_private_key together"
            )
        if self.enable_mtls and self.connect_certificate is None:
            raise ConfigError(
                "link.tls.enable_mtls: expected connect_certificate and connect_private_key "
                "when mutual TLS is on"
            )
        for name in ("enable_mtls", "verify_name_on_connect"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"link.tls.{name}: expected true or false")
