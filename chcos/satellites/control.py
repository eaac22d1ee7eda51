"""control - the typed requests a host sends a satellite on its control key, and their wire form.

A host (:mod:`chcos.satellites.host`) asks satellite N on ``chcos/<system>/m/<N>/ctl`` with one
of the requests below; :func:`encode` makes the JSON object that travels (``{"op": ...}``),
:func:`decode` checks what a satellite received and turns it back into its type, so the
satellite (:mod:`chcos.satellites.satellite`) dispatches on types, never on strings. The
answer is a JSON object ``{"ok": true, ...}`` or ``{"ok": false, "error": text, "type": the
exception's class name}``.

=============== ====================================== =========================================
op              request                                answer
=============== ====================================== =========================================
``map``         :class:`MapRequest` (part, token)      ``page``, ``part``, ``parts``, ``token``:
                                                       one page of the JSON text of ``map``,
                                                       ``alive``, ``rejected``
``log``         :class:`LogRequest`                    ``log``: the install log
``head``        :class:`HeadRequest`                   ``length``, ``hash`` of the committed
                                                       install log, ``pending``: the entry
                                                       accepted at ``length`` (or null)
``hello``       :class:`HelloRequest` (nonce)          ``machine``, ``nonce``: proof that this
                                                       satellite is up now (its sealed answer
                                                       repeats the host's fresh nonce)
``sync``        :class:`SyncRequest` (source, need)    ``applied``: entries fetched and applied
``exec``        :class:`ExecRequest` (line)            ``answer``: a runtime command's answer
``prepare``     :class:`ChangeRequest` (PREPARE)       ``seq``: checked at this log length;
                                                       ``pending``: the entry accepted at seq
``accept``      :class:`ChangeRequest` (ACCEPT)        ``seq``: saved as the uncommitted entry
``commit``      :class:`ChangeRequest` (COMMIT)        ``answer``, ``seq``: applied as entry seq
=============== ====================================== =========================================
"""

from __future__ import annotations

import enum
import json
from dataclasses import dataclass
from typing import Any

#: Longest command line accepted in a request (and in an install log).
MAX_LINE = 4096
#: Characters of the map answer's JSON text per page: the text is ASCII (``ensure_ascii``), and
#: carried in a JSON string it at most doubles, so a page stays far below the link's 1 MiB.
MAP_PAGE = 256 * 1024


class Phase(enum.Enum):
    """The step of a table change (see :mod:`chcos.satellites.satellite`)."""

    PREPARE = "prepare"   # every live satellite checks the line at log length ``seq``
    ACCEPT = "accept"     # saved as the uncommitted entry ``seq`` (the sequencer first:
                          # compare-and-set), durably, not applied
    COMMIT = "commit"     # applied as entry ``seq`` (the sequencer first: the commit point)


@dataclass(frozen=True)
class MapRequest:
    """This satellite's view of the system map, who is alive, what it refused: page ``part``
    (of MAP_PAGE characters) of the answer made for ``token`` (part 0 without a token makes a
    new answer and its token; a large system's map does not fit one link message)."""

    part: int = 0
    token: str = ""


@dataclass(frozen=True)
class LogRequest:
    """The install log."""


@dataclass(frozen=True)
class HeadRequest:
    """The install log's length and hash."""


@dataclass(frozen=True)
class HelloRequest:
    """Prove that this satellite is up: answer with its machine and ``nonce`` (fresh random
    text the host drew, at most :data:`MAX_NONCE` characters), sealed as every answer is with
    the satellite role's key. A liveliness token anyone with the link's password can declare;
    this answer only a satellite, now."""

    nonce: str


#: Longest nonce a hello carries.
MAX_NONCE = 64


@dataclass(frozen=True)
class SyncRequest:
    """Fetch the log entries this satellite misses from satellite ``source``, up to ``need``."""

    source: int
    need: int


@dataclass(frozen=True)
class ExecRequest:
    """Run a command that does not change the tables (invoke, suspend, inject...)."""

    line: str


@dataclass(frozen=True)
class ChangeRequest:
    """One step of a table change: ``line`` at log position ``seq``; ``leader`` is the
    sequencer the host chose (None: any live satellite)."""

    phase: Phase
    line: str
    seq: int
    leader: int | None = None


ControlRequest = (MapRequest | LogRequest | HeadRequest | HelloRequest | SyncRequest
                  | ExecRequest | ChangeRequest)

_PLAIN: dict[str, type[Any]] = {"log": LogRequest, "head": HeadRequest}


def encode(req: ControlRequest) -> bytes:
    """The JSON bytes that carry ``req``. Raises TypeError if it is not a control request."""
    doc: dict[str, Any]
    if isinstance(req, MapRequest):
        doc = {"op": "map", "part": req.part, "token": req.token}
    elif isinstance(req, HelloRequest):
        doc = {"op": "hello", "nonce": req.nonce}
    elif isinstance(req, SyncRequest):
        doc = {"op": "sync", "source": req.source, "need": req.need}
    elif isinstance(req, ExecRequest):
        doc = {"op": "exec", "line": req.line}
    elif isinstance(req, ChangeRequest):
        doc = {"op": req.phase.value, "line": req.line, "seq": req.seq}
        if req.leader is not None:
            doc["leader"] = req.leader
    else:
        op = next((op for op, cls in _PLAIN.items() if isinstance(req, cls)), None)
        if op is None:
            raise TypeError(f"expected a control request, got {type(req).__name__}")
        doc = {"op": op}
    return json.dumps(doc).encode()


def _int(doc: dict[str, Any], key: str, what: str, *, optional: bool = False) -> Any:
    value = doc.get(key)
    if value is None and optional:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise TypeError(f"{key}: expected {what}, got {value!r:.40}")
    return value


def _line(doc: dict[str, Any]) -> str:
    line = doc.get("line", "")
    if not isinstance(line, str) or len(line) > MAX_LINE:
        raise TypeError(f"line: expected a command line string of at most {MAX_LINE} "
                        "characters")
    return line


def decode(payload: bytes) -> ControlRequest:
    """The request in ``payload``. Raises ValueError (not JSON) or TypeError naming the key and
    what was expected (not an object, unknown op, a bad field)."""
    doc = json.loads(payload)
    if not isinstance(doc, dict):
        raise TypeError(f"expected a JSON object, got {type(doc).__name__}")
    op = doc.get("op")
    if isinstance(op, str) and op in _PLAIN:
        plain: ControlRequest = _PLAIN[op]()
        return plain
    if op == "map":
        token = doc.get("token", "")
        if not isinstance(token, str) or len(token) > 64:
            raise TypeError(f"token: expected a map answer's token, got {token!r:.40}")
        return MapRequest(_int(doc, "part", "a page number", optional=True) or 0, token)
    if op == "hello":
        nonce = doc.get("nonce")
        if not isinstance(nonce, str) or not 0 < len(nonce) <= MAX_NONCE:
            raise TypeError(f"nonce: expected 1 to {MAX_NONCE} characters, got {nonce!r:.40}")
        return HelloRequest(nonce)
    if op == "sync":
        return SyncRequest(_int(doc, "source", "a machine"), _int(doc, "need", "a log length"))
    if op == "exec":
        return ExecRequest(_line(doc))
    try:
        phase = Phase(op)
    except ValueError:
        raise TypeError(f"op: expected one of map, log, head, hello, sync, exec, prepare, "
                        f"accept, commit, got {op!r:.40}") from None
    return ChangeRequest(phase, _line(doc), _int(doc, "seq", "a log position >= 0"),
                         _int(doc, "leader", "a machine", optional=True))
