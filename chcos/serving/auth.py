"""auth - who may command a running system from the north side: users, roles and passwords.

One users file serves the live view, the OPC UA server and the Modbus facade (TOML)::

    [users.alice]
    role = "operator"          # observer | operator | supervisor
    password_hash = "pbkdf2-sha256$200000$<salt hex>$<hash hex>"   # chcos north passwd

Roles and the host commands they may issue (:data:`ROLE_COMMANDS`): an *observer* only reads; an
*operator* may ``invoke``, ``setpri`` and ``estop``; a *supervisor* may also ``suspend`` and
``resume``. Every command still goes through the system manager's own checks. Passwords are never
stored: PBKDF2-HMAC-SHA256 with a random salt, compared in constant time.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from chcos.errors import ConfigError
from chcos.helpers import load_toml

ROLE_COMMANDS: Mapping[str, frozenset[str]] = {
    "observer": frozenset(),
    "operator": frozenset({"invoke", "setpri", "estop"}),
    "supervisor": frozenset({"invoke", "setpri", "estop", "suspend", "resume"}),
}
#: The iteration count new hashes get.
ITERATIONS = 200_000
_SCHEME = "pbkdf2-sha256"


def hash_password(password: str, iterations: int = ITERATIONS, salt: bytes | None = None) -> str:
    """A storable hash of ``password`` (``pbkdf2-sha256$N$salt$hash``)."""
    salt = salt if salt is not None else secrets.token_bytes(16)
    digest = hashlib.pbkdf2_hmac("sha256", password.encode(), salt, iterations)
    return f"{_SCHEME}${iterations}${salt.hex()}${digest.hex()}"


def verify_password(password: str, stored: str) -> bool:
    """True if ``password`` matches ``stored`` (from :func:`hash_password`); constant time."""
    try:
        scheme, n, salt, want = stored.split("$")
        if scheme != _SCHEME:
            return False
        got = hashlib.pbkdf2_hmac("sha256", password.encode(), bytes.fromhex(salt), int(n))
    except ValueError:
        return False
    return hmac.compare_digest(got.hex(), want)


@dataclass(frozen=True)
class User:
    """One account: its name, role and password hash."""

    name: str
    role: str
    password_hash: str

    def may(self, command: str) -> bool:
        """True if this user's role allows host command ``command`` (``invoke``, ``estop``...)."""
        return command in ROLE_COMMANDS.get(self.role, frozenset())


class Users:
    """The accounts that may log in to the north-side services."""

    def __init__(self, users: Mapping[str, User]) -> None:
        self.users = dict(users)

    @classmethod
    def from_file(cls, path: str | Path) -> Users:
        """Load a users file; raises ConfigError naming the file, the key and what was
        expected."""
        return cls.from_dict(load_toml(path, "users file"), str(path))

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any], source: str = "<users>") -> Users:
        """Accounts from a parsed users document; raises ConfigError on a bad entry."""
        extra = set(doc) - {"users"}
        if extra:
            raise ConfigError(f"{source}: unknown top-level key(s) {sorted(extra)}: expected "
                              "[users.NAME] tables")
        table = doc.get("users", {})
        if not isinstance(table, dict) or not table:
            raise ConfigError(f"{source}: users: expected at least one [users.NAME] table")
        users: dict[str, User] = {}
        for name, entry in table.items():
            key = f"users.{name}"
            if not isinstance(entry, dict):
                raise ConfigError(f"{source}: {key}: expected a table")
            unknown = set(entry) - {"role", "password_hash"}
            if unknown:
                raise ConfigError(f"{source}: {key}: unknown key(s) {sorted(unknown)}; "
                                  "expected role and password_hash")
            role = entry.get("role")
            if not isinstance(role, str) or role not in ROLE_COMMANDS:
                raise ConfigError(f"{source}: {key}.role: expected one of "
                                  f"{', '.join(ROLE_COMMANDS)}, got {role!r}")
            ph = entry.get("password_hash")
            if not isinstance(ph, str) or not ph.startswith(_SCHEME + "$") or ph.count("$") != 3:
                raise ConfigError(f"{source}: {key}.password_hash: expected a hash from "
                                  "`chcos north passwd` (pbkdf2-sha256$N$salt$hash)")
            users[name] = User(name, role, ph)
        return cls(users)

    def check(self, name: str, password: str) -> User | None:
        """The user ``name`` if ``password`` is right, else None."""
        user = self.users.get(name)
        if user is None:
            return None
        return user if verify_password(password, user.password_hash) else None


__all__ = ["ROLE_COMMANDS", "User", "Users", "hash_password", "verify_password"]
