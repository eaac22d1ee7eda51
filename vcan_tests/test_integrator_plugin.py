"""The chcos.testing pytest plugin (loaded here through its pytest11 entry point, as in a user's
project) and the ``chcos new`` scaffold."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from chcos.cli import main as cli
from chcos.cli import scaffold
from chcos.errors import ConfigError, DeviceError, TaskError
from chcos.testing import TestCell


@pytest.fixture
def project(tmp_path: Path) -> Path:
    scaffold.create(tmp_path / "cell", port=5020)
    return tmp_path / "cell"


def test_plugin_drives_and_reads_a_scaffolded_cell(
        project: Path, chcos_cell: Callable[..., TestCell]) -> None:
    cell = chcos_cell(project / "system.toml")
    assert cell.peer("valve") == 0  # the idle output holds its safe value
    cell.set("level", 110.0)
    cell.run_for(1.0)
    assert cell.now == pytest.approx(1.0)
    assert cell.value("level") == pytest.approx(110.0) and cell.status("level") == "OK"
    assert cell.peer("valve") == 20 and cell.value("valve") == 20
    assert cell.task("fill").steps >= 10
    cell.invoke("fill", setpoint=150)  # a newer command pre-empts the running activation
    cell.run_for(0.5)
    assert cell.peer("valve") == 80
    cell.inject("level", 149.0)  # straight into Devtab; the next poll brings 110 back
    assert "fill" in cell.execute("map")
    with pytest.raises(TaskError, match="no task named 'nope'"):
        cell.task("nope")
    with pytest.raises(DeviceError, match="no device named 'nope'"):
        cell.set("nope", 1)


def test_plugin_fault_injection_silences_the_slave(
        project: Path, chcos_cell: Callable[..., TestCell]) -> None:
    cell = chcos_cell(project / "system.toml")
    cell.set("level", 100.0)
    cell.run_for(1.0)
    cell.silence("plc")
    cell.run_for(3.0)
    assert cell.status("level") in ("failed", "stale")
    assert cell.task("fill").abnormal == 1
    assert "level" in cell.task("fill").last_error
    with pytest.raises(DeviceError, match="bus 'nobus' has no simulated peer"):
        cell.silence("nobus")


def test_plugin_outputs_off_logs_writes(project: Path,
                                        chcos_cell: Callable[..., TestCell]) -> None:
    cell = chcos_cell(project / "system.toml", outputs=False)
    cell.set("level", 100.0)
    cell.run_for(1.0)
    assert cell.peer("valve") == 0  # never sent
    assert cell.value("valve") == 40  # but commanded
    assert {d for _, d, _ in cell.outputs_log} == {"valve"}
    assert any(v == 40 for _, _, v in cell.outputs_log)


def test_new_refuses_a_non_empty_directory(tmp_path: Path) -> None:
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "keep.txt").write_text("mine", encoding="utf-8")
    with pytest.raises(ConfigError, match="exists and is not an empty directory"):
        scaffold.create(tmp_path / "x")
    assert cli.main(["new", str(tmp_path / "x")]) == 2
    assert (tmp_path / "x" / "keep.txt").read_text(encoding="utf-8") == "mine"
    with pytest.raises(ConfigError, match="cell name 'a b'"):
        scaffold.create(tmp_path / "y", name="a b")
