"""installlog - the replicated install log of a satellite: its entries, its file, and the
check of a task's code reference before anything is imported (see
:mod:`chcos.satellites.satellite`).

The log is a list of host command lines that change the tables (install, setpri, resetpri,
boot), applied in order on every satellite. A satellite keeps its *committed* entries in
``m<N>.log`` in the system's state directory, one JSON string per line, fsync'd on every
append; peers exchange it as one JSON list. The one entry it accepted but does not yet know to
be committed (see :mod:`chcos.satellites.satellite` for the protocol) is kept apart, in
``m<N>.pending`` (``{"seq": N, "line": "..."}``, fsync'd), so that a restart can tell its
committed log from its uncommitted tail.
"""

from __future__ import annotations

import importlib.machinery
import json
import os
import sys
from pathlib import Path

from chcos.errors import ChcosError, LinkError
from chcos.satellites.control import MAX_LINE
from chcos.system import cmdline

#: The requests an install log may hold: those that change the tables.
MUTATING = (cmdline.Install, cmdline.SetPri, cmdline.ResetPri, cmdline.Boot)


def code_problem(ref: str, task_path: tuple[Path, ...]) -> str | None:
    """Why the task code reference ``ref`` may not be loaded, or None; imports nothing.

    A file reference (``dir/A1.py[:func]``, ``A1.py``) must resolve to an existing file inside
    one of the ``task_path`` directories; a bare name (``A1``) is looked up there first; a
    dotted module name must exist on the Python path (found without importing it)."""
    target = ref.partition(":")[0]
    dirs = [d.resolve() for d in task_path]
    where = ", ".join(str(d) for d in dirs) or "no task path"
    if target.endswith(".py") or "/" in target:
        path = Path(target)
        candidates = [path] if path.is_absolute() else [d / path for d in dirs]
        for c in candidates:
            c = c.resolve()
            if any(c.is_relative_to(d) for d in dirs):
                return None if c.is_file() else f"task code {ref}: no file {c}"
        return (f"task code {ref}: {target} is outside the system's task path ({where}); "
                "task code is loaded only from there or from modules on the Python path")
    if "." not in target and any((d / f"{target}.py").is_file() for d in dirs):
        return None
    locations: list[str] | None = None
    parts = target.split(".")
    for i in range(len(parts)):
        name = ".".join(parts[:i + 1])
        mod = sys.modules.get(name)
        if mod is not None:
            locations = list(getattr(mod, "__path__", []) or [])
            continue
        try:
            spec = importlib.machinery.PathFinder.find_spec(name, locations)
        except (ImportError, ValueError) as exc:
            return f"task code {ref}: no module {target} ({exc})"
        if spec is None:
            return (f"task code {ref}: no module {target} (looked in {where} and on the "
                    "Python path)")
        locations = list(spec.submodule_search_locations or [])
    return None


def parse_log(raw: bytes) -> list[str]:
    """The install log in a peer's answer: a JSON list of install/setpri/boot lines. Raises
    LinkError saying what is wrong with anything else."""
    try:
        entries = json.loads(raw)
    except ValueError as exc:
        raise LinkError(f"malformed install log from a peer: not JSON ({exc})") from exc
    if not isinstance(entries, list):
        raise LinkError(f"malformed install log from a peer: expected a list of install lines, "
                        f"got {type(entries).__name__}")
    for i, line in enumerate(entries):
        if not isinstance(line, str) or len(line) > MAX_LINE:
            raise LinkError(f"malformed install log from a peer: entry {i} is not an install "
                            "line")
        try:
            req = cmdline.parse(line)
        except ChcosError as exc:
            raise LinkError(f"malformed install log from a peer: entry {i}: {exc}") from exc
        if not isinstance(req, MUTATING):
            raise LinkError(f"malformed install log from a peer: entry {i} ({line!r}) is not "
                            "an install, setpri or boot")
    return entries


def read_log(path: Path) -> list[str]:
    """The install log saved in ``path`` ([] if there is no file). Raises LinkError naming the
    file if it is corrupt."""
    try:
        raw = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return []
    try:
        return parse_log(("[" + ",".join(raw.splitlines()) + "]").encode())
    except LinkError as exc:
        raise LinkError(f"{path}: {exc}") from exc


def _open_private(path: Path, flags: int) -> int:
    """A descriptor on ``path`` opened with ``flags``, the file owner-only (0600) whatever
    mode an older file had (install lines name code and devices: not for other users)."""
    fd = os.open(path, flags | os.O_CREAT, 0o600)
    try:
        os.fchmod(fd, 0o600)
    except BaseException:
        os.close(fd)
        raise
    return fd


def write_log(path: Path, entries: list[str]) -> None:
    """Write the whole install log to ``path`` (atomically: temporary file, fsync, rename;
    owner-only, 0600). Raises OSError if it cannot be written."""
    tmp = path.with_name(f".{path.name}.tmp")
    with os.fdopen(_open_private(tmp, os.O_WRONLY | os.O_TRUNC), "w", encoding="utf-8") as f:
        f.write("".join(json.dumps(line) + "\n" for line in entries))
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def append_log(path: Path, line: str) -> None:
    """Append one entry to the install log in ``path`` (fsync'd; the file owner-only, 0600).
    Raises OSError."""
    with os.fdopen(_open_private(path, os.O_WRONLY | os.O_APPEND), "a", encoding="utf-8") as f:
        f.write(json.dumps(line) + "\n")
        f.flush()
        os.fsync(f.fileno())


def read_pending(path: Path) -> tuple[int, str] | None:
    """The uncommitted entry saved in ``path`` as (log position, line), or None if there is no
    file. Raises LinkError naming the file if it is corrupt."""
    try:
        raw = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    try:
        doc = json.loads(raw)
        seq, line = doc["seq"], doc["line"]
        if isinstance(seq, bool) or not isinstance(seq, int) or seq < 0:
            raise ValueError(f"seq: expected a log position, got {seq!r:.40}")
        parse_log(json.dumps([line]).encode())
    except (ValueError, KeyError, TypeError, LinkError) as exc:
        raise LinkError(f"{path}: not an uncommitted install log entry ({exc})") from exc
    return seq, str(line)


def write_pending(path: Path, seq: int, line: str) -> None:
    """Save the uncommitted entry ``line`` at log position ``seq`` in ``path`` (atomically,
    fsync'd, owner-only). Raises OSError if it cannot be written."""
    tmp = path.with_name(f".{path.name}.tmp")
    with os.fdopen(_open_private(tmp, os.O_WRONLY | os.O_TRUNC), "w", encoding="utf-8") as f:
        f.write(json.dumps({"seq": seq, "line": line}))
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def clear_pending(path: Path) -> None:
    """Remove the uncommitted entry saved in ``path`` (no error if there is none)."""
    path.unlink(missing_ok=True)
