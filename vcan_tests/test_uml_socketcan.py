"""test_uml_socketcan - real SocketCAN: python-can against can-utils on vcan0 inside UML.

Three layers: checks of the vcan_tests.uml helpers that run anywhere; tests marked ``socketcan``
that need vcan0 and so run inside UML (deselected by conftest on a host kernel without CAN); and
host-side tests marked ``uml`` that boot UML (the boot self-test first: it fails with the cause,
say the panic line, when UML cannot boot), check the run-in-uml wrapper, and run
``pytest -m socketcan`` (these tests and every other engineer's socketcan variants) inside it.
"""

from __future__ import annotations

import os
import selectors
import shutil
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import pytest

from vcan_tests.conftest import require
from vcan_tests.uml import (
    BACKGROUND,
    CAN_MODULES,
    GUEST_MARKER,
    GUEST_RESULTS,
    REPO_ROOT,
    RUN_IN_UML,
    BackgroundUml,
    can_channel,
    can_interfaces,
    require_uml,
    run_in_uml,
    socketcan_test_files,
    uml_available,
    uml_boot_problem,
)

UML_REASON = uml_available()
STEP_TIMEOUT = 10.0  # bound on every wait inside the guest; UML syscalls are slow, not this slow


# -- helpers usable anywhere -------------------------------------------------------------------


def test_uml_available_names_a_missing_kernel(tmp_path: Path) -> None:
    kernel = tmp_path / "no-such-linux"
    reason = uml_available(kernel=kernel)
    assert reason is not None
    if UML_REASON is None:  # every earlier check passes here, so the kernel must be the reason
        assert str(kernel) in reason


def test_uml_available_names_a_missing_can_module(tmp_path: Path) -> None:
    kernel = tmp_path / "linux"
    kernel.write_text("#!/bin/sh\necho 9.9.9-test\n")
    kernel.chmod(0o755)
    reason = uml_available(kernel=kernel, modules_root=tmp_path / "modules")
    assert reason is not None
    if UML_REASON is None:
        assert str(tmp_path / "modules" / "9.9.9-test" / "kernel" / "net/can/can.ko") in reason


def test_run_in_uml_rejects_an_empty_command() -> None:
    with pytest.raises(ValueError, match="empty argv"):
        run_in_uml([])


def test_can_channel_gives_fresh_virtual_channels_and_rejects_unknown_interfaces() -> None:
    assert can_channel("virtual") != can_channel("virtual")
    with pytest.raises(ValueError, match="'pcan'"):
        can_channel("pcan")


def test_can_interfaces_mark_the_socketcan_variant() -> None:
    params = can_interfaces()
    assert [p.id for p in params] == ["virtual", "socketcan"]
    assert not params[0].marks
    assert "socketcan" in {m.name for m in params[1].marks}


# -- inside UML: python-can against the kernel's CAN stack and can-utils -------------------------


@pytest.fixture
def can_utils() -> None:
    """can-utils, the independent peer of the socketcan tests, must be on PATH."""
    for tool in ("cansend", "candump"):
        require(shutil.which(tool), f"{tool} on PATH (apt-get install can-utils)")


@pytest.fixture
def vcan0_bus(can_utils: None) -> Iterator[can.BusABC]:
    bus = can.Bus(interface="socketcan", channel=can_channel("socketcan"))
    try:
        yield bus
    finally:
        bus.shutdown()


def _recv(bus: can.BusABC) -> can.Message:
    msg = bus.recv(timeout=STEP_TIMEOUT)
    assert msg is not None, f"no frame on {bus.channel_info} within {STEP_TIMEOUT}s"
    return msg


class _LineReader:
    """Lines from a child's stdout, each wait bounded (select on the pipe, no sleeping)."""

    def __init__(self, proc: subprocess.Popen[bytes]) -> None:
        assert proc.stdout is not None
        self._fd = proc.stdout.fileno()
        os.set_blocking(self._fd, False)
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._fd, selectors.EVENT_READ)
        self._buf = b""
        self.seen: list[str] = []

    def readline(self, timeout: float) -> str | None:
        deadline = time.monotonic() + timeout
        while b"\n" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0 or not self._sel.select(left):
                return None
            chunk = os.read(self._fd, 4096)
            if not chunk:
                return None
            self._buf += chunk
        line, self._buf = self._buf.split(b"\n", 1)
        text = line.decode()
        self.seen.append(text)
        return text

    def close(self) -> None:
        self._sel.close()


