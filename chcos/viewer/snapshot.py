"""snapshot - a running system as JSON-ready snapshots: the map, message rates, ages, events.

:class:`EventLog` is an :class:`~chcos.kernel.instrument.Instrument` that overrides only ``event``:
the
kernel thread appends (kind, detail) with the clock time under a short lock, and readers copy
what is newer than the sequence number they saw. :class:`Snapshotter` takes snapshots of a
:class:`~chcos.system.embedded.System` for the viewer at the viewer's own rate.

Reading the tables from another thread: a snapshot calls ``sysmgr.map_doc()`` on the viewer's
thread while the kernel may be running on its own. We accept torn reads rather than stop the cell
(an interrupt to the kernel thread would cost the cell time at every snapshot): each counter and
status is read atomically under the GIL, but two counters of one snapshot may be a few messages
apart, which the rates (differences over about a second) smooth out. A table that changes size
while it is walked (an install during the snapshot) raises inside ``map_doc``; the snapshot is
then simply taken again (up to :data:`RETRIES` times, then ViewerError).
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from chcos.kernel.clock import Clock
from chcos.kernel.instrument import Instrument
from chcos.viewer import ViewerError
from chcos.viewer.graph import Live, render_svg
from chcos.viewer.layout import link_key

if TYPE_CHECKING:
    from chcos.system.embedded import System

RETRIES = 5
#: Message rates are averaged over at least this much clock time (seconds).
RATE_WINDOW = 1.0


@dataclass(frozen=True)
class Event:
    """One system event as the viewer shows it."""

    seq: int
    time: float
    kind: str
    detail: str

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {"seq": self.seq, "time": self.time, "kind": self.kind, "detail": self.detail}


class EventLog(Instrument):
    """The newest ``keep`` system events, numbered from 1; fed by the kernel's ``event`` hook.
    Times are seconds since ``t0`` (default: the clock's time when the log was made, which is
    when the system was built: the page shows times since start, not the machine's uptime)."""

    def __init__(self, clock: Clock, keep: int = 500, t0: float | None = None) -> None:
        self.clock = clock
        self.t0 = clock.now() if t0 is None else t0
        self._events: deque[Event] = deque(maxlen=keep)
        self._seq = 0
        self._lock = threading.Lock()

    def event(self, kind: str, detail: str) -> None:
        """Keep one event (runs on the kernel thread; never blocks for long)."""
        with self._lock:
            self._seq += 1
            self._events.append(Event(self._seq, self.clock.now() - self.t0, kind, detail))

    @property
    def last_seq(self) -> int:
        """The number of the newest event (0 if none yet)."""
        return self._seq

    def since(self, seq: int) -> list[Event]:
        """The events numbered above ``seq`` that are still kept, oldest first."""
        with self._lock:
            return [e for e in self._events if e.seq > seq]


def event_marks(kind: str, detail: str, names: set[str]) -> list[tuple[str, str | None]]:
    """Which tasks or devices an event marks: (name, kind), kind None to clear a mark.

    ``abnormal``/``estop`` (``T: reason``) mark T; ``suspend`` (``host suspend T`` or ``A
    suspended T``) marks T and ``resume`` clears it; ``preempt`` (``L took T from O``) marks T;
    ``device-failed``/``device-stale`` (``D: reason``) mark D and ``device-ok`` clears it."""
    words = detail.replace(":", " ").split()
    if not words:
        return []
    if kind in ("abnormal", "estop") or kind.startswith("device-"):
        name = detail.split(":", 1)[0].strip()
        if name not in names:
            return []
        return [(name, None if kind == "device-ok" else kind)]
    if kind in ("suspend", "resume"):
        name = words[-1]
        return [(name, kind if kind == "suspend" else None)] if name in names else []
    if kind == "preempt" and len(words) >= 3 and words[2] in names:
        return [(words[2], kind)]
    return []


class Snapshotter:
    """Takes snapshots of ``system`` and remembers enough of the past for message rates.

    ``events`` is the log to report from; by default the EventLog already listening on the
    kernel (so events from before the viewer started are shown), else a new one is added.

    Not thread-safe itself: use one per thread (the viewer uses it on its own loop thread only).
    """

    def __init__(self, system: System, events: EventLog | None = None,
                 implicit: bool = False) -> None:
        self.system = system
        if events is None:  # one already listening (added before the installs), else a new one
            events = next((i for i in system.kernel.instruments if isinstance(i, EventLog)),
                          None) or EventLog(system.kernel.clock)
        self.events = events
        if events not in system.kernel.instruments:
            system.kernel.add_instrument(events)
        self.implicit = implicit
        self.seq = 0
        self._history: deque[tuple[float, dict[str, int]]] = deque()
        self._rates: dict[str, float] = {}
        self._marks: dict[str, tuple[str, str]] = {}
        self._marked_upto = 0

    def map_doc(self) -> dict[str, Any]:
        """``sysmgr.map_doc()`` plus what only the live tables know: device reasons and update
        times, frozen tasks. Retried on a torn read; raises ViewerError if it keeps failing."""
        s = self.system
        last: Exception | None = None
        for _ in range(RETRIES):
            try:
                doc = s.sysmgr.map_doc()
                frozen = [t.name for t in list(s.tsktab) if t.frozen]
                extra = {d.name: (d.updated_at, d.reason) for d in list(s.devtab)}
            except (RuntimeError, KeyError, AttributeError) as exc:  # table changed under us
                last = exc
                continue
            for d in doc["devices"]:
                d["updated_at"], d["reason"] = extra.get(
                    d["name"], (d.get("updated_at"), d.get("reason", "")))
            doc.setdefault("frozen", frozen)
            return doc
        raise ViewerError(f"no consistent snapshot of the tables after {RETRIES} tries: "
                          f"{last}") from last

    def _update_rates(self, now: float, counters: dict[str, int]) -> None:
        hist = self._history
        if hist and now <= hist[-1][0]:
            return  # the clock has not moved: keep the last rates
        base = None
        while hist and hist[0][0] <= now - RATE_WINDOW:
            base = hist.popleft()
        if base is not None:
            hist.appendleft(base)
        elif hist:
            base = hist[0]
        if base is not None:
            dt = now - base[0]
            self._rates = {k: max(0, v - base[1].get(k, 0)) / dt for k, v in counters.items()}
        hist.append((now, counters))

    def _update_marks(self, names: set[str]) -> None:
        for e in self.events.since(self._marked_upto):
            for name, kind in event_marks(e.kind, e.detail, names):
                if kind is None:
                    self._marks.pop(name, None)
                else:
                    self._marks[name] = (kind, e.detail)
            self._marked_upto = e.seq

    def take(self, events_since: int | None = None, svg: bool = True) -> dict[str, Any]:
        """One snapshot: ``seq``, ``time`` (seconds since the system started), ``map`` (the map
        document, its ``time`` also since start), ``rates`` (messages per second by
        :func:`~chcos.viewer.layout.link_key`), ``ages`` (seconds since each device's last
        value), ``marks`` (latest notable event per name), ``events`` (those
        numbered above ``events_since``; none if it is None), ``last_event`` and ``svg`` (the
        drawing, unless ``svg`` is false). Raises ViewerError if the tables cannot be read."""
        doc = self.map_doc()
        now = float(doc["time"]) - self.events.t0
        doc["time"] = now
        counters = {link_key(lk): int(lk.get("sent", 0)) for lk in doc["links"]}
        self._update_rates(now, counters)
        names = {t["name"] for t in doc["tasks"]} | {d["name"] for d in doc["devices"]}
        self._update_marks(names)
        t0 = self.events.t0
        ages: dict[str, float | None] = {
            d["name"]: (None if d.get("updated_at") is None
                        else max(0.0, now - (d["updated_at"] - t0)))
            for d in doc["devices"]}
        for lk in doc["links"]:
            lk["key"] = link_key(lk)
            lk["rate"] = self._rates.get(lk["key"], 0.0)
        self.seq += 1
        snap: dict[str, Any] = {
            "seq": self.seq, "time": now, "t0": t0, "map": doc, "rates": dict(self._rates),
            "ages": ages,
            "marks": {k: {"kind": v[0], "detail": v[1]} for k, v in self._marks.items()},
            "events": ([] if events_since is None else
                       [e.as_dict() for e in self.events.since(events_since)]),
            "last_event": self.events.last_seq,
        }
        if svg:
            live = Live(self._rates, ages, dict(self._marks), frozenset(doc["frozen"]))
            snap["svg"] = render_svg(doc, live, self.implicit)
        return snap


def stream_state(snap: dict[str, Any]) -> dict[str, Any]:
    """What the live page keeps of a snapshot from :meth:`Snapshotter.take`: tasks, links and
    devices keyed by name (so a change is a small merge patch, see :func:`merge_diff`), with
    rates, ages and frozen flags folded in, and ``errors``, what the system collected (see
    ``System.check``). ``svg`` is carried over if the snapshot has one."""
    doc = snap["map"]
    frozen = set(doc.get("frozen", ()))
    tasks = {t["name"]: {"level": t["level"], "machine": t["machine"], "status": t["status"],
                         "owner": t["owner"], "priority": t["priority"], "steps": t["steps"],
                         "abnormal": t["abnormal"], "last_error": t["last_error"],
                         "frozen": t["name"] in frozen} for t in doc["tasks"]}
    links = {lk["key"]: {"src": lk["src"], "dst": lk["dst"], "type": lk["type"],
                         "priority": lk["priority"], "status": lk["status"],
                         "implicit": lk["implicit"], "sent": lk["sent"],
                         "overwritten": lk["overwritten"], "rate": round(lk["rate"], 2)}
             for lk in doc["links"]}
    ages = snap["ages"]
    t0 = snap.get("t0", 0.0)
    devices = {d["name"]: {"direction": d["direction"], "machine": d["machine"],
                           "status": d["status"], "reason": d.get("reason", ""),
                           "value": d["value"], "units": d["units"],
                           "age": None if ages.get(d["name"]) is None
                           else round(ages[d["name"]], 2),
                           "since": None if d.get("since") is None
                           else round(float(d["since"]) - t0, 3),
                           "pending": d.get("pending"),
                           "write_errors": d.get("write_errors", 0),
                           "last_write_error": d.get("last_write_error", "")}
               for d in doc["devices"]}
    state: dict[str, Any] = {"seq": snap["seq"], "time": round(snap["time"], 3),
                             "machines": doc["machines"], "tasks": tasks, "links": links,
                             "devices": devices, "marks": snap["marks"],
                             "last_event": snap["last_event"],
                             "errors": list(doc.get("errors", []))}
    if "svg" in snap:
        state["svg"] = snap["svg"]
    if "error" in snap:
        state["error"] = snap["error"]
    return state


class _Same:
    pass


SAME: Any = _Same()


def merge_diff(old: Any, new: Any) -> Any:
    """The JSON merge patch (RFC 7386) that turns ``old`` into ``new``, or :data:`SAME` if they
    are equal. A removed key is patched to None; the page treats a missing key as null, so a
    None value and an absent key mean the same to it."""
    if isinstance(old, dict) and isinstance(new, dict):
        patch: dict[str, Any] = {}
        for k, v in new.items():
            if k not in old:
                patch[k] = v
            else:
                d = merge_diff(old[k], v)
                if d is not SAME:
                    patch[k] = d
        for k in old:
            if k not in new:
                patch[k] = None
        return patch if patch else SAME
    return SAME if old == new and type(old) is type(new) else new


def structure_key(state: dict[str, Any]) -> Any:
    """What the drawing depends on apart from rates and ages: when this changes the SVG is
    redrawn at once, otherwise at most once per SVG period."""
    return (tuple((n, t["status"], t["owner"], t["priority"], t["frozen"], t["abnormal"])
                  for n, t in state["tasks"].items()),
            tuple((k, lk["priority"], lk["status"]) for k, lk in state["links"].items()),
            tuple((n, d["status"]) for n, d in state["devices"].items()),
            tuple(sorted((k, v["kind"]) for k, v in state["marks"].items())))
