"""textview - the system map drawn as text: levels top to bottom, tasks, links, devices, buses
(with their remote nodes' lifecycles and SYNC cycles).

Works on the document of :meth:`chcos.system.manager.SystemManager.map_doc` or a sysfile.map read
with
:func:`chcos.system.sysmap.read`, so it draws a running system and a saved one alike. The graphic
forms
(SVG, dot) and the live page are in :mod:`chcos.viewer`.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping
from typing import Any

from chcos.devices.status import DriverStatus


def _rate(lk: dict[str, Any], rates: Mapping[str, float] | None) -> str:
    if rates is None:
        return ""
    star = "*" if lk.get("implicit") else ""
    key = f"{lk['src']}/{lk['dst']}:{lk['type']}{star}"
    return f" {rates.get(key, 0.0):6.1f}/s"


def bus_status_lines(status: Mapping[str, DriverStatus]) -> list[str]:
    """One line per remote node (its lifecycle state, boot-ups seen, NMT starts, heartbeat
    losses, EMCYs, error register, last EMCY, restarts of its recovery policy, why it is not
    ready), one per SYNC cycle (cycles, complete, missing TPDOs, late SYNCs, late answers,
    acyclic TPDOs, jitter, cycles given up) and one per bus
    controller's error state, from :meth:`chcos.devices.devtab.Devtab.statuses`."""
    out = []
    for bus, st in status.items():
        for n in st.nodes:
            reg = n.error_register
            text = (f"node     {bus}/{n.node:<13} {n.state}, {n.boots} boot-up(s) seen, "
                    f"{n.nmt_starts} NMT start(s), {n.heartbeat_losses} heartbeat "
                    f"loss(es), {n.emcys} EMCY(s), error register "
                    f"{'-' if reg is None else f'0x{reg:02X}'}, last EMCY "
                    f"{n.last_emcy or 'none'}")
            if n.restarts:
                text += f", {n.restarts} restart(s)"
            if n.heartbeat_lost:
                text += ", heartbeat LOST"
            if n.reason:
                text += f" ({n.reason})"
            out.append(text)
        sy = st.sync
        if sy is not None:
            out.append(f"SYNC     {bus:<16} {sy.cycles} cycles of {sy.period * 1e3:g} ms, "
                       f"{sy.complete} complete, {sy.missing} TPDOs missing, "
                       f"{sy.late} late, {sy.late_writes} late answers, "
                       f"{sy.acyclic} acyclic TPDOs; jitter p50 "
                       f"{sy.jitter_p50 * 1e3:.3f} ms, p99 {sy.jitter_p99 * 1e3:.3f} ms, "
                       f"max {sy.jitter_max * 1e3:.3f} ms"
                       + (f"; {sy.given_up} cycles given up" if sy.given_up else ""))
        bs = st.bus_state
        if bs is not None:
            counters = ("" if bs.tx_errors is None or bs.rx_errors is None
                        else f", TEC {bs.tx_errors}, REC {bs.rx_errors}")
            out.append(f"CAN      {bus:<16} {bs.state.value}{counters}, "
                       f"{bs.bus_offs} bus-off(s), {bs.restarts} restart(s), "
                       f"{bs.error_passive} time(s) error-passive, {bs.error_frames} error "
                       f"frame(s)")
        for c in st.cyclic:
            sent = "" if c.frames is None else f", {c.frames} frame(s) sent"
            out.append(f"cyclic   {bus:<16} {c.message} every {c.period * 1e3:g} ms"
                       f"{sent if c.started else ', not started (no command yet)'}")
    return out


