"""digest - a run's digest: what a virtual-time run did, as one document and one hash.

A run on virtual time must give the same answer on every machine (issue 47): the same device
readings and commands, the same task executions, the same events at the same virtual instants,
on a quiet or a loaded machine and whatever ``PYTHONHASHSEED``. :class:`EventRecord` is the
instrument that keeps the event log with its virtual times; :func:`system_doc` takes a System's
part of the digest (every device's readings, commands, refusals, status and last value, every
task's executions, activations, completions and abnormal ends, the event log, the clock);
:func:`digest_of` hashes a document (canonical JSON, floats by ``repr``, so the hash changes with
any bit of any figure); :func:`differences` names what two documents disagree on, for a test's
message. The welding cell adds its weld figures (:func:`chcos.apps.weld.runner` has the
``--digest`` tool, :mod:`chcos.apps.weld.rundigest` the job).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from chcos.kernel.instrument import Instrument

if TYPE_CHECKING:
    from chcos.kernel.clock import Clock
    from chcos.system.embedded import System


class EventRecord(Instrument):
    """Keeps every system event (``kind``, ``detail``) with the clock time it happened at."""

    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        #: (clock time, kind, detail) of every event, oldest first
        self.events: list[tuple[float, str, str]] = []

    def event(self, kind: str, detail: str) -> None:
        """Record one event at the clock's time."""
        self.events.append((self.clock.now(), kind, detail))


def system_doc(system: System, events: EventRecord | None = None) -> dict[str, Any]:
    """The System's part of a run digest: per device (by name) its readings, commands,
    refusals, overwrites, dropped readings, status and last value; per task its executions,
    activations, completions, abnormal ends and restarts; the clock; the event log, if an
    :class:`EventRecord` kept it. Plain data (JSON-ready, values as given)."""
    devices = {e.name: {"readings": e.readings, "commands": e.commands, "rejected": e.rejected,
                        "overwrites": e.overwrites, "dropped": e.dropped,
                        "status": e.status.value, "value": _plain(e.value)}
               for e in sorted(system.devtab, key=lambda e: e.name)}
    tasks = {t.name: {"steps": t.steps, "activations": t.activations,
                      "completions": t.completions, "abnormal": t.abnormal,
                      "restarts": t.restarts}
             for t in sorted(system.tsktab, key=lambda t: t.name)}
    doc: dict[str, Any] = {"clock": system.kernel.clock.now(), "devices": devices,
                           "tasks": tasks}
    if events is not None:
        doc["events"] = [[t, kind, detail] for t, kind, detail in events.events]
    return doc


def _plain(value: Any) -> Any:
    """``value`` as JSON can carry it exactly (a float by its repr, so no bit is lost)."""
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, bool | int | str) or value is None:
        return value
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in sorted(value.items(), key=lambda kv: str(kv[0]))}
    return repr(value)


def digest_of(doc: Any) -> str:
    """The SHA-256 of ``doc`` as canonical JSON (sorted keys, every float by ``repr``)."""
    text = json.dumps(_plain(doc), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def differences(a: Any, b: Any, path: str = "", limit: int = 20) -> list[str]:
    """Where documents ``a`` and ``b`` disagree (``path: a != b``), the first ``limit``."""
    return list(_diff(_plain(a), _plain(b), path))[:limit]


def _diff(a: Any, b: Any, path: str) -> Iterator[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                yield f"{path}/{k}: only in {'the second' if k not in a else 'the first'}"
            else:
                yield from _diff(a[k], b[k], f"{path}/{k}")
    elif isinstance(a, list) and isinstance(b, list):
        for i, (x, y) in enumerate(zip(a, b, strict=False)):
            yield from _diff(x, y, f"{path}[{i}]")
        if len(a) != len(b):
            yield f"{path}: {len(a)} items != {len(b)}"
    elif a != b:
        yield f"{path}: {a!r} != {b!r}"
