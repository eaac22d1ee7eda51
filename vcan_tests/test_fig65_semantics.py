"""Figure 6.5 as section 6.1.5 describes it (issue 16 item 5): A3 samples 'testfile' at the rate
set at download and sees edits; A4 reads a real terminal (a pty here) and logs system events; C1's
priority-9 command makes B1 take every A-level task and shut it down; a second
``install -m0 sysfile`` reloads the satellite from scratch."""

from __future__ import annotations

import os
import shutil
import threading
from pathlib import Path

from chcos.apps import fig65
from chcos.apps.fig65.runner import default_devmap
from chcos.kernel.clock import RealClock, VirtualClock
from chcos.kernel.instrument import Instrument
from chcos.system.embedded import System
from chcos.tables.messages import Link, LinkStatus
from chcos.tables.tasks import TaskEntry


def _system(tmp_path: Path, *, real: bool = False, tty: str | None = None) -> System:
    shutil.copy(fig65.HERE / "testfile", tmp_path / "testfile")
    s = System([default_devmap()], clock=RealClock() if real else VirtualClock(),
               task_path=[fig65.HERE], base_dir=tmp_path, map_path=tmp_path / "sysfile.map")
    if real:
        s.start()
    for line in fig65.SCRIPT.read_text().splitlines():
        s.execute(line.replace("/dev/tty0", tty) if tty else line)
    return s


def test_a3_samples_testfile_at_the_download_rate_and_sees_edits(tmp_path: Path) -> None:
    with _system(tmp_path) as s:
        assert 'rate=10' in (fig65.SCRIPT.read_text())
        a3 = s.tsktab.get("A3")
        assert a3.standing and a3.coro is not None  # samples from the install on
        s.run_for(1.0)
        assert s.msgtab.find("A3", "B2").sent == 10  # 10 Hz, set at download
        (tmp_path / "testfile").write_text("# edited\n777\n778\n")
        s.run_for(0.25)
        wm = a3.world
        assert wm is not None and wm.sensory["sample"] in ("777", "778")
        assert s.msgtab.find("A3", "B2").sent == 12


class _Seen(Instrument):
    """Sets ``flag`` once a task step of ``task`` has run after a message from ``source``."""

    def __init__(self, source: str, task: str) -> None:
        self.source = source
        self.task = task
        self.armed = False
        self.flag = threading.Event()

    def message_sent(self, link: Link) -> None:
        if link.src == self.source:
            self.armed = True

    def after_step(self, t: TaskEntry) -> None:
        if self.armed and t.name == self.task:
            self.flag.set()


def test_a4_reads_a_real_terminal_and_logs_system_events(tmp_path: Path) -> None:
    master, slave = os.openpty()
    tty = os.ttyname(slave)
    s = _system(tmp_path, real=True, tty=tty)
    try:
        seen = _Seen(tty, "A4")
        s.call(s.kernel.add_instrument, seen)
        s.execute("invoke C1")
        s.execute("setpri -12 A4 C1")
        os.write(master, b"hello from the pty\n")
        assert seen.flag.wait(15.0), "A4 never got the terminal line"
        s.call(s.devtab.fail, "S1", "cable cut")
        s.execute("suspend B2")
        text = s.call((tmp_path / "log").read_text)
        assert "tty hello from the pty" in text
        assert "command C1 started" in text
        assert "event invoke: host -> C1" in text
        assert "event setpri: A4/C1 9 -> 12" in text
        assert "event device-failed: S1: cable cut" in text
        assert "event suspend: host suspend B2" in text
    finally:
        s.shutdown()
        os.close(master)
        os.close(slave)


def test_c1_priority_9_command_makes_b1_take_and_shut_down_the_a_level(tmp_path: Path) -> None:
    with _system(tmp_path) as s:
        s.execute("setpri -6 B2 A3")  # B2 will take A3 from B1
        s.execute("invoke C1")
        s.run_for(2.0)
        assert s.tsktab.get("A3").owner is s.msgtab.find("B2", "A3")
        assert s.devtab.get("M1").value not in (None, 0.0)
        s.execute("inject /dev/tty0 shutdown")
        s.run_for(1.0)
        for name in ("A1", "A2", "A3"):
            t = s.tsktab.get(name)
            assert t.coro is None and t.owner is None, name
        assert s.msgtab.find("B2", "A3").status is LinkStatus.PREEMPTED
        assert s.devtab.get("M1").value == 0.0 and s.devtab.get("M2").value == 0.0
        b1 = s.tsktab.get("B1").world
        assert b1 is not None
        assert set(b1.command["answers"]) == {"A1", "A2", "A3"}
        assert all(v.startswith("normal completion") for v in b1.command["answers"].values())
        assert "A level shut down" in (tmp_path / "log").read_text()


def test_second_install_of_sysfile_reloads_the_satellite_from_scratch(tmp_path: Path) -> None:
    with _system(tmp_path) as s:
        s.execute("invoke C1")
        s.run_for(2.0)
        a1, b1 = s.tsktab.get("A1"), s.tsktab.get("B1")
        assert b1.owner is not None and a1.owner is not None
        before = a1.activations
        assert "reloaded from scratch" in s.execute("install -m0 sysfile")
        assert s.devtab.get("M1").value == 0.0
        assert b1.coro is None and b1.owner is None and a1.owner is None
        assert s.msgtab.find("C1", "B1").status is LinkStatus.PREEMPTED
        assert a1.activations == before + 1  # the standing loop starts afresh
        assert a1.world is not None and a1.world.snapshot()["sensory"] == {}
        s.run_for(1.0)
        # machine 1 goes on: B2 still serves C1; A2, released by the reloaded B1, runs its own loop
        assert s.tsktab.get("B2").owner is not None and s.tsktab.get("B2").coro is not None
        assert s.tsktab.get("A2").coro is not None
        assert a1.world.snapshot()["sensory"] != {}
