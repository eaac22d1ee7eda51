"""secret - the per-system secret that every node of a chcos system authenticates with.

A system's nodes prove two things to each other on every payload they exchange:

* **membership**: Zenoh user/password authentication (``transport.auth.usrpwd``) keeps a process
  that does not hold the secret from opening a session with any satellite at all, so it can
  neither read nor send anything. The credentials and the dictionary file every listening node
  checks them against are derived from the secret (:meth:`SystemSecret.zenoh_auth`);
* **role**: every payload carries an HMAC-SHA256 tag made with the key of the sender's role
  (:class:`Sealer`). Satellites accept host requests (install, setpri, boot, invoke, suspend,
  resume, inject) only when sealed with the *host* key, and device values, actuator commands,
  statuses and e-stops only when sealed with the *satellite* key. A tag also binds the Zenoh key
  the payload was sent on, so a payload cannot be replayed onto another key.

The secret is generated on first use (``secrets.token_bytes``) and stored as JSON with
owner-only permissions (0600, directory 0700) in the system's state directory, or where the
system file's ``secret_file`` says. Every machine of a system spread over several computers
needs a copy of the same file (copy it with ``scp -p``; keep it 0600).
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
import os
import secrets
import shutil
import stat
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from chcos.errors import ConfigError, LinkError

log = logging.getLogger("chcos.comm")

FORMAT = "chcos-secret/1"
#: The roles of a system's nodes, and the byte that names each in a sealed payload.
ROLES: dict[str, int] = {"host": 1, "satellite": 2}
_ROLE_OF = {v: k for k, v in ROLES.items()}
TAG_BYTES = 16
SEAL_BYTES = 1 + TAG_BYTES


def _owner_only(path: Path) -> None:
    """Raise ConfigError if ``path`` can be read or written by anyone but its owner."""
    mode = path.stat().st_mode
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise ConfigError(
            f"{path}: secret file is accessible by group or others (mode {stat.filemode(mode)});"
            f" expected owner-only permissions: chmod 600 {path}")


@dataclass(frozen=True)
class SystemSecret:
    """The secret of system ``system``: an identity and one key per role."""

    path: Path
    system: str
    identity: str
    keys: dict[str, bytes]

    def __repr__(self) -> str:  # never print the keys
        return f"SystemSecret({self.system!r}, identity={self.identity!r}, path={self.path})"

    def password(self, role: str) -> str:
        """The Zenoh password of ``role`` (derived from its key)."""
        return hmac.new(self.keys[role], b"chcos zenoh usrpwd", hashlib.sha256).hexdigest()

    def dictionary(self) -> Path:
        """Write (atomically, mode 0600) and return the Zenoh dictionary file beside the secret:
        one ``role:password`` line per role."""
        path = self.path.with_name(self.path.stem + ".users")
        text = "".join(f"{role}:{self.password(role)}\n" for role in ROLES)
        if not path.exists() or path.read_text(encoding="utf-8") != text:
            _write_private(path, text)
        return path

    def sealer(self, role: str) -> Sealer:
        """The :class:`Sealer` of a node of ``role``. Raises ConfigError on an unknown role."""
        if role not in ROLES:
            raise ConfigError(f"role {role!r}: expected one of {', '.join(ROLES)}")
        return Sealer(role, self.keys, self.identity)


def _write_private(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(text)
    os.replace(tmp, path)


def load_or_create(path: Path, system: str) -> SystemSecret:
    """The secret of ``system`` at ``path``: read it, or generate it there (mode 0600, its
    directory 0700) if there is none yet. Several processes starting at once agree on one
    secret (the first to create the file wins; the others read it).

    Raises ConfigError if the file is not a secret of ``system``, is malformed, or is readable
    by group or others."""
    path = Path(path)
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        doc = {"format": FORMAT, "system": system, "identity": secrets.token_hex(16),
               "keys": {role: secrets.token_hex(32) for role in ROLES}}
        tmp = path.with_name(f".{path.name}.{os.getpid()}.new")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(doc, f)
        try:
            os.link(tmp, path)  # atomic, fails if another process was first
            log.info("generated the secret of system %s in %s", system, path)
        except FileExistsError:
            pass
        finally:
            tmp.unlink()
    _owner_only(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        if doc.get("format") != FORMAT:
            raise ValueError(f"format {doc.get('format')!r}, expected {FORMAT!r}")
        keys = {role: bytes.fromhex(doc["keys"][role]) for role in ROLES}
        if any(len(k) < 16 for k in keys.values()):
            raise ValueError("a key shorter than 16 bytes")
        identity = str(doc["identity"])
        owner = doc["system"]
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ConfigError(f"{path}: not a chcos secret file: {exc}") from exc
    if owner != system:
        raise ConfigError(f"{path}: the secret of system {owner!r}, not of {system!r}")
    return SystemSecret(path, system, identity, keys)


_EXT = ("subjectAltName = IP:127.0.0.1,IP:::1,DNS:localhost\nbasicConstraints = CA:FALSE\n"
        "keyUsage = digitalSignature\nextendedKeyUsage = serverAuth, clientAuth\n")


def loopback_pki(directory: Path, system: str) -> tuple[Path, Path, Path] | None:
    """The system's own loopback TLS files (ca.pem, node.pem, node.key) in ``directory/tls``,
    made on first use with the openssl tool (EC P-256, ten years, naming 127.0.0.1, ::1 and
    localhost; the CA's key is deleted once the node certificate is signed, so nothing else can
    be signed with it). Returns None if the openssl tool is missing. Raises ConfigError if
    openssl fails or the files are readable by others."""
    final = directory / "tls"
    files = (final / "ca.pem", final / "node.pem", final / "node.key")
    if not final.exists():
        openssl = shutil.which("openssl")
        if openssl is None:
            return None
        directory.mkdir(parents=True, exist_ok=True, mode=0o700)
        work = Path(tempfile.mkdtemp(prefix=".tls-", dir=directory))
        ec = ("-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes")
        (work / "ext.cnf").write_text(_EXT)
        try:
            for args in (
                ("req", "-x509", *ec, "-keyout", "ca.key", "-out", "ca.pem", "-days", "3650",
                 "-subj", f"/CN=chcos {system} CA"),
                ("req", *ec, "-keyout", "node.key", "-out", "node.csr",
                 "-subj", f"/CN=chcos {system} node"),
                ("x509", "-req", "-in", "node.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
                 "-CAcreateserial", "-out", "node.pem", "-days", "3650", "-extfile", "ext.cnf"),
            ):
                subprocess.run([openssl, *args], cwd=work, check=True, capture_output=True,
                               timeout=60)
            for name in ("ca.key", "node.csr", "ext.cnf", "ca.srl"):
                (work / name).unlink(missing_ok=True)
            for f in work.iterdir():
                f.chmod(0o600)
            try:
                work.rename(final)  # atomic; another process may have been first
            except OSError:
                if not final.exists():
                    raise
        except (OSError, subprocess.SubprocessError) as exc:
            err = getattr(exc, "stderr", b"") or b""
            raise ConfigError(f"{final}: cannot make the loopback TLS certificates with "
                              f"openssl: {exc} {err.decode(errors='replace')[:300]}") from exc
        finally:
            shutil.rmtree(work, ignore_errors=True)
        log.info("made the loopback TLS certificates of system %s in %s", system, final)
    for f in files:
        if not f.is_file():
            raise ConfigError(f"{final}: expected {f.name} (remove the directory to remake it)")
        _owner_only(f)
    return files


class Sealer:
    """Seals payloads with the key of this node's ``role`` and opens sealed payloads, telling
    which role sealed them. Thread-safe (stateless apart from counters)."""

    def __init__(self, role: str, keys: dict[str, bytes], identity: str) -> None:
        self.role = role
        self.identity = identity
        self._keys = {ROLES[r]: hmac.new(k, digestmod=hashlib.sha256) for r, k in keys.items()}
        self._mine = ROLES[role]

    def _tag(self, role: int, key_expr: str, payload: bytes) -> bytes:
        h = self._keys[role].copy()  # keyed state made once; copying it is cheaper than a new key
        h.update(key_expr.encode() + b"\0" + bytes((role,)))
        h.update(payload)
        return h.digest()[:TAG_BYTES]

    def seal(self, key_expr: str, payload: bytes) -> bytes:
        """``payload`` followed by this node's role byte and the tag over key and payload."""
        return payload + bytes((self._mine,)) + self._tag(self._mine, key_expr, payload)

    def open(self, key_expr: str, data: bytes) -> tuple[str, bytes]:
        """(role, payload) of a sealed ``data`` received on ``key_expr``. Raises LinkError if
        it is too short, names no known role, or its tag does not match (not sealed by a member
        of this system, altered, or sent on another key)."""
        if len(data) < SEAL_BYTES:
            raise LinkError("unauthenticated: payload too short to carry a seal")
        payload, role, tag = data[:-SEAL_BYTES], data[-SEAL_BYTES], data[-TAG_BYTES:]
        if role not in self._keys:
            raise LinkError(f"unauthenticated: unknown role byte {role}")
        if not hmac.compare_digest(tag, self._tag(role, key_expr, payload)):
            raise LinkError("unauthenticated: bad seal (not sealed by a member of this system)")
        return _ROLE_OF[role], payload


class Throttle:
    """Counts rejected or malformed input by cause, and logs each cause at most once per
    ``interval`` seconds (with how many were suppressed meanwhile), never with a traceback.
    Thread-safe."""

    def __init__(self, logger: logging.Logger, interval: float = 10.0) -> None:
        self.logger = logger
        self.interval = interval
        self.counts: dict[str, int] = {}
        self._last: dict[str, tuple[float, int]] = {}
        self._lock = threading.Lock()

    def note(self, cause: str, detail: str) -> None:
        """Count one event of ``cause``; log it unless that cause was logged recently."""
        now = time.monotonic()
        with self._lock:
            n = self.counts[cause] = self.counts.get(cause, 0) + 1
            last = self._last.get(cause)
            if last is not None and now - last[0] < self.interval:
                return
            since = n - (last[1] if last else 0) - 1
            self._last[cause] = (now, n)
        more = f" ({since} more since the last report)" if since else ""
        self.logger.warning("%s: %s%s", cause, detail[:300], more)

    @property
    def total(self) -> int:
        """How many events were counted, all causes together."""
        with self._lock:
            return sum(self.counts.values())
