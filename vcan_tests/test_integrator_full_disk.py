"""A full disk is an error, not a traceback (issue 50): ENOSPC injected at each write site of
``chcos run`` (the workdir check, sysfile.map during the run, the ``--log`` file) and of
``chcos shell`` (sysfile.map), and a real full filesystem (a small tmpfs, mounted and removed
here when the test runs as root). Each time: one line naming the file and ENOSPC, no
traceback; a workdir that cannot be written stops ``chcos run`` with status 2 before the cell
starts; a disk that fills during the run keeps the cell under control (its safe values are
written), the summary says what could not be written, and the status (1) agrees with it."""

from __future__ import annotations

import errno
import logging
import os
import shutil
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from chcos.cli import cellrun
from chcos.cli import main as cli
from chcos.system import mapfile

ROOT = Path(__file__).resolve().parent.parent
FIG65 = ROOT / "chcos" / "apps" / "fig65"
FULL = "No space left on device (ENOSPC)"


def _enospc(*_a: Any, **_k: Any) -> None:
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


@pytest.fixture
def system(tmp_path: Path) -> Path:
    """Figure 6.5 as a system file (C1 invoked by the install script)."""
    (tmp_path / "testfile").write_bytes((FIG65 / "testfile").read_bytes())
    (tmp_path / "install.chcos").write_text(
        (FIG65 / "install.chcos").read_text(encoding="utf-8") + "invoke C1\n", encoding="utf-8")
    path = tmp_path / "system.toml"
    path.write_text(f'[system]\nname = "fig65"\ndevmaps = ["{FIG65}/fig65.toml"]\n'
                    f'task_path = ["{FIG65}"]\ninstall = "install.chcos"\n', encoding="utf-8")
    return path


def _during_the_run(monkeypatch: pytest.MonkeyPatch, arm: Callable[[], None]) -> None:
    """Call ``arm`` once the cell runs (the first time its loop is entered)."""
    loop = cellrun._loop

    def armed(*args: Any, **kwargs: Any) -> None:
        arm()
        loop(*args, **kwargs)

    monkeypatch.setattr(cellrun, "_loop", armed)


def _no_traceback(err: str) -> None:
    assert "Traceback" not in err and "Logging error" not in err, err


def test_a_workdir_that_takes_no_file_stops_the_run_before_the_cell_starts(
        system: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(cellrun.os, "fsync", _enospc)
    work = tmp_path / "w"
    assert cli.main(["run", str(system), "--virtual", "--duration", "1",
                     "--workdir", str(work)]) == 2
    out, err = capsys.readouterr()
    _no_traceback(err)
    assert err.strip().splitlines() == [f"chcos run: --workdir {work}: cannot write there: "
                                        f"{FULL}"]
    assert "system fig65" not in out  # the cell never started


def test_the_map_failing_during_a_run_is_in_the_summary_and_the_status(
        system: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    _during_the_run(monkeypatch, lambda: monkeypatch.setattr(mapfile.sysmap, "write", _enospc))
    work = tmp_path / "w"
    assert cli.main(["run", str(system), "--virtual", "--duration", "2",
                     "--workdir", str(work)]) == 1
    out, err = capsys.readouterr()
    _no_traceback(err)
    summary = out[out.index("\nsummary"):]
    assert "UNHEALTHY" in summary
    assert f"could not be written: cannot write {work / 'sysfile.map'}: {FULL}" in summary
    assert "executions" in summary and "NOT written" not in summary  # the cell ran, safe end


def test_the_log_file_failing_during_a_run_is_one_line_and_in_the_summary(
        system: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    class Full:
        """A file on a full disk: position 0, every write refused."""

        def seek(self, *_a: Any) -> int:
            return 0

        def tell(self) -> int:
            return 0

        def write(self, _text: str) -> int:
            _enospc()
            return 0

        def flush(self) -> None:
            _enospc()

        def close(self) -> None:
            _enospc()

    def fill() -> None:
        for h in logging.getLogger().handlers:
            if isinstance(h, cellrun._RotatingLog):
                h.stream.close()
                h.stream = Full()  # type: ignore[assignment]
                logging.getLogger("chcos.run").warning("this line cannot be written")

    _during_the_run(monkeypatch, fill)
    log = tmp_path / "run.log"
    assert cli.main(["run", str(system), "--virtual", "--duration", "1",
                     "--log", str(log)]) == 1
    out, err = capsys.readouterr()
    _no_traceback(err)
    lines = [line for line in err.splitlines() if str(log) in line]
    assert lines == [f"chcos run: cannot write {log}: {FULL}; the cell goes on, log lines are "
                     "lost"], err
    summary = out[out.index("\nsummary"):]
    assert "UNHEALTHY" in summary and f"could not be written: cannot write {log}: {FULL}" \
        in summary


def test_chcos_shell_prints_the_map_failure_once_and_ends_with_status_1(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(mapfile.sysmap, "write", _enospc)
    script = tmp_path / "script.chcos"
    script.write_text("install -m0 sysfile\ninstall -m0 --code=vcan_tests.support_view:follow "
                      "T1\nmap\n", encoding="utf-8")
    path = tmp_path / "sysfile.map"
    assert cli.main(["shell", "--virtual", "--script", str(script), "--map", str(path)]) == 1
    out, err = capsys.readouterr()
    _no_traceback(err)
    assert err.strip().splitlines() == [f"error: cannot write {path}: {FULL}"]
    assert "T1" in out  # the script went on: the map command answered


@pytest.fixture
def small_fs(tmp_path: Path) -> Iterator[Path]:
    """A 256 KiB tmpfs (root only), removed at the end."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a tmpfs needs root")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mnt)],
                          capture_output=True, text=True, check=False)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], check=True)


def test_a_full_filesystem_as_workdir(system: Path, small_fs: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    with open(small_fs / "filler", "wb", buffering=0) as fh, pytest.raises(OSError) as full:
        while True:  # fill it: the kernel's own ENOSPC
            fh.write(b"\0" * 4096)
    assert full.value.errno == errno.ENOSPC
    assert cli.main(["run", str(system), "--virtual", "--duration", "1",
                     "--workdir", str(small_fs)]) == 2
    _out, err = capsys.readouterr()
    _no_traceback(err)
    assert err.strip().splitlines() == [f"chcos run: --workdir {small_fs}: cannot write "
                                        f"there: {FULL}"]
