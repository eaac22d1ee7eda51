"""bench_weld_modbus_share - the welding cell's Modbus share on the simulated buses (issue 47):
the CPU seconds per virtual second of the whole process and of the threads the Modbus power
source's bus runs on (the driver's worker, the simulated server), read from the kernel's count
of each thread's CPU time (``/proc/self/task/<tid>/stat``) after a job of ``--seconds`` virtual
seconds. A lower bound of the Modbus share: what the kernel thread itself spends on it (the
settle rounds that wait for those threads, the readings) is counted with the rest.

``python -m tools.bench_weld_modbus_share [--seconds V]``
"""

from __future__ import annotations

import argparse
import os
import threading
import time
from pathlib import Path

from chcos.apps.weld.cell import open_cell

TICKS = os.sysconf("SC_CLK_TCK")


def thread_cpu(native_id: int) -> float:
    """The CPU seconds (user and system) of this process's thread ``native_id``."""
    fields = Path(f"/proc/self/task/{native_id}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS


def modbus_threads() -> dict[str, float]:
    """The CPU seconds so far of each thread of the Modbus bus, by name."""
    return {t.name: thread_cpu(t.native_id) for t in threading.enumerate()
            if t.native_id is not None and t.name.startswith("modbus")}


def main() -> None:
    """One buses-binding job, then the CPU of each Modbus thread beside the process's."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="virtual seconds of the job")
    args = ap.parse_args()
    with open_cell("buses") as cell:
        cell.start_job()
        before = modbus_threads()
        cpu0, wall0, t0 = time.process_time(), time.perf_counter(), cell.system.kernel.clock.now()
        cell.run(args.seconds, until_done=False)
        cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
        virtual = cell.system.kernel.clock.now() - t0
        modbus = {name: c - before.get(name, 0.0) for name, c in modbus_threads().items()}
    share = sum(modbus.values())
    print(f"welding cell, buses binding, {virtual:g} virtual s: real-time factor "
          f"{virtual / wall:.1f}x, {cpu / virtual:.4f} CPU-s per virtual s")
    for name, c in sorted(modbus.items()):
        print(f"  thread {name:<28} {c / virtual:.4f} CPU-s per virtual s")
    print(f"  Modbus threads together: {share / virtual:.4f} CPU-s per virtual s, "
          f"{share / cpu:.1%} of the process (a lower bound: see the module doc)")


if __name__ == "__main__":
    main()
