"""Simulated devices driven like the vendor's (issue 39): ``chcos run --virtual --value`` scripts,
a user's plant model (a Python callable per step) on ``chcos run --virtual --plant`` and in the
pytest plugin, on the scaffold's tank cell (a Modbus PLC simulated from its device map)."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import pytest

from chcos.apps.sim.from_map import SimSlaves
from chcos.cli import cellrun, scaffold
from chcos.cli.cellsystem import open_cell
from chcos.cli.main import main as cli_main
from chcos.errors import ConfigError
from chcos.helpers import free_port

PLANT = '''\
"""A tank: the valve's opening fills it, a constant outflow drains it."""


def tank(t, slaves):
    level = slaves.get("level") or 0.0
    opening = slaves.get("valve") or 0.0
    slaves.set("level", max(0.0, min(200.0, level + (opening * 0.5 - 10.0) * 0.01)))
'''


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    scaffold.create(tmp_path / "cell", port=free_port())
    (tmp_path / "cell" / "plant.py").write_text(PLANT, encoding="utf-8")
    return tmp_path / "cell"


def test_run_virtual_takes_value_scripts(cell: Path) -> None:
    out = io.StringIO()
    result = cellrun.run(cell / "system.toml", virtual=True, duration=2.0, out=out,
                         values=["level=100"])
    assert result.healthy, out.getvalue()
    devs = {d["name"]: d for d in result.snapshot["devices"]}
    assert devs["level"]["value"] == pytest.approx(100.0)
    assert devs["valve"]["commands"] > 1   # 40 % while it ran (2 % per cm below 120)


def test_run_virtual_value_on_the_command_line(cell: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["run", str(cell / "system.toml"), "--virtual", "--duration", "1.5",
                     "--value", "level=ramp(100, 110, 10)"]) == 0
    out = capsys.readouterr().out
    assert "healthy" in out and "UNHEALTHY" not in out
    assert cli_main(["run", str(cell / "system.toml"), "--virtual", "--duration", "1",
                     "--value", "valve=3"]) == 2
    assert "'valve' is not a sensor" in capsys.readouterr().err
    assert cli_main(["run", str(cell / "system.toml"), "--duration", "1",
                     "--value", "level=3"]) == 2
    assert "need virtual time" in capsys.readouterr().err


def test_a_plant_model_closes_the_loop(cell: Path) -> None:
    """The task opens the valve below its set-point (120 cm), the plant fills the tank with
    the valve's opening: the level climbs from 0 and settles inside the proportional band."""
    with open_cell(cell / "system.toml", virtual=True, plants=["plant.py:tank"],
                   base_dir=cell) as c:
        c.run_for(60.0)
        level = c.device("level").value
    # 20 % opening balances the 10 cm/s outflow at 110 cm; but the level register counts
    # 0.1 cm and from 105 cm up the plant's 10 ms step adds half a count or less, which the
    # register rounds away: the level settles between 105 cm and the set-point
    assert 105.0 <= level < 120.0


def test_run_virtual_plant_on_the_command_line(cell: Path, monkeypatch: pytest.MonkeyPatch,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(cell)
    assert cli_main(["run", "system.toml", "--virtual", "--duration", "60",
                     "--plant", "plant.py:tank"]) == 0
    summary = capsys.readouterr().out.split("summary")[-1]
    level = float(summary.split("sensor   level")[1].split("last")[1].split()[0])
    assert 105.0 <= level < 120.0, summary   # see test_a_plant_model_closes_the_loop


def test_a_bad_plant_is_refused_naming_it(cell: Path) -> None:
    for ref, what in [("plant.py:nope", "has no function nope"), ("nofile.py:f", "no file"),
                      ("plant", "expected FILE.py:function")]:
        with pytest.raises(ConfigError, match=what), \
                open_cell(cell / "system.toml", virtual=True, plants=[ref], base_dir=cell):
            pass


def test_pytest_plugin_takes_values_and_a_plant(cell: Path, chcos_cell: Any) -> None:
    seen: list[float] = []

    def tank(t: float, slaves: SimSlaves) -> None:
        seen.append(t)
        opening = slaves.get("valve") or 0.0
        level = slaves.get("level") or 0.0
        slaves.set("level", max(0.0, level + (opening * 0.5 - 10.0) * 0.01))

    scripted = chcos_cell(cell / "system.toml", values={"level": "square(130, 90, 2)"})
    scripted.run_for(0.5)
    assert scripted.value("level") == pytest.approx(130.0)
    assert scripted.peer("valve") == 0          # above the set-point: closed
    scripted.run_for(1.0)
    assert scripted.value("level") == pytest.approx(90.0)
    assert scripted.peer("valve") == 60         # 30 cm below: 60 %
    modelled = chcos_cell(cell / "system.toml", plant=tank)
    modelled.run_for(60.0)
    assert 105.0 <= modelled.value("level") < 120.0   # see test_a_plant_model_closes_the_loop
    assert seen and seen[-1] > 59.0
    modelled.script("level", "40")
    modelled.run_for(0.5)                        # the script wins over the plant it follows
    assert modelled.peer("valve") == 100


def test_sim_from_takes_a_plant_too(cell: Path, monkeypatch: pytest.MonkeyPatch,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    """A plant that fills the tank at 10 cm/s: the level the simulated PLC serves climbs."""
    (cell / "inflow.py").write_text(
        "def inflow(t, slaves):\n"
        "    slaves.set('level', min(200.0, (slaves.get('level') or 0.0) + 0.1))\n",
        encoding="utf-8")
    monkeypatch.chdir(cell)
    capsys.readouterr()
    assert cli_main(["sim", "--from", "devices.toml", "--plant", "inflow.py:inflow",
                     "--duration", "1.5", "--every", "0.5"]) == 0
    levels = [float(line.split("level=")[1].split()[0])
              for line in capsys.readouterr().out.splitlines() if "level=" in line]
    assert len(levels) >= 2 and levels == sorted(levels) and levels[-1] > 5.0, levels
    assert cli_main(["sim", "--from", "devices.toml", "--plant", "inflow.py:nope",
                     "--duration", "1"]) == 2
    assert "has no function nope" in capsys.readouterr().err
