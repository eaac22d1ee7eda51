"""The shutdown window on virtual time (issue 38): the clock keeps running after the last task
step, so a safe action that takes time finishes and is reported as what the device confirmed.

- A CiA 402 axis moving at shutdown (``chcos run --virtual``'s simulated drive, the model the
  durand drive checks in test_cia402_sim.py): the drive applies the quick stop, comes to rest and
  has its voltage disabled, and the summary says its safe value was written.
- pyModbusTCP's server in its own process, frozen (SIGSTOP) when a System on a virtual clock
  shuts down: the safe value is reported NOT written after the window, the shutdown returns
  within the window's wall time, and the server never got the value.
"""

from __future__ import annotations

import io
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from chcos.apps.sim.cia402_drive import Cia402Drive, Power
from chcos.cli import cellrun, cellsystem
from chcos.devices import devtab
from chcos.devices.devmap import check_main
from chcos.errors import KernelError
from chcos.kernel.clock import VirtualClock
from chcos.kernel.scheduler import Kernel
from chcos.system.embedded import System
from chcos.tables.tasks import TaskEntry
from chcos.user.context import TaskContext
from tools.peers import ModbusPeer
from vcan_tests.netutil import free_port
from vcan_tests.support_cia402 import imported_sync_drive
from vcan_tests.support_faults import wait_until

M = "vcan_tests.test_faults_shutdown_virtual"
NODE = 4
FAR = 1_000_000.0   # a target the axis is still travelling to when the run ends


async def mover(ctx: TaskContext, command: Any) -> None:
    """Enables the axis and sends it far away (the run ends while it moves)."""
    axis = ctx.axis("axis")
    await axis.set_mode("PP")
    await axis.enable()
    await axis.move_to(FAR)


def _axis_cell(tmp_path: Path) -> Path:
    devmap = imported_sync_drive(tmp_path, NODE, "Vendor servo")
    assert check_main([str(devmap)]) == 0
    (tmp_path / "install.chcos").write_text(
        f"install -m0 sysfile\ninstall -m0o1 --code={M}:mover mover axis\ninvoke mover\n",
        encoding="utf-8")
    system = tmp_path / "system.toml"
    system.write_text(f'[system]\nname = "axis"\ndevmaps = ["{devmap.name}"]\n'
                      'install = "install.chcos"\n', encoding="utf-8")
    return system


def test_an_axis_moving_at_shutdown_on_virtual_time_ends_quick_stopped_and_disabled(
        tmp_path: Path) -> None:
    system = _axis_cell(tmp_path)
    with cellsystem.open_cell(system, virtual=True, workdir=tmp_path / "work") as cell:
        assert cell.slaves is not None
        drive = cell.slaves.canopen_node("drive", NODE)
        assert isinstance(drive, Cia402Drive)
        deadline = time.monotonic() + 60.0
        # moving, on the drive's side and as chcos last heard it
        while abs(drive.model.velocity) < 1.0 or not cell.device("axis.velocity").value:
            assert time.monotonic() < deadline, drive.model.history
            cell.run_for(0.05)
        assert drive.model.power is Power.ENABLED
        cell.close()                                    # the shutdown, on virtual time
        outcome = cell.system.devtab.safe_outcomes["axis"]
        assert outcome.written, outcome
        # what the drive applied after the move: the quick stop (0x02), on which it ramped down
        # to rest and (quick stop option 2) went on to switch on disabled
        cws = drive.received
        tail = cws[max(i for i, cw in enumerate(cws) if cw & 0x0F == 0x0F) + 1:]
        assert 0x02 in tail, [hex(c) for c in cws]
        assert drive.model.history[-2:] == [Power.QUICK_STOP, Power.SWITCH_ON_DISABLED]
        assert drive.model.power is Power.SWITCH_ON_DISABLED, drive.model.power
        assert drive.model.velocity == 0


def test_chcos_run_virtual_stopped_mid_move_reports_the_safe_stop_written(
        tmp_path: Path) -> None:
    system = _axis_cell(tmp_path)
    out = io.StringIO()
    result = cellrun.run(system, virtual=True, duration=2.0, out=out, workdir=tmp_path / "w")
    text = out.getvalue()
    summary = text.split("summary")[-1]
    assert "safe value axis = 0: written" in summary, summary
    assert "sensor   axis.state       last OPERATION_ENABLED" in summary, summary
    assert result.healthy, result.problems


@pytest.fixture
def peer(tmp_path: Path) -> Iterator[ModbusPeer]:
    p = ModbusPeer(free_port(), tmp_path / "peer.log", {"0": 80})
    p.start()
    try:
        yield p
    finally:
        p.kill()


