"""graph - the system map laid out by level and drawn as SVG (no graphviz needed) or as dot.

The layout is the thesis' picture of a hierarchy: one row per level, the highest level on top,
tasks on the rows of their levels and devices, files and terminals on level 0 at the bottom.
Within a row nodes are ordered by a few barycentre sweeps (each node moves towards the mean
position of its neighbours) so links cross little; everything is deterministic. Sensory links are
drawn upwards and command links downwards, each coloured by type and labelled with its priority;
a :class:`Live` overlay adds message rates, overwrites, device ages and event marks. The same code
draws ``chcos map --format svg`` and the live page of ``chcos view``.

The input is the document of :meth:`chcos.system.manager.SystemManager.map_doc` or a sysfile.map
read
with :func:`chcos.system.sysmap.read`; :func:`check_doc` raises ViewerError for anything else.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any
from xml.sax.saxutils import escape, quoteattr

from chcos.viewer import ViewerError

SENSORY_COLOR = "#1b8a3a"
COMMAND_COLOR = "#1f5fbf"
TAP_COLOR = "#9a9a9a"
ALERT_COLOR = "#d32f2f"

NODE_W = 140.0
NODE_H = 68.0
GAP = 40.0
ROW_GAP = 160.0
MARGIN = 24.0
TOP = 56.0

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


@dataclass
class Node:
    """One box of the drawing: a task, a sensor or actuator, a file, a terminal or the host."""

    name: str
    kind: str
    level: int
    data: dict[str, Any]
    x: float = 0.0
    y: float = 0.0


@dataclass
class Edge:
    """One link of the drawing, from ``src`` to ``dst`` (its message direction)."""

    link: dict[str, Any]
    key: str
    src: Node
    dst: Node
    x1: float = 0.0
    y1: float = 0.0
    x2: float = 0.0
    y2: float = 0.0


@dataclass
class Layout:
    """Nodes with centre coordinates, edges with end points, and the drawing's size."""

    nodes: dict[str, Node]
    edges: list[Edge]
    rows: list[list[Node]]
    width: float
    height: float


def link_key(link: Mapping[str, Any]) -> str:
    """The key a link has in rates and on the page: ``SRC/DST:type`` (``*`` for implicit)."""
    star = "*" if link.get("implicit") else ""
    return f"{link['src']}/{link['dst']}:{link['type']}{star}"


def check_doc(doc: Any) -> dict[str, Any]:
    """Return ``doc`` if it looks like a system map (tasks and links lists of dicts); raises
    ViewerError naming what is missing."""
    if not isinstance(doc, dict):
        raise ViewerError("system map: expected a JSON object")
    for key in ("tasks", "links"):
        items = doc.get(key)
        if not isinstance(items, list) or not all(isinstance(i, dict) for i in items):
            raise ViewerError(f"system map: {key!r} missing or not a list of objects")
    for t in doc["tasks"]:
        if "name" not in t or "level" not in t:
            raise ViewerError(f"system map: task {t!r} has no name or level")
    for lk in doc["links"]:
        if not {"src", "dst", "type"} <= lk.keys():
            raise ViewerError(f"system map: link {lk!r} lacks src, dst or type")
    return doc


def _endpoint_kind(name: str) -> str:
    if name == "host":
        return "host"
    return "terminal" if name.startswith("/dev/tty") else "file"


def _nodes(doc: dict[str, Any], links: list[dict[str, Any]]) -> dict[str, Node]:
    nodes: dict[str, Node] = {}
    for t in doc["tasks"]:
        nodes[t["name"]] = Node(t["name"], "task", int(t["level"]), t)
    for d in doc.get("devices", []):
        nodes.setdefault(d["name"], Node(d["name"], str(d.get("direction", "device")), 0, d))
    top = max((n.level for n in nodes.values()), default=0) + 1
    for lk in links:
        for name in (lk["src"], lk["dst"]):
            if name not in nodes:
                kind = _endpoint_kind(name)
                nodes[name] = Node(name, kind, top if kind == "host" else 0, {"name": name})
    return nodes


