#!/usr/bin/env python3
"""bench_rtf - the real-time factor of each shipped cell on virtual time, side by side in one run
(issue 47): virtual seconds per wall second and CPU seconds per virtual second (every thread of
the process) of the welding cell on the simulated buses, the same cell on the protocol-free
binding, the from-vendor-files cell (docs/from-vendor-files.md: a CiA 402 drive from an EDS, a
gripper from a DBC, a Modbus meter) and the ``chcos new`` scaffold; and the ceiling: the factor
of a plain loop that only moves the buses cell's CAN frames (as many per virtual second as the
cell put on its two CAN buses) through python-can's virtual bus, with no protocol and no model.

Each cell runs in a fresh interpreter (``--one``), built first and timed only while its virtual
time runs. ``tools/bench_suite.py`` prints it as its "real-time factor" section.
Usage: python -m tools.bench_rtf [--seconds S] [--repeat N] [--json FILE]
Errors: whatever building a cell raises (the cell's line then says so).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CELLS = ("weld-buses", "weld-direct", "vendor-files", "scaffold")
#: issue 47's targets: (real-time factor at least, as a share of the direct binding's at least)
TARGETS: dict[str, tuple[float, float | None]] = {
    "weld-buses": (20.0, 0.5), "weld-direct": (50.0, None), "vendor-files": (50.0, None)}


@dataclass(frozen=True)
class Factor:
    """One cell's run: virtual seconds, wall seconds and CPU seconds while it ran, and what
    else it counted (CAN frames for the buses cell)."""

    cell: str
    virtual: float
    wall: float
    cpu: float
    frames: int = 0

    @property
    def rtf(self) -> float:
        """Virtual seconds per wall second."""
        return self.virtual / self.wall

    @property
    def cpu_per_virtual(self) -> float:
        """CPU seconds per virtual second."""
        return self.cpu / self.virtual


def _timed(cell: str, run: Callable[[], float], frames: Callable[[], int] = lambda: 0
           ) -> Factor:
    t0, c0 = time.perf_counter(), time.process_time()
    virtual = run()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return Factor(cell, virtual, wall, cpu, frames())


def measure_weld(binding: str, seconds: float) -> Factor:
    """The welding job on ``binding`` for ``seconds`` of virtual time (built before timing)."""
    from chcos.apps.weld.cell import open_cell

    with open_cell(binding) as cell:
        cell.start_job()

        def frames() -> int:    # both ways, on the two CAN buses
            kinds = {b.name: b.kind for b in cell.system.devmap.buses}
            return sum(s.counts["frames"] + s.counts["frames-sent"]
                       for name, s in cell.system.devtab.bus_stats.items()
                       if kinds.get(name) in ("can", "canopen"))

        return _timed(f"weld-{binding}", lambda: cell.run(seconds), frames)


def tutorial_cell(where: Path) -> Path:
    """The from-vendor-files tutorial's cell in ``where``, built by its own commands (up to its
    first ``chcos run``). Raises RuntimeError naming a command that failed."""
    from tools.doccmds import doc_commands

    for f in ("drive.eds", "gripper.dbc", "meter.csv"):
        shutil.copy(ROOT / "docs" / "vendor" / f, where / f)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    for cmd in doc_commands(ROOT / "docs" / "from-vendor-files.md"):
        if cmd.startswith("chcos run"):
            break
        res = subprocess.run(["bash", "-c", cmd], cwd=where, env=env, text=True,
                             capture_output=True, timeout=300, check=False)
        if res.returncode != 0:
            raise RuntimeError(f"{cmd}: {res.stdout}{res.stderr}")
    return where / "system.toml"


def scaffold_cell(where: Path) -> Path:
    """A ``chcos new`` project in ``where``/cell; its system file."""
    from chcos.cli.scaffold import main as new
    from chcos.helpers import free_port

    target = where / "cell"
    if new([str(target), "--port", str(free_port())]) != 0:
        raise RuntimeError(f"chcos new {target} failed")
    return target / "system.toml"


def measure_system(name: str, system_file: Path, seconds: float) -> Factor:
    """A user's system file on virtual time against its simulated slaves."""
    from chcos.cli.cellsystem import open_cell

    with open_cell(system_file, virtual=True, workdir=system_file.parent / "work") as cell:
        def run() -> float:
            cell.run_for(seconds)
            return seconds

        return _timed(name, run)


def measure_ceiling(frames_per_virtual_second: float, seconds: float) -> Factor:
    """The plain loop: ``frames_per_virtual_second`` CAN frames a virtual second sent on one
    python-can virtual bus handle and received on another, for ``seconds`` virtual seconds."""
    import can

    channel = f"rtf-ceiling-{os.getpid()}"
    tx = can.Bus(interface="virtual", channel=channel)
    rx = can.Bus(interface="virtual", channel=channel)
    n = max(1, round(frames_per_virtual_second * seconds))
    msg = can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False)

    def run() -> float:
        for _ in range(n):
            tx.send(msg)
            rx.recv(0)
        return seconds

    try:
        return _timed("ceiling", run, lambda: n)
    finally:
        tx.shutdown()
        rx.shutdown()


