"""remote - a system on satellites seen through the host's authenticated link, for the viewer.

:class:`HostSystem` gives :class:`~chcos.viewer.server.Viewer` what it reads of a local
:class:`~chcos.system.embedded.System` — ``sysmgr.map_doc()``, ``execute(line)``, a clock and the
event
hook — from a :class:`chcos.satellites.host.Host` session: the map is the host's merged map (each
task,
device and link as its own satellite reports it), commands go through ``Host.execute`` (the same
prepare/commit path as ``chcos host``), and the event log is made by comparing successive maps
(installs, setpri, owners, abnormal completions, device status, satellites lost), since the
satellites do not stream their kernel events to the host. Times are seconds since the view
attached; device ages are computed on each device's own satellite (its clock minus the value's
time) and shown as update times on the view's clock; frozen tasks come from the tasks' flags.
Every call is a round trip over Zenoh, so the view's period should stay at 0.2 s or more for a
remote system.
"""

from __future__ import annotations

import threading
from typing import TYPE_CHECKING, Any

from chcos.kernel.clock import RealClock
from chcos.kernel.instrument import Instrument

if TYPE_CHECKING:
    from chcos.satellites.host import Host


class _Kernel:
    """The parts of a kernel the viewer touches: a clock and the instruments."""

    def __init__(self) -> None:
        self.clock = RealClock()
        self.instruments: tuple[Instrument, ...] = ()

    def add_instrument(self, instrument: Instrument) -> None:
        self.instruments = (*self.instruments, instrument)


class _Sysmgr:
    def __init__(self, remote: HostSystem) -> None:
        self.remote = remote

    def map_doc(self) -> dict[str, Any]:
        return self.remote.map_doc()


class HostSystem:
    """A multi-satellite system behind ``host``, shaped for the viewer (see the module doc)."""

    def __init__(self, host: Host) -> None:
        self.host = host
        self.kernel = _Kernel()
        self.sysmgr = _Sysmgr(self)
        self.tsktab: tuple[Any, ...] = ()
        self.devtab: tuple[Any, ...] = ()
        self._last: dict[str, Any] | None = None
        self._lock = threading.Lock()

    def _event(self, kind: str, detail: str) -> None:
        for i in self.kernel.instruments:
            i.event(kind, detail)

    def map_doc(self) -> dict[str, Any]:
        """The host's merged map, its time the view's clock; logs what changed since the last
        one. Raises LinkError if no satellite answers."""
        doc = self.host.map_doc()
        now = self.kernel.clock.now()
        doc["time"] = now
        for d in doc["devices"]:  # the satellite's age, as an update time on the view's clock
            age = d.get("age")
            d["updated_at"] = None if age is None else now - float(age)
        doc["frozen"] = [t["name"] for t in doc["tasks"] if t.get("frozen")]
        with self._lock:
            self._diff(self._last, doc)
            self._last = doc
        return doc

    def _diff(self, old: dict[str, Any] | None, new: dict[str, Any]) -> None:
        if old is None:
            self._event("attach", f"machines {', '.join(map(str, new.get('alive', [])))} up")
            return
        before = {t["name"]: t for t in old["tasks"]}
        for t in new["tasks"]:
            o = before.get(t["name"])
            if o is None:
                self._event("install", f"{t['name']} on machine {t['machine']}")
                continue
            if t["abnormal"] > o["abnormal"]:
                self._event("abnormal", f"{t['name']}: {t.get('last_error') or 'failed'}")
            if t["owner"] != o["owner"] and t["owner"] is not None:
                self._event("owner", f"{t['name']} owned by {t['owner']}")
        links = {(lk["src"], lk["dst"]): lk for lk in old["links"]}
        for lk in new["links"]:
            o = links.get((lk["src"], lk["dst"]))
            if o is not None and o["priority"] != lk["priority"] and not lk.get("implicit"):
                self._event("setpri", f"{lk['src']}/{lk['dst']} {o['priority']} -> "
                                      f"{lk['priority']}")
        devs = {d["name"]: d for d in old["devices"]}
        for d in new["devices"]:
            o = devs.get(d["name"])
            if o is not None and o["status"] != d["status"]:
                kind = "device-ok" if d["status"] == "OK" else f"device-{d['status'].lower()}"
                self._event(kind, f"{d['name']}: {d.get('reason')}" if d.get("reason")
                            else d["name"])
        lost = set(old.get("alive", [])) - set(new.get("alive", []))
        for m in sorted(lost):
            self._event("satellite-down", f"machine {m}")

    def execute(self, line: str) -> str:
        """One host command over the link (raises what ``Host.execute`` raises)."""
        return self.host.execute(line)


__all__ = ["HostSystem"]
