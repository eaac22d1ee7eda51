"""The ``chcos`` command as a user meets it: help texts written for users (no module docstrings,
no internals), every command described, warnings shown by default, consistent options."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from chcos.cli import main as cli
from chcos.helpers import free_port

COMMANDS = ["run", "new", "import", "monitor", "check", "sim", "shell", "satellite", "host",
            "map", "view"]


def _help(*args: str) -> str:
    res = subprocess.run([sys.executable, "-m", "chcos.cli.main", *args, "--help"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    return res.stdout


def _no_internals(text: str, where: str) -> None:
    assert "``" not in text, f"{where}: reST markup in help"
    assert "handed to" not in text and ":main" not in text, f"{where}: internals in help"
    assert not re.search(r"^\w+ - ", text, flags=re.M), f"{where}: a module docstring leaks"


def test_top_level_help_lists_every_command() -> None:
    text = _help()
    _no_internals(text, "chcos --help")
    for cmd in COMMANDS:
        assert re.search(rf"^  chcos {cmd}\b", text, flags=re.M), cmd


@pytest.mark.parametrize("cmd", [*COMMANDS, "import eds", "import dbc", "import modbus",
                                 "sim can", "sim canopen", "run weld"])
def test_every_command_has_a_description_for_users(cmd: str) -> None:
    text = _help(*cmd.split())
    _no_internals(text, f"chcos {cmd} --help")
    usage, _, rest = text.partition("\n\n")
    assert usage.startswith("usage: chcos")
    first = rest.strip().splitlines()[0]
    assert not first.startswith(("positional arguments", "options")), \
        f"chcos {cmd} --help has no description"


def test_run_help_shows_all_three_forms() -> None:
    text = _help("run")
    assert "SYSTEM" in text and "--outputs" in text and "--virtual" in text
    assert "--binding" in text and "--scenario" in text
    assert "--example fig65" in text


def test_output_location_is_workdir_everywhere() -> None:
    for cmd in (["run"], ["run", "weld"], ["shell"]):
        assert "--workdir" in _help(*cmd), cmd


def test_shell_workdir_holds_the_map(tmp_path: Path) -> None:
    script = tmp_path / "s.chcos"
    script.write_text("install -m0 sysfile\n", encoding="utf-8")
    root = Path(__file__).resolve().parent.parent
    assert cli.main(["shell", str(root / "chcos" / "apps" / "fig65" / "fig65.toml"), "--virtual",
                     "--script", str(script), "--workdir", str(tmp_path / "w")]) == 0
    assert (tmp_path / "w" / "sysfile.map").exists()


def test_warnings_are_shown_by_default(tmp_path: Path) -> None:
    port = free_port()
    (tmp_path / "d.toml").write_text(f"""
[[bus]]
name = "plc"
kind = "modbus-tcp"
host = "127.0.0.1"
port = {port}
timeout = 0.2

[[device]]
name = "level"
direction = "sensor"
bus = "plc"
address = {{ table = "input", address = 0 }}
""", encoding="utf-8")
    (tmp_path / "system.toml").write_text('[system]\nname = "w"\ndevmaps = ["d.toml"]\n',
                                          encoding="utf-8")
    res = subprocess.run([sys.executable, "-m", "chcos.cli.main", "run", "system.toml",
                          "--duration", "1"], cwd=tmp_path, capture_output=True, text=True,
                         timeout=60, env=dict(os.environ))
    assert res.returncode == 1, res.stdout  # unhealthy: the sensor never answered
    # chcos' warnings are shown (the Modbus transport is chcos' own: no library log between)
    assert f"cannot connect to 127.0.0.1:{port}" in res.stderr, res.stderr
    assert "WARNING chcos.devices.devtab.faults: device level failed" in res.stderr, res.stderr
    assert "sensor level never delivered a value" in res.stdout or "level is failed" in res.stdout


def test_the_readme_satellite_example_has_its_system_file() -> None:
    from chcos.satellites import sysfile

    root = Path(__file__).resolve().parent.parent
    sf = sysfile.load(root / "chcos" / "apps" / "fig65" / "system.toml")
    assert sorted(sf.satellites) == [0, 1, 2]
    assert [p.name for p in sf.install] == ["install.chcos"] and sf.install[0].exists()
    assert all(p.exists() for p in sf.devmaps)
    readme = (root / "README.md").read_text(encoding="utf-8")
    assert "cd chcos/apps/fig65" in readme   # the folder the assertions above read


def test_shell_run_on_real_time_and_times_since_start(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = Path(__file__).resolve().parent.parent
    script = tmp_path / "s.chcos"
    script.write_text("install -m0 sysfile\nrun 0.5\nmap\n", encoding="utf-8")
    assert cli.main(["shell", str(root / "chcos" / "apps" / "fig65" / "fig65.toml"),
                     "--script", str(script),
                     "--workdir", str(tmp_path / "w")]) == 0
    out = capsys.readouterr().out
    m = re.search(r"time (\d+\.\d+) s", out)
    assert m is not None and 0.5 <= float(m.group(1)) < 30, out  # since start, not uptime
    assert re.search(r"S1 +m0 sensor +OK +value \d", out), out  # the kernel ran meanwhile
    script.write_text("run soon\n", encoding="utf-8")
    assert cli.main(["shell", "--script", str(script), "--workdir", str(tmp_path / "w")]) == 1
    assert "expected 'run SECONDS'" in capsys.readouterr().err
