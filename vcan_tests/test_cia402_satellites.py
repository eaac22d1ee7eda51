"""A CiA 402 axis in a system of satellites (issue 37): two satellites on the real link (Zenoh on
loopback, sealed, in this process so that satellite 1's CANopen bus reaches the independent
durand drive on a python-can virtual channel), a host session, real time. The operator's
``axis x ...`` lines go from the host to the satellite hosting the axis on its authenticated
control key; a task on satellite 0 commands the axis of satellite 1 through ``ctx.axis``. Every
assertion is about what the DRIVE received and the state it is in, or the answers the host
gets."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from chcos.errors import InstallError
from chcos.satellites import sysfile
from chcos.satellites.host import Host
from chcos.satellites.satellite import Satellite
from chcos.user.context import TaskContext
from vcan_tests.netutil import free_port, unique_channel
from vcan_tests.peers.durand_cia402 import ENABLED, SOD, DurandCia402Drive
from vcan_tests.support_cia402 import drive_eds, remote_axis_map
from vcan_tests.support_faults import wait_until

M = "vcan_tests.test_cia402_satellites"
NODE = 5
STEP = 0.02


async def mover(ctx: TaskContext, cmd: dict[str, Any]) -> str:
    """Sets axis x's mode, enables it and runs it at ``cmd["v"]`` mm/s; returns the state the
    result confirmed (a failure ends the task abnormally, naming it)."""
    x = ctx.axis("x")
    await x.set_mode()
    await x.enable()
    result = await x.at_velocity(float(cmd["v"]))
    return "" if result.state is None else result.state.name




@dataclass
class Cell:
    host: Host
    drive: DurandCia402Drive


@pytest.fixture
def cell(tmp_path: Path) -> Iterator[Cell]:
    channel = unique_channel("axsat")
    (tmp_path / "drive.eds").write_text(drive_eds(), encoding="utf-8")
    (tmp_path / "devices.toml").write_text(
        remote_axis_map(channel, tmp_path / "drive.eds", NODE), encoding="utf-8")
    (tmp_path / "users.txt").write_text("host:s3cret\nsat:s3cret\n", encoding="utf-8")
    sats = "".join(f"[[satellite]]\nmachine = {m}\nport = {free_port()}\n" for m in (0, 1))
    (tmp_path / "system.toml").write_text(
        f'[system]\nname = "ax{free_port()}"\ndevmaps = ["devices.toml"]\nbase_dir = "."\n'
        f'state_dir = "state"\n\n{sats}\n'
        '[link.auth]\nuser = "sat"\npassword = "s3cret"\ndictionary_file = "users.txt"\n',
        encoding="utf-8")
    sf = sysfile.load(tmp_path / "system.toml")
    drive = DurandCia402Drive(channel, NODE, quick_stop_option=2)
    stop = threading.Event()

    def motor() -> None:                # the drive's own time, in real time as the satellites'
        while not stop.wait(0.005):
            drive.step(STEP)

    stepper = threading.Thread(target=motor, daemon=True)
    sats_up: list[Satellite] = []
    host: Host | None = None
    try:
        for m in (0, 1):
            sat = Satellite(sf, m)
            sats_up.append(sat)
            sat.start()
        host = Host(sf, timeout=15.0)
        host.wait_for([0, 1])
        host.execute("install -m0 sysfile")
        host.execute("install -m1 sysfile")
        host.execute(f"install -m0o1 --code={M}:mover T x")
        stepper.start()
        assert wait_until(lambda: "state SWITCH_ON_DISABLED" in host.execute("axis x"))
        yield Cell(host, drive)
    finally:
        if host is not None:
            host.close()
        for sat in reversed(sats_up):
            sat.stop()
        stop.set()
        if stepper.is_alive():
            stepper.join(5)
        drive.close()


def test_the_operator_resets_a_fault_through_the_host(cell: Cell) -> None:
    host, d = cell.host, cell.drive
    assert "set mode done" in host.execute("axis x set-mode PV")
    answer = host.execute("axis x enable")
    assert answer.startswith("axis x: enable done") and d.state == ENABLED
    assert d.received == [0x00, 0x06, 0x07, 0x0F]
    d.inject_fault(0x2310)
    assert wait_until(lambda: "state FAULT," in host.execute("axis x"))
    assert "0x603F 0x2310" in host.execute("axis x")
    with pytest.raises(InstallError, match="enable failed: the drive is in FAULT"):
        host.execute("axis x enable")
    n = len(d.received)
    assert "fault reset done" in host.execute("axis x fault-reset")
    assert d.received[n:] == [0x00, 0x80] and d.state == SOD and d.emcys[-1] == 0
    with pytest.raises(InstallError, match="no task or device named 'nope'"):
        host.execute("axis nope enable")


def test_a_task_on_one_satellite_moves_the_axis_of_the_other(cell: Cell) -> None:
    host, d = cell.host, cell.drive
    host.execute("invoke T v=1.5")
    assert wait_until(lambda: d.state == ENABLED and d.velocity == 1500), d.received
    assert d.received[:4] == [0x00, 0x06, 0x07, 0x0F] and d.read(0x6061) == 3

    def t_done() -> dict[str, Any]:
        return next(t for t in host.map_doc()["tasks"] if t["name"] == "T")

    assert wait_until(lambda: t_done().get("completions", 0) >= 1), t_done()
    assert t_done()["abnormal"] == 0, t_done()
    assert "state OPERATION_ENABLED" in host.execute("axis x")
    n = len(d.log)
    assert "safe stop done" in host.execute("axis x safe-stop")
    assert d.state == SOD and d.log[n][0] == 0x02 and d.log[n][2] > 0
    assert all(speed == 0 for cw, _s, speed in d.log[n:] if cw == 0x00)
