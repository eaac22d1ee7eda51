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
from typing import Any

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


#: what stays in the checkout: notes beside the code, no runtime data
NOT_SHIPPED = (".md", ".txt")


def data_files(top: Path) -> set[str]:
    """Every file under the import packages that is not Python source, a cache or a note."""
    out = set()
    for name in TOP_LEVEL:
        for path in (top / name).rglob("*"):
            if (path.is_file() and path.suffix not in (".py", ".pyc", *NOT_SHIPPED)
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


def test_the_wheel_ships_every_data_file_that_runs_and_only_our_packages(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert tops == TOP_LEVEL
    missing = sorted(data_files(ROOT) - names)
    assert not missing, f"in chcos/ or drivers/ but not in the wheel (pyproject package-data): " \
                        f"{missing}"
    notes = sorted(n for n in names if n.endswith(NOT_SHIPPED) and n.split("/")[0] in TOP_LEVEL)
    assert not notes, f"notes in the wheel: {notes}"
    plain = sorted(n for n in names if "." not in n.rsplit("/", 1)[-1]
                   and n.split("/")[0] in TOP_LEVEL)
    assert plain == ["chcos/apps/fig65/testfile"], plain   # the file figure 6.5's A3 samples
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


# ---- the distribution's metadata: ranges, pins, extras, a core without them ------------------
EXTRAS = ("can", "canopen", "modbus", "serial", "satellites", "north", "view", "mcap", "sunspec",
          "all", "dev")
#: the optional packages by import name: what the core must import without
OPTIONAL = ("can", "canopen", "pymodbus", "serial", "cantools", "zenoh", "aiohttp", "asyncua",
            "prometheus_client", "msgpack", "cryptography", "mcap", "sunspec2")


def _requirements() -> list[Any]:
    from importlib.metadata import metadata

    from packaging.requirements import Requirement

    return [Requirement(r) for r in metadata("chcos").get_all("Requires-Dist") or ()]


def test_the_version_and_the_extras_are_declared() -> None:
    from importlib.metadata import metadata, version

    from chcos.devices.registry import EXTRAS as KIND_EXTRAS

    assert version("chcos") == "0.2.0"
    declared = set(metadata("chcos").get_all("Provides-Extra") or ())
    assert declared == set(EXTRAS)
    assert set(KIND_EXTRAS.values()) <= declared
    reqs = _requirements()
    assert not [r for r in reqs if r.marker is None], "the core needs no third-party package"
    by_extra: dict[str, set[str]] = {}
    for r in reqs:
        for extra in EXTRAS:
            if r.marker is not None and r.marker.evaluate({"extra": extra}):
                by_extra.setdefault(extra, set()).add(r.name)
    assert {"python-can", "cantools"} <= by_extra["can"]
    assert {"canopen", "python-can"} <= by_extra["canopen"]
    assert {"pymodbus", "pyserial"} <= by_extra["modbus"]
    assert "pyserial" in by_extra["serial"]
    assert {"eclipse-zenoh", "cryptography"} <= by_extra["satellites"]
    assert {"asyncua", "prometheus-client", "pymodbus", "aiohttp"} <= by_extra["north"]
    assert "aiohttp" in by_extra["view"]
    assert "mcap" in by_extra["mcap"]
    assert "pysunspec2" in by_extra["sunspec"]             # chcos import sunspec


def test_runtime_dependencies_are_ranges_and_constraints_pin_them_inside() -> None:
    """A range per dependency (never ``==``, always an upper bound), and constraints.txt (what
    CI and tools/run-cell install) pins each exactly, within its range."""
    from packaging.utils import canonicalize_name

    pins: dict[str, str] = {}
    for line in (ROOT / "constraints.txt").read_text(encoding="utf-8").splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            name, sep, ver = line.partition("==")
            assert sep, f"constraints.txt: {line!r} is no exact pin"
            pins[canonicalize_name(name)] = ver
    for r in _requirements():
        if r.name == "chcos":    # chcos[all] inside the dev extra
            continue
        ops = {s.operator for s in r.specifier}
        assert "==" not in ops and ops & {"<", "<="}, f"{r}: expected a bounded range"
        pin = pins.get(canonicalize_name(r.name))
        assert pin is not None, f"{r.name} is not pinned in constraints.txt"
        assert r.specifier.contains(pin, prereleases=True), f"{r.name}=={pin} outside {r}"
    boot = (ROOT / "tools" / "bootstrap.sh").read_text(encoding="utf-8")
    assert "--constraint constraints.txt" in boot


CORE_RUN = """
import importlib.abc, sys

class Blocker(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r} (blocked)", name=name)
        return None

BLOCKED = set(sys.argv[1].split(","))
sys.meta_path.insert(0, Blocker())

import chcos.cli.main, chcos.devices.mapref, chcos.testing
from chcos.devices.devmap import load
from chcos.devices.registry import driver_class
from chcos.errors import DriverNotAvailable
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System

driver_class("memory"), driver_class("signal")
try:
    driver_class("can")
except DriverNotAvailable as exc:
    print("can:", exc)
with System(load(sys.argv[2]), clock=VirtualClock(), base_dir=sys.argv[3]) as s:
    s.execute("install -m0 sysfile")
    s.run_for(1.0)
    print("readings:", s.devtab.get("S").readings)
print("loaded:", sorted(n for n in sys.modules if n.split(".")[0] in BLOCKED))
"""

SIGNAL_MAP = """
[[bus]]
name = "b"
kind = "signal"

[[device]]
name = "S"
direction = "sensor"
bus = "b"
address = { waveform = "sine", rate_hz = 10 }
"""


def test_the_core_runs_without_any_optional_package(tmp_path: Path) -> None:
    """In a subprocess whose every import of an optional package fails (a meta-path blocker:
    nothing installed or removed, no network), the OS, the pytest plugin and the command line
    import, a system on a signal bus runs, and a bus kind whose library is missing names the
    extra that brings it."""
    devmap = tmp_path / "m.toml"
    devmap.write_text(SIGNAL_MAP, encoding="utf-8")
    out = run([sys.executable, "-c", CORE_RUN, ",".join(OPTIONAL), str(devmap), str(tmp_path)],
              cwd=tmp_path)
    assert "pip install 'chcos[can]'" in out, out
    assert re.search(r"^readings: (9|10|11)$", out, re.M), out
    assert "loaded: []" in out, out