def render_text(doc: dict[str, Any], rates: Mapping[str, float] | None = None,
                implicit: bool = False) -> str:
    """The hierarchy as lines of text (highest level first), each task with its links, then
    devices, files and terminals. ``rates`` (messages per second by
    :func:`chcos.viewer.layout.link_key`) adds a rate to every link; ``implicit`` also lists
    implicit links (exception taps, assassin and host links)."""
    out: list[str] = []
    by_level: dict[int, list[dict[str, Any]]] = defaultdict(list)
    for t in doc["tasks"]:
        by_level[int(t["level"])].append(t)
    links_from: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for lk in doc["links"]:
        if implicit or not lk.get("implicit"):
            links_from[lk["src"]].append(lk)
    out.append(f"machines: {', '.join(str(m) for m in doc['machines']) or 'none'}"
               f"   time {doc.get('time', 0.0):.3f} s")
    for level in sorted(by_level, reverse=True):
        out.append(f"level {level}")
        for t in by_level[level]:
            owner = f" owner {t['owner']}" if t.get("owner") else ""
            role = f" [{t['role']}]" if t.get("role", "task") != "task" else ""
            err = f" last error: {t['last_error']}" if t.get("last_error") else ""
            out.append(f"  {t['name']:<8} m{t['machine']} {t.get('status', '?'):<9} "
                       f"p{t.get('priority', '?')}{owner}{role} "
                       f"steps {t.get('steps', 0)}{err}")
            for lk in links_from.get(t["name"], []):
                arrow = "^" if lk["type"] == "sensory" else "v"
                out.append(f"      {arrow} {lk['src']}/{lk['dst']:<10} {lk['type']:<7} "
                           f"p{lk['priority']:<3} {lk['status']:<19} sent {lk.get('sent', 0)} "
                           f"overwritten {lk.get('overwritten', 0)}{_rate(lk, rates)}")
    devs = doc.get("devices", [])
    if devs:
        out.append("level 0 (devices)")
        for d in devs:
            val = d.get("value")
            pend = (f" (pending {d['pending']!r})" if d.get("pending") is not None else "")
            why = (f" since t={d['since']:.3f}: {d['reason']}" if d.get("reason")
                   and d.get("since") is not None else f": {d['reason']}" if d.get("reason")
                   else "")
            werr = (f" [{d['write_errors']} write error(s): {d.get('last_write_error', '')}]"
                    if d.get("write_errors") else "")
            out.append(f"  {d['name']:<8} m{d['machine']} {d['direction']:<8} "
                       f"{d.get('status', '?'):<9} value {val!r} {d.get('units', '')}{pend}"
                       f"{why}{werr}")
            for lk in links_from.get(d["name"], []):
                out.append(f"      ^ {lk['src']}/{lk['dst']:<10} sensory p{lk['priority']} "
                           f"sent {lk.get('sent', 0)} overwritten {lk.get('overwritten', 0)}"
                           f"{_rate(lk, rates)}")
    for bus, st in (doc.get("buses") or {}).items():
        counts = " ".join(f"{k} {v}" for k, v in sorted(st.get("counts", {}).items()))
        errors = " ".join(f"{k} {v}" for k, v in sorted(st.get("errors", {}).items()))
        out.append(f"  bus {bus}: {counts or 'no traffic'}"
                   f"{'; errors: ' + errors if errors else ''}")
    status = {bus: DriverStatus.from_json(st) for bus, st in (doc.get("bus_status") or {}).items()}
    out.extend(f"  {line}" for line in bus_status_lines(status))
    k = doc.get("kernel")
    if k:
        out.append(f"  kernel: {k.get('steps', 0)} steps, {k.get('ready', 0)} ready, "
                   f"{k.get('timers', 0)} timers, {k.get('skipped_periods', 0)} timer periods "
                   f"skipped (late), {k.get('handler_errors', 0)} handler errors")
    known = {t["name"] for t in doc["tasks"]} | {d["name"] for d in devs}
    others = sorted({lk["src"] for lk in doc["links"] if lk["src"] not in known}
                    - {"host"})
    if others:
        out.append("level 0 (files and terminals)")
        for name in others:
            kind = "terminal" if name.startswith("/dev/tty") else "file"
            out.append(f"  {name:<8} {kind}")
            for lk in links_from.get(name, []):
                out.append(f"      ^ {lk['src']}/{lk['dst']:<10} sensory p{lk['priority']} "
                           f"sent {lk.get('sent', 0)} overwritten {lk.get('overwritten', 0)}"
                           f"{_rate(lk, rates)}")
    collected = doc.get("errors") or []
    if collected:
        out.append(f"collected errors ({len(collected)}; System.check raises them)")
        out.extend(f"  {e}" for e in collected)
    return "\n".join(out)
