"""CPU pinning (``[system] cpus``, ``[[satellite]] cpus``): the keys are checked naming file and
key; :func:`chcos.system.affinity.pin_process` pins every thread of the process, those started
before and after; ``chcos run`` and ``chcos satellite`` pin their own process, as the
operating system reports for each of its threads."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

from chcos.errors import ConfigError
from chcos.satellites import sysfile
from vcan_tests.support_sat import Cluster
from vcan_tests.test_integrator_run import _modbus_cell

ROOT = Path(__file__).resolve().parent.parent
#: a CPU this process may use that is not the only one where there are several (so that
#: pinning changes what the threads may use)
CPU = max(os.sched_getaffinity(0))


def _allowed(pid: int) -> set[str]:
    """Every thread's ``Cpus_allowed_list`` of process ``pid``, as the kernel reports it."""
    out = set()
    for task in Path(f"/proc/{pid}/task").iterdir():
        for line in (task / "status").read_text().splitlines():
            if line.startswith("Cpus_allowed_list:"):
                out.add(line.split(":", 1)[1].strip())
    return out


def test_cpus_keys_are_read_and_bad_ones_named(tmp_path: Path) -> None:
    path = tmp_path / "system.toml"
    path.write_text('[system]\nname = "cell"\ncpus = [1, 0]\n\n'
                    '[[satellite]]\nmachine = 0\nport = 17447\ncpus = [1]\n\n'
                    '[[satellite]]\nmachine = 1\nport = 17448\n', encoding="utf-8")
    sf = sysfile.load(path)
    assert sf.cpus == frozenset({0, 1})
    assert sf.satellite_cpus == {0: frozenset({1})}
    for bad in ("[]", '"1"', "[-1]", "[true]", "[1.5]"):
        path.write_text(f'[system]\nname = "cell"\ncpus = {bad}\n', encoding="utf-8")
        with pytest.raises(ConfigError, match=r"system.toml: system.cpus: expected a non-empty "
                                              r"list of CPU numbers >= 0"):
            sysfile.load(path)
    path.write_text('[system]\nname = "cell"\n\n[[satellite]]\nmachine = 0\nport = 17447\n'
                    'cpus = 2\n', encoding="utf-8")
    with pytest.raises(ConfigError, match=r"satellite\[0\].cpus: expected a non-empty list"):
        sysfile.load(path)


PIN_SCRIPT = """
import os, threading
from chcos.errors import ConfigError
from chcos.system.affinity import pin_process

def threads():
    return {int(t): sorted(os.sched_getaffinity(int(t))) for t in os.listdir('/proc/self/task')}

stop = threading.Event()
before = threading.Thread(target=stop.wait)
before.start()
try:
    pin_process({10_000}, 'sys.toml: system.cpus')
except ConfigError as exc:
    refused = str(exc)
unchanged = threads()
pin_process({CPU}, 'sys.toml: system.cpus')
seen = []
after = threading.Thread(target=lambda: seen.append(sorted(os.sched_getaffinity(0))))
after.start(); after.join()
print(repr({'refused': refused, 'unchanged': unchanged, 'pinned': threads(), 'after': seen,
            'n': len(unchanged)}))
stop.set()
"""


def test_pin_process_pins_the_threads_running_and_those_started_later() -> None:
    res = subprocess.run([sys.executable, "-c", PIN_SCRIPT.replace("CPU", str(CPU))],
                         cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    got = ast.literal_eval(res.stdout.strip())
    assert got["refused"].startswith("sys.toml: system.cpus: CPU(s) 10000 not available to "
                                     "this process; expected CPUs this machine lets it use")
    everything = sorted(os.sched_getaffinity(0))
    assert got["n"] >= 2 and all(c == everything for c in got["unchanged"].values())
    assert all(c == [CPU] for c in got["pinned"].values())
    assert got["after"] == [[CPU]]


def test_chcos_run_pins_its_process_to_system_cpus(tmp_path: Path) -> None:
    probe = ("open('affinity.txt', 'w').write(repr(sorted({tuple(sorted("
             "__import__('os').sched_getaffinity(int(t)))) for t in "
             "__import__('os').listdir('/proc/self/task')})))")
    system = _modbus_cell(tmp_path, 5020, task=probe)
    system.write_text(system.read_text(encoding="utf-8") + f"cpus = [{CPU}]\n", encoding="utf-8")
    res = subprocess.run([sys.executable, "-m", "chcos.cli.main", "run", str(system),
                          "--virtual", "--duration", "1"], cwd=tmp_path, capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    assert f"pinned to CPU(s) {CPU} (system.cpus)" in res.stdout
    # every thread of the process (kernel, drivers, simulated slaves) as the task saw them
    assert ast.literal_eval((tmp_path / "affinity.txt").read_text()) == [(CPU,)]
    system.write_text(system.read_text(encoding="utf-8").replace(f"cpus = [{CPU}]",
                                                                 "cpus = [10000]"))
    res = subprocess.run([sys.executable, "-m", "chcos.cli.main", "run", str(system),
                          "--virtual", "--duration", "1"], cwd=tmp_path, capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 2
    assert "system.toml: system.cpus: CPU(s) 10000 not available to this process" in res.stderr


def test_a_satellite_pins_its_process_to_its_cpus(tmp_path: Path) -> None:
    c = Cluster(tmp_path, machines=(0,), cpus={0: [CPU]})
    try:
        c.start(0)
        c.host.wait_for([0], timeout=60)
        # Zenoh's threads, the kernel's and the drivers': all on the one CPU
        assert _allowed(c.procs[0].pid) == {str(CPU)}
    finally:
        c.close()


BENCH_SCRIPT = """
import os, logging
from chcos.apps.bench.emergency import run_emergency
logging.getLogger('chcos').setLevel(logging.ERROR)
r = run_emergency(3, 1000.0, gap=(0.005, 0.01), cpus=[CPU])
print(repr({'trials': r.trials, 'failed': r.failed, 'pinned': r.cpus_pinned,
            'after': sorted({tuple(sorted(os.sched_getaffinity(int(t))))
                             for t in os.listdir('/proc/self/task')})}))
"""


def test_the_emergency_benchmark_runs_pinned_and_gives_the_cpus_back() -> None:
    res = subprocess.run([sys.executable, "-c", BENCH_SCRIPT.replace("CPU", str(CPU))],
                         cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    got = ast.literal_eval(res.stdout.strip().splitlines()[-1])
    assert (got["trials"], got["failed"], got["pinned"]) == (3, 0, (CPU,))
    assert got["after"] == [tuple(sorted(os.sched_getaffinity(0)))]
