#!/usr/bin/env python3
"""bench_growth - how setup costs grow with the size of the work (issue 21, "linear setup").

For sizes N = 10², 10³, 10⁴ (--sizes to change) it times, in one process:
1. ``install``: N tasks installed through ``System.execute`` (one exception task and one
   assassin installed first, so every install also gets its exception tap and assassin link),
   no sysfile.map;
2. ``install+map``: the same with sysfile.map kept current (the map on disk at the end holds
   all N tasks; the number of map writes is printed);
3. ``devmap load``: a device map of N sensors on one DBC-decoded CAN bus, loaded and validated
   (``chcos.devices.devmap.load``: TOML, checks, the DBC parsed — the parse count is printed);
4. ``chcos check``: the same map through ``chcos check`` (``chcos.devices.devmap.check_main``).
Prints seconds per size, the growth exponent between successive sizes (1.0 = linear, 2.0 =
quadratic) and a least-squares exponent over all sizes, beside the issue's targets (10,000
installs ≤ 1 s, ≤ 2 s with the map; 1,000 devices ≤ 0.5 s; check of 5,000 devices ≤ 2 s — the
last two are measured at 10³ and interpolated at 5·10³ from the fit when not in --sizes).
Usage: python -m tools.bench_growth [--sizes 100,1000,10000] [--json FILE]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import itertools
import json
import logging
import math
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cantools

from chcos.devices import devmap
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System
from chcos.user.context import TaskContext

CODE = "tools.bench_growth:idle"


async def idle(ctx: TaskContext, cmd: Any) -> None:
    """The task every benchmark install names (never activated)."""


def installs(n: int, work: Path | None) -> tuple[float, dict[str, Any]]:
    """Seconds for ``n`` installs (plus the exception task and assassin installed first) and
    what was checked: the tasks in the map (when ``work`` is given) and the map writes."""
    map_path = work / "sysfile.map" if work is not None else None
    with System(clock=VirtualClock(), machines=[0], base_dir=work or ".",
                map_path=map_path) as s:
        s.execute(f"install -m0 --role=exception --level=1000 --code={CODE} EXC")
        s.execute(f"install -m0 --role=assassin --level=999 --code={CODE} ASN")
        t0 = time.perf_counter()
        for i in range(n):
            s.execute(f"install -m0 --code={CODE} T{i}")
        s.sysmgr.flush_map()
        dt = time.perf_counter() - t0
        info: dict[str, Any] = {"links": len(s.msgtab.links)}
        if map_path is not None:
            info["map_writes"] = s.sysmgr.map_writes
            info["tasks_in_map"] = len(json.loads(map_path.read_text())["tasks"])
            if info["tasks_in_map"] != n + 2:
                raise SystemExit(f"sysfile.map holds {info['tasks_in_map']} tasks, not {n + 2}")
    return dt, info


def write_dbc_map(n: int, work: Path) -> Path:
    """A device map of ``n`` sensors on one CAN bus decoded by a generated DBC (8 one-byte
    signals per message)."""
    msgs = (n + 7) // 8
    lines = ['VERSION ""', "", "NS_ :", "", "BS_:", "", "BU_: Node Chcos", ""]
    for m in range(msgs):
        lines.append(f"BO_ {m + 1} M{m}: 8 Node")
        for k in range(8):
            lines.append(f' SG_ S{k} : {8 * k}|8@1+ (1,0) [0|255] "" Chcos')
        lines.append("")
    (work / "big.dbc").write_text("\n".join(lines) + "\n", encoding="utf-8")
    toml = ['[[bus]]', 'name = "can0"', 'kind = "can"', 'interface = "virtual"',
            'channel = "bench-growth"', 'dbc = "big.dbc"', ""]
    for i in range(n):
        toml += ["[[device]]", f'name = "D{i}"', 'direction = "sensor"', 'bus = "can0"',
                 f'address = {{ message = "M{i // 8}", signal = "S{i % 8}" }}', ""]
    path = work / "big.toml"
    path.write_text("\n".join(toml), encoding="utf-8")
    return path


def _count_parses() -> tuple[list[int], Callable[[], None]]:
    """Count cantools DBC parses (the wrapped loader of drivers.codecs.can)."""
    count = [0]
    real = cantools.database.load_file

    def counting(*a: Any, **k: Any) -> Any:
        count[0] += 1
        return real(*a, **k)

    cantools.database.load_file = counting

    def undo() -> None:
        cantools.database.load_file = real

    return count, undo


def devmap_load(n: int, work: Path) -> tuple[float, dict[str, Any]]:
    """Seconds to load (parse and validate) a map of ``n`` devices on one DBC bus."""
    path = write_dbc_map(n, work)
    count, undo = _count_parses()
    try:
        t0 = time.perf_counter()
        dm = devmap.load(path)
        dt = time.perf_counter() - t0
    finally:
        undo()
    if len(dm.devices) != n:
        raise SystemExit(f"device map has {len(dm.devices)} devices, not {n}")
    return dt, {"dbc_parses": count[0]}


def check_cmd(n: int, work: Path) -> tuple[float, dict[str, Any]]:
    """Seconds for ``chcos check`` of the same map (its output discarded)."""
    path = write_dbc_map(n, work)
    out = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        status = devmap.check_main([str(path)])
    dt = time.perf_counter() - t0
    if status != 0:
        raise SystemExit(f"chcos check of {n} devices failed:\n{out.getvalue()[-2000:]}")
    return dt, {}


def slope(points: list[tuple[int, float]]) -> float:
    """Least-squares exponent k of t ~ n^k."""
    xs = [math.log(n) for n, _ in points]
    ys = [math.log(max(t, 1e-9)) for _, t in points]
    mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
    den = sum((x - mx) ** 2 for x in xs)
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True)) / den if den else 0.0


def at(points: list[tuple[int, float]], n: int) -> float:
    """The time at size ``n``: measured if it is one of the sizes, else from the fit through
    the two nearest measured sizes."""
    for m, t in points:
        if m == n:
            return t
    (n1, t1), (n2, t2) = sorted(points, key=lambda p: abs(math.log(p[0] / n)))[:2]
    k = math.log(t2 / t1) / math.log(n2 / n1) if n1 != n2 else 1.0
    return float(t1 * (n / n1) ** k)


BENCHES: list[tuple[str, Callable[[int, Path], tuple[float, dict[str, Any]]], int, float]] = [
    ("install, no map", lambda n, w: installs(n, None), 10_000, 1.0),
    ("install, sysfile.map kept current", installs, 10_000, 2.0),
    ("device map load, one DBC bus", devmap_load, 1_000, 0.5),
    ("chcos check, one DBC bus", check_cmd, 5_000, 2.0),
]


def run(sizes: list[int]) -> dict[str, Any]:
    """Every benchmark at every size; returns {name: {points, info, slope, target...}}."""
    logging.getLogger("chcos").setLevel(logging.ERROR)
    res: dict[str, Any] = {}
    for name, fn, tn, tsec in BENCHES:
        points: list[tuple[int, float]] = []
        infos: list[dict[str, Any]] = []
        for n in sizes:
            with tempfile.TemporaryDirectory(prefix="chcos-growth-") as tmp:
                dt, info = fn(n, Path(tmp))
            points.append((n, dt))
            infos.append(info)
        t_at = at(points, tn)
        res[name] = {"points": points, "info": infos, "slope": slope(points),
                     "target_n": tn, "target_s": tsec, "at_target": t_at,
                     "met": t_at <= tsec}
    return res


def report(res: dict[str, Any]) -> list[str]:
    """The table lines for ``res``."""
    out = []
    for name, r in res.items():
        pts = r["points"]
        steps = " ".join(f"{math.log(t2 / t1) / math.log(n2 / n1):.2f}"
                         for (n1, t1), (n2, t2) in itertools.pairwise(pts))
        curve = ", ".join(f"{n:,}: {t:.3f} s" for n, t in pts)
        extra = "; ".join(f"{k}={v}" for k, v in r["info"][-1].items() if k != "links")
        out.append(f"{name}: {curve}; growth exponent {r['slope']:.2f} (steps {steps})"
                   + (f"; at {pts[-1][0]:,}: {extra}" if extra else ""))
        out.append(f"  target {r['target_n']:,} in <= {r['target_s']} s: "
                   f"{r['at_target']:.3f} s -> {'yes' if r['met'] else 'NO'}")
    return out


def main(argv: list[str] | None = None) -> int:
    doc = __doc__ or "bench_growth"
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--sizes", default="100,1000,10000",
                    help="comma-separated sizes (default 100,1000,10000)")
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = ap.parse_args(argv)
    sizes = [int(x) for x in args.sizes.split(",")]
    res = run(sizes)
    print("\n".join(report(res)))
    if args.json is not None:
        args.json.write_text(json.dumps(res, indent=2) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
