"""test_packaging - a regular install (the wheel, not the editable checkout) runs the main job.

The wheel is built from a copy of the sources (so the build leaves nothing in the checkout) with
``pip wheel --no-deps``, installed with ``--no-deps`` into a fresh virtual environment, and
``chcos run`` welds the seam from a temporary directory: the device maps, DBC/EDS files, install
scripts and learned models are found as package data (``chcos.resources``), not by climbing from
``__file__`` to a source tree. The new environment sees the running interpreter's dependencies
through a directory of links to them that leaves out chcos itself (its editable finder, its
dist-info) and ``drivers``, so the only chcos it can import is the wheel's; the test asserts so.
"""

from __future__ import annotations

import os
import re
import shutil
import site
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
#: what the wheel carries: the two import packages (see README, "Layout").
TOP_LEVEL = {"chcos", "drivers"}
#: names in the running interpreter's site-packages the new environment must not see.
OURS = ("chcos", "drivers", "__editable__", "__editable___chcos")
WAIT = 300.0   # generous wall-clock bound for a build or a run on a loaded machine


def run(args: list[str], cwd: Path, env: dict[str, str] | None = None) -> str:
    """Run ``args`` and return its output; fails the test with the output when it fails."""
    done = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=WAIT,
                          check=False)
    assert done.returncode == 0, (f"{' '.join(args)} exited {done.returncode}\n"
                                  f"{done.stdout[-4000:]}\n{done.stderr[-4000:]}")
    return done.stdout


def data_files(top: Path) -> set[str]:
    """Every file under the import packages that is not Python source or a cache."""
    out = set()
    for name in TOP_LEVEL:
        for path in (top / name).rglob("*"):
            if (path.is_file() and path.suffix not in (".py", ".pyc")
                    and "__pycache__" not in path.parts):
                out.add(path.relative_to(top).as_posix())
    return out


def dependency_links(into: Path) -> Path:
    """A directory of links to everything the running interpreter has installed except chcos."""
    into.mkdir()
    dirs = [*site.getsitepackages()]
    if site.ENABLE_USER_SITE:
        dirs.append(site.getusersitepackages())
    for d in map(Path, dirs):
        if not d.is_dir():
            continue
        for entry in d.iterdir():
            if entry.name.startswith(OURS) or entry.suffix == ".pth":
                continue
            link = into / entry.name
            if not link.exists():
                link.symlink_to(entry)
    return into


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The wheel ``pip wheel --no-deps`` builds from a copy of the checkout."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    for name in TOP_LEVEL:
        shutil.copytree(ROOT / name, src / name,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    out = tmp / "dist"
    run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--disable-pip-version-check",
         "-q", "-w", str(out), str(src)], cwd=tmp)
    (found,) = out.glob("chcos-*.whl")
    return found


def test_the_wheel_ships_every_data_file_and_only_our_packages(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert tops == TOP_LEVEL
    missing = sorted(data_files(ROOT) - names)
    assert not missing, f"in chcos/ or drivers/ but not in the wheel (pyproject package-data): " \
                        f"{missing}"
    for required in ("chcos/apps/weld/maps/weld_cell.toml", "chcos/apps/weld/maps/weld_cell.dbc",
                     "chcos/apps/weld/maps/weld_servo.eds", "chcos/apps/weld/install.chcos",
                     "chcos/apps/fig65/fig65.toml", "chcos/apps/nbs/tables/H1.toml",
                     "chcos/apps/sim/eds/servo_drive.eds", "chcos/viewer/static/index.html",
                     "chcos/py.typed", "drivers/py.typed"):
        assert required in names, required


@pytest.mark.slow
def test_installed_wheel_welds_the_seam_from_another_directory(wheel: Path,
                                                               tmp_path: Path) -> None:
    venv = tmp_path / "venv"
    run([sys.executable, "-m", "venv", "--without-pip", str(venv)], cwd=tmp_path)
    py = venv / "bin" / "python"
    run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps",
         "--disable-pip-version-check", "-q", str(wheel)], cwd=tmp_path)
    purelib = run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                  cwd=tmp_path).strip()
    deps = dependency_links(tmp_path / "deps")
    Path(purelib, "_chcos_test_deps.pth").write_text(f"{deps}\n", encoding="utf-8")

    cwd = tmp_path / "elsewhere"
    cwd.mkdir()
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP", "VIRTUAL_ENV")}
    env.update(HOME=str(tmp_path / "home"), CHCOS_STATE_DIR=str(tmp_path / "state"))

    where = run([str(py), "-c",
                 "import chcos, drivers, chcos.resources as r; print(chcos.__file__); "
                 "print(drivers.__file__); "
                 "print(r.path('chcos.apps.weld', 'maps', 'weld_cell.toml'))"],
                cwd=cwd, env=env).split()
    for path in where:
        assert Path(path).is_relative_to(purelib), f"{path} is not the wheel's ({purelib})"

    out = run([str(venv / "bin" / "chcos"), "run", "weld", "--binding", "direct",
               "--workdir", str(cwd)], cwd=cwd, env=env)
    assert "job outcome: welded" in out, out[-3000:]
    assert "weld length 300 of 300 mm" in out, out[-3000:]
    assert (cwd / "weld-report.html").is_file()

    # the buses binding's map (its DBC and EDS files resolved beside it) and figure 6.5's
    # system (its map, install script and the file its sampler reads), from the wheel too
    maps = Path(purelib, "chcos", "apps", "weld", "maps", "weld_cell.toml")
    checked = run([str(venv / "bin" / "chcos"), "check", str(maps)], cwd=cwd, env=env)
    assert checked.startswith("ok: "), checked
    fig = run([str(venv / "bin" / "chcos"), "run", "--example", "fig65", "--duration", "5"],
              cwd=cwd, env=env)
    assert re.search(r"all tasks: [1-9]\d* executions", fig), fig[-2000:]
