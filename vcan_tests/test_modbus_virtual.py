"""Modbus on the kernel's thread in virtual time (issue 47) and the SunSpec address keys: a map
simulated in-process (``simulate``: the bus's ``direct``) is driven with no thread, socket or
event loop - the request's exact bytes (MBAP header, RTU frame with its CRC) handed to the
simulated slave in a call - and every timeout, retry and period is a kernel timer, so a silent
slave costs exactly its timeout in virtual time and two runs give the same events.

The address keys agreed with the importers (SunSpec maps): ``type = "string"`` with ``count``
(the value is text, carried by Devtab to a task), ``scale_factor`` (raw x 10^sf, the factor read
in the same request where it is next to the value, else in its own), ``unimplemented`` (no
value: the sensor fails, "not implemented"), ``int64``/``uint64``; unit 0 on a serial line as a
write-only broadcast.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from chcos.apps.sim.from_map import SimSlaves, simulate
from chcos.devices.devmap import load
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System

MAP = """
[[bus]]
name = "inv"
kind = "modbus-tcp"
host = "192.0.2.10"
timeout = 0.5
poll_period = 0.1

[[device]]
name = "model"
direction = "sensor"
bus = "inv"
address = {{ table = "holding", address = 40004, type = "string", count = 8 }}

[[device]]
name = "amps"
direction = "sensor"
bus = "inv"
address = {{ table = "holding", address = 40072, type = "int16", scale_factor = 40074 }}

[[device]]
name = "amps_a"
direction = "sensor"
bus = "inv"
address = {{ table = "holding", address = 40073, type = "uint16", scale_factor = 40074 }}

[[device]]
name = "watts"
direction = "sensor"
bus = "inv"
address = {{ table = "holding", address = 40083, type = "int16", scale_factor = 40200 }}

[[device]]
name = "hz"
direction = "sensor"
bus = "inv"
address = {{ table = "holding", address = 40084, type = "uint16", unimplemented = 65535 }}

[[device]]
name = "energy"
direction = "sensor"
bus = "inv"
address = {{ table = "holding", address = 40093, type = "uint64" }}

[[device]]
name = "limit"
direction = "actuator"
bus = "inv"
address = {{ table = "holding", address = 40300, type = "int16", scale_factor = 40301 }}
safe_value = 100

[[bus]]
name = "line"
kind = "modbus-rtu"
port = "/dev/ttyUSB7"
timeout = {timeout}
retries = 1

[[device]]
name = "level1"
direction = "sensor"
bus = "line"
address = {{ unit = 1, table = "input", address = 3 }}

[[device]]
name = "level2"
direction = "sensor"
bus = "line"
address = {{ unit = 2, table = "input", address = 3 }}

