"""Papercuts a new user met on the journey from vendor files to a running cell (issue 39).

Each test failed before its fix: ``chcos check --system`` on the scaffold's system file,
``chcos run --help | head -1``, ``chcos run -v``, ``read_any`` answering with a port index when
given names, ``chcos run`` on a system whose install script has a bad task name.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from chcos.cli import scaffold
from chcos.cli.main import main as cli_main
from chcos.helpers import free_port
from chcos.user.context import TaskContext
from vcan_tests.conftest import MakeSystem, memory_map

M = "vcan_tests.test_journey_papercuts"


def _chcos(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "chcos.cli.main", *args], capture_output=True,
                          text=True, timeout=120, cwd=cwd)


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    """A scaffolded cell project (``chcos new``) on a free loopback port."""
    scaffold.create(tmp_path / "cell", port=free_port())
    return tmp_path / "cell"


def test_check_system_on_the_scaffold_says_ok(cell: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    capsys.readouterr()
    assert cli_main(["check", "--system", str(cell / "system.toml")]) == 0
    out, err = capsys.readouterr()
    assert out.startswith("ok: system cell") and "2 devices" in out, out
    assert "Traceback" not in err


def test_check_system_checks_the_maps_it_names(cell: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    devices = cell / "devices.toml"
    devices.write_text(devices.read_text(encoding="utf-8").replace("[[device]]",
                                                                   "[[device]]\nbogus = 1", 1),
                       encoding="utf-8")
    capsys.readouterr()
    assert cli_main(["check", "--system", str(cell / "system.toml")]) == 1
    _out, err = capsys.readouterr()
    assert "devices.toml" in err and "bogus" in err, err


def test_check_help_shows_system() -> None:
    res = _chcos("check", "--help")
    assert res.returncode == 0 and "--system" in res.stdout


def test_help_into_a_closed_pipe_ends_quietly() -> None:
    shell = subprocess.run(f"{sys.executable} -m chcos.cli.main run --help | head -1",
                           shell=True, capture_output=True, text=True, timeout=120)
    assert shell.stdout.startswith("usage: chcos run")
    assert "Traceback" not in shell.stderr and "BrokenPipeError" not in shell.stderr, \
        shell.stderr


@pytest.mark.parametrize("where", ["after", "before"])
def test_run_takes_verbose(cell: Path, where: str) -> None:
    args = ["run", "-v", str(cell / "system.toml")] if where == "after" else \
        ["-v", "run", str(cell / "system.toml")]
    res = _chcos(*args, "--virtual", "--duration", "1")
    assert res.returncode == 0, res.stderr
    assert "INFO" in res.stderr and "healthy" in res.stdout


def test_run_with_a_bad_task_name_exits_2_naming_the_rule(cell: Path) -> None:
    (cell / "install.chcos").write_text("install -m0 sysfile\ninstall -m0i1 .. level\n",
                                        encoding="utf-8")
    res = _chcos("run", str(cell / "system.toml"), "--virtual", "--duration", "1")
    assert res.returncode == 2, res.stderr
    assert "Traceback" not in res.stderr
    assert "task name '..' breaks the rule" in res.stderr


# ---- read_any answers with what the caller named ----------------------------------------------
async def named_reader(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    while True:
        cmd["log"].append(await ctx.read_any(cmd["ports"]))


@pytest.mark.parametrize("ports", [["S1", "S2"], [1, 0], ["S2", 0]])
def test_read_any_returns_the_port_as_named(make_system: MakeSystem, ports: list[Any]) -> None:
    s = make_system(memory_map(["S1", "S2"]))
    s.execute(f"install -m0i2 --code={M}:named_reader R S1 S2")
    log: list[Any] = []
    s.invoke("R", {"log": log, "ports": ports})
    s.run_for(0.1)
    s.devtab.inject("S2", 2.0)
    s.run_for(0.1)
    s.devtab.inject("S1", 1.0)
    s.run_for(0.1)
    by_source = {"S1": 0, "S2": 1}
    expected = [next(p for p in ports if p in (src, by_source[src])) for src in ("S2", "S1")]
    assert [port for port, _value in log] == expected
    assert [value for _port, value in log] == [2.0, 1.0]


# ---- chcos sim --from: one line per device, only changes; virtual channels refused ------------
def test_sim_from_prints_one_line_per_device_and_only_changes(
        cell: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capsys.readouterr()
    assert cli_main(["sim", "--from", str(cell / "devices.toml"), "--value", "level=42",
                     "--duration", "2.5", "--every", "0.5"]) == 0
    out = capsys.readouterr().out.splitlines()
    shown = [ln for ln in out if ln.startswith("t=")]
    assert all(len(ln) < 100 for ln in out), out
    # level is constant and valve idle: each is shown once, however long the run
    assert [ln.split()[-2] for ln in shown] == ["level=42", "valve=0"], out


CAN_MAP = """\
[[bus]]
name = "cell"
kind = "can"
interface = "virtual"
channel = "cell"

