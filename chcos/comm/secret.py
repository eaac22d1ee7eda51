"""secret - the per-system secret that every node of a chcos system authenticates with.

A system's nodes prove two things to each other on every payload they exchange:

* **membership**: Zenoh user/password authentication (``transport.auth.usrpwd``) keeps a process
  that does not hold the secret from opening a session with any satellite at all, so it can
  neither read nor send anything. The credentials and the dictionary file every listening node
  checks them against are derived from the secret (:meth:`SystemSecret.zenoh_auth`);
* **role**: every payload is sealed (:class:`Sealer`) with a key derived from the key of the
  sender's role. Satellites accept host requests (install, setpri, boot, invoke, suspend,
  resume, inject) only when sealed with the *host* key, and device values, actuator commands,
  statuses and e-stops only when sealed with the *satellite* key. A seal also binds the Zenoh
  key the payload was sent on, so a payload cannot be moved onto another key;
* **freshness**: every seal carries its sender's identity, the sender's run (a random epoch
  drawn at each start), a sequence number and a time stamp. A receiver refuses a payload
  older than :data:`MAX_AGE_S`, further ahead than :data:`MAX_AHEAD_S`, sealed before the
  receiver itself started (so a restarted receiver, whose replay windows start empty, takes
  nothing recorded before its restart), from a run its sender has replaced, already
  accepted, or reordered beyond :data:`WINDOW`, and counts each refusal by kind
  (:class:`Refusal`);
* **confidentiality**: payloads are encrypted (AES-256-GCM, a key per sender's run derived
  with HKDF-SHA256 from the role key, the nonce made of the epoch and the sequence number):
  a session that passed the Zenoh authentication (it holds a ``[link.auth]`` password, or the
  TLS files) but not the secret sees only headers and ciphertext.

The secret is generated on first use (``secrets.token_bytes``) and stored as JSON with
owner-only permissions (0600, directory 0700) in the system's state directory, or where the
system file's ``secret_file`` says. Every machine of a system spread over several computers
needs a copy of the same file (copy it with ``scp -p``; keep it 0600).
"""

from __future__ import annotations

import enum
import functools
import hashlib
import hmac
import itertools
import json
import logging
import os
import secrets
import shutil
import stat
import struct
import subprocess
import tempfile
import threading
import time
import types
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

from chcos.errors import ConfigError, LinkError

if TYPE_CHECKING:
    from cryptography.hazmat.primitives.ciphers.aead import AESGCM

log = logging.getLogger("chcos.comm")

FORMAT = "chcos-secret/1"
#: The roles of a system's nodes, and the byte that names each in a sealed payload.
ROLES: dict[str, int] = {"host": 1, "satellite": 2}
_ROLE_OF = {v: k for k, v in ROLES.items()}
TAG_BYTES = 16
#: Bytes a seal adds to a payload (header and AEAD tag).
SEAL_BYTES = 35 + TAG_BYTES


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

    def sealer(self, role: str, sender: str | None = None) -> Sealer:
        """The :class:`Sealer` of a node of ``role``, named ``sender`` if it keeps one identity
        across restarts (a satellite's machine), else a sender of its own. Raises ConfigError
        on an unknown role."""
        if role not in ROLES:
            raise ConfigError(f"role {role!r}: expected one of {', '.join(ROLES)}")
        return Sealer(role, self.keys, self.identity, sender=sender)


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


class Refusal(enum.Enum):
    """Why :meth:`Sealer.open` refused a payload (each kind is counted apart)."""

    UNAUTHENTICATED = "unauthenticated"          # too short, unknown version/role, bad tag
    REPLAYED = "replayed"                        # its sequence number was already accepted
    BEHIND_WINDOW = "behind the replay window"   # reordered further back than WINDOW
    STALE = "too old"                            # time stamp older than the age bound
    FUTURE = "from the future"                   # time stamp beyond the clock skew allowance
    OLD_RUN = "from a sender's earlier run"      # an epoch the sender has since replaced
    BEFORE_START = "sealed before this receiver started"  # recorded before its (re)start


class SealRefused(LinkError):
    """A payload :meth:`Sealer.open` refused; ``refusal`` says which kind."""

    def __init__(self, refusal: Refusal, detail: str) -> None:
        super().__init__(f"{refusal.value}: {detail}")
        self.refusal = refusal


