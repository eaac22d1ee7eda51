"""sysmap - sysfile.map: the system's record of itself, written soon after every change.

A readable JSON document: the loaded machines and device maps, every task in install order with
its code, links, parameters and options (standing, restart policy, back-off), every link with its
type and current priority, every device; beside them the runtime fields (status, owner, counters),
which are as current as the last time the map was written (soon after every table change or
host task operation — at most every quarter second during a burst, see
:mod:`chcos.system.mapfile` — and at ``map``, the end of a script or run, shutdown), and
``errors``: what the system collected and :meth:`chcos.system.embedded.System.check` raises
(failed interrupt handlers, link errors), oldest first. One task, link or device per line. It
is written atomically (temporary file, fsync, rename), so a crash never leaves half a map, and
:func:`replay` rebuilds a restarted system from it (installs in order, then priorities).
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
from pathlib import Path
from typing import Any

from chcos.errors import ConfigError

FORMAT = "chcos-sysfile.map/1"


def _plain(value: Any) -> Any:
    """What JSON has no form for: a dataclass instance (a typed message a task keeps in its
    world model) as a dict of its fields, anything else as its text."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
    return str(value)


_ENCODER = json.JSONEncoder(default=_plain)  # one encoder for every record (C encoder, no indent)


def write(path: str | Path, doc: dict[str, Any]) -> None:
    """Write ``doc`` to ``path`` atomically. Raises OSError if the directory is not writable."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    body = encode({"format": FORMAT, **doc})
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(body)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def encode(doc: dict[str, Any]) -> str:
    """``doc`` as readable JSON: one top-level key per line, and a list of records (tasks,
    links, devices) one record per line. Uses the C encoder (``indent`` would select the
    pure-Python one, several times slower on a map of 10,000 tasks)."""
    enc = _ENCODER.encode
    parts = []
    for key, value in doc.items():
        name = enc(key)
        if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            rows = ",\n    ".join(map(enc, value))
            parts.append(f"  {name}: [\n    {rows}\n  ]")
        else:
            parts.append(f"  {name}: {enc(value)}")
    return "{\n" + ",\n".join(parts) + "\n}\n"


def read(path: str | Path) -> dict[str, Any]:
    """Read a sysfile.map. Raises ConfigError naming the file if it is unreadable, not JSON, or
    not a chcos map."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read system map: {exc}") from exc
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path}: line {exc.lineno}: not valid JSON: {exc.msg}") from exc
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ConfigError(f"{path}: not a chcos system map (expected \"format\": \"{FORMAT}\")")
    for key in ("machines", "tasks", "links"):
        if not isinstance(doc.get(key), list):
            raise ConfigError(f"{path}: key {key!r} missing or not a list")
    return doc


def install_lines(doc: dict[str, Any]) -> list[str]:
    """The map as the host commands that rebuild it, in the thesis' syntax: boots, installs in
    order, then a setpri for every link whose priority differs from its default."""
    lines = [f"install -m{m} sysfile" for m in doc["machines"]]
    for t in doc["tasks"]:
        flags = f"-m{t['machine']}i{len(t['inputs'])}o{len(t['outputs'])}"
        extra = []
        if t.get("code") and t["code"] != t["name"]:
            extra.append(f"--code={t['code']}")
        if t.get("role", "task") != "task":
            extra.append(f"--role={t['role']}")
        if t.get("level_given"):
            extra.append(f"--level={t['level']}")
        for k, v in t.get("params", {}).items():
            extra.append(f"--param={k}={json.dumps(v)}")
        for k, v in t.get("queued", {}).items():
            extra.append(f"--queue={k}={v}")
        if t.get("standing"):
            extra.append("--standing")
        if t.get("restart", "never") != "never":
            extra.append(f"--restart={t['restart']}")
        if t.get("backoff", 1.0) != 1.0:
            extra.append(f"--backoff={t['backoff']}")
        words = ["install", flags, *extra, t["name"], *t["inputs"], *t["outputs"]]
        lines.append(" ".join(_quote(w) for w in words))
    for lk in doc["links"]:
        if lk.get("priority") != lk.get("default_priority") and not lk.get("implicit"):
            lines.append(f"setpri -{lk['priority']} {lk['src']} {lk['dst']}")
    return lines


def _quote(word: str) -> str:
    import shlex

    return shlex.quote(word)