[[device]]
name = "all_off"
direction = "actuator"
bus = "line"
address = {{ unit = 0, table = "holding", address = 9 }}
safe_value = 0
"""


def cell(tmp_path: Path, timeout: float = 0.3) -> tuple[System, SimSlaves]:
    path = tmp_path / "cell.toml"
    path.write_text(MAP.format(timeout=timeout), encoding="utf-8")
    slaves = simulate(load([path]))
    system = System(slaves.devmap, clock=VirtualClock(), machines=[0])
    slaves.attach(system.kernel)
    system.devtab.peers_on_clock = True
    return system, slaves


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[tuple[System, SimSlaves]]:
    system, slaves = cell(tmp_path)
    try:
        yield system, slaves
    finally:
        system.shutdown()
        slaves.close()


def value(system: System, name: str) -> Any:
    return system.devtab.get(name).value


async def reader(ctx: Any, cmd: dict[str, Any]) -> None:
    """Reads its input (the model string) into the command."""
    cmd["seen"] = await ctx.read("model")


def test_a_task_reads_a_string_sensor_as_text(tmp_path: Path) -> None:
    path = tmp_path / "cell.toml"
    path.write_text(MAP.format(timeout=0.3), encoding="utf-8")
    slaves = simulate(load([path]))
    system = System(slaves.devmap, clock=VirtualClock(), base_dir=tmp_path)
    slaves.attach(system.kernel)
    try:
        slaves.peers["inv"].store.set_value(    # type: ignore[attr-defined]
            1, "holding", 40004, "SE5000H", "string", count=8)
        system.execute("install -m0 sysfile")
        system.execute("install -m0i1 --code=vcan_tests.test_modbus_virtual:reader R model")
        cmd: dict[str, Any] = {}
        system.run_for(0.2)
        system.invoke("R", cmd)
        system.run_for(0.2)
        assert cmd["seen"] == "SE5000H"
    finally:
        system.shutdown()
        slaves.close()


def test_no_thread_socket_or_settle_and_the_values_arrive(rig: tuple[System, SimSlaves]) -> None:
    system, slaves = rig
    store = slaves.peers["inv"].store        # type: ignore[attr-defined]
    store.set_value(1, "holding", 40004, "SE5000H", "string", count=8)
    store.set_value(1, "holding", 40072, 2345, "int16")
    store.set_value(1, "holding", 40073, 1170, "uint16")
    store.set_value(1, "holding", 40074, -2, "int16")
    store.set_value(1, "holding", 40083, 523, "int16")
    store.set_value(1, "holding", 40200, 1, "int16")
    store.set_value(1, "holding", 40084, 0xFFFF, "uint16")
    store.set_value(1, "holding", 40093, 2**40 + 7, "uint64")
    slaves.set("level1", 11)
    slaves.set("level2", 22)
    requests = store.requests
    system.run_for(0.15)          # the first poll, and the RTU line's wire time
    assert not [t.name for t in threading.enumerate() if t.name.startswith("modbus")]
    assert all(not d.settles for d in system.devtab.drivers)      # nothing for the kernel to wait
    assert value(system, "model") == "SE5000H"                      # text, through Devtab
    assert value(system, "amps") == 23.45 and value(system, "amps_a") == 11.7
    assert value(system, "watts") == 5230
    assert value(system, "energy") == 2**40 + 7
    assert (value(system, "level1"), value(system, "level2")) == (11, 22)
    hz = system.devtab.get("hz")
    assert hz.value is None and hz.status.value == "failed"
    assert "not implemented" in hz.reason and "holds 65535" in hz.reason
    # the model string, 40072..40074 (the factor next to its values), 40083..40084, the
    # energy, and the factor at 40200 (next to nothing) in its own: 5 requests a poll
    assert store.requests - requests == 5
    store.set_value(1, "holding", 40084, 5000, "uint16")
    system.run_for(0.15)
    assert value(system, "hz") == 5000 and system.devtab.get("hz").status.value == "OK"


def test_a_broadcast_is_written_to_every_unit_never_read_and_confirmed_at_shutdown(
        rig: tuple[System, SimSlaves]) -> None:
    system, slaves = rig
    store = slaves.peers["line"].store        # type: ignore[attr-defined]
    slave = slaves.peers["line"].slave        # type: ignore[attr-defined]
    system.run_for(0.5)
    system.devtab.write("all_off", 7)
    system.run_for(0.2)
    assert store.read(1, "holding", 9) == [7] and store.read(2, "holding", 9) == [7]
    assert value(system, "all_off") == 7 and system.devtab.get("all_off").status.value == "OK"
    assert slave.ignored == 0                 # no read of unit 0 was ever sent
    store.write(1, "holding", 9, [5])
    assert system.devtab.stop_drivers() == []     # the safe value went out: written
    assert store.read(1, "holding", 9) == [0] and store.read(2, "holding", 9) == [0]


def test_an_actuator_with_a_scale_factor_reads_it_before_each_write(
        rig: tuple[System, SimSlaves]) -> None:
    system, slaves = rig
    store = slaves.peers["inv"].store        # type: ignore[attr-defined]
    store.set_value(1, "holding", 40301, -1, "int16")      # tenths
    system.run_for(0.2)
    system.devtab.write("limit", 12.3)
    system.run_for(0.1)
    assert store.get_value(1, "holding", 40300, "int16") == 123
    assert value(system, "limit") == 12.3
    system.devtab.write("limit", 12.34)                     # not a multiple of 0.1
    system.run_for(0.1)
    assert store.get_value(1, "holding", 40300, "int16") == 123
    limit = system.devtab.get("limit")
    assert limit.write_errors == 1 and "no integer multiple of 10^-1" in limit.last_write_error


def events(tmp_path: Path) -> list[tuple[float, str, bool, str]]:
    """A silent unit 2 from t = 1 s to 3 s; every health change with its virtual time."""
    system, slaves = cell(tmp_path, timeout=2.5)
    seen: list[tuple[float, str, bool, str]] = []
    system.devtab.add_health_listener(
        lambda d, ok, why: seen.append((round(system.kernel.clock.now(), 6), d, ok, why)))
    try:
        system.run_for(1.0)
        slaves.peers["line"].slave.silence_units({2})   # type: ignore[attr-defined]
        system.run_for(8.0)
        slaves.peers["line"].slave.silence_units(set())  # type: ignore[attr-defined]
        system.run_for(100.0)          # its next try: 950 poll periods on (dead_unit_first)
    finally:
        system.shutdown()
        slaves.close()
    return seen


def test_a_silent_unit_costs_its_timeout_in_virtual_time_and_runs_repeat(
        tmp_path: Path) -> None:
    first = events(tmp_path)
    assert first == events(tmp_path)          # the same events at the same virtual instants
    fails = [(t, d) for t, d, ok, _ in first if not ok and d == "level2" and t > 1.0]
    assert fails, first
    t_fail = fails[0][0]
    # polled within a poll period of its silence: no answer within 2.5 s, the retry neither
    # (2 x 2.5 s), plus the wire time of the two requests at 19200 baud (6 ms each)
    assert 1.0 + 5.0 < t_fail < 1.1 + 5.0 + 0.02, first
    assert not [e for e in first if e[1] == "level1" and e[0] > 1.0]   # the live unit: never
    assert [d for t, d, ok, _ in first if ok and t > t_fail] == ["level2"]   # and came back


def test_a_simulated_tcp_server_that_stops_is_a_lost_link_and_its_return_recovers(
        rig: tuple[System, SimSlaves]) -> None:
    """On the kernel's thread too: a silenced server takes no connection (the devices fail
    with the link, reconnects are tried on virtual time) and its return recovers them; the
    safe value of an actuator is written first."""
    system, slaves = rig
    system.run_for(0.5)
    assert system.devtab.get("energy").status.value == "OK"
    slaves.silence("inv")
    system.run_for(1.0)
    energy = system.devtab.get("energy")
    assert energy.status.value == "failed" and "127.0.0.1" not in energy.reason
    assert "192.0.2.10:502" in energy.reason and "connect" in energy.reason
    failed_at = system.devtab.bus_stats["inv"].counts.get("connect-failed", 0)
    assert failed_at >= 2
    store = slaves.peers["inv"].store        # type: ignore[attr-defined]
    store.set_value(1, "holding", 40300, 7, "int16")
    store.set_value(1, "holding", 40301, -1, "int16")     # tenths
    slaves.restore("inv")
    system.run_for(6.0)                      # the backoff has grown to 1.6 s at most by then
    assert energy.status.value == "OK" and system.devtab.get("limit").status.value == "OK"
    assert store.get_value(1, "holding", 40300, "int16") == 1000      # 100 at factor 10^-1