@functools.cache
def _crypto() -> Any:
    """The pieces of the cryptography package a seal needs (``AESGCM``, ``HKDF``, ``hashes``,
    ``InvalidTag``), imported when a seal is first made or opened: a system in one process
    needs none (cryptography comes with the ``satellites`` extra). Raises ConfigError naming
    the extra when it is not installed."""
    try:
        from cryptography.exceptions import InvalidTag
        from cryptography.hazmat.primitives import hashes
        from cryptography.hazmat.primitives.ciphers.aead import AESGCM
        from cryptography.hazmat.primitives.kdf.hkdf import HKDF
    except ImportError as exc:
        raise ConfigError(f"sealed messages between satellites need the cryptography package "
                          f"(pip install 'chcos[satellites]'): {exc}") from exc
    return types.SimpleNamespace(AESGCM=AESGCM, HKDF=HKDF, hashes=hashes, InvalidTag=InvalidTag)


def _derive(key: bytes, role: int, sender: bytes, epoch: bytes) -> AESGCM:
    """The AEAD of one run (``epoch``) of one sender of ``role``: its own key, derived from the
    role's key of the system secret with HKDF-SHA256."""
    c = _crypto()
    hkdf = c.HKDF(algorithm=c.hashes.SHA256(), length=32, salt=None,
                  info=b"chcos-seal/2 " + bytes((role,)) + sender + epoch)
    aead: AESGCM = c.AESGCM(hkdf.derive(key))
    return aead


class _Window:
    """The sequence numbers accepted lately on one stream of one sender's run: the highest
    (``top``) and a bitmap of the :data:`WINDOW` below it kept in 64-bit blocks used as a ring
    (RFC 6479): a message in order sets one bit, and clears a block when it enters a new one,
    whatever the window's size."""

    __slots__ = ("blocks", "top")

    def __init__(self) -> None:
        self.top = 0
        self.blocks = [0] * _BLOCKS

    def admit(self, seq: int) -> Refusal | None:
        """Record ``seq`` and return None if it is new and within the window, else say why
        not (and record nothing)."""
        top = self.top
        blocks = self.blocks
        if seq > top:  # ahead of all accepted: nothing of it recorded yet
            block = seq >> 6
            current = top >> 6
            if block != current:
                if block - current >= _BLOCKS:  # a jump past the whole window: all new
                    blocks[:] = _EMPTY
                else:
                    for b in range(current + 1, block + 1):  # the blocks entered are new
                        blocks[b % _BLOCKS] = 0
            self.top = seq
            blocks[block % _BLOCKS] |= 1 << (seq & 63)
            return None
        if top - seq >= WINDOW:
            return Refusal.BEHIND_WINDOW
        i = (seq >> 6) % _BLOCKS
        bit = 1 << (seq & 63)
        if blocks[i] & bit:
            return Refusal.REPLAYED
        blocks[i] |= bit
        return None


@dataclass
class _Sender:
    """What a receiver remembers of one sender: its current run (epoch), the first time stamp
    seen in it, one window per (receiver, stream), and the runs it replaced."""

    epoch: bytes
    first_ns: int
    last_ns: int
    aead: AESGCM
    windows: dict[tuple[int, int], _Window] = field(default_factory=dict)
    retired: list[bytes] = field(default_factory=list)


#: Receive windows kept per stream (sequence numbers a message may be reordered by).
WINDOW = 4096
_BLOCKS = WINDOW // 64 + 1  # the ring of a window: WINDOW bits and the block being filled
_EMPTY = [0] * _BLOCKS
#: Oldest message accepted, and furthest into the future (clock skew allowance), in seconds.
MAX_AGE_S = 30.0
MAX_AHEAD_S = 30.0
#: Senders a receiver remembers; beyond this the first heard is forgotten (and nothing older
#: than its newest message is accepted from an unknown sender again).
MAX_SENDERS = 4096
#: Windows kept per sender (one per receiver and stream).
MAX_WINDOWS = 256
#: Earlier runs remembered per sender.
RETIRED_RUNS = 16
#: The stream of replies to requests (publications and requests use their priority band).
REPLY_STREAM = 255

_HEADER = struct.Struct(">BBB8s8sQQ")  # version, role, stream, sender, epoch, sequence, time
_HEADER_SIZE = _HEADER.size
_unpack_header = _HEADER.unpack_from
_PREFIX = struct.Struct(">BBB8s8s")  # what a run seals alike on a stream: version to epoch
_TAIL = struct.Struct(">QQ")  # sequence number, time stamp
_pack_tail = _TAIL.pack
#: Where a sealed payload's nonce lies in its header: the epoch's first four bytes, then the
#: sequence number.
_NONCE_RUN = slice(11, 15)
_NONCE_SEQ = slice(19, 27)
SEAL_VERSION = 2


