"""The tutorial docs/from-vendor-files.md, run verbatim (issue 39): three vendor files (an EDS, a
DBC, a Modbus register table) imported, checked, run on virtual time, then simulated and run on
real time in two processes over udp_multicast and Modbus TCP — every command inside a network
namespace of the test's own whose only interface is loopback. The tutorial's pytest example runs
too."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from vcan_tests.support_docs import doc_commands
from vcan_tests.support_import import needs_can_messages, needs_modbus_sunspec
from vcan_tests.support_netns import loopback_only

ROOT = Path(__file__).resolve().parent.parent
TUTORIAL = ROOT / "docs" / "from-vendor-files.md"


def commands(kind: str = "sh") -> list[str]:
    """Every command of the tutorial's ``kind`` blocks, in order (:func:`doc_commands`)."""
    return doc_commands(TUTORIAL, kind)


@pytest.fixture
def netns() -> Iterator[str]:
    with loopback_only("c39t") as name:
        yield name


@needs_can_messages
@needs_modbus_sunspec
def test_from_vendor_files_verbatim(tmp_path: Path, netns: str) -> None:
    for f in ("drive.eds", "gripper.dbc", "meter.csv", "vehicle.dbc", "inverter.json"):
        shutil.copy(ROOT / "docs" / "vendor" / f, tmp_path / f)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env.pop("PYTEST_ADDOPTS", None)
    cmds = commands()
    assert any(c.startswith("chcos sim --from") and c.endswith("&") for c in cmds)
    # the shell's jobs: %1, %2... in the order they were started, with what each printed
    jobs: list[tuple[subprocess.Popen[str], list[str]]] = []
    outputs: dict[str, subprocess.CompletedProcess[str]] = {}
    finished: dict[str, str] = {}   # a background job's command -> all it printed

    def shell(cmd: str) -> list[str]:
        return ["ip", "netns", "exec", netns, "bash", "-c", cmd]

    try:
        for cmd in cmds:
            if cmd.endswith("&"):
                proc = subprocess.Popen(shell(f"exec {cmd[:-1]}"), cwd=tmp_path, env=env,
                                        stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                        text=True)
                out: list[str] = []
                jobs.append((proc, out))
                ready = threading.Event()

                def read(p: subprocess.Popen[str] = proc, out: list[str] = out,
                         ready: threading.Event = ready) -> None:
                    assert p.stdout is not None
                    for line in p.stdout:
                        out.append(line)
                        if line.startswith("t="):   # the simulator and the run are up
                            ready.set()
                    ready.set()

                threading.Thread(target=read, daemon=True).start()
                assert ready.wait(120) and proc.poll() is None, "".join(out)
                continue
            job = re.fullmatch(r"(wait|kill) %(\d)", cmd)
            if job:
                proc, out = jobs[int(job.group(2)) - 1]
                if job.group(1) == "kill":
                    proc.terminate()
                assert proc.wait(timeout=300) == 0, "".join(out)
                finished[proc.args[-1]] = "".join(out)
                continue
            res = subprocess.run(shell(cmd), cwd=tmp_path, env=env, text=True,
                                 capture_output=True, timeout=300)
            assert res.returncode == 0, f"{cmd}\n{res.stdout}\n{res.stderr}"
            outputs[cmd] = res
    finally:
        for proc, _ in jobs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    imported = next(r for c, r in outputs.items() if c.startswith("chcos import dbc gripper"))
    assert "GripCommand" not in imported.stderr           # the algorithm given: no guess
    gripper = (tmp_path / "gripper.toml").read_text(encoding="utf-8")
    assert 'checksum = { signal = "CRC8", algorithm = "crc8-sae-j1850" }' in gripper
    vehicle = next(r for c, r in outputs.items() if c.startswith("chcos import dbc vehicle"))
    assert "STEERING_CONTROL: checksum CHECKSUM: algorithm sum is a guess" in vehicle.stderr
    assert "no cycle time (GenMsgCycleTime) for DOORS_STATUS" in vehicle.stderr
    more = next(r.stdout for c, r in outputs.items() if c.startswith("chcos run more.toml"))
    assert "healthy" in more.split("summary")[-1] and "wheel_speed_fl" in more, more
    checked = next(r for c, r in outputs.items() if c.startswith("chcos check drive.toml"))
    assert checked.stdout.startswith("ok: 3 buses, 19 devices"), checked.stdout
    virtual = next(r.stdout for c, r in outputs.items() if c.startswith("chcos run"))
    real = next(out for c, out in finished.items() if "chcos run" in c)
    for out in (virtual, real):   # virtual, then real time in a second process
        summary = out.split("summary")[-1]
        assert "healthy" in summary and "UNHEALTHY" not in summary, out
        assert "sensor   axis.state       last OPERATION_ENABLED" in summary, summary
        assert re.search(r"actuator setpoint +last [\d.]+ mm, [1-9]\d* commands", summary), summary
    # the simulated gripper (the other process) received the set-points the task wrote
    sim = next(out for c, out in finished.items() if "chcos sim" in c)
    received = [float(m) for m in re.findall(r"actuator setpoint=([\d.]+) mm", sim)]
    assert any(v > 0 for v in received), sim
    # the monitor (a third process, listen-only) saw the drive enabled and nothing amiss
    monitor = next(r.stdout for c, r in outputs.items() if c.startswith("chcos monitor"))
    assert re.search(r"actuator axis +0x00[0-9A-F]{2} enable operation", monitor), monitor
    assert monitor.rstrip().endswith("mismatches: none"), monitor
    # the live view's history of the drive's position, as curl fetched it
    history = next(r.stdout for c, r in outputs.items() if c.startswith("curl"))
    assert re.search(r"^[\d.]+,axis\.position,[\d.-]+$", history, flags=re.M), history
    # the log file the run wrote
    log = (tmp_path / "cell.log").read_text(encoding="utf-8")
    assert "healthy" in log, log
    # the tutorial's pytest examples, in the same directory
    (tmp_path / "test_cell.py").write_text("\n\n".join(commands("python")), encoding="utf-8")
    res = subprocess.run(shell(f"{sys.executable} -m pytest -q -p no:cacheprovider "
                               "test_cell.py"), cwd=tmp_path, env=env, text=True,
                         capture_output=True, timeout=300)
    assert res.returncode == 0 and "2 passed" in res.stdout, res.stdout + res.stderr
