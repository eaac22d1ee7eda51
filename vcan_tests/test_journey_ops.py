"""Operations a cell needs (issue 39): ``chcos run --log FILE`` with rotation."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from chcos.cli import scaffold
from chcos.cli.main import main as cli_main
from chcos.helpers import free_port


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    scaffold.create(tmp_path / "cell", port=free_port())
    return tmp_path / "cell"


def test_run_log_file_has_the_story_and_rotates(cell: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "run.log"
    root_level = logging.getLogger().level
    assert cli_main(["run", str(cell / "system.toml"), "--virtual", "--duration", "3",
                     "--value", "level=100", "--log", str(log)]) == 0
    text = log.read_text(encoding="utf-8")
    assert "install: fill on machine 0" in text          # INFO events, without -v
    assert "chcos.run: system cell: healthy after 3.0 s" in text
    assert "INFO" not in capsys.readouterr().err         # the terminal keeps its level
    assert logging.getLogger().level == root_level       # put back after the run
    # a small size: the file rotates and keeps --log-keep old ones
    for _ in range(4):
        assert cli_main(["run", str(cell / "system.toml"), "--virtual", "--duration", "1",
                         "--value", "level=100", "--log", str(log), "--log-size", "0.0005",
                         "--log-keep", "2"]) == 0
    assert (tmp_path / "run.log.1").exists() and (tmp_path / "run.log.2").exists()
    assert not (tmp_path / "run.log.3").exists()
    assert "healthy after 1.0 s" in log.read_text(encoding="utf-8") + \
        (tmp_path / "run.log.1").read_text(encoding="utf-8")


def test_run_log_refuses_an_unwritable_file(cell: Path, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["run", str(cell / "system.toml"), "--virtual", "--duration", "1",
                     "--log", str(tmp_path / "no" / "such" / "dir" / "run.log")]) == 2
    assert "--log" in capsys.readouterr().err
