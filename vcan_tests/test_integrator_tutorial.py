"""The tutorial docs/first-cell.md, run verbatim: from an empty directory to a cell running against
an independent Modbus TCP server (pyModbusTCP's) on loopback, stopped with SIGINT, the safe value
in the server's register."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

from pyModbusTCP.client import ModbusClient  # dev extra: the independent peer

from vcan_tests.support_docs import doc_commands

ROOT = Path(__file__).resolve().parent.parent
TUTORIAL = ROOT / "docs" / "first-cell.md"
PLC_PORT = 5020


def tutorial_commands() -> list[str]:
    """Every command of the tutorial's ``sh`` blocks, in order (:func:`doc_commands`)."""
    return doc_commands(TUTORIAL)


def _valve_register() -> int | None:
    regs = ModbusClient(host="127.0.0.1", port=PLC_PORT, timeout=2.0).read_holding_registers(1, 1)
    return None if not regs else int(regs[0])


def _wait(pred: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return
        threading.Event().wait(0.1)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


class _Reader:
    """Collects a process's output on a thread, so it never blocks on a full pipe."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.text = ""
        self._lock = threading.Lock()
        self._t = threading.Thread(target=self._run, args=(proc,), daemon=True)
        self._t.start()

    def _run(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            with self._lock:
                self.text += line

    def get(self) -> str:
        with self._lock:
            return self.text


def test_tutorial_commands_verbatim(tmp_path: Path) -> None:
    commands = tutorial_commands()
    assert "chcos new mycell" in commands and "chcos run system.toml --outputs on" in commands
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env.pop("PYTEST_ADDOPTS", None)
    cwd = tmp_path
    background: list[subprocess.Popen[str]] = []
    outputs: dict[str, str] = {}
    try:
        for cmd in commands:
            if cmd.startswith("cd "):
                cwd = cwd / cmd[3:].strip()
                continue
            if cmd.endswith("&"):
                proc = subprocess.Popen(["bash", "-c", f"exec {cmd[:-1]}"], cwd=cwd, env=env,
                                        stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                        text=True)
                background.append(proc)
                reader = _Reader(proc)
                _wait(lambda r=reader: "PLC: level" in r.get(), 30, "the PLC stand-in to run")
                assert _valve_register() == 0
                continue
            if cmd == "chcos run system.toml --outputs on":  # interactive: until Ctrl-C
                proc = subprocess.Popen(["bash", "-c", f"exec {cmd}"], cwd=cwd, env=env,
                                        stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                        text=True)
                reader = _Reader(proc)
                try:
                    # the value flows: the task opens the valve in the independent server
                    _wait(lambda: (_valve_register() or 0) > 0, 30, "the valve to open")
                    _wait(lambda r=reader: "t=    2.0 s" in r.get(), 30, "progress lines")
                    proc.send_signal(signal.SIGINT)
                    rc = proc.wait(timeout=30)
                finally:
                    if proc.poll() is None:
                        proc.kill()
                out = reader.get()
                assert rc == 0, out
                assert re.search(r"sensor   level +\d+(\.\d+)? cm", out), out
                assert "safe value valve = 0 %: written" in out and "healthy" in out, out
                outputs[cmd] = out
                continue
            res = subprocess.run(["bash", "-c", cmd], cwd=cwd, env=env, text=True,
                                 capture_output=True, timeout=180)
            assert res.returncode == 0, f"{cmd}\n{res.stdout}\n{res.stderr}"
            outputs[cmd] = res.stdout
            if cmd.startswith("chcos run") and "--outputs off" in cmd:
                assert "actuator writes logged, not sent" in res.stdout, res.stdout
                assert _valve_register() == 0  # nothing was sent
        assert "3 passed" in outputs["pytest -q"]
        last = commands[-1]
        assert last.startswith("python -c") and "valve register: [0]" in outputs[last]
        assert _valve_register() == 0  # the safe value is in the server's register
    finally:
        for proc in background:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