def layout(doc: dict[str, Any], implicit: bool = False) -> Layout:
    """Lay out the map: rows by level (highest first), nodes ordered to keep links short.
    Implicit links (exception taps, assassin and host links) are left out unless ``implicit``.
    Raises ViewerError if ``doc`` is not a system map."""
    check_doc(doc)
    links = [lk for lk in doc["links"] if implicit or not lk.get("implicit")]
    nodes = _nodes(doc, links)
    by_level: dict[int, list[Node]] = defaultdict(list)
    for n in nodes.values():
        by_level[n.level].append(n)
    rows = [by_level[lv] for lv in sorted(by_level, reverse=True)]
    neigh: dict[str, list[str]] = defaultdict(list)
    for lk in links:
        neigh[lk["src"]].append(lk["dst"])
        neigh[lk["dst"]].append(lk["src"])
    pos: dict[str, float] = {}

    def place(row: list[Node]) -> None:
        for i, n in enumerate(row):
            pos[n.name] = (i + 0.5) / len(row)

    for row in rows:
        place(row)
    for sweep in range(6):
        down = sweep % 2 == 0
        order = range(1, len(rows)) if down else range(len(rows) - 2, -1, -1)
        for r in order:
            row = rows[r]
            keys = {n.name: _barycentre(n, down, neigh, nodes, pos) for n in row}
            row.sort(key=lambda n: keys[n.name])
            place(row)
    width = max(len(r) * NODE_W + (len(r) - 1) * GAP for r in rows) + 2 * MARGIN if rows else 300
    width = max(width, 520.0)  # the legend and the clock side by side
    for r, row in enumerate(rows):
        row_w = len(row) * NODE_W + (len(row) - 1) * GAP
        x0 = (width - row_w) / 2 + NODE_W / 2
        for i, n in enumerate(row):
            n.x = x0 + i * (NODE_W + GAP)
            n.y = TOP + r * ROW_GAP + NODE_H / 2
    height = TOP + max(len(rows) - 1, 0) * ROW_GAP + NODE_H + MARGIN
    edges = [Edge(lk, link_key(lk), nodes[lk["src"]], nodes[lk["dst"]]) for lk in links]
    _attach(edges)
    return Layout(nodes, edges, rows, width, height)


def _barycentre(n: Node, above: bool, neigh: Mapping[str, list[str]],
                nodes: Mapping[str, Node], pos: Mapping[str, float]) -> float:
    """Mean position of ``n``'s neighbours in the rows above (or below) it; its own position
    if it has none there."""
    ns = [pos[m] for m in neigh[n.name]
          if nodes[m].level != n.level and (nodes[m].level > n.level) == above]
    return sum(ns) / len(ns) if ns else pos[n.name]


def _attach(edges: list[Edge]) -> None:
    """Spread the ends of the edges along the top and bottom sides of their nodes."""
    bottom: dict[str, list[tuple[float, int, Edge, bool]]] = defaultdict(list)
    top: dict[str, list[tuple[float, int, Edge, bool]]] = defaultdict(list)
    for e in edges:
        src_upper = e.src.level >= e.dst.level
        upper, lower = (e.src, e.dst) if src_upper else (e.dst, e.src)
        order = 0 if e.link["type"] == "sensory" else 1
        bottom[upper.name].append((lower.x, order, e, src_upper))
        top[lower.name].append((upper.x, order, e, not src_upper))
    for side, ends in (("bottom", bottom), ("top", top)):
        for _name, lst in ends.items():
            lst.sort(key=lambda item: (item[0], item[1]))
            for i, (_x, _o, e, is_src) in enumerate(lst):
                node = e.src if is_src else e.dst
                x = node.x - NODE_W / 2 + NODE_W * (i + 1) / (len(lst) + 1)
                y = node.y + NODE_H / 2 if side == "bottom" else node.y - NODE_H / 2
                if is_src:
                    e.x1, e.y1 = x, y
                else:
                    e.x2, e.y2 = x, y


def _fmt_value(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if v is None:
        return "-"
    text = str(v)
    return text if len(text) <= 14 else text[:13] + "…"


def _fmt_rate(r: float) -> str:
    return f"{r:.1f}/s" if r < 100 else f"{r:.0f}/s"


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
        lines.append((f"{n.name} ({n.kind})", "name"))
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
