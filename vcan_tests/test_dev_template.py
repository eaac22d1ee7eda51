"""The driver template (issue 14): :meth:`drivers.base.Driver.write` checks every write before a
driver sees it, no driver can override it, and the codecs import no I/O."""

from __future__ import annotations

import subprocess
import sys
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, Literal

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from chcos.errors import DeviceError
from drivers.base import Driver
from drivers.can_raw import CanDriver
from drivers.memory import MemoryDriver
from drivers.registry import driver_class
from vcan_tests.support_dev import FakeHost, bus, device

ROOT = Path(__file__).resolve().parent.parent


class Recording(Driver):
    """A confirming driver whose ``_write`` only records what reached it."""

    kind = "recording-test"
    confirms_writes = True

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self.seen: list[tuple[str, Any]] = []

    def start(self) -> None:
        self._running = True

    def stop(self) -> None:
        self._running = False

    def settle(self, timeout: float) -> bool:
        return True

    def _write(self, device: str, value: Any) -> None:
        self.seen.append((device, value))
        self.host.written(device, value)


def rig() -> tuple[Recording, FakeHost]:
    host = FakeHost()
    drv = Recording(bus("memory"), [device("S", "sensor", i=0), device("A", "actuator", i=1)],
                    host)
    return drv, host


def test_a_driver_cannot_override_the_template() -> None:
    with pytest.raises(TypeError, match=r"overrides Driver\.write.*implement _write instead"):
        class Bypass(Recording):
            def write(self, device: str, value: Any) -> None:  # type: ignore[misc]
                self.seen.append((device, value))


class FastPath(Recording):
    """A confirming driver with a fast path that records what reached it and can refuse."""

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self.now_seen: list[tuple[str, Any]] = []
        self.link_free = True

    def _write_now(self, device: str, value: Any) -> bool:
        self.now_seen.append((device, value))
        return self.link_free


def test_a_driver_cannot_override_the_fast_path_templates() -> None:
    for name, hook in (("write_now", "_write_now"), ("write_now_many", "_write_now_many")):
        with pytest.raises(TypeError, match=rf"overrides Driver\.{name}, .*implement {hook} "):
            type("Bypass", (Recording,), {name: lambda self, *a: True})


def test_the_fast_path_checks_as_write_does_and_counts_in_one_place() -> None:
    host = FakeHost()
    drv = FastPath(bus("memory"), [device("S", "sensor", i=0), device("A", "actuator", i=1),
                                   device("B", "actuator", i=2)], host)
    assert drv.write_now("A", 1.0) is False                 # not started: the hook not asked
    drv.start()
    assert drv.write_now("S", 2.0) is False and drv.write_now("nope", 3.0) is False
    assert drv.write_now("A", 4.0) is True
    drv.link_free = False
    assert drv.write_now("B", 5.0) is False                 # the hook said no: not counted
    drv.link_free = True
    assert drv.write_now_many([("B", 6.0), ("S", 7.0), ("A", 8.0)]) == [True, False, True]
    drv.stop()
    assert drv.write_now_many([("A", 9.0)]) == [False]
    assert drv.now_seen == [("A", 4.0), ("B", 5.0), ("B", 6.0), ("A", 8.0)]
    assert drv.write_counts == {"A": 2, "B": 1}
    drv.start()
    drv.write("A", 10.0)                                    # the queued path counts there too
    assert drv.write_counts == {"A": 3, "B": 1}
    # the fast path reports nothing: no error, no written() (Devtab records it itself)
    assert host.errors == [] and host.writes == [("A", 10.0, "")]


def test_readings_taken_together_reach_the_host_as_one_batch() -> None:
    from drivers.base import deliver_all

    class Batches(FakeHost):
        def __init__(self) -> None:
            super().__init__()
            self.batches: list[tuple[list[tuple[str, Any]], float | None]] = []

        def deliver_many(self, readings: Any, at: float | None = None) -> None:
            self.batches.append((list(readings), at))

    host = Batches()
    deliver_all(host, [])
    deliver_all(host, [("S1", 1), ("S2", 2)], at=0.5)
    deliver_all(host, [("S1", 3)])
    assert host.batches == [([("S1", 1), ("S2", 2)], 0.5), ([("S1", 3)], None)]
    assert host.delivered == []


