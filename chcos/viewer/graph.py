"""graph - the system map drawn as SVG (no graphviz needed) or as dot.

The map is laid out by :mod:`chcos.viewer.layout` (one row per level, the highest on top, few
crossings, deterministic). Sensory links are
drawn upwards and command links downwards, each coloured by type and labelled with its priority;
a :class:`Live` overlay adds message rates, overwrites, device ages and event marks. The same code
draws ``chcos map --format svg`` and the live page of ``chcos view``.

The input is the document of :meth:`chcos.system.manager.SystemManager.map_doc` or a sysfile.map
read with :func:`chcos.system.sysmap.read`; ViewerError for anything else.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any
from xml.sax.saxutils import escape, quoteattr

from chcos.viewer.layout import (
    NODE_H,
    NODE_W,
    Edge,
    Layout,
    Node,
    layout,
)

SENSORY_COLOR = "#1b8a3a"
COMMAND_COLOR = "#1f5fbf"
TAP_COLOR = "#9a9a9a"
ALERT_COLOR = "#d32f2f"

TASK_FILL = {
    "current": "#ffd54f", "ready": "#fff1b8", "waiting": "#dcebff", "asleep": "#e6e3f6",
    "suspended": "#f1f1f1",
}
DEVICE_FILL = {"OK": "#e3f4e6", "suspended": "#eeeeee", "failed": "#ff8a80", "stale": "#ff8a80"}
ALERT_MARKS = frozenset({"abnormal", "estop", "suspend", "preempt", "device-failed",
                         "device-stale"})


@dataclass
class Live:
    """What a running system adds to the map: messages per second by :func:`link_key`, device
    ages in seconds (None: never updated), and the latest notable event per task or device
    (kind, detail)."""

    rates: Mapping[str, float] = field(default_factory=dict)
    ages: Mapping[str, float | None] = field(default_factory=dict)
    marks: Mapping[str, tuple[str, str]] = field(default_factory=dict)
    frozen: frozenset[str] = frozenset()


def _fmt_value(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if v is None:
        return "-"
    text = str(v)
    return text if len(text) <= 14 else text[:13] + "…"


def _fmt_rate(r: float) -> str:
    return f"{r:.1f}/s" if r < 100 else f"{r:.0f}/s"


#: Characters that fit a node's width: a bold 12 px name (about 7.4 px a character) and a
#: 10.5 px line (about 6.2 px), with 4 px of padding each side. Longer text is cut with "…" so
#: labels of neighbouring nodes never run into each other; the full name is the node's title.
NAME_CHARS = int((NODE_W - 8) / 7.4)
LINE_CHARS = int((NODE_W - 8) / 6.2)


def fit(text: str, chars: int) -> str:
    """``text`` cut to ``chars`` characters, the last one "…" when cut."""
    return text if len(text) <= chars else text[:chars - 1] + "…"


def _text(x: float, y: float, text: str, cls: str, **attrs: str) -> str:
    extra = "".join(f" {k.replace('_', '-')}={quoteattr(v)}" for k, v in attrs.items())
    return (f'<text x="{x:.1f}" y="{y:.1f}" class={quoteattr(cls)}{extra}>'
            f"{escape(text)}</text>")


def _bezier(e: Edge, t: float) -> tuple[float, float]:
    dy = (e.y2 - e.y1) / 2
    p = ((e.x1, e.y1), (e.x1, e.y1 + dy), (e.x2, e.y2 - dy), (e.x2, e.y2))
    u = 1 - t
    x = u**3 * p[0][0] + 3 * u * u * t * p[1][0] + 3 * u * t * t * p[2][0] + t**3 * p[3][0]
    y = u**3 * p[0][1] + 3 * u * u * t * p[1][1] + 3 * u * t * t * p[2][1] + t**3 * p[3][1]
    return x, y


def _label_text(e: Edge, live: Live | None) -> str:
    lk = e.link
    text = f"p{lk.get('priority', '?')}"
    if live is not None:
        text += f" {_fmt_rate(live.rates.get(e.key, 0.0))}"
    if lk.get("overwritten"):
        text += f" ow {lk['overwritten']}"
    if str(lk.get("status", "OK")) != "OK":
        text += f" {lk.get('status')}"
    return text


#: Where along its curve a link's label may sit, in order of preference.
LABEL_TS = (0.3, 0.42, 0.2, 0.55, 0.12, 0.66, 0.5, 0.36)


def place_labels(lay: Layout, live: Live | None) -> dict[int, float]:
    """Where (curve parameter) each edge's label goes so that labels do not overlap each other
    or a node box: the first position in :data:`LABEL_TS` that is free (estimated at 6.6 px a
    character of 11 px text), else the default."""
    boxes = [(n.x - NODE_W / 2, n.y - NODE_H / 2, n.x + NODE_W / 2, n.y + NODE_H / 2)
             for n in lay.nodes.values()]
    placed: dict[int, float] = {}
    for i, e in enumerate(lay.edges):
        w = 6.6 * len(_label_text(e, live)) / 2 + 2
        for t in LABEL_TS:
            x, y = _bezier(e, t)
            box = (x - w, y - 8, x + w, y + 7)
            if not any(box[0] < b[2] and b[0] < box[2] and box[1] < b[3] and b[1] < box[3]
                       for b in boxes):
                placed[i] = t
                boxes.append(box)
                break
        else:
            placed[i] = LABEL_TS[0]
    return placed


def _edge_svg(e: Edge, live: Live | None, t: float = LABEL_TS[0]) -> str:
    lk = e.link
    implicit = bool(lk.get("implicit"))
    color = TAP_COLOR if implicit else SENSORY_COLOR if lk["type"] == "sensory" else COMMAND_COLOR
    marker = "tap" if implicit else str(lk["type"])
    dy = (e.y2 - e.y1) / 2
    d = (f"M{e.x1:.1f},{e.y1:.1f} C{e.x1:.1f},{e.y1 + dy:.1f} {e.x2:.1f},{e.y2 - dy:.1f} "
         f"{e.x2:.1f},{e.y2:.1f}")
    status = str(lk.get("status", "OK"))
    dash = ' stroke-dasharray="5 4"' if implicit or status == "suspended" else ""
    width = "2.2" if status in ("OK", "normal completion") else "3"
    stroke = ALERT_COLOR if status in ("pre-empted", "abnormal completion") else color
    lx, ly = _bezier(e, t)
    parts = [f'<g class="link {lk["type"]}{" implicit" if implicit else ""}" '
             f'data-link={quoteattr(lk["src"] + "/" + lk["dst"])} data-key={quoteattr(e.key)} '
             f'data-type={quoteattr(str(lk["type"]))}>',
             f"<title>{escape(lk['src'])}/{escape(lk['dst'])} {escape(str(lk['type']))} "
             f"priority {lk.get('priority', '?')} status {escape(status)} "
             f"sent {lk.get('sent', 0)} overwritten {lk.get('overwritten', 0)}</title>",
             f'<path d="{d}" fill="none" stroke="{stroke}" stroke-width="{width}"{dash} '
             f'marker-end="url(#arrow-{marker})"/>',
             f'<text x="{lx:.1f}" y="{ly + 4:.1f}" class="label" text-anchor="middle" '
             f'font-size="11" fill="{color}" stroke="#fff" stroke-width="3" '
             f'paint-order="stroke">',
             f'<tspan class="prio" font-weight="bold">p{lk.get("priority", "?")}</tspan>']
    if live is not None:
        parts.append(f'<tspan class="rate"> {_fmt_rate(live.rates.get(e.key, 0.0))}</tspan>')
    if lk.get("overwritten"):
        parts.append(f'<tspan class="over" fill="#b26a00"> ow {lk["overwritten"]}</tspan>')
    if status not in ("OK",):
        parts.append(f'<tspan class="lstatus"> {escape(status)}</tspan>')
    parts.append("</text></g>")
    return "".join(parts)


def _node_svg(n: Node, live: Live | None) -> str:
    d = n.data
    x, y = n.x - NODE_W / 2, n.y - NODE_H / 2
    lines: list[tuple[str, str]] = []
    classes = ["node", n.kind]
    stroke, fill, rx, dash = "#555", "#ffffff", 4, ""
    mark = live.marks.get(n.name) if live is not None else None
    if n.kind == "task":
        status = str(d.get("status", "?"))
        frozen = live is not None and n.name in live.frozen
        classes.append(f"status-{status}")
        fill = TASK_FILL.get(status, "#ffffff")
        role = d.get("role", "task")
        title = n.name + (f" [{role}]" if role not in ("task", None) else "")
        lines.append((title, "name"))
        lines.append((f"L{n.level} m{d.get('machine', '?')} · "
                      f"{'FROZEN' if frozen else status}", "status"))
        owner = d.get("owner") or "-"
        lines.append((f"owner {owner} · p{d.get('priority', '?')}", "owner"))
        if frozen:
            classes.append("frozen")
            fill, stroke, dash = "#ffd6d6", ALERT_COLOR, ' stroke-dasharray="6 3"'
        if d.get("abnormal"):
            classes.append("abnormal")
            stroke = ALERT_COLOR
    elif n.kind in ("sensor", "actuator"):
        status = str(d.get("status", "?"))
        classes.append(f"status-{status}")
        fill = DEVICE_FILL.get(status, "#ffffff")
        rx = 14
        if status in ("failed", "stale"):
            stroke = ALERT_COLOR
            classes.append("alert")
        named = f"{n.name} ({n.kind})"   # the kind goes first when the name is long
        lines.append((named if len(named) <= NAME_CHARS else n.name, "name"))
        lines.append((f"{_fmt_value(d.get('value'))} {d.get('units', '')}".strip(), "value"))
        age = live.ages.get(n.name) if live is not None else None
        age_txt = (f"age {age:.2f} s · " if age is not None else
                   "" if live is not None else f"m{d.get('machine', '?')} · ")
        lines.append((f"{age_txt}{status}", "status"))
    else:
        fill, rx = "#f5f5f5", 2
        lines.append((n.name, "name"))
        lines.append((n.kind, "status"))
    if mark is not None and mark[0] in ALERT_MARKS:
        classes.append("marked")
        classes.append(f"mark-{mark[0]}")
        stroke = ALERT_COLOR
    parts = [f'<g class={quoteattr(" ".join(classes))} data-name={quoteattr(n.name)} '
             f'data-kind="{n.kind}">',
             f"<title>{escape(n.name)}</title>",
             f'<rect x="{x:.1f}" y="{y:.1f}" width="{NODE_W:.0f}" height="{NODE_H:.0f}" '
             f'rx="{rx}" fill="{fill}" stroke="{stroke}" stroke-width="1.6"{dash}/>']
    for i, (text, cls) in enumerate(lines):
        weight = {"font_weight": "bold"} if cls == "name" else {}
        text = fit(text, NAME_CHARS if cls == "name" else LINE_CHARS)  # full name: <title>
        parts.append(_text(n.x, y + 16 + i * 15, text, cls, text_anchor="middle",
                           font_size="12" if cls == "name" else "10.5", **weight))
    if mark is not None and mark[0] in ALERT_MARKS:
        parts.append(_text(n.x, y + 16 + len(lines) * 15, f"⚠ {mark[0]}", "mark",
                           text_anchor="middle", font_size="10.5", fill=ALERT_COLOR,
                           font_weight="bold"))
    parts.append("</g>")
    return "".join(parts)


def render_svg(doc: dict[str, Any], live: Live | None = None, implicit: bool = False) -> str:
    """The map as a standalone SVG document (colours inline, no stylesheet needed). ``live``
    adds rates, ages and marks. Raises ViewerError if ``doc`` is not a system map."""
    lay = layout(doc, implicit)
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" class="chcos-map" '
           f'width="{lay.width:.0f}" height="{lay.height:.0f}" '
           f'viewBox="0 0 {lay.width:.0f} {lay.height:.0f}" '
           f'font-family="DejaVu Sans, Helvetica, Arial, sans-serif">', "<defs>"]
    for name, color in (("sensory", SENSORY_COLOR), ("command", COMMAND_COLOR),
                        ("tap", TAP_COLOR)):
        out.append(f'<marker id="arrow-{name}" viewBox="0 0 10 10" refX="9" refY="5" '
                   f'markerWidth="7" markerHeight="7" orient="auto-start-reverse">'
                   f'<path d="M0,0 L10,5 L0,10 z" fill="{color}"/></marker>')
    out.append("</defs>")
    out.append(f'<rect x="0" y="0" width="{lay.width:.0f}" height="{lay.height:.0f}" '
               'fill="#ffffff"/>')
    # legend
    out.append(f'<g class="legend" font-size="11"><line x1="12" y1="16" x2="40" y2="16" '
               f'stroke="{SENSORY_COLOR}" stroke-width="2.2"/>'
               f'<text x="46" y="20" fill="{SENSORY_COLOR}">sensory (up)</text>'
               f'<line x1="140" y1="16" x2="168" y2="16" stroke="{COMMAND_COLOR}" '
               f'stroke-width="2.2"/><text x="174" y="20" fill="{COMMAND_COLOR}">'
               f"command (down)</text>"
               f'<text x="290" y="20" fill="#444">p = priority</text>'
               f'<text x="{lay.width - 12:.0f}" y="20" text-anchor="end" fill="#444" '
               f'class="clock">t = {float(doc.get("time", 0.0)):.2f} s</text></g>')
    for row in lay.rows:
        level = row[0].level
        y = row[0].y
        label = "host" if row[0].kind == "host" else (
            f"level {level}" if level else "level 0: devices")
        out.append(_text(6, y - NODE_H / 2 - 8, label, "level-label", font_size="10",
                         fill="#888"))
    where = place_labels(lay, live)
    for i, e in enumerate(lay.edges):
        out.append(_edge_svg(e, live, where[i]))
    for n in lay.nodes.values():
        out.append(_node_svg(n, live))
    out.append("</svg>")
    return "\n".join(out)


def _dot_id(name: str) -> str:
    return '"' + name.replace("\\", "\\\\").replace('"', '\\"') + '"'


def render_dot(doc: dict[str, Any], implicit: bool = False) -> str:
    """The map as a graphviz ``digraph``: one ``rank=same`` group per level, sensory links
    pointing up, command links down, coloured by type and labelled with priority. Raises
    ViewerError if ``doc`` is not a system map."""
    lay = layout(doc, implicit)
    out = ["digraph chcos {", '  rankdir=TB; newrank=true;',
           '  node [shape=box, style="rounded,filled", fontname="Helvetica", fontsize=10];',
           '  edge [fontname="Helvetica", fontsize=9];']
    for row in lay.rows:
        out.append(f"  {{ rank=same; /* level {row[0].level} */")
        for n in row:
            d = n.data
            if n.kind == "task":
                label = (f"{n.name}\\nm{d.get('machine', '?')} {d.get('status', '?')}\\n"
                         f"owner {d.get('owner') or '-'} p{d.get('priority', '?')}")
                fill = TASK_FILL.get(str(d.get("status")), "#ffffff")
            elif n.kind in ("sensor", "actuator"):
                label = f"{n.name}\\n{n.kind} {d.get('status', '?')}"
                fill = DEVICE_FILL.get(str(d.get("status")), "#ffffff")
            else:
                label, fill = f"{n.name}\\n{n.kind}", "#f5f5f5"
            label = label.replace('"', '\\"')
            out.append(f'    {_dot_id(n.name)} [label="{label}", fillcolor="{fill}"];')
        out.append("  }")
    for e in lay.edges:
        lk = e.link
        color = (TAP_COLOR if lk.get("implicit") else
                 SENSORY_COLOR if lk["type"] == "sensory" else COMMAND_COLOR)
        style = ', style="dashed"' if lk.get("implicit") else ""
        attrs = f'color="{color}", fontcolor="{color}", label="p{lk.get("priority", "?")}"{style}'
        if e.src.level < e.dst.level:  # drawn upwards: keep the upper node as the tail
            out.append(f"  {_dot_id(e.dst.name)} -> {_dot_id(e.src.name)} [{attrs}, dir=back];")
        else:
            out.append(f"  {_dot_id(e.src.name)} -> {_dot_id(e.dst.name)} [{attrs}];")
    out.append("}")
    return "\n".join(out) + "\n"