@pytest.mark.socketcan
def test_python_can_receives_a_frame_from_cansend(vcan0_bus: can.BusABC) -> None:
    subprocess.run(["cansend", "vcan0", "123#DEADBEEF"], check=True, timeout=STEP_TIMEOUT)
    msg = _recv(vcan0_bus)
    assert msg.arbitration_id == 0x123
    assert not msg.is_extended_id
    assert not msg.is_remote_frame
    assert msg.dlc == 4
    assert bytes(msg.data) == bytes.fromhex("DEADBEEF")
    assert msg.channel == "vcan0"


@pytest.mark.socketcan
def test_candump_sees_frames_python_can_sends(vcan0_bus: can.BusABC) -> None:
    probe = can.Message(arbitration_id=0x7FF, data=b"\x00", is_extended_id=False)
    proc = subprocess.Popen(["candump", "-L", "vcan0"], stdout=subprocess.PIPE)
    reader = _LineReader(proc)
    try:
        # candump is ready once it prints a probe: send one, wait briefly for it, repeat (bounded).
        deadline = time.monotonic() + STEP_TIMEOUT
        ready = False
        while not ready and time.monotonic() < deadline:
            vcan0_bus.send(probe)
            line = reader.readline(timeout=0.2)
            ready = line is not None and line.endswith(" vcan0 7FF#00")
        assert ready, f"candump printed no probe within {STEP_TIMEOUT}s: {reader.seen}"

        vcan0_bus.send(
            can.Message(arbitration_id=0x321, data=b"\xca\xfe\xf0\x0d", is_extended_id=False)
        )
        vcan0_bus.send(
            can.Message(arbitration_id=0x1ABCDE12, data=b"\x01\x02", is_extended_id=True)
        )
        wanted = [" vcan0 321#CAFEF00D", " vcan0 1ABCDE12#0102"]
        got: list[str] = []
        while len(got) < len(wanted):
            line = reader.readline(timeout=STEP_TIMEOUT)
            assert line is not None, f"candump stopped short of {wanted}: {reader.seen}"
            if not line.endswith(" vcan0 7FF#00"):  # late echoes of probes are fine
                got.append(line)
        assert [g[g.index(" vcan0 ") :] for g in got] == wanted
        assert all(g.startswith("(") for g in got), got  # -L: "(timestamp) iface id#data"
    finally:
        reader.close()
        proc.terminate()
        proc.wait(timeout=STEP_TIMEOUT)
        assert proc.stdout is not None
        proc.stdout.close()


@pytest.mark.socketcan
def test_kernel_filter_passes_only_the_subscribed_id(can_utils: None) -> None:
    bus = can.Bus(
        interface="socketcan",
        channel=can_channel("socketcan"),
        can_filters=[{"can_id": 0x200, "can_mask": 0x7FF, "extended": False}],
    )
    try:
        for frame in ("100#01", "200#02", "201#03", "200#04"):
            subprocess.run(["cansend", "vcan0", frame], check=True, timeout=STEP_TIMEOUT)
        first, second = _recv(bus), _recv(bus)
        assert [(m.arbitration_id, bytes(m.data)) for m in (first, second)] == [
            (0x200, b"\x02"),
            (0x200, b"\x04"),
        ]
    finally:
        bus.shutdown()


# -- on the host: boot UML ----------------------------------------------------------------------


def _fake_kernel(tmp_path: Path) -> dict[str, str]:
    """An environment whose "UML kernel" prints what Debian's UML 6.1 prints when it panics at
    boot on a host with a large XSAVE area, then 40 stack frames, and aborts."""
    kernel = tmp_path / "linux"
    kernel.write_text(
        "#!/bin/sh\n"
        '[ "$1" = --version ] && { echo 6.1.0-fake; exit 0; }\n'
        "echo 'Linux version 6.1.0-fake'\n"
        "echo 'userspace - ptrace set fp regs failed, errno = 14'\n"
        "echo 'Kernel panic - not syncing: Attempted to kill init! exitcode=0x00000009'\n"
        "i=0; while [ $i -lt 40 ]; do echo \" [<6003${i}d2>] ? os_dump_core+0x0/0x40\"; "
        "i=$((i+1)); done\n"
        "kill -ABRT $$\n"
    )
    kernel.chmod(0o755)
    for module in CAN_MODULES:
        (tmp_path / "kernel" / module).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "kernel" / module).write_bytes(b"")
    return dict(os.environ, CHCOS_UML_KERNEL=str(kernel), CHCOS_UML_MODULES=str(tmp_path))