def measure(cell: str, seconds: float, frames_per_second: float = 0.0) -> Factor:
    """One cell (a name of :data:`CELLS`, or ``ceiling``) in this interpreter."""
    import logging

    logging.getLogger("chcos").setLevel(logging.CRITICAL)
    if cell.startswith("weld-"):
        return measure_weld(cell.removeprefix("weld-"), seconds)
    if cell == "ceiling":
        return measure_ceiling(frames_per_second, seconds)
    with tempfile.TemporaryDirectory(prefix=f"rtf-{cell}-") as tmp:
        where = Path(tmp)
        system = tutorial_cell(where) if cell == "vendor-files" else scaffold_cell(where)
        return measure_system(cell, system, seconds)


def in_subprocess(cell: str, seconds: float, frames_per_second: float = 0.0) -> Factor:
    """:func:`measure` in a fresh interpreter. Raises RuntimeError with its output if it
    fails."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    res = subprocess.run([sys.executable, "-m", "tools.bench_rtf", "--one", cell, "--seconds",
                          str(seconds), "--frames-per-second", str(frames_per_second)],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=1800,
                         check=False)
    if res.returncode != 0:
        raise RuntimeError(f"{cell}: {res.stdout}{res.stderr}")
    return Factor(**json.loads(res.stdout.strip().splitlines()[-1]))


def run_all(seconds: float, repeat: int = 1) -> dict[str, list[Factor]]:
    """Every cell and the ceiling, ``repeat`` rounds, the cells interleaved in each round."""
    out: dict[str, list[Factor]] = {c: [] for c in (*CELLS, "ceiling")}
    for _ in range(repeat):
        for cell in CELLS:
            out[cell].append(in_subprocess(cell, seconds))
        buses = out["weld-buses"][-1]
        out["ceiling"].append(in_subprocess("ceiling", seconds,
                                            buses.frames / buses.virtual))
    return out


def median(xs: list[float]) -> float:
    """The median of ``xs`` (not empty)."""
    s = sorted(xs)
    return s[len(s) // 2] if len(s) % 2 else (s[len(s) // 2 - 1] + s[len(s) // 2]) / 2


def rows(results: dict[str, list[Factor]]) -> list[tuple[str, str, str, str]]:
    """The table rows (figure, target, measured, met?), targets judged on the median."""
    direct = median([f.rtf for f in results["weld-direct"]])
    out = []
    for cell, runs in results.items():
        rtf = median([f.rtf for f in runs])
        cpu = median([f.cpu_per_virtual for f in runs])
        spread = f"{min(f.rtf for f in runs):.1f} / {rtf:.1f} / {max(f.rtf for f in runs):.1f}"
        target, share = TARGETS.get(cell, (None, None))
        want = "-" if target is None else f">= {target:g}x" + (
            f" and >= {share:g} of weld-direct" if share is not None else "")
        met = "-" if target is None else ("yes" if rtf >= target and (
            share is None or rtf >= share * direct) else "no")
        extra = f", {runs[-1].frames / runs[-1].virtual:,.0f} frames/virtual s" \
            if runs[-1].frames else ""
        label = ("ceiling: a plain loop moving the buses cell's CAN frames (no protocol)"
                 if cell == "ceiling" else f"real-time factor, {cell} cell")
        out.append((f"{label}: virtual s per wall s (min / median / max), CPU-s per virtual s",
                    want, f"{spread}x, {cpu:.3f} CPU-s/s{extra}", met))
    return out


def main(argv: list[str] | None = None) -> int:
    """Measure and print the table (or, with ``--one``, one cell's figures as JSON)."""
    doc = __doc__ or "bench_rtf"
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="virtual seconds a cell (20)")
    ap.add_argument("--repeat", type=int, default=1, help="rounds (1)")
    ap.add_argument("--json", type=Path, help="write the figures here")
    ap.add_argument("--one", choices=(*CELLS, "ceiling"), help=argparse.SUPPRESS)
    ap.add_argument("--frames-per-second", type=float, default=0.0, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        print(json.dumps(asdict(measure(args.one, args.seconds, args.frames_per_second))))
        return 0
    results = run_all(args.seconds, args.repeat)
    for figure, target, measured, met in rows(results):
        print(f"{figure}\n    target {target}; measured {measured}; met: {met}")
    if args.json:
        args.json.write_text(json.dumps({c: [asdict(f) for f in fs]
                                         for c, fs in results.items()}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
