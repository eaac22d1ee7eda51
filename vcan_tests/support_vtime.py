"""Shared by the virtual-time tests (issue 47): busy processes that load every core the test may
use, and the run digest of the welding job taken in a fresh interpreter."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent


@contextmanager
def busy_cores(extra: int = 0) -> Iterator[list[subprocess.Popen[bytes]]]:
    """One busy Python loop per core this process may run on (plus ``extra``), started here and
    killed (each by its own process) when the block ends."""
    n = len(os.sched_getaffinity(0)) + extra
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"],
                              stdin=subprocess.DEVNULL) for _ in range(n)]
    try:
        yield procs
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait(timeout=30)


def digest_in_subprocess(binding: str, seconds: float, hashseed: int, out: Path,
                         timeout: float = 600.0) -> tuple[str, dict[str, Any]]:
    """``python -m tools.run_digest`` in a fresh interpreter with ``PYTHONHASHSEED=hashseed``:
    (the digest it printed, the document it wrote to ``out``). Raises AssertionError with its
    output if it fails."""
    env = dict(os.environ, PYTHONHASHSEED=str(hashseed), PYTHONPATH=str(ROOT))
    env.pop("PYTEST_ADDOPTS", None)
    res = subprocess.run([sys.executable, "-m", "tools.run_digest", "--binding", binding,
                          "--seconds", str(seconds), "--json", str(out)], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=timeout, check=False)
    assert res.returncode == 0, f"run_digest failed ({res.returncode}):\n{res.stdout}\n{res.stderr}"
    line = res.stdout.strip().splitlines()[-1]
    assert line.startswith("digest "), res.stdout
    return line.split()[1], json.loads(out.read_text(encoding="utf-8"))
