"""``chcos run SYSTEM``: a user's system file run in one process, on virtual time against simulated
slaves from its maps and on real time against an independent Modbus TCP server (pyModbusTCP);
``--outputs off``; SIGTERM; exit status; the welding cell still behind ``chcos run``."""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from pyModbusTCP.server import DataHandler, ModbusServer

from chcos.cli import cellrun
from chcos.cli import main as cli
from chcos.errors import ConfigError
from chcos.helpers import free_port
from chcos.satellites import sysfile

ROOT = Path(__file__).resolve().parent.parent
FIG65 = ROOT / "chcos" / "apps" / "fig65"


class CountingHandler(DataHandler):  # type: ignore[misc]
    """pyModbusTCP's data handler, counting the writes it is asked for."""

    def __init__(self) -> None:
        super().__init__()
        self.writes: list[tuple[int, list[int]]] = []

    def write_h_regs(self, address: int, words_l: list[int], srv_info: Any) -> Any:
        self.writes.append((address, list(words_l)))
        return super().write_h_regs(address, words_l, srv_info)

    def write_coils(self, address: int, bits_l: list[bool], srv_info: Any) -> Any:
        self.writes.append((address, [int(b) for b in bits_l]))
        return super().write_coils(address, bits_l, srv_info)


@pytest.fixture
def plc() -> Iterator[tuple[ModbusServer, CountingHandler]]:
    handler = CountingHandler()
    server = ModbusServer(host="127.0.0.1", port=free_port(), no_block=True, data_hdl=handler)
    server.start()
    try:
        yield server, handler
    finally:
        server.stop()


def _wait(pred: Callable[[], bool], timeout: float, what: str) -> None:
    done = threading.Event()
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        done.wait(0.05)


def _modbus_cell(tmp_path: Path, port: int, *, safe: float = 5.0,
                 task: str = "ctx.write('valve', round(level))") -> Path:
    (tmp_path / "tasks").mkdir()
    (tmp_path / "tasks" / "follow.py").write_text(
        "async def main(ctx, command):\n"
        "    while True:\n"
        "        level = await ctx.read('level')\n"
        f"        {task}\n", encoding="utf-8")
    (tmp_path / "devices.toml").write_text(f"""
[[bus]]
name = "plc"
kind = "modbus-tcp"
host = "127.0.0.1"
port = {port}
poll_period = 0.05

[[device]]
name = "level"
direction = "sensor"
machine = 0
bus = "plc"
address = {{ table = "input", address = 0 }}
units = "cm"
stale_after = 2.0

[[device]]
name = "valve"
direction = "actuator"
machine = 0
bus = "plc"
address = {{ table = "holding", address = 1 }}
limits = [0.0, 100.0]
safe_value = {safe}
units = "%"
""", encoding="utf-8")
    (tmp_path / "install.chcos").write_text(
        "install -m0 sysfile\ninstall -m0i1o1 follow level valve\ninvoke follow\n",
        encoding="utf-8")
    system = tmp_path / "system.toml"
    system.write_text('[system]\nname = "cell"\ndevmaps = ["devices.toml"]\n'
                      'task_path = ["tasks"]\ninstall = "install.chcos"\n', encoding="utf-8")
    return system


def test_system_file_install_key_and_no_satellites(tmp_path: Path) -> None:
    system = _modbus_cell(tmp_path, 5020)
    sf = sysfile.load(system)
    assert sf.install == ((tmp_path / "install.chcos").resolve(),)
    assert sf.satellites == {}
    system.write_text('[system]\nname = "cell"\ninstall = 3\n', encoding="utf-8")
    with pytest.raises(ConfigError, match=r"system.toml: system.install: expected the path"):
        sysfile.load(system)


def test_fig65_as_a_system_file_on_virtual_time(tmp_path: Path) -> None:
    (tmp_path / "testfile").write_bytes((FIG65 / "testfile").read_bytes())
    script = tmp_path / "install.chcos"
    script.write_text((FIG65 / "install.chcos").read_text(encoding="utf-8") + "invoke C1\n",
                      encoding="utf-8")
    system = tmp_path / "system.toml"
    system.write_text(f'[system]\nname = "fig65"\n'
                      f'devmaps = ["{ROOT}/chcos/apps/fig65/fig65.toml"]\n'
                      f'task_path = ["{FIG65}"]\ninstall = "install.chcos"\n', encoding="utf-8")
    out = io.StringIO()
    result = cellrun.run(system, virtual=True, duration=3.0, out=out, workdir=tmp_path / "w")
    text = out.getvalue()
    assert result.healthy, text
    assert result.seconds == pytest.approx(3.0)
    assert "t=    1.0 s" in text and "t=    3.0 s" in text  # times since the start
    for name in ("S1", "S2", "S3", "M1", "M2", "A1", "C1"):
        assert f" {name} " in text
    steps = {t["name"]: t["steps"] for t in result.snapshot["tasks"]}
    assert steps["A1"] > 0 and steps["C1"] > 0
    assert "safe value M1 = 0 %: written" in text and "safe value M2 = 0 %: written" in text
    assert (tmp_path / "w" / "sysfile.map").exists()