def _modbus_map(tmp_path: Path, port: int) -> Path:
    path = tmp_path / "plc.toml"
    path.write_text(f"""
[[bus]]
name = "plc"
kind = "modbus-tcp"
host = "127.0.0.1"
port = {port}
poll_period = 0.05
timeout = 0.3
retries = 0
reconnect_delay = 0.05
reconnect_delay_max = 0.2

[[device]]
name = "valve"
direction = "actuator"
bus = "plc"
address = {{ table = "holding", address = 1 }}
limits = [0.0, 100.0]
safe_value = 0
""", encoding="utf-8")
    return path


def test_a_frozen_server_on_virtual_time_is_not_written_and_the_shutdown_ends(
        tmp_path: Path, peer: ModbusPeer, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(devtab, "SHUTDOWN_FLUSH", 1.5)
    s = System([_modbus_map(tmp_path, peer.port)], clock=VirtualClock(), machines=[0])
    try:
        s.devtab.write("valve", 80)
        deadline = time.monotonic() + 30.0
        while peer.holding(1) != 80:
            assert time.monotonic() < deadline
            s.run_for(0.1)
        peer.freeze()
        began, v0 = time.monotonic(), s.kernel.clock.now()
        ended = threading.Event()
        shut = threading.Thread(target=lambda: (s.shutdown(), ended.set()), daemon=True)
        shut.start()
        assert ended.wait(30.0), "the shutdown hangs"
        took = time.monotonic() - began
        outcome = s.devtab.safe_outcomes["valve"]
        assert not outcome.written and outcome.reason, outcome
        assert took < 1.5 + 10.0, took     # the window's wall time, and the drivers' stop
        assert s.kernel.clock.now() - v0 <= 1.5 + 1e-6
    finally:
        thawed = time.monotonic()
        peer.thaw()
    assert [w for w in peer.writes() if w.address == 1 and w.values == [0]
            and w.at < thawed] == []


def test_a_server_back_within_the_window_on_virtual_time_gets_its_safe_value(
        tmp_path: Path, peer: ModbusPeer) -> None:
    s = System([_modbus_map(tmp_path, peer.port)], clock=VirtualClock(), machines=[0])
    s.devtab.write("valve", 80)
    deadline = time.monotonic() + 30.0
    while peer.holding(1) != 80:
        assert time.monotonic() < deadline
        s.run_for(0.1)
    peer.freeze()
    thaw = threading.Timer(0.5, peer.thaw)
    thaw.start()
    try:
        s.shutdown()
    finally:
        thaw.join(30.0)
        peer.thaw()
    assert s.devtab.safe_outcomes["valve"].written, s.devtab.safe_outcomes
    assert wait_until(lambda: peer.holding(1) == 0)


def test_the_window_runs_timers_and_interrupts_on_virtual_time_and_steps_no_task() -> None:
    k = Kernel(VirtualClock())
    fired: list[float] = []
    k.every(0.1, lambda: fired.append(k.clock.now()))
    ran: list[str] = []

    async def task() -> None:
        ran.append("stepped")

    coro = task()
    t = TaskEntry(tid=0, name="T", machine=0, level=1, func=lambda *a: None)  # type: ignore
    t.coro = coro
    k.ready(t, 5)
    heard: list[float] = []
    k.interrupt(lambda: heard.append(k.clock.now()))
    # until a condition: the clock jumps from timer to timer, interrupts are handled
    k.run_drivers(10.0, lambda: len(fired) >= 3, time.monotonic() + 30.0)
    assert fired == pytest.approx([0.1, 0.2, 0.3]) and heard == [0.0]
    assert k.clock.now() == pytest.approx(0.3)
    # until the window's end
    k.run_drivers(1.0, lambda: False, time.monotonic() + 30.0)
    assert k.clock.now() == pytest.approx(1.0) and len(fired) == 10
    # nothing can happen (no timer): the time passes at once
    k.timers.heap.clear()
    k.run_drivers(2.5, lambda: False, time.monotonic() + 30.0)
    assert k.clock.now() == pytest.approx(2.5)
    # the wall-time bound: a condition never met, a window far away
    k.every(0.1, lambda: None)
    k.run_drivers(1e9, lambda: False, time.monotonic() + 0.2)
    assert k.clock.now() < 1e9
    assert ran == [] and k.steps == 0 and not k.running     # the task never ran
    coro.close()
    with pytest.raises(KernelError, match="virtual clock"):
        Kernel().run_drivers(1.0, lambda: True, time.monotonic() + 1.0)
