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
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from vcan_tests.conftest import require
from vcan_tests.support_netns import missing

ROOT = Path(__file__).resolve().parent.parent
TUTORIAL = ROOT / "docs" / "from-vendor-files.md"


def commands(kind: str = "sh") -> list[str]:
    """Every command of the tutorial's ``kind`` blocks, in order; a here-document is one
    command (``python`` blocks: each block is one)."""
    blocks = re.findall(rf"^```{kind}\n(.*?)^```", TUTORIAL.read_text(encoding="utf-8"),
                        flags=re.S | re.M)
    if kind != "sh":
        return blocks
    out: list[str] = []
    for block in blocks:
        lines = iter(block.splitlines())
        for line in lines:
            if not line.strip():
                continue
            m = re.search(r"<<'(\w+)'", line)
            if m:
                body = [line]
                for more in lines:
                    body.append(more)
                    if more == m.group(1):
                        break
                out.append("\n".join(body))
            else:
                out.append(line)
    return out


@pytest.fixture
def netns() -> Iterator[str]:
    require(not missing(), missing() or "network namespaces")
    name = f"c39t{os.getpid()}x{uuid.uuid4().hex[:6]}"
    subprocess.run(["ip", "netns", "add", name], check=True, timeout=30)
    try:
        for args in (["link", "set", "lo", "up"], ["route", "add", "224.0.0.0/4", "dev", "lo"]):
            subprocess.run(["ip", "-n", name, *args], check=True, timeout=30)
        yield name
    finally:
        subprocess.run(["ip", "netns", "del", name], timeout=30)


def test_from_vendor_files_verbatim(tmp_path: Path, netns: str) -> None:
    for f in ("drive.eds", "gripper.dbc", "meter.csv"):
        shutil.copy(ROOT / "docs" / "vendor" / f, tmp_path / f)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env.pop("PYTEST_ADDOPTS", None)
    cmds = commands()
    assert any(c.startswith("chcos sim --from") and c.endswith("&") for c in cmds)
    background: list[subprocess.Popen[str]] = []
    bg_out: list[str] = []
    outputs: dict[str, subprocess.CompletedProcess[str]] = {}

    def shell(cmd: str) -> list[str]:
        return ["ip", "netns", "exec", netns, "bash", "-c", cmd]

    try:
        for cmd in cmds:
            if cmd.endswith("&"):
                proc = subprocess.Popen(shell(f"exec {cmd[:-1]}"), cwd=tmp_path, env=env,
                                        stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                        text=True)
                background.append(proc)
                ready = threading.Event()

                def read(p: subprocess.Popen[str] = proc, ready: threading.Event = ready) -> None:
                    assert p.stdout is not None
                    for line in p.stdout:
                        bg_out.append(line)
                        if line.startswith("t="):
                            ready.set()

                threading.Thread(target=read, daemon=True).start()
                assert ready.wait(60), "".join(bg_out)
                continue
            if cmd == "kill %1":
                for p in background:
                    p.terminate()
                    assert p.wait(timeout=30) == 0, "".join(bg_out)
                continue
            res = subprocess.run(shell(cmd), cwd=tmp_path, env=env, text=True,
                                 capture_output=True, timeout=300)
            assert res.returncode == 0, f"{cmd}\n{res.stdout}\n{res.stderr}"
            outputs[cmd] = res
    finally:
        for p in background:
            if p.poll() is None:
                p.kill()
                p.wait()
    imported = next(r for c, r in outputs.items() if c.startswith("chcos import dbc"))
    assert "RollingCounter (rolling counter), CRC8 (checksum), left out" in imported.stderr
    checked = next(r for c, r in outputs.items() if c.startswith("chcos check drive.toml"))
    assert checked.stdout.startswith("ok: 3 buses, 19 devices"), checked.stdout
    runs = [r.stdout for c, r in outputs.items() if c.startswith("chcos run")]
    assert len(runs) == 2
    for out in runs:   # virtual, then real time in a second process
        summary = out.split("summary")[-1]
        assert "healthy" in summary and "UNHEALTHY" not in summary, out
        assert "sensor   axis.state       last OPERATION_ENABLED" in summary, summary
        assert re.search(r"actuator setpoint +last [\d.]+ mm, [1-9]\d* commands", summary), summary
    # the simulated gripper (the other process) received the set-points the task wrote
    received = [float(m) for m in re.findall(r"actuator setpoint=([\d.]+) mm", "".join(bg_out))]
    assert any(v > 0 for v in received), "".join(bg_out)
    # the tutorial's pytest example, in the same directory
    (tmp_path / "test_vendor.py").write_text(commands("python")[0], encoding="utf-8")
    res = subprocess.run(shell(f"{sys.executable} -m pytest -q -p no:cacheprovider "
                               "test_vendor.py"), cwd=tmp_path, env=env, text=True,
                         capture_output=True, timeout=300)
    assert res.returncode == 0 and "1 passed" in res.stdout, res.stdout + res.stderr
