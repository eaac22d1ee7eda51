"""auth - who may command a running system from the north side: users, roles and passwords.

One users file serves the live view, the OPC UA server and the Modbus facade (TOML)::

    [users.alice]
    role = "operator"          # observer | operator | supervisor
    password_hash = "pbkdf2-sha256$200000$<salt hex>$<hash hex>"   # chcos north passwd

Roles and the host commands they may issue (:data:`ROLE_COMMANDS`): an *observer* only reads; an
*operator* may ``invoke``, ``setpri`` and ``estop``; a *supervisor* may also ``suspend`` and
``resume``. Every command still goes through the system manager's own checks. Passwords are never
stored: PBKDF2-HMAC-SHA256 with a random salt, compared in constant time; a name that is not an
account costs the same check against a dummy hash, so the time of a refusal does not tell which
names exist.

Wrong passwords are slowed down by :class:`LoginThrottle`, per client address *and* per user
name, for the live view and the OPC UA server alike: each attempt is counted *before* its
password is checked (a burst of concurrent attempts cannot all pass the bar while the first
ones are being checked), the first :data:`FREE_ATTEMPTS` cost nothing, each further one bars
that address and that name for 1 s doubled per attempt, at most :data:`LONGEST_BAR` seconds; a
right login clears both counts.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping
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
#: Wrong logins per client address and per user name that cost nothing.
FREE_ATTEMPTS = 5
#: The first bar after the free attempts, seconds (doubled per further attempt).
FIRST_BAR = 1.0
#: The longest bar, seconds.
LONGEST_BAR = 300.0
#: Addresses and names a throttle remembers (the least recently failed forgotten first).
REMEMBERED = 10_000


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


def _iterations(stored: str) -> int:
    try:
        return int(stored.split("$")[1])
    except (IndexError, ValueError):
        return ITERATIONS


class Users:
    """The accounts that may log in to the north-side services."""

    def __init__(self, users: Mapping[str, User]) -> None:
        self.users = dict(users)
        # what a name that is no account is checked against: the same work as a real one
        # (the accounts' iteration count), and no password matches it
        n = max((_iterations(u.password_hash) for u in self.users.values()), default=ITERATIONS)
        self._dummy = f"{_SCHEME}${n}${secrets.token_hex(16)}${'0' * 64}"

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
        """The user ``name`` if ``password`` is right, else None. A name that is no account
        costs the same time as a wrong password (checked against a dummy hash)."""
        user = self.users.get(name)
        ok = verify_password(password, self._dummy if user is None else user.password_hash)
        return user if ok and user is not None else None


class LoginThrottle:
    """Slows down repeated wrong logins, per key (a client address, a user name): the first
    ``free`` attempts cost nothing, then each further one bars the key for ``base`` seconds
    doubled per attempt (at most ``longest``). :meth:`begin` counts an attempt of a name from
    an address *before* its password is checked, and refuses it while either is barred;
    :meth:`end` with a right password clears both. ``clock`` is in seconds (monotonic). At
    most ``clients`` keys are remembered. Thread-safe. ``refused`` counts the attempts refused
    unchecked."""

    def __init__(self, *, free: int = FREE_ATTEMPTS, base: float = FIRST_BAR,
                 longest: float = LONGEST_BAR, clients: int = REMEMBERED,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.free = free
        self.base = base
        self.longest = longest
        self.clients = clients
        self.clock = clock
        self.refused = 0
        #: attempts whose password was checked (or is being checked)
        self.checked = 0
        self._failed: OrderedDict[str, tuple[int, float]] = OrderedDict()  # count, barred to
        self._lock = threading.Lock()

    def wait(self, key: str) -> float:
        """Seconds ``key`` must still wait before it may try again (0: it may now)."""
        with self._lock:
            entry = self._failed.get(key)
            return 0.0 if entry is None else max(0.0, entry[1] - self.clock())

    def failed(self, key: str) -> None:
        """Count an attempt of ``key`` and bar it if it had its free attempts."""
        with self._lock:
            self._count(key)

    def _count(self, key: str) -> None:
        count = self._failed.pop(key, (0, 0.0))[0] + 1
        delay = (0.0 if count <= self.free
                 else min(self.longest, self.base * 2.0 ** (count - self.free - 1)))
        self._failed[key] = (count, self.clock() + delay)
        while len(self._failed) > self.clients:
            self._failed.popitem(last=False)

    def succeeded(self, key: str) -> None:
        """A right login of ``key``: forget its attempts."""
        with self._lock:
            self._failed.pop(key, None)

    @staticmethod
    def keys(address: str, user: str) -> tuple[str, str]:
        """The keys of an attempt: its client address and its user name."""
        return f"address {address}", f"user {user}"

    def begin(self, address: str, user: str) -> float:
        """An attempt of ``user`` from ``address``: 0.0 if its password may be checked now
        (the attempt is then counted against both, before the check), else the seconds until
        it may (refused, not counted)."""
        keys = self.keys(address, user)
        with self._lock:
            now = self.clock()
            wait = max(max(0.0, self._failed.get(k, (0, 0.0))[1] - now) for k in keys)
            if wait > 0:
                self.refused += 1
                return wait
            for k in keys:
                self._count(k)
            self.checked += 1
            return 0.0

    def end(self, address: str, user: str, ok: bool) -> None:
        """The attempt :meth:`begin` let through was checked: a right password (``ok``)
        clears the counts of its address and name; a wrong one stays counted."""
        if ok:
            with self._lock:
                for k in self.keys(address, user):
                    self._failed.pop(k, None)


__all__ = ["ROLE_COMMANDS", "LoginThrottle", "User", "Users", "hash_password",
           "verify_password"]
