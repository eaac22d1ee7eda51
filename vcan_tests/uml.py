"""uml - real SocketCAN for the tests: run commands inside User-Mode Linux, and detect vcan0.

The host kernel of our machines has no CAN; Debian's UML kernel does. ``run_in_uml`` boots it
(through ``tools/uml/run-in-uml``) with the host's file system as its root, so this work tree and
its ``.venv`` are at the same paths inside, and runs one command there with vcan0 up.

Test classes that talk CAN are parametrised over the interface with :func:`can_interfaces` and
:func:`can_channel`: they run on python-can's ``virtual`` bus everywhere, and on ``socketcan`` /
``vcan0`` (marked ``socketcan``) where :func:`socketcan_channel` finds it, that is inside UML.
The host-side test in ``test_uml_socketcan.py`` runs ``pytest -m socketcan`` inside UML; on the
host, conftest deselects the ``socketcan`` tests. Host-side tests that boot UML call
:func:`require_uml` first: it boots UML once per session (:func:`uml_boot_problem`) and skips,
or under CI fails, with the cause when UML cannot run here.
"""

from __future__ import annotations

import functools
import math
import os
import socket
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pytest

from vcan_tests.netutil import unique_channel

REPO_ROOT = Path(__file__).resolve().parent.parent
RUN_IN_UML = REPO_ROOT / "tools" / "uml" / "run-in-uml"
UML_KERNEL = Path("/usr/bin/linux")
UML_MODULES_ROOT = Path("/usr/lib/uml/modules")
CAN_MODULES = (
    "net/can/can.ko",
    "net/can/can-raw.ko",
    "drivers/net/can/dev/can-dev.ko",
    "drivers/net/can/vcan.ko",
)
HOST_TOOLS = ("insmod", "ip", "timeout")
SOCKETCAN_CHANNEL = "vcan0"
GUEST_MARKER = "CHCOS_IN_UML"
"""Set to 1 by tools/uml/guest-init in the environment of the command it runs inside UML."""
DEFAULT_TIMEOUT = 600.0
_HOST_GRACE = 30.0  # the wrapper's own timeout fires first; this only catches a wedged wrapper
_IFF_UP = 0x1


class UmlUnavailable(RuntimeError):
    """UML cannot be used here; the message says why (what is missing)."""


def in_uml_guest() -> bool:
    """True inside a command started by ``run_in_uml`` (the guest init marks its environment)."""
    return os.environ.get(GUEST_MARKER) == "1"


