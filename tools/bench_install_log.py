#!/usr/bin/env python3
"""bench_install_log - the replicated install log at scale: 8 satellite processes, 1,000 tasks.

Six satellite processes start; one host script boots all eight machines and installs ``--tasks``
tasks (default 1,000) spread over the eight machines; then the two remaining satellites start
late and catch up. Printed: the install rate, each late joiner's catch-up time (start of the
process to its liveliness token, which it declares only once it has applied the whole log), and
the log length and SHA-256 of every satellite, which must all be equal (exit status 1 if not).

Usage: python -m tools.bench_install_log [--tasks N] [--machines M] [--late L] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent

from chcos.helpers import free_ports  # noqa: E402
from chcos.satellites import sysfile  # noqa: E402
from chcos.satellites.host import Host  # noqa: E402
from chcos.user.context import TaskContext  # noqa: E402


async def idle(ctx: TaskContext, cmd: Any) -> None:
    """A task that is installed and never invoked."""
    await ctx.sleep(1.0)


def run(tasks: int, machines: int, late: int) -> dict[str, Any]:
    """Install ``tasks`` tasks on ``machines`` machines, ``late`` of which start afterwards."""
    tmp = Path(tempfile.mkdtemp(prefix="chcos-bench-log-"))
    ports = free_ports(machines)
    sats = "".join(f"[[satellite]]\nmachine = {m}\nport = {ports[m]}\n"
                   for m in range(machines))
    (tmp / "system.toml").write_text(
        f'[system]\nname = "benchlog{os.getpid()}"\nstate_dir = "state"\n\n{sats}')
    sf = sysfile.load(tmp / "system.toml")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    procs: dict[int, subprocess.Popen[bytes]] = {}
    started: dict[int, float] = {}

    def start(m: int) -> None:
        started[m] = time.monotonic()
        log = open(tmp / f"sat{m}.log", "ab")  # noqa: SIM115 - the child keeps it
        procs[m] = subprocess.Popen(
            [sys.executable, "-m", "chcos.cli.main", "satellite", "-m", str(m), "--system",
             str(sf.path)], cwd=ROOT, env=env, stdout=log, stderr=log)

    early = list(range(machines - late))
    host = Host(sf, timeout=60.0)
    try:
        for m in early:
            start(m)
        host.wait_for(early, timeout=120)
        script = [f"install -m{m} sysfile" for m in range(machines)]
        script += [f"install -m{i % machines} --code=tools.bench_install_log:idle T{i}"
                   for i in range(tasks)]
        t0 = time.monotonic()
        for line in script:
            host.execute(line)
        install_s = time.monotonic() - t0
        up_at: dict[int, float] = {}
        cond = threading.Condition()

        def joined(key: str) -> None:
            m = int(key.rsplit("/", 1)[-1])
            with cond:
                up_at.setdefault(m, time.monotonic())
                cond.notify_all()

        lates = list(range(machines - late, machines))
        with host.transport.watch(f"{sf.prefix}/alive/*", joined, lambda _k: None):
            for m in lates:
                start(m)
            with cond:
                cond.wait_for(lambda: all(m in up_at for m in lates), timeout=600)
        catch_up = {m: up_at[m] - started[m] for m in lates if m in up_at}
        heads = host.log_heads()
        return {"tasks": tasks, "machines": machines, "late": late,
                "install_s": install_s, "installs_per_s": len(script) / install_s,
                "catch_up_s": catch_up, "heads": {m: list(v) for m, v in heads.items()},
                "same_log": len(set(heads.values())) == 1 and len(heads) == machines
                and all(v[0] == len(script) for v in heads.values())}
    finally:
        host.close()
        for p in procs.values():
            p.terminate()
        for p in procs.values():
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()
        shutil.rmtree(tmp, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print the figures; 1 if the logs differ."""
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tasks", type=int, default=1000)
    p.add_argument("--machines", type=int, default=8)
    p.add_argument("--late", type=int, default=2)
    p.add_argument("--json", help="also write the figures here")
    args = p.parse_args(argv)
    r = run(args.tasks, args.machines, args.late)
    print(f"{r['machines']} satellites, {r['tasks']} tasks from one script: installed in "
          f"{r['install_s']:.1f} s ({r['installs_per_s']:.1f} installs/s)")
    for m, s in sorted(r["catch_up_s"].items()):
        print(f"late joiner machine {m}: caught up with the log and up in {s:.2f} s")
    for m, (n, h) in sorted(r["heads"].items()):
        print(f"machine {m}: {n} log entries, sha256 {h[:16]}")
    print("same log everywhere" if r["same_log"] else "LOGS DIFFER")
    if args.json:
        Path(args.json).write_text(json.dumps(r, indent=2, default=str))
    return 0 if r["same_log"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