class Sealer:
    """Seals payloads as this node (``role``, a sender identity and a run of its own) and opens
    sealed payloads, telling which role sealed them.

    A sealed payload is a header (version, role, stream, sender id, epoch, sequence number,
    time stamp in ns) followed by the payload encrypted with AES-256-GCM under a key derived
    (HKDF-SHA256) from the role's key, the sender id and the epoch; the nonce is the epoch's
    first four bytes and the sequence number, which never repeats within a run, and the
    header and the Zenoh key are authenticated with it. ``sender`` names the node (a
    satellite passes its machine, so that its restarts are one sender's successive runs);
    without one every Sealer is a sender of its own. Each Sealer starts a new run: a random
    64-bit epoch, sequence numbers from 1.

    Receiving, :meth:`open` refuses (:class:`SealRefused`, counted in :attr:`refused` by
    :class:`Refusal`) a payload that does not authenticate, is older than ``max_age_s`` or
    further ahead than ``max_ahead_s`` of ``clock`` (ns since the epoch), was sealed before
    this Sealer was made (``clock`` then: a receiver's restart forgets its windows, so it
    takes nothing recorded before it), comes from a run its sender has since replaced,
    repeats a sequence number already accepted, or falls behind the :data:`WINDOW` of its
    stream. Between computers this start bound is as good as their clocks agree (a sender's
    clock behind the receiver's delays its first messages by the difference); a clock stepped
    back since the start (``monotonic`` tells) moves the bound back by as much. Thread-safe.

    Per message, sealing packs a time stamp and a counter behind a header prefix made once
    per stream, and opening uses the AEAD derived once per sender's run (kept with the run,
    looked up without the lock) and a ring of window blocks (one bit set per message in
    order)."""

    def __init__(self, role: str, keys: dict[str, bytes], identity: str, *,
                 sender: str | None = None, clock: Callable[[], int] = time.time_ns,
                 monotonic: Callable[[], int] = time.monotonic_ns,
                 max_age_s: float = MAX_AGE_S, max_ahead_s: float = MAX_AHEAD_S) -> None:
        self.role = role
        self.identity = identity
        self._role_keys = {ROLES[r]: k for r, k in keys.items()}
        self._mine = ROLES[role]
        self.sender = (hashlib.sha256(f"{identity}/{role}/{sender}".encode()).digest()[:8]
                       if sender is not None else secrets.token_bytes(8))
        self.epoch = secrets.token_bytes(8)
        self._aead = _derive(self._role_keys[self._mine], self._mine, self.sender, self.epoch)
        self._encrypt = self._aead.encrypt
        self._nonce = self.epoch[:4]
        self._prefixes = [_PREFIX.pack(SEAL_VERSION, self._mine, stream, self.sender, self.epoch)
                          for stream in range(256)]
        self._seq = itertools.count(1)  # next() is atomic: concurrent seals never share one
        self._clock = clock
        self._started = clock()  # nothing sealed before this is accepted (see above)
        self._monotonic = monotonic
        self._started_mono = monotonic()
        self._max_age = int(max_age_s * 1e9)
        self._max_ahead = int(max_ahead_s * 1e9)
        self._lock = threading.Lock()
        # senders by (role, id), oldest first; their current (epoch, AEAD) apart for the
        # lock-free look-up
        self._senders: dict[tuple[int, bytes], _Sender] = {}
        self._runs: dict[tuple[int, bytes], tuple[bytes, AESGCM]] = {}
        self._floor = 0  # no unknown sender is accepted at or before this time stamp (ns)
        self.refused: dict[Refusal, int] = dict.fromkeys(Refusal, 0)

    def seal(self, key_expr: str, payload: bytes, stream: int = 0) -> bytes:
        """``payload`` sealed for ``key_expr``: the header then the encrypted payload and its
        tag. ``stream`` (0..255) is the ordering domain the receiver keeps a window for:
        messages that the transport may reorder among each other (e.g. two priority bands)
        belong to different streams."""
        tail = _pack_tail(next(self._seq), self._clock())
        header = self._prefixes[stream] + tail
        return header + self._encrypt(self._nonce + tail[:8], payload,
                                      header + key_expr.encode())

    def open(self, key_expr: str, data: bytes, receiver: int = 0) -> tuple[str, bytes]:
        """(role, payload) of a sealed ``data`` received on ``key_expr`` by ``receiver`` (one
        number per subscriber or server of this node: each gets a message once). Raises SealRefused
        (a LinkError) saying why it is refused: not sealed by a member of this system (too
        short, unknown version or role, altered, sent on another key), too old or ahead of
        the clock, sealed before this receiver started, from a sender's earlier run,
        replayed, or behind the window."""
        if len(data) < SEAL_BYTES:
            return self._refuse(Refusal.UNAUTHENTICATED, "payload too short to carry a seal")
        version, role, stream, sender, epoch, seq, stamp = _unpack_header(data)
        if version != SEAL_VERSION:
            return self._refuse(Refusal.UNAUTHENTICATED, f"seal version {version}, expected "
                                f"{SEAL_VERSION}")
        ident = (role, sender)
        known = self._runs.get(ident)  # read without the lock: one tuple, replaced whole
        if known is not None and known[0] == epoch:
            aead = known[1]
        else:
            key = self._role_keys.get(role)
            if key is None:
                return self._refuse(Refusal.UNAUTHENTICATED, f"unknown role byte {role}")
            aead = _derive(key, role, sender, epoch)
        try:
            payload = aead.decrypt(data[_NONCE_RUN] + data[_NONCE_SEQ], data[_HEADER_SIZE:],
                                   data[:_HEADER_SIZE] + key_expr.encode())
        except _crypto().InvalidTag:    # (evaluated only when decrypt raised)
            return self._refuse(Refusal.UNAUTHENTICATED, "bad seal (not sealed by a member of "
                                "this system, altered, or sent on another key)")
        if stamp < self._started and stamp < self._start_now():
            return self._refuse(Refusal.BEFORE_START, f"sealed "
                                f"{(self._started - stamp) / 1e9:.3f} s before this receiver "
                                f"started (recorded and replayed, or its sender's clock is "
                                f"behind)")
        now = self._clock()
        if stamp < now - self._max_age:
            return self._refuse(Refusal.STALE, f"sealed {(now - stamp) / 1e9:.1f} s ago, at "
                                f"most {self._max_age / 1e9:g} s accepted")
        if stamp > now + self._max_ahead:
            return self._refuse(Refusal.FUTURE, f"sealed {(stamp - now) / 1e9:.1f} s ahead of "
                                f"this clock, at most {self._max_ahead / 1e9:g} s accepted")
        with self._lock:
            s = self._senders.get(ident)
            if (s is not None and s.epoch == epoch
                    and (window := s.windows.get((receiver, stream))) is not None):
                why = window.admit(seq)  # the usual case: a run and a stream heard before
                if why is None and stamp > s.last_ns:
                    s.last_ns = stamp
            else:
                why = self._admit(ident, epoch, aead, (receiver, stream), seq, stamp)
        if why is not None:
            return self._refuse(why, f"sequence {seq} of stream {stream} of sender "
                                f"{sender.hex()} run {epoch.hex()}")
        return _ROLE_OF[role], payload

    def _start_now(self) -> int:
        """This receiver's start on ``clock`` as it reads now: the wall clock at the start, or
        earlier by as much as the clock has been stepped back since (measured against the
        monotonic clock), so that a clock stepped back does not refuse what is sealed after
        the start."""
        since = self._monotonic() - self._started_mono
        return min(self._started, self._clock() - since)

    def _admit(self, ident: tuple[int, bytes], epoch: bytes, aead: AESGCM,
               stream: tuple[int, int], seq: int, stamp: int) -> Refusal | None:
        """Record an authenticated message in its sender's state (lock held), or say why it
        is refused."""
        s = self._senders.get(ident)
        if s is None:
            if stamp <= self._floor:
                return Refusal.STALE
            s = self._senders[ident] = _Sender(epoch, stamp, stamp, aead)
            self._runs[ident] = (epoch, aead)
            if len(self._senders) > MAX_SENDERS:  # forget the oldest (it may come back as new)
                gone = next(iter(self._senders))
                old = self._senders.pop(gone)
                self._runs.pop(gone, None)
                self._floor = max(self._floor, old.last_ns)
        elif s.epoch != epoch:
            if epoch in s.retired or stamp < s.first_ns:
                return Refusal.OLD_RUN
            s.retired.append(s.epoch)
            del s.retired[:-RETIRED_RUNS]
            s.epoch, s.first_ns, s.aead, s.windows = epoch, stamp, aead, {}
            self._runs[ident] = (epoch, aead)
        window = s.windows.get(stream)
        if window is None:
            window = s.windows[stream] = _Window()
            if len(s.windows) > MAX_WINDOWS:  # receivers come and go: forget the oldest
                del s.windows[next(iter(s.windows))]
        why = window.admit(seq)
        if why is None and stamp > s.last_ns:
            s.last_ns = stamp
        return why

    def _refuse(self, refusal: Refusal, detail: str) -> NoReturn:
        with self._lock:
            self.refused[refusal] += 1
        raise SealRefused(refusal, detail)


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