@functools.cache
def _kernel_version(kernel: Path) -> str | None:
    """The UML kernel's release (``linux --version``), or None if it does not answer."""
    try:
        out = subprocess.run(
            [str(kernel), "--version"],
            stdin=subprocess.DEVNULL,
            capture_output=True,
            text=True,
            timeout=30,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    version = out.stdout.strip()
    return version if out.returncode == 0 and version else None


def uml_available(kernel: Path = UML_KERNEL, modules_root: Path = UML_MODULES_ROOT) -> str | None:
    """None when ``run_in_uml`` can work here, else the reason it cannot (for a skip message)."""
    if not sys.platform.startswith("linux"):
        return f"User-Mode Linux needs a Linux host, not {sys.platform}"
    if in_uml_guest():
        return "already inside User-Mode Linux (UML does not nest here)"
    if os.geteuid() != 0:
        return "User-Mode Linux with the host root as hostfs needs root"
    if not RUN_IN_UML.is_file():
        return f"{RUN_IN_UML} is missing"
    if not os.access(kernel, os.X_OK):
        return f"UML kernel {kernel} not installed (Debian: apt-get install user-mode-linux)"
    version = _kernel_version(kernel)
    if version is None:
        return f"UML kernel {kernel} did not answer --version"
    moddir = modules_root / version / "kernel"
    for module in CAN_MODULES:
        if not (moddir / module).is_file():
            return f"UML CAN module {moddir / module} missing (user-mode-linux {version})"
    path = os.environ.get("PATH", os.defpath)
    for tool in HOST_TOOLS:
        if not any(os.access(Path(d) / tool, os.X_OK) for d in path.split(os.pathsep) if d):
            return f"host tool {tool} not found on PATH (Debian: kmod, iproute2, coreutils)"
    return None


@functools.cache
def uml_boot_problem() -> str | None:
    """None when UML boots here with vcan0 and vcan1 up, else why not: the first lines of what
    ``run-in-uml`` reported (the panic line, the missing package). Boots once per process."""
    reason = uml_available()
    if reason is not None:
        return reason
    probe = "ip -o link show vcan0 && ip -o link show vcan1"
    try:
        result = run_in_uml(["sh", "-c", probe], timeout=120)
    except subprocess.TimeoutExpired:
        return "run-in-uml did not return within its timeout"
    if result.returncode == 0 and result.stdout.count("UP") >= 2:
        return None
    lines = []  # the cause lines run-in-uml puts first, not the console log's tail after them
    for line in result.stderr.splitlines():
        if "console log ends" in line or len(lines) == 4:
            break
        if line.strip():
            lines.append(line.strip())
    return (f"User-Mode Linux does not boot or has no vcan0/vcan1 (status {result.returncode}): "
            + " | ".join(lines or [result.stdout.strip()[:200]]))


def require_uml() -> None:
    """Skip the running test (fail under CI=true) when UML cannot boot here, naming the cause."""
    from vcan_tests.support_env import require

    reason = uml_boot_problem()
    require(reason is None, str(reason))


def _uml_command(argv: Sequence[str], timeout: float, mem: str) -> tuple[list[str], int]:
    """The host command line that runs ``argv`` in UML, and its timeout in whole seconds.
    Raises like :func:`run_in_uml`."""
    if not argv:
        raise ValueError("run_in_uml: empty argv")
    if timeout <= 0:
        raise ValueError(f"run_in_uml: timeout must be positive, not {timeout}")
    reason = uml_available()
    if reason is not None:
        raise UmlUnavailable(reason)
    seconds = max(1, math.ceil(timeout))
    return ["bash", str(RUN_IN_UML), "--timeout", str(seconds), "--mem", mem, "--", *argv], seconds


def run_in_uml(
    argv: Sequence[str],
    env: Mapping[str, str] | None = None,
    timeout: float = DEFAULT_TIMEOUT,
    cwd: str | os.PathLike[str] | None = None,
    mem: str = "512M",
) -> subprocess.CompletedProcess[str]:
    """Run ``argv`` inside UML with vcan0 up and return its captured stdout, stderr and status.

    ``env`` is the command's whole environment (None: this process's); ``cwd`` its working
    directory (None: ours). ``timeout`` (seconds) bounds the whole boot-run-halt on the host side;
    when it expires UML is killed and ``returncode`` is 124. ``returncode`` 125 means UML could
    not run the command (stderr says why, with the console log). Raises :class:`UmlUnavailable`
    when :func:`uml_available` finds a reason, ``ValueError`` for an empty ``argv``.
    """
    cmd, seconds = _uml_command(argv, timeout, mem)
    return subprocess.run(
        cmd,
        env=dict(env) if env is not None else None,
        cwd=cwd,
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=seconds + _HOST_GRACE,
        check=False,
    )


class BackgroundUml:
    """A :func:`run_in_uml` that runs while the caller goes on (UML takes one core; the rest of
    a test session uses the other). Start it with :meth:`start`, collect it with :meth:`result`.
    """

    def __init__(self, proc: subprocess.Popen[str], out: Path, err: Path, seconds: int) -> None:
        self._proc, self._out, self._err, self._seconds = proc, out, err, seconds
        self.started = time.monotonic()
        """When it was started (``time.monotonic()``)."""

    @classmethod
    def start(
        cls,
        argv: Sequence[str],
        workdir: Path,
        env: Mapping[str, str] | None = None,
        timeout: float = DEFAULT_TIMEOUT,
        cwd: str | os.PathLike[str] | None = None,
        mem: str = "512M",
    ) -> BackgroundUml:
        """Boot UML and start ``argv`` there; its output goes to files in ``workdir``. Raises
        like :func:`run_in_uml`."""
        cmd, seconds = _uml_command(argv, timeout, mem)
        out, err = workdir / "uml.stdout", workdir / "uml.stderr"
        with out.open("w") as fo, err.open("w") as fe:
            proc = subprocess.Popen(cmd, env=dict(env) if env is not None else None, cwd=cwd,
                                    stdin=subprocess.DEVNULL, stdout=fo, stderr=fe, text=True)
        return cls(proc, out, err, seconds)

    def result(self) -> subprocess.CompletedProcess[str]:
        """Wait for the command (bounded by its timeout) and return what :func:`run_in_uml`
        would have returned."""
        try:
            code = self._proc.wait(timeout=self._seconds + _HOST_GRACE)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            code = self._proc.wait()
        return subprocess.CompletedProcess(self._proc.args, code, self._out.read_text(),
                                           self._err.read_text())

    def kill(self) -> None:
        """Stop it now (the session ended without asking for the result)."""
        if self._proc.poll() is None:
            self._proc.terminate()
            try:
                self._proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self._proc.kill()


@functools.cache
def socketcan_channel() -> str | None:
    """The name "vcan0" if this process can open a SocketCAN raw socket on an up vcan0, or None."""
    af_can = getattr(socket, "AF_CAN", None)
    if af_can is None:
        return None
    try:
        with socket.socket(af_can, socket.SOCK_RAW, socket.CAN_RAW) as sock:
            sock.bind((SOCKETCAN_CHANNEL,))
    except OSError:
        return None
    try:
        flags = int(Path(f"/sys/class/net/{SOCKETCAN_CHANNEL}/flags").read_text(), 16)
    except (OSError, ValueError):
        return None
    return SOCKETCAN_CHANNEL if flags & _IFF_UP else None


def socketcan_skip_reason() -> str:
    """Why this process has no socketcan channel (for a :func:`vcan_tests.conftest.require`)."""
    return (
        f"no SocketCAN {SOCKETCAN_CHANNEL} in this process (host kernel without CAN?); "
        "these run inside User-Mode Linux via vcan_tests/test_uml_socketcan.py"
    )


def can_interfaces() -> list[Any]:
    """pytest params for a CAN test's interface: "virtual" always, "socketcan" marked (conftest
    deselects those where there is no vcan0, and they run inside UML).

    Use as ``@pytest.fixture(params=can_interfaces())`` and open the bus with
    ``can.Bus(interface=request.param, channel=can_channel(request.param))``.
    """
    return [
        pytest.param("virtual", id="virtual"),
        pytest.param(
            "socketcan",
            id="socketcan",
            marks=[pytest.mark.socketcan],
        ),
    ]


def can_channel(interface: str) -> str:
    """The channel a test should use on ``interface``: a fresh virtual channel, or vcan0."""
    if interface == "virtual":
        return unique_channel("can")
    if interface == "socketcan":
        from vcan_tests.support_env import require

        channel = socketcan_channel()
        require(channel is not None, socketcan_skip_reason())
        return str(channel)
    raise ValueError(f"can_channel: unknown CAN interface {interface!r} (virtual or socketcan)")


def socketcan_test_files() -> list[str]:
    """The test files (paths from the checkout's root) that hold ``socketcan`` tests: those
    marking it, or parametrising over :func:`can_interfaces` or asking :func:`socketcan_channel`
    (the guest collects only these; the whole suite took minutes to collect inside UML, where
    every system call is slow)."""
    here = REPO_ROOT / "vcan_tests"
    signs = ("mark.socketcan", "can_interfaces(", "socketcan_channel()")
    return [p.relative_to(REPO_ROOT).as_posix() for p in sorted(here.glob("test_*.py"))
            if any(s in p.read_text(encoding="utf-8") for s in signs)]


GUEST_RESULTS = pytest.StashKey[list[str]]()
"""Lines for the terminal summary: what the guest runs did (counts, times), by the UML tests."""

BACKGROUND = pytest.StashKey[dict[str, tuple[BackgroundUml, Path]]]()
"""Long UML runs started when the session's tests are collected, by name (see conftest)."""
