"""``chcos monitor SYSTEM``: every bus listen-only against independent peers (pyModbusTCP's server,
python-can nodes sending CAN and CANopen frames by hand); mismatches flagged; the peers see no
write, no frame, no NMT and no SDO from the monitor."""

from __future__ import annotations

import io
import itertools
import os
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import pytest
from pyModbusTCP.server import DataHandler, ModbusServer

from chcos.cli import main as cli
from chcos.cli import monitor
from chcos.helpers import free_port

VENDOR = Path(__file__).resolve().parent / "vendor"
_chan = itertools.count()


class CountingHandler(DataHandler):  # type: ignore[misc]
    def __init__(self) -> None:
        super().__init__()
        self.writes: list[Any] = []

    def write_h_regs(self, address: int, words_l: list[int], srv_info: Any) -> Any:
        self.writes.append(("holding", address, words_l))
        return super().write_h_regs(address, words_l, srv_info)

    def write_coils(self, address: int, bits_l: list[bool], srv_info: Any) -> Any:
        self.writes.append(("coil", address, bits_l))
        return super().write_coils(address, bits_l, srv_info)


def _wait(pred: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    ev = threading.Event()
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        ev.wait(0.05)


@pytest.fixture
def cell(tmp_path: Path) -> Iterator[dict[str, Any]]:
    handler = CountingHandler()
    server = ModbusServer(host="127.0.0.1", port=free_port(), no_block=True, data_hdl=handler)
    server.start()
    server.data_bank.set_input_registers(0, [120, 50])
    server.data_bank.set_holding_registers(1, [33])
    n = next(_chan)
    can_chan, co_chan = f"i18-mon-can-{os.getpid()}-{n}", f"i18-mon-co-{os.getpid()}-{n}"
    eds_map = tmp_path / "axis.toml"
    assert cli.main(["import", "eds", str(VENDOR / "acme_amd200.eds"), "--node", "5", "--bus",
                     "axis", "--interface", "virtual", "--channel", co_chan, "--no-sdo", "--plain",
                     "-o", str(eds_map)]) == 0
    dead = free_port()  # nobody listens there
    (tmp_path / "cell.toml").write_text(f"""
[[bus]]
name = "plc"
kind = "modbus-tcp"
host = "127.0.0.1"
port = {server.port}
poll_period = 0.05

[[bus]]
name = "ghost"
kind = "modbus-tcp"
host = "127.0.0.1"
port = {dead}
timeout = 0.2

[[bus]]
name = "line"
kind = "can"
interface = "virtual"
channel = "{can_chan}"

[[device]]
name = "level"
direction = "sensor"
bus = "plc"
address = {{ table = "input", address = 0 }}
limits = [0.0, 200.0]

[[device]]
name = "pressure"
direction = "sensor"
bus = "plc"
address = {{ table = "input", address = 1 }}
limits = [0.0, 10.0]

[[device]]
name = "valve"
direction = "actuator"
bus = "plc"
address = {{ table = "holding", address = 1 }}
safe_value = 7.0

[[device]]
name = "missing"
direction = "sensor"
bus = "ghost"
address = {{ table = "input", address = 0 }}

[[device]]
name = "temp"
direction = "sensor"
bus = "line"
address = {{ id = 0x123, start = 0, length = 16, dlc = 2 }}

[[device]]
name = "fan"
direction = "actuator"
bus = "line"
address = {{ id = 0x200, start = 0, length = 8, dlc = 1 }}
safe_value = 0.0
""", encoding="utf-8")
    system = tmp_path / "system.toml"
    system.write_text('[system]\nname = "mon"\ndevmaps = ["cell.toml", "axis.toml"]\n',
                      encoding="utf-8")
    can_peer = can.Bus(interface="virtual", channel=can_chan)
    co_peer = can.Bus(interface="virtual", channel=co_chan)
    try:
        yield {"system": system, "server": server, "handler": handler, "can": can_peer,
               "co": co_peer}
    finally:
        can_peer.shutdown()
        co_peer.shutdown()
        server.stop()


def test_monitor_shows_devices_flags_mismatches_and_never_writes(cell: dict[str, Any]) -> None:
    can_peer, co_peer = cell["can"], cell["co"]
    mon = monitor.Monitor(cell["system"], grace=0.5)
    try:
        can_peer.send(can.Message(arbitration_id=0x123, data=(215).to_bytes(2, "little"),
                                  is_extended_id=False))
        can_peer.send(can.Message(arbitration_id=0x555, data=b"\x01", is_extended_id=False))
        can_peer.send(can.Message(arbitration_id=0x200, data=b"\x09", is_extended_id=False))
        # TPDO1 of node 5: statusword 0x0237, position -4096; TPDO2 too short; heartbeats
        co_peer.send(can.Message(arbitration_id=0x185, is_extended_id=False,
                                 data=(0x0237).to_bytes(2, "little")
                                 + (-4096).to_bytes(4, "little", signed=True)))
        co_peer.send(can.Message(arbitration_id=0x285, data=b"\x00\x01\x02",
                                 is_extended_id=False))
        co_peer.send(can.Message(arbitration_id=0x705, data=b"\x05", is_extended_id=False))
        co_peer.send(can.Message(arbitration_id=0x709, data=b"\x05", is_extended_id=False))

        def rows() -> dict[str, dict[str, Any]]:
            return {r["name"]: r for r in mon.rows()}

        _wait(lambda: rows()["level"]["value"] == 120 and rows()["temp"]["value"] == 215
              and rows()["position_actual_value"]["value"] == -4096
              and rows()["missing"]["flags"] != [] and rows()["fan"]["value"] == 9
              and rows()["valve"]["value"] == 33, 20, "the devices")
        r = rows()
        assert r["level"]["flags"] == []
        assert r["pressure"]["flags"] == ["value 50 outside limits [0.0, 10.0]"]
        assert r["missing"]["flags"][0].startswith("no answer")
        assert r["statusword"]["value"] == 0x0237
        assert r["valve"]["value"] == 33 and r["valve"]["state"].startswith("output, read back")
        assert r["fan"]["value"] == 9  # another node's command frame, observed
        flags = "\n".join(mon.bus_flags())
        assert "bus line: unknown-id" in flags and "0x555" in flags
        assert "heartbeat of node 9, which is not in the map" in flags
        assert "TPDO2 of node 5 (id 0x285) has 3 bytes, the map's EDS mapping fills 6" in flags
        assert "node 5: no heartbeat" not in flags
    finally:
        mon.close()
    # nothing was written: not the safe values at the end either
    assert cell["handler"].writes == []
    assert mon.writes_held == []  # read-back outputs are inputs here: not even a safe value
    assert can_peer.recv(timeout=0.2) is None       # no CAN frame from the monitor
    assert co_peer.recv(timeout=0.2) is None        # no NMT, no SDO, no SYNC
    assert cell["server"].data_bank.get_holding_registers(1) == [33]


def test_monitor_command_exit_status(cell: dict[str, Any],
                                     capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["monitor", str(cell["system"]), "--duration", "1", "--grace", "0.5"]) == 1
    out = capsys.readouterr().out
    assert "listen-only (nothing is written)" in out and "t=    1.0 s" in out
    assert "mismatches:" in out and "pressure: value 50 outside limits" in out
    assert cell["handler"].writes == []
    out_io = io.StringIO()
    assert cli.main(["monitor", str(cell["system"].parent / "nope.toml")]) == 2
    del out_io
