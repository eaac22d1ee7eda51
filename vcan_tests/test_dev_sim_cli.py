"""``chcos sim``: the CAN and serial simulators driven through their command line, and dispatch."""

from __future__ import annotations

import sys
import threading
import types
from pathlib import Path

import pytest

from chcos.apps.sim.cli import main
from drivers.can_raw import CanDriver
from drivers.serial_line import SerialDriver
from vcan_tests.netutil import free_port, unique_channel
from vcan_tests.support_dev import CELL_DBC, WAIT, FakeHost, bus, device


def test_sim_can_sends_rounds_a_driver_decodes(capsys: pytest.CaptureFixture[str]) -> None:
    channel = unique_channel("cli")
    host = FakeHost()
    drv = CanDriver(bus("can", interface="virtual", channel=channel, dbc=str(CELL_DBC)),
                    [device("T1", "sensor", message="Temps", signal="T1")], host)
    drv.start()
    try:
        assert main(["can", "--dbc", str(CELL_DBC), "--channel", channel, "--send", "Temps",
                     "--set", "Temps.T1=12.5", "--count", "3", "--rate", "1000"]) == 0
        assert drv.settle(WAIT)
        assert host.values("T1") == [pytest.approx(12.5)] * 3
    finally:
        drv.stop()
    assert capsys.readouterr().out.endswith("sent 3 frames, received 0\n")


def test_sim_can_reports_unknown_message(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["can", "--dbc", str(CELL_DBC), "--channel", unique_channel("cli"),
                 "--send", "Nope", "--count", "1"]) == 1
    assert "no message 'Nope' in the DBC" in capsys.readouterr().err


def test_sim_serial_tcp_starts_on_command(capsys: pytest.CaptureFixture[str]) -> None:
    port = free_port()
    status: list[int] = []
    t = threading.Thread(target=lambda: status.append(main(
        ["serial", "--tcp", str(port), "--line", "W={n}", "--count", "3", "--rate", "1000",
         "--start-on-rx", "--wait-client", str(WAIT)])))
    t.start()
    host = FakeHost()
    spec = bus("serial", url=f"socket://127.0.0.1:{port}", protocol="line",
               pattern=r"W=(?P<w>\d+)", reconnect_min=0.01, reconnect_max=0.05)
    drv = SerialDriver(spec, [device("W", "sensor", i=0, group="w"),
                              device("Go", "actuator", i=1, format="GO")], host)
    drv.start()
    try:
        assert drv.wait_open(WAIT)          # the simulator may start listening late
        drv.write("Go", 1)
        assert host.wait(lambda h: len(h.values("W")) == 3)
        assert host.values("W") == [0.0, 1.0, 2.0]
    finally:
        t.join(WAIT)
        drv.stop()
    assert status == [0]
    out = capsys.readouterr().out
    assert f"serial device at socket://127.0.0.1:{port}" in out and "rx b'GO\\n'" in out


def test_delegated_simulators_get_their_argv(monkeypatch: pytest.MonkeyPatch,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    seen: list[list[str]] = []
    fake = types.ModuleType("chcos.apps.sim.modbus_server")
    def fake_main(argv: list[str]) -> int:
        seen.append(argv)
        return 7

    fake.main = fake_main  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "chcos.apps.sim.modbus_server", fake)
    assert main(["modbus", "--port", "5020"]) == 7 and seen == [["--port", "5020"]]
    monkeypatch.setitem(sys.modules, "chcos.apps.weld.plant", None)   # import fails
    assert main(["weld"]) == 2
    assert "chcos.apps.weld.plant is not available" in capsys.readouterr().err


def test_usage_errors_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["serial", "--line", "x"])
    assert info.value.code == 2
    assert "one of the arguments --tcp --pty is required" in capsys.readouterr().err
    assert Path(CELL_DBC).exists()