[[device]]
name = "T1"
direction = "sensor"
bus = "cell"
address = { id = 0x100, start = 0, length = 16 }
"""


def test_sim_from_refuses_a_process_local_virtual_channel(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    devices = tmp_path / "can.toml"
    devices.write_text(CAN_MAP, encoding="utf-8")
    assert cli_main(["sim", "--from", str(devices), "--duration", "1"]) == 2
    err = capsys.readouterr().err
    assert "can.toml: bus[0] (cell)" in err and "inside one process" in err
    assert "udp_multicast" in err


def test_run_on_real_time_warns_of_a_virtual_channel(tmp_path: Path) -> None:
    (tmp_path / "can.toml").write_text(CAN_MAP, encoding="utf-8")
    (tmp_path / "system.toml").write_text('[system]\nname = "c"\ndevmaps = ["can.toml"]\n',
                                          encoding="utf-8")
    res = _chcos("run", str(tmp_path / "system.toml"), "--duration", "0.5")
    assert "warning: bus cell" in res.stdout and "inside this process" in res.stdout, res.stdout


def test_no_doc_tells_users_to_pip_install_chcos_from_pypi() -> None:
    """chcos is not on PyPI: every install line names a checkout, a path or a git URL."""
    root = Path(__file__).resolve().parent.parent
    for doc in sorted((root / "docs").glob("*.md")):
        text = doc.read_text(encoding="utf-8")
        assert "pip install chcos`" not in text and "pip install chcos\n" not in text, doc


def test_scaffold_installs_its_loop_with_a_restart_policy(cell: Path) -> None:
    install = (cell / "install.chcos").read_text(encoding="utf-8")
    assert "--standing --restart=on-recovery" in install
    assert "--restart=on-recovery" in (cell / "README.md").read_text(encoding="utf-8")


def test_scaffold_service_unit_runs_the_cell(cell: Path) -> None:
    """The unit's ExecStart, run as systemd would (in its WorkingDirectory; here on virtual
    time for a second), runs the cell healthy and writes the rotating log it names."""
    import configparser
    import os
    import shlex

    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.read(cell / "chcos-cell.service", encoding="utf-8")
    service = unit["Service"]
    assert service["Restart"] == "on-failure"
    assert Path(service["WorkingDirectory"]) == cell.resolve()
    argv = shlex.split(service["ExecStart"])
    assert argv[1:5] == ["-m", "chcos.cli.main", "run", "system.toml"]
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parent.parent))
    res = subprocess.run([*argv, "--virtual", "--duration", "1"], cwd=service["WorkingDirectory"],
                         capture_output=True, text=True, timeout=120, env=env)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "healthy" in (cell / "cell.log").read_text(encoding="utf-8")


def test_check_warns_of_udp_multicast_buses_sharing_a_port(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    one = CAN_MAP.replace('"virtual"', '"udp_multicast"').replace('channel = "cell"',
                                                                  'channel = "239.1.2.3"')
    two = one.replace('name = "cell"', 'name = "cell2"').replace('bus = "cell"',
                                                                 'bus = "cell2"') \
        .replace("239.1.2.3", "239.1.2.4").replace('name = "T1"', 'name = "T2"')
    (tmp_path / "a.toml").write_text(one, encoding="utf-8")
    (tmp_path / "b.toml").write_text(two, encoding="utf-8")
    capsys.readouterr()
    assert cli_main(["check", str(tmp_path / "a.toml"), str(tmp_path / "b.toml")]) == 0
    err = capsys.readouterr().err
    assert "b.toml: bus[0] (cell2): udp_multicast port 43113 is also bus cell's" in err, err
    (tmp_path / "b.toml").write_text(two.replace('channel = "239.1.2.4"',
                                                 'channel = "239.1.2.4"\nport = 43120'),
                                     encoding="utf-8")
    assert cli_main(["check", str(tmp_path / "a.toml"), str(tmp_path / "b.toml")]) == 0
    assert "udp_multicast port" not in capsys.readouterr().err
