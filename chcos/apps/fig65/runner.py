"""runner - run the figure 6.5 example system end to end and report what it did.

Used by ``chcos run --example fig65``: loads chcos/apps/fig65/fig65.toml, executes the thesis'
install
script, invokes C1 from the host, runs on virtual time (or real time), prints live progress once a
second and a summary at the end: task executions per task and per level, messages sent, delivered
and overwritten, against the thesis' estimate of 51 task executions a second for this load.
"""

from __future__ import annotations

import shutil
import sys
from collections import Counter
from pathlib import Path
from typing import TextIO

from chcos import resources
from chcos.apps import fig65
from chcos.kernel.clock import Clock, RealClock, VirtualClock
from chcos.kernel.instrument import Counters
from chcos.system.embedded import System


def default_devmap() -> Path:
    """The figure 6.5 device map shipped with chcos (``chcos/apps/fig65/fig65.toml``)."""
    return resources.path("chcos.apps.fig65", "fig65.toml")


def build(clock: Clock, workdir: Path) -> System:
    """The figure 6.5 system on ``clock`` (booted, nothing installed), its map, log and the test
    file task A3 samples in ``workdir`` (created). Raises ChcosError if it cannot be built."""
    workdir.mkdir(parents=True, exist_ok=True)
    shutil.copy(fig65.HERE / "testfile", workdir / "testfile")
    return System([default_devmap()], clock=clock, task_path=[fig65.HERE], base_dir=workdir,
                  map_path=workdir / "sysfile.map")


def run(duration: float = 20.0, *, real_time: bool = False, workdir: Path | None = None,
        out: TextIO = sys.stdout, tty: str | None = None) -> dict[str, float]:
    """Run the example for ``duration`` seconds of clock time; returns the summary figures.
    ``tty`` names a real terminal A4 reads instead of /dev/tty0 (lines typed there reach C1).
    Raises ChcosError if the system cannot be built."""
    workdir = workdir or Path("out") / "fig65"
    clock: Clock = RealClock() if real_time else VirtualClock()
    counters = Counters()
    with build(clock, workdir) as s:
        s.kernel.add_instrument(counters)
        for line in fig65.SCRIPT.read_text(encoding="utf-8").splitlines():
            answer = s.execute(line.replace("/dev/tty0", tty) if tty else line)
            if answer:
                print(f"  host: {answer}", file=out)
        print(f"  host: {s.execute('invoke C1')}", file=out)
        start = s.kernel.clock.now()
        last_steps, last_sent = 0, 0
        for sec in range(1, int(duration) + 1):
            s.run(until=start + sec)
            steps = sum(counters.steps.values())
            sent = sum(counters.sent.values())
            print(f"  t={sec:5.1f} s  executions/s {steps - last_steps:4d}  "
                  f"messages/s {sent - last_sent:4d}  M1={s.devtab.get('M1').value!s:.6}  "
                  f"M2={s.devtab.get('M2').value!s:.6}", file=out, flush=True)
            last_steps, last_sent = steps, sent
        elapsed = s.kernel.clock.now() - start
        by_level: Counter[int] = Counter()
        for t in s.tsktab:
            by_level[t.level] += t.steps
        print("\nsummary", file=out)
        print(f"  {'task':<5}{'level':>6}{'machine':>8}{'executions':>12}{'per s':>8}", file=out)
        for t in s.tsktab:
            print(f"  {t.name:<5}{t.level:>6}{t.machine:>8}{t.steps:>12}"
                  f"{t.steps / elapsed:>8.1f}", file=out)
        total = sum(by_level.values())
        for level in sorted(by_level):
            print(f"  level {level}: {by_level[level]} executions "
                  f"({by_level[level] / elapsed:.1f}/s)", file=out)
        sent = sum(lk.sent for lk in s.msgtab)
        over = sum(lk.overwritten for lk in s.msgtab)
        delivered = sum(lk.delivered for lk in s.msgtab)
        print(f"  all tasks: {total} executions in {elapsed:.1f} s = {total / elapsed:.1f}/s "
              "(thesis estimate for 4 inputs at 10 Hz: 51/s)", file=out)
        print(f"  messages: {sent} sent, {delivered} delivered, {over} overwritten", file=out)
        print(f"  system map: {workdir / 'sysfile.map'}   log: {workdir / 'log'}", file=out)
        return {"executions_per_s": total / elapsed, "messages": float(sent),
                "overwritten": float(over), "seconds": elapsed}