def test_virtual_run_against_simulated_modbus_slave(tmp_path: Path) -> None:
    system = _modbus_cell(tmp_path, 5020)  # the port is replaced by the simulated slave's
    with cellrun.open_cell(system, virtual=True, workdir=tmp_path / "w") as cell:
        assert cell.slaves is not None
        assert cell.slaves.get("valve") == 5  # an idle output holds its safe value
        cell.slaves.set("level", 42)
        cell.run_for(0.5)
        assert cell.device("level").value == 42
        assert cell.slaves.get("valve") == 42
    assert cell.slaves.get("valve") == 5  # shut down: the safe value reached the slave


def test_outputs_off_sends_nothing_to_an_independent_server(
        tmp_path: Path, plc: tuple[ModbusServer, CountingHandler]) -> None:
    server, handler = plc
    server.data_bank.set_input_registers(0, [33])
    system = _modbus_cell(tmp_path, server.port)
    out = io.StringIO()
    stop = threading.Event()
    result = cellrun.run(system, outputs=False, duration=1.0, out=out, stop=stop,
                         workdir=tmp_path / "w")
    text = out.getvalue()
    assert handler.writes == [], text  # the peer saw no write at all, not even the safe value
    assert result.healthy, text
    assert "outputs off (logged, not sent)" in text
    assert "safe value valve = 5 %: written (logged, not sent: outputs off)" in text
    n = int(text.split("actuator writes logged, not sent: ")[1].split()[0])
    assert n >= 2  # the task's writes and the safe value, logged
    # outputs on: the same run drives the valve, and ends with the safe value on the wire
    result = cellrun.run(system, duration=1.0, out=io.StringIO(), workdir=tmp_path / "w")
    assert result.healthy
    assert (1, [33]) in handler.writes
    assert handler.writes[-1] == (1, [5])
    assert server.data_bank.get_holding_registers(1) == [5]


def test_sigterm_stops_a_real_time_run_with_safe_values(
        tmp_path: Path, plc: tuple[ModbusServer, CountingHandler]) -> None:
    server, handler = plc
    server.data_bank.set_input_registers(0, [61])
    system = _modbus_cell(tmp_path, server.port)
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    proc = subprocess.Popen([sys.executable, "-m", "chcos.cli.main", "run", str(system),
                             "--outputs", "on"],
                            cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        _wait(lambda: server.data_bank.get_holding_registers(1) == [61], 30, "the task's write")
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, out
    assert server.data_bank.get_holding_registers(1) == [5], out
    assert handler.writes[-1] == (1, [5])
    assert "healthy" in out and "UNHEALTHY" not in out


def test_exit_status_says_whether_the_run_was_healthy(tmp_path: Path) -> None:
    system = _modbus_cell(tmp_path, 5020, task="raise RuntimeError('valve stuck')")
    assert cli.main(["run", str(system), "--virtual", "--duration", "1"]) == 1
    out = io.StringIO()
    result = cellrun.run(system, virtual=True, duration=1.0, out=out)
    assert not result.healthy
    assert "UNHEALTHY" in out.getvalue() and "valve stuck" in out.getvalue()
    bad = tmp_path / "bad.toml"
    bad.write_text('[system]\nname = "x"\ndevmap = []\n', encoding="utf-8")
    assert cli.main(["run", str(bad), "--virtual", "--duration", "1"]) == 2


def test_bad_system_file_names_file_and_key(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[system]\nname = "x"\ndevmap = []\n', encoding="utf-8")
    assert cli.main(["run", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.toml: system.devmap: unknown key" in err


def test_welding_cell_still_behind_chcos_run(tmp_path: Path) -> None:
    for args in (["run", "weld", "--binding", "direct", "--duration", "3"],
                 ["run", "--binding", "direct", "--duration", "2"]):
        res = subprocess.run([sys.executable, "-m", "chcos.cli.main", *args], cwd=tmp_path,
                             capture_output=True, text=True, timeout=300)
        assert res.returncode in (0, 1), res.stderr  # 1: the duration limit came first
        assert "welding cell on the direct binding" in res.stdout and "summary" in res.stdout


def test_the_welding_cell_is_a_system_file(tmp_path: Path) -> None:
    out = io.StringIO()
    result = cellrun.run(ROOT / "chcos" / "apps" / "weld" / "system.toml", virtual=True,
                         duration=15.0, out=out, workdir=tmp_path)
    text = out.getvalue()
    assert result.healthy, text
    steps = {t["name"]: t["steps"] for t in result.snapshot["tasks"]}
    assert len(steps) == 19 and steps["E2"] > 0 and steps["D1"] > 0  # inspecting the gap
    for device in ("drives_enable", "volts_set", "wire_set", "gas_valve"):
        assert f"safe value {device} = 0" in text
