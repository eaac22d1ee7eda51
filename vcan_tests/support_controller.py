"""support_controller - a controller process for the SocketCAN tests that kill it: a Python
script (a CanopenDriver started on the guest's bus) run in a process of its own, and the check
that what it produced stops on the wire once it is gone."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import can

from vcan_tests.support_fb import WAIT

ROOT = Path(__file__).resolve().parent.parent


@contextmanager
def controller(source: str, where: Path) -> Iterator[subprocess.Popen[str]]:
    """Run ``source`` (dedented) as a script in ``where`` in a process of its own, with the
    repository importable; yields the process once it printed ``started``. The process is
    killed on exit if it still runs. Raises AssertionError if it does not start."""
    script = where / "controller.py"
    script.write_text(textwrap.dedent(source), encoding="utf-8")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, env=env,
                            text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "started"
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(WAIT)


def assert_quiet(seen: can.BusABC, what: str) -> None:
    """Nothing more arrives on ``seen`` (a filtered listener): what was queued before is
    drained, then none comes within 0.3 s. Raises AssertionError saying ``what``."""
    while seen.recv(0) is not None:
        pass
    assert seen.recv(0.3) is None, what