def test_every_registered_driver_uses_the_template() -> None:
    from chcos.devices.driver import _PENDING_RENAME

    for ep in entry_points(group="chcos.drivers"):
        cls = driver_class(ep.name)
        assert cls.write is Driver.write, ep.name
        owner = next(k for k in cls.__mro__ if "write_now" in vars(k))
        assert owner is Driver or owner.__module__ in _PENDING_RENAME, ep.name
        assert "_write" in {n for k in cls.__mro__ if k is not Driver for n in vars(k)}, ep.name


def test_writes_before_start_after_stop_and_to_non_actuators_never_reach_the_driver() -> None:
    drv, host = rig()
    drv.write("A", 1.0)                        # not started
    drv.start()
    drv.write("S", 2.0)                        # a sensor
    drv.write("nope", 3.0)                     # not on this bus
    drv.write("A", 4.0)                        # the one that goes through
    drv.stop()
    drv.write("A", 5.0)                        # stopped
    assert drv.seen == [("A", 4.0)]
    assert host.error_kinds() == ["stopped", "unknown-device", "unknown-device", "stopped"]
    assert "not an actuator of this bus; expected one of A" in host.errors[1][2]
    assert "'nope'" in host.errors[2][2]
    assert host.writes == [("A", 1.0, "recording-test bus b is not running"), ("A", 4.0, ""),
                           ("A", 5.0, "recording-test bus b is not running")]
    assert drv.write_counts == {"A": 1}
    assert drv.refused_writes == {"stopped": 2, "unknown-device": 2}


def test_a_driver_that_does_not_confirm_writes_raises_what_it_refuses() -> None:
    host = FakeHost()
    drv = MemoryDriver(bus("memory"), [device("A", "actuator")], host)
    with pytest.raises(DeviceError, match="memory bus b is not running"):
        drv.write("A", 1.0)
    drv.start()
    with pytest.raises(DeviceError, match="not an actuator of this bus"):
        drv.write("B", 1.0)
    drv.write("A", 2.0)
    assert drv.store.history("A") == [2.0]
    assert host.error_kinds() == ["stopped", "unknown-device"]


def test_a_stream_driver_refuses_a_write_after_stop() -> None:
    host = FakeHost()
    drv = CanDriver(bus("can", interface="virtual", channel="template-test"),
                    [device("A", "actuator", id=0x10, start=0, length=8)], host)
    drv.start()
    drv.stop()
    drv.write("A", 1)
    assert host.error_kinds() == ["stopped"]
    assert host.writes == [("A", 1, "can bus b is not running")]


def test_the_codecs_import_no_io() -> None:
    """The serial, Modbus and CANopen codecs pull in no bus library, socket, thread or event
    loop at all (the CAN codec's cantools imports python-can itself; test_layers checks that
    no codec imports I/O directly)."""
    code = ("import sys\n"
            "import drivers.codecs.serial, drivers.codecs.modbus, drivers.codecs.canopen\n"
            "bad = [m for m in ('can', 'serial', 'canopen', 'pymodbus', 'asyncio', 'socket',\n"
            "                   'threading', 'selectors', 'zenoh') if m in sys.modules]\n"
            "print(bad)\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         check=True, timeout=60)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


@settings(max_examples=300, deadline=None, derandomize=True)
@given(st.sampled_from(["int16", "uint16", "int32", "uint32", "float32", "float64"]),
       st.sampled_from(["big", "little"]), st.data())
def test_register_packing_agrees_with_pymodbus(type_: str, order: Literal["big", "little"],
                                               data: Any) -> None:
    """The codec packs registers by hand (pymodbus cannot be imported without its asyncio
    clients); pymodbus' own conversion is the independent reference."""
    from pymodbus.client.mixin import ModbusClientMixin as Mixin

    from drivers.codecs.modbus import REGISTER_TYPES, from_registers, to_registers

    dt = getattr(Mixin.DATATYPE, type_.upper())
    size = REGISTER_TYPES[type_][1]
    regs = data.draw(st.lists(st.integers(0, 0xFFFF), min_size=size, max_size=size))
    theirs = Mixin.convert_from_registers(regs, dt, order)
    mine = from_registers(type_, regs, order)
    assert mine == theirs or (mine != mine and theirs != theirs)   # nan == nan
    if mine == mine:
        assert to_registers(type_, mine, order) == Mixin.convert_to_registers(mine, dt, order)


@settings(derandomize=True)
@given(st.binary(max_size=64))
def test_rtu_crc_agrees_with_pymodbus(data: bytes) -> None:
    from pymodbus.framer import FramerRTU

    from drivers.codecs.modbus import crc16

    assert crc16(data) == FramerRTU.compute_CRC(data)