def test_run_in_uml_reports_a_boot_panic_by_its_cause_first(tmp_path: Path) -> None:
    require(os.geteuid() == 0, "root (run-in-uml needs it; CI runs as root)")
    require(shutil.which("gcc"), "gcc (apt-get install gcc libc6-dev: builds the UML boot shim)")
    env = _fake_kernel(tmp_path)
    result = subprocess.run(["bash", str(RUN_IN_UML), "--timeout", "60", "--", "true"], env=env,
                            capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 125, result
    first = result.stderr.splitlines()[:2]
    assert first == [
        "run-in-uml: UML exited (134) without running the command: "
        "userspace - ptrace set fp regs failed, errno = 14",
        "run-in-uml:   Kernel panic - not syncing: Attempted to kill init! exitcode=0x00000009",
    ], result.stderr
    assert "Aborted" not in result.stderr  # no shell job notice ahead of the cause
    assert result.stderr.count("os_dump_core") <= 15  # only the log's tail, after the cause


def test_boot_problem_names_the_panic_first(tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """What a UML test fails with (under CI) when UML panics at boot: the cause, not frames."""
    require(UML_REASON is None, f"the UML set-up ({UML_REASON})")
    for name, value in _fake_kernel(tmp_path).items():
        monkeypatch.setenv(name, value)
    problem = uml_boot_problem.__wrapped__()
    assert problem is not None
    assert problem.startswith("User-Mode Linux does not boot or has no vcan0/vcan1 (status 125): "
                              "run-in-uml: UML exited (134) without running the command: "
                              "userspace - ptrace set fp regs failed, errno = 14"), problem
    assert "os_dump_core" not in problem


@pytest.mark.uml
def test_uml_boots_with_vcan0_and_vcan1() -> None:
    """The boot self-test: the other UML tests depend on it; its message is the cause."""
    require_uml()
    assert uml_boot_problem() is None


@pytest.mark.uml
@pytest.mark.slow
def test_run_in_uml_passes_environment_cwd_output_and_status(tmp_path: Path) -> None:
    require_uml()
    script = (
        'printf "probe=%s\\n" "$CHCOS_UML_PROBE"; printf "marker=%s\\n" "$' + GUEST_MARKER + '"; '
        'printf "cwd=%s\\n" "$(pwd -P)"; ip -o link show vcan0 | grep -o "<[^>]*>"; '
        'echo "to stderr" >&2; exit 7'
    )
    env = dict(os.environ, CHCOS_UML_PROBE="a b 'c' $d")
    result = run_in_uml(["sh", "-c", script], env=env, cwd=tmp_path, timeout=120)
    assert result.returncode == 7, result.stderr
    lines = result.stdout.splitlines()
    assert lines[:3] == ["probe=a b 'c' $d", "marker=1", f"cwd={tmp_path.resolve()}"]
    assert "UP" in lines[3].strip("<>").split(","), lines
    assert result.stderr.strip() == "to stderr"


@pytest.mark.uml
@pytest.mark.slow
def test_run_in_uml_kills_a_guest_that_overruns_its_timeout() -> None:
    require_uml()
    start = time.monotonic()
    result = run_in_uml(["sleep", "600"], timeout=8)
    elapsed = time.monotonic() - start
    assert result.returncode == 124, result.stderr
    assert "timed out after 8s" in result.stderr
    assert elapsed < 8 + 15, elapsed  # timeout, then at most the wrapper's kill-after grace


@pytest.mark.uml
@pytest.mark.slow
def test_run_in_uml_reports_a_guest_setup_failure(tmp_path: Path) -> None:
    require_uml()
    for module in CAN_MODULES:  # present, so the host check passes, but not loadable
        (tmp_path / "kernel" / module).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "kernel" / module).write_bytes(b"not an ELF module\n")
    env = dict(os.environ, CHCOS_UML_MODULES=str(tmp_path))
    result = run_in_uml(["echo", "must not run"], env=env, timeout=120)
    assert result.returncode == 125, result
    assert result.stdout == ""
    assert f"setup step failed: insmod {tmp_path}/kernel/net/can/can.ko" in result.stderr
    assert "insmod" in result.stderr.split("the guest log ends:", 1)[1]


GUEST_DESELECT = "vcan_tests/test_weldcell_socketcan.py::test_good_gap_over_socketcan"
"""Runs in its own UML guest (test_weldcell_socketcan.py), overlapping the session."""
GUEST_LEGS = {  # module -> what it covers; each must have passed tests inside the guest
    "test_uml_socketcan": "raw CAN, python-can against can-utils",
    "test_dev_can": "raw CAN driver (DBC) against the simulated CAN node",
    "test_fb_canopen": "CANopen driver against the simulated servo drive",
    "test_fuzz_bus": "CAN receive overrun: a cangen flood past the socket buffer, frames lost",
    "test_faults_can_flood": "raw CAN under a cangen flood: kernel filters, ignore_ids, "
                             "aggregated warnings, kernel receive stamps",
}


def start_in_background(config: pytest.Config) -> None:
    """Boot UML and run ``pytest -m socketcan`` there (once per session; nothing where UML
    cannot boot), overlapping the rest of the session like the welding job's guest."""
    runs = config.stash.setdefault(BACKGROUND, {})
    if "socketcan" in runs or uml_boot_problem() is not None:
        return
    workdir = Path(tempfile.mkdtemp(prefix="chcos-socketcan-uml-"))
    files = socketcan_test_files()   # only those: collecting all of vcan_tests in UML is slow
    argv = [sys.executable, "-m", "pytest", "-m", "socketcan", "-rs",
            f"--junitxml={workdir / 'socketcan.xml'}", "--deselect", GUEST_DESELECT, *files]
    runs["socketcan"] = (BackgroundUml.start(argv, workdir, timeout=900, cwd=REPO_ROOT),
                         workdir)


@pytest.mark.uml
@pytest.mark.slow
@pytest.mark.uml_background
def test_socketcan_suite_passes_inside_uml(
    record_property: Callable[[str, object], None], request: pytest.FixtureRequest
) -> None:
    require_uml()
    start_in_background(request.config)   # already running unless this test was selected late
    run, workdir = request.config.stash[BACKGROUND]["socketcan"]
    result = run.result()
    elapsed = time.monotonic() - run.started
    junit = workdir / "socketcan.xml"
    record_property("uml_round_trip_s", round(elapsed, 2))
    detail = f"status {result.returncode}\n{result.stdout[-6000:]}\n{result.stderr[-3000:]}"
    assert result.returncode == 0, detail
    suite = ET.parse(junit).getroot()
    suite = suite if suite.tag == "testsuite" else suite[0]
    outcomes: dict[str, str] = {}
    skip_messages: dict[str, str] = {}
    for case in suite.iter("testcase"):
        name = f"{case.get('classname')}::{case.get('name')}"
        kinds = [child for child in case if child.tag in ("failure", "error", "skipped")]
        outcomes[name] = kinds[0].tag if kinds else "passed"
        if kinds and kinds[0].tag == "skipped":
            skip_messages[name] = kinds[0].get("message", "")
    assert outcomes, f"pytest -m socketcan collected nothing inside UML\n{detail}"
    assert all(v in ("passed", "skipped") for v in outcomes.values()), outcomes
    mine = {k: v for k, v in outcomes.items() if k.startswith("vcan_tests.test_uml_socketcan::")}
    assert len(mine) == 3 and set(mine.values()) == {"passed"}, mine
    # Inside the guest nothing may skip (only opt-in runs, which are deselected above).
    assert not skip_messages, f"skipped inside UML: {skip_messages}"
    per_module: dict[str, int] = {}
    for name, outcome in outcomes.items():
        module = name.split("::")[0].rsplit(".", 1)[-1]
        per_module[module] = per_module.get(module, 0) + (outcome == "passed")
    for module, what in GUEST_LEGS.items():
        assert per_module.get(module, 0) > 0, f"no {what} test ({module}) passed in the guest"
    record_property("uml_socketcan_passed", len(outcomes))
    counts = ", ".join(f"{m} {n}" for m, n in sorted(per_module.items()))
    request.config.stash.setdefault(GUEST_RESULTS, []).append(
        f"{len(outcomes)} socketcan tests passed inside UML ({counts}; {elapsed:.0f} s from boot "
        f"to collection, overlapping the session)")
