"""Support for the HIL evidence tests: processes that load the machine, and ``chcos`` run in a
fresh interpreter."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path


def env(**extra: str) -> dict[str, str]:
    """The environment for a child ``chcos`` or ``pytest``: this interpreter's scripts first on
    the PATH, none of the parent pytest's own variables."""
    out = dict(os.environ)
    for key in ("PYTEST_ADDOPTS", "PYTEST_XDIST_WORKER", "PYTEST_CURRENT_TEST"):
        out.pop(key, None)
    out["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{out.get('PATH', '')}"
    out.update(extra)
    return out


def chcos(where: Path, args: Sequence[str], timeout: float = 900,
          **extra: str) -> subprocess.CompletedProcess[str]:
    """``chcos ARGS`` in ``where``, in a fresh interpreter."""
    return subprocess.run([sys.executable, "-m", "chcos.cli.main", *args], cwd=where,
                          env=env(**extra), text=True, capture_output=True, timeout=timeout)


@contextmanager
def busy_processes(n: int = 2) -> Iterator[list[subprocess.Popen[bytes]]]:
    """``n`` processes that spin on the CPU while the block runs (killed at its end)."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield procs
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait(timeout=30)
