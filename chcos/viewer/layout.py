"""layout - the system map laid out by level, for :mod:`chcos.viewer.graph` to draw.

The layout is the thesis' picture of a hierarchy: one row per level, the highest level on top,
tasks on the rows of their levels and devices, files and terminals on level 0 at the bottom.
Within a row nodes are ordered by a few barycentre sweeps (each node moves towards the mean
position of its neighbours) so links cross little; everything is deterministic.

The input is the document of :meth:`chcos.system.manager.SystemManager.map_doc` or a sysfile.map
read with :func:`chcos.system.sysmap.read`; :func:`check_doc` raises ViewerError for anything
else. :func:`link_key` names a link the same way everywhere (rates, marks, the page).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from chcos.viewer import ViewerError

NODE_W = 140.0
NODE_H = 68.0
GAP = 40.0
ROW_GAP = 160.0
MARGIN = 24.0
TOP = 56.0


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
